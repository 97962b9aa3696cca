// magvecd's real devices with a scalar magnetometer, end to end over pseudo-terminals: the
// simulated serial fluxgate and the simulated G-882 write their lines into two ptys in real time
// (200 Hz, 10 Hz), RealDevices opens both through termios from the configuration text, its
// DeviceFeed aligns each fluxgate sample with the scalar reading at its time, and the daemon's
// EventPipeline (through the LCM messages, as magvecd) calibrates and validates against that F.
// The field changes (10 nT, 10-s period), so a constant reference would be wrong by up to 10 nT;
// calibration.reference_field_nT is nan: without the scalar the calibration could not validate.
// The INS is a fake hal::AttitudeSource fed with the simulator's INS attitude (no SocketCAN on
// the test host; the CAN path is tested in the VM).
#include <gtest/gtest.h>

#include <chrono>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <deque>
#include <filesystem>
#include <functional>
#include <optional>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "logged_daemon.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/sim_g882.hpp"
#include "magvec/host/daemon/daemon_error.hpp"
#include "magvec/host/daemon/devices.hpp"
#include "magvec/host/daemon/position_reference.hpp"
#include "magvec/host/geomag/reference_field.hpp"
#include "support/pty_pair.hpp"

namespace magvec::host::daemon {
namespace {

namespace fs = std::filesystem;

struct FakeIns final : hal::AttitudeSource {
  std::deque<hal::AttitudeSample> queue;
  hal::AttitudeCounters c{};
  hal::Status read(hal::AttitudeSample& out, std::uint32_t) noexcept override {
    if (queue.empty()) return hal::Status::kTimeout;
    out = queue.front();
    queue.pop_front();
    ++c.samples;
    return hal::Status::kOk;
  }
  const hal::AttitudeCounters& counters() const noexcept override { return c; }
};

struct FakePositions final : hal::PositionSource {
  std::deque<hal::PositionSample> queue;
  hal::PositionCounters c{};
  hal::Status read(hal::PositionSample& out, std::uint32_t) noexcept override {
    if (queue.empty()) return hal::Status::kNoData;
    out = queue.front();
    queue.pop_front();
    ++c.samples;
    return hal::Status::kOk;
  }
  const hal::PositionCounters& counters() const noexcept override { return c; }
};

struct Handler final : EventHandler {
  test::LoggedDaemon& d;
  std::vector<std::uint64_t> t_us;
  std::vector<double> f_nT;
  std::uint32_t read_errors{0};
  std::vector<std::pair<std::string, double>> model_references;
  explicit Handler(test::LoggedDaemon& daemon) : d(daemon) {}
  // As Daemon::on_model_reference: the REFERENCE event, in feed order.
  void on_model_reference(const std::string& model, double sigma_nT) override {
    model_references.emplace_back(model, sigma_nT);
    d.event(
        reference_event(100 + static_cast<std::int64_t>(model_references.size()), model, sigma_nT));
  }
  void on_attitude(const hal::AttitudeSample& a) override { d.on_attitude(a); }
  void on_magnetometer(const hal::MagnetometerSample& s, double f) override {
    t_us.push_back(s.t_us);
    f_nT.push_back(f);
    d.on_magnetometer(s, f);
  }
  void on_read_error(hal::Status) override {
    ++read_errors;
    d.on_read_error(hal::Status::kMalformed);
  }
};

void patch(std::string& text, const std::string& from, const std::string& to) {
  const std::size_t at = text.find(from);
  ASSERT_NE(at, std::string::npos) << from;
  text.replace(at, from.size(), to);
}

class ScalarPty : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "magvec_scalar_XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
    fluxgate_pty_ = std::make_unique<magvec::test::PtyPair>(dir_ / "ttyFLUX");
    scalar_pty_ = std::make_unique<magvec::test::PtyPair>(dir_ / "ttyG882");
  }
  void TearDown() override {
    fluxgate_pty_.reset();
    scalar_pty_.reset();
    fs::remove_all(dir_);
  }

  std::string config_text(bool scalar) const {
    std::string text = test::fast_config_text("li", 200);
    patch(text, "link = \"spi\"", "link = \"serial\"");
    patch(text, "serial_device = \"/dev/ttyUSB0\"",
          "serial_device = \"" + (dir_ / "ttyFLUX").string() + "\"");
    patch(text, "rate_hz = 100.0                 # INS output rate", "rate_hz = 200.0 #");
    // FakeIns stamps an epoch when it is queued, with no CAN transit to compensate: the default
    // 500 us would pair each sample with the attitude 0.5 ms later, a tenth of the next 5-ms
    // step (about 25 nT RMS of E/N/U scatter at these rates, twice the attitude-noise floor).
    patch(text, "latency_comp_us = 500", "latency_comp_us = 0");
    patch(text, "solve_on_worker = true", "solve_on_worker = false");
    patch(text, "li_min_samples = 100", "li_min_samples = 300");
    patch(text, "validation_samples = 100", "validation_samples = 200");
    // The simulated noise, so that validation's bounds do not depend on estimates from 100
    // samples.
    patch(text, "noise_nT = nan", "noise_nT = 0.3");
    patch(text, "attitude_noise_deg = nan", "attitude_noise_deg = 0.015");
    if (scalar) {
      patch(text, "enabled = false", "enabled = true");
      patch(text, "device = \"/dev/ttyUSB1\"", "device = \"" + (dir_ / "ttyG882").string() + "\"");
      patch(text, "latency_us = 50000", "latency_us = 0");
      // 60 of the 64 INS epochs at 200 Hz less the 50-ms fusion horizon: 250 ms (the 10-Hz scalar
      // needs 100 ms and the transit).
      patch(text, "horizon_us = 300000", "horizon_us = 200000");
    }
    return text;
  }

  // The qemu guest's rotation (tests/vm/vm_magvecd_test.cpp): up to 60 deg/s, at 200 Hz.
  static drivers::sim::ScenarioConfig rotation() {
    drivers::sim::ScenarioConfig sc = drivers::sim::scenario_rotation();
    sc.rate_hz = 200;
    sc.rotation.heading_rate_deg_s = 30;
    sc.rotation.pitch_amp_deg = 40;
    sc.rotation.pitch_period_s = 4.2;
    sc.rotation.roll_amp_deg = 35;
    sc.rotation.roll_period_s = 3.7;
    sc.num_samples = 200 * 40;
    return sc;
  }

  struct Played {
    std::vector<double> truth;        // |h_n| of each sample written, in order
    std::vector<double> reading_t_s;  // times of the scalar readings written
    std::uint64_t scalar_lines{0};
    double applied_t_s{std::nan("")};
  };
  // Plays `sc` in real time into the ptys (the G-882's lines too when `scalar`) and the fake INS,
  // polling `devices` into `h` after each sample, until 400 samples after the calibration was
  // applied or the scenario ends; before_sample(i) runs first for each sample i.
  void play(const drivers::sim::ScenarioConfig& sc, Devices& devices, FakeIns& ins, Handler& h,
            bool scalar, const std::function<void(std::size_t)>& before_sample, Played* out) {
    drivers::sim::Simulator sim(sc, 17);
    drivers::sim::SimSerialFluxgate fluxgate(drivers::sim::SimSerialConfig{});
    drivers::sim::SimG882 g882(drivers::sim::SimG882Config{});
    drivers::LinuxClock clock;
    const auto t0 = std::chrono::steady_clock::now();
    drivers::sim::SimSample s{};
    std::uint32_t after_applied = 0;
    for (std::size_t i = 0; sim.next(&s) && after_applied < 400; ++i) {
      std::this_thread::sleep_until(
          t0 + std::chrono::microseconds(static_cast<std::int64_t>(s.t_s * 1e6)));
      before_sample(i);
      // The attitude of this sample at the times before its line is written and after it has
      // been read: the sample's receive time lies between, where the buffer interpolates between
      // two equal attitudes (one INS epoch per sample would put a fraction of the next epoch's
      // turn into it: at 90 deg/s, 0.5 ms of transit is 0.05 deg, 40 nT).
      hal::AttitudeSample a;
      const core::Quat<double> q = core::quat_from_r_bn(s.r_bn_ins);
      a.q_nb = {q.w(), q.x(), q.y(), q.z()};
      a.flags = hal::kAttAttitudeValid | hal::kAttHeadingValid | hal::kAttStatusKnown;
      a.t_us = clock.now_us();
      ins.queue.push_back(a);
      auto pump = [](hal::SerialPort& from, magvec::test::PtyPair& to) {
        std::array<std::uint8_t, 128> buf{};
        std::size_t n = 0;
        while (from.read(buf, n, 0) == hal::Status::kOk)
          if (!to.write_all(std::span<const std::uint8_t>(buf.data(), n))) return false;
        return true;
      };
      if (scalar) {
        if (g882.transmit(s)) out->reading_t_s.push_back(s.t_s);
        ASSERT_TRUE(pump(g882, *scalar_pty_));
      }
      fluxgate.transmit(s);
      ASSERT_TRUE(pump(fluxgate, *fluxgate_pty_));
      out->truth.push_back(s.h_n_true_nT.norm());
      ASSERT_TRUE(devices.poll(h, 20'000));
      a.t_us = clock.now_us();
      ins.queue.push_back(a);
      if (h.d.ep.pipeline()->status().state == core::CalState::kApplied) {
        if (after_applied++ == 0) out->applied_t_s = s.t_s;
      }
    }
    out->scalar_lines = g882.injected().lines;
  }

  fs::path dir_;
  std::unique_ptr<magvec::test::PtyPair> fluxgate_pty_;
  std::unique_ptr<magvec::test::PtyPair> scalar_pty_;
};

TEST_F(ScalarPty, CalibratesAndValidatesAgainstTheTimeAlignedScalarField) {
  const std::string text = config_text(true);
  const Config c = parse_config(text, "test");
  ASSERT_TRUE(c.scalar.enabled);
  ASSERT_TRUE(std::isnan(c.calibration.reference_field_nT));
  FakeIns ins;
  auto devices = open_real_devices(
      c, [](std::uint32_t) {}, &ins);
  fluxgate_pty_->close_slave();
  scalar_pty_->close_slave();

  drivers::sim::ScenarioConfig sc = rotation();
  sc.diurnal_nT = sc.h_n_nT.normalized() * 10.0;  // |h| changes by +-10 nT
  sc.diurnal_period_s = 4;

  test::LoggedDaemon d;
  d.event(session_start_event(1, text));
  d.event(start_calibration_event(2));
  Handler h(d);
  Played run;
  play(
      sc, *devices, ins, h, true, [](std::size_t) {}, &run);
  ASSERT_FALSE(HasFatalFailure());
  const std::vector<double>& truth = run.truth;
  const std::vector<double>& reading_t_s = run.reading_t_s;
  const double applied_t_s = run.applied_t_s;
  devices->flush(h);
  d.stop();

  // The health message's scalar part (Devices::scalar_health): the lines written were read
  // (the last one may still be in the pty when the loop ends), none rejected, no silence, and
  // every sample got its F from a reading.
  const std::optional<ScalarHealth> health = devices->scalar_health();
  ASSERT_TRUE(health.has_value());
  EXPECT_LE(health->source.samples, run.scalar_lines);
  EXPECT_GE(health->source.samples + 1, run.scalar_lines);
  EXPECT_EQ(health->source.malformed + health->source.garbage_bytes + health->read_errors, 0u);
  EXPECT_EQ(health->timeouts, 0u);
  EXPECT_EQ(health->f_interpolated + health->f_nearest + health->f_fallback, h.f_nT.size());
  EXPECT_GT(health->f_interpolated, h.f_nT.size() * 9 / 10);

  // Every sample was delivered, in order, with F at its own time.
  ASSERT_EQ(h.f_nT.size(), truth.size());
  EXPECT_EQ(h.read_errors, 0u);
  const std::size_t n_aligned =
      static_cast<std::size_t>(reading_t_s.back() * sc.rate_hz);  // before the last reading
  // F against the truth, and what the nearest reading (one every 20 samples) would have given.
  double f_min = 1e9, f_max = -1e9, ss_aligned = 0, ss_nearest = 0;
  for (std::size_t i = 0; i < n_aligned; ++i) {
    f_min = std::min(f_min, truth[i]);
    f_max = std::max(f_max, truth[i]);
    ss_aligned += (h.f_nT[i] - truth[i]) * (h.f_nT[i] - truth[i]);
    const std::size_t nearest = (i + 10) / 20 * 20;
    ss_nearest += (truth[nearest] - truth[i]) * (truth[nearest] - truth[i]);
  }
  const double rms_aligned = std::sqrt(ss_aligned / static_cast<double>(n_aligned));
  const double rms_nearest = std::sqrt(ss_nearest / static_cast<double>(n_aligned));
  EXPECT_GT(f_max - f_min, 19.0);  // the field did change
  // Interpolated at the sample's time: the scalar noise (2 pT), the line's 1 pT, the curvature
  // over 100 ms between readings and the pacing jitter of a loaded machine.
  EXPECT_LT(rms_aligned, 0.05) << "over " << n_aligned << " samples";
  EXPECT_LT(rms_aligned, rms_nearest / 4) << rms_nearest;
  std::printf(
      "F per sample vs true |h|: RMS %.4f nT interpolated (nearest reading: %.4f nT) "
      "over %zu samples; calibration applied after %.1f s\n",
      rms_aligned, rms_nearest, n_aligned, applied_t_s);

  // The calibration was applied and validated against the scalar F.
  const CalibrationStatus st = d.ep.pipeline()->status();
  EXPECT_EQ(st.state, core::CalState::kApplied)
      << core::cal_failure_name(st.failure) << " " << st.solver_reason;
  EXPECT_LT(st.validation_rms_nT, 1.0);
  // Records of the applied calibration: |h| against the true field.
  double ss = 0;
  std::size_t n = 0;
  for (std::size_t i = 0; i < d.sink.records.size() && i < truth.size(); ++i) {
    const hal::OutputRecord& r = d.sink.records[i];
    if (r.cal_id == 0 || !std::isfinite(r.f_nT)) continue;
    ss += (r.f_nT - truth[i]) * (r.f_nT - truth[i]);
    ++n;
  }
  ASSERT_GT(n, 300u);
  EXPECT_LT(std::sqrt(ss / static_cast<double>(n)), 1.0);
  EXPECT_LT(d.sink.records.back().sigma_f_nT, 1.0);
  std::printf("validation RMS %.3f nT, records |h| - true RMS %.3f nT (%zu records)\n",
              st.validation_rms_nT, std::sqrt(ss / static_cast<double>(n)), n);
}

// Without a scalar magnetometer or a configured reference_field_nT (the defaults), F is the
// WMM2025's at the INS position: the fluxgate sees the model's field at the site plus a 40-nT
// anomaly (inside the model's 138 nT), the first position fix arrives 1 s into the calibration
// (which starts over then), which validates by the scatter about the mean, and its records are
// flagged as model-referenced with sigma_f including the 138 nT; |h| sits on the model's F, 40 nT
// below the truth, which is what a model reference can give.
TEST_F(ScalarPty, WithoutAScalarMagnetometerTheModelAtTheInsPositionIsTheReference) {
  const std::string text = config_text(false);
  const Config c = parse_config(text, "test");
  ASSERT_TRUE(uses_model_reference(c));
  FakeIns ins;
  FakePositions positions;
  auto devices = open_real_devices(
      c, [](std::uint32_t) {}, &ins, &positions);
  fluxgate_pty_->close_slave();
  EXPECT_NE(devices->describe().find("reference field from wmm2025"), std::string::npos)
      << devices->describe();

  hal::PositionSample fix;
  fix.lat_deg = 52.0;
  fix.lon_deg = 5.0;
  fix.altitude_m = 10;
  fix.undulation_m = 45;
  fix.flags = hal::kPosValid | hal::kPosStatusKnown;
  geomag::Site site;
  site.lat_deg = fix.lat_deg;
  site.lon_deg = fix.lon_deg;
  site.height_m = fix.height_m();
  const geomag::ReferenceField model =
      geomag::MagneticModel::wmm2025().field(site, PositionReference::utc_decimal_year_now());
  constexpr double kAnomaly_nT = 40;
  drivers::sim::ScenarioConfig sc = rotation();
  sc.h_n_nT = model.enu_nT * (1 + kAnomaly_nT / model.total_nT);

  test::LoggedDaemon d;
  d.event(session_start_event(1, text));
  d.event(start_calibration_event(2));
  Handler h(d);
  Played run;
  core::CalState state_before_fix = core::CalState::kIdle;
  play(
      sc, *devices, ins, h, false,
      [&](std::size_t i) {
        if (i == 200) {
          state_before_fix = d.ep.pipeline()->state();
          hal::PositionSample invalid = fix;  // not yet valid: not used
          invalid.flags = hal::kPosStatusKnown;
          invalid.lat_deg = -30;
          positions.queue.push_back(invalid);
          positions.queue.push_back(fix);
        } else if (i > 200 && i % 20 == 0) {
          positions.queue.push_back(fix);  // 10 Hz, the same place
        }
      },
      &run);
  ASSERT_FALSE(HasFatalFailure());
  devices->flush(h);
  d.stop();

  // Announced once, before the first sample with the model's F; the samples before it had none.
  ASSERT_EQ(h.model_references.size(), 1u);
  EXPECT_EQ(h.model_references[0].first, "WMM2025");
  EXPECT_DOUBLE_EQ(h.model_references[0].second, 138.0);
  EXPECT_EQ(state_before_fix, core::CalState::kCollecting);  // li skips samples without F
  ASSERT_EQ(h.f_nT.size(), run.truth.size());
  std::size_t with_f = 0;
  for (std::size_t i = 0; i < h.f_nT.size(); ++i) {
    if (i <= 200) {  // read before the fix was taken (after sample 200's read)
      EXPECT_TRUE(std::isnan(h.f_nT[i])) << i;
    }
    if (std::isfinite(h.f_nT[i])) {
      EXPECT_DOUBLE_EQ(h.f_nT[i], model.total_nT) << i;
      ++with_f;
    }
  }
  EXPECT_GT(with_f, h.f_nT.size() / 2);

  const CalibrationStatus st = d.ep.pipeline()->status();
  ASSERT_EQ(st.state, core::CalState::kApplied)
      << core::cal_failure_name(st.failure) << " " << st.solver_reason;
  EXPECT_TRUE(st.output.model_reference);
  EXPECT_LT(st.validation_rms_nT, 1.0);  // the scatter about the mean
  double sum = 0, sum_sq = 0;
  std::size_t n = 0;
  for (std::size_t i = 0; i < d.sink.records.size() && i < run.truth.size(); ++i) {
    const hal::OutputRecord& r = d.sink.records[i];
    if (r.cal_id == 0) continue;
    EXPECT_NE(r.flags & core::kOutModelReference, 0u) << i;
    EXPECT_GE(r.sigma_f_nT, 138.0) << i;
    const double e = r.f_nT - run.truth[i];
    sum += e;
    sum_sq += e * e;
    ++n;
  }
  ASSERT_GT(n, 300u);
  const double mean = sum / static_cast<double>(n);
  const double scatter = std::sqrt(std::fmax(sum_sq / static_cast<double>(n) - mean * mean, 0.0));
  EXPECT_NEAR(mean, -kAnomaly_nT, 2.0);
  EXPECT_LT(scatter, 1.0);
  std::printf(
      "model F %.1f nT at the site; records |h| - true: mean %.2f nT, scatter %.3f nT "
      "(%zu records); applied after %.1f s\n",
      model.total_nT, mean, scatter, n, run.applied_t_s);
}

TEST_F(ScalarPty, ConfigurationErrorsNameTheKey) {
  auto error_of = [](const std::string& toml) {
    try {
      (void)parse_config(toml, "cfg.toml");
    } catch (const ConfigError& e) {
      return std::string(e.what());
    }
    return std::string();
  };
  EXPECT_NE(error_of("[devices.scalar]\nformat = \"gsmp\"\n")
                .find("cfg.toml: devices.scalar.format: 'gsmp' is not one of g882"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.scalar]\npreamble = \"5\"\n").find("devices.scalar.preamble"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.scalar]\npreamble = \"$$\"\n").find("devices.scalar.preamble"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.scalar]\nmin_field_nT = 60000.0\nmax_field_nT = 50000.0\n")
                .find("devices.scalar.max_field_nT: must be above min_field_nT"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.scalar]\nanalog_channels = 9\n")
                .find("devices.scalar.analog_channels: out of range [0, 8]"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.scalar]\nbaud = 9600.5\n").find("devices.scalar.baud"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.scalar]\ndevise = \"/dev/ttyS0\"\n")
                .find("devices.scalar.devise: unknown key"),
            std::string::npos);
  // The wait must fit the INS attitude buffer (64 epochs: 600 ms at 100 Hz less the horizon).
  EXPECT_NE(error_of("[devices.scalar]\nenabled = true\nhorizon_us = 700000\n")
                .find("devices.scalar.horizon_us: 700000 is longer than the INS attitude buffer"),
            std::string::npos);
  EXPECT_EQ(error_of("[devices.scalar]\nenabled = false\nhorizon_us = 700000\n"), "");
  EXPECT_NE(error_of("[devices.magnetometer]\nrate_hz = 5000.0\n[devices.scalar]\nenabled = "
                     "true\nhorizon_us = 300000\n")
                .find("holds more than 1024 magnetometer samples"),
            std::string::npos);
  // The defaults: fallback = calibration.reference_field_nT.
  const Config c = parse_config("[calibration]\nreference_field_nT = 50000.0\n", "t");
  EXPECT_FALSE(c.scalar.enabled);
  EXPECT_EQ(c.scalar.baud, 9600u);
  EXPECT_EQ(c.scalar.line.preamble, '$');
  EXPECT_DOUBLE_EQ(c.scalar.align.fallback_nT, 50000.0);
}

TEST_F(ScalarPty, AMissingScalarDeviceIsNamedWithTheDeviceExitCode) {
  std::string text = config_text(true);
  patch(text, (dir_ / "ttyG882").string(), "/nonexistent/ttyG882");
  const Config c = parse_config(text, "test");
  FakeIns ins;
  try {
    (void)open_real_devices(
        c, [](std::uint32_t) {}, &ins);
    FAIL() << "opened";
  } catch (const DaemonError& e) {
    EXPECT_EQ(e.code(), kExitDevice);
    EXPECT_NE(std::string(e.what()).find("scalar magnetometer serial port"), std::string::npos)
        << e.what();
    EXPECT_NE(std::string(e.what()).find("/nonexistent/ttyG882"), std::string::npos) << e.what();
  }
}

}  // namespace
}  // namespace magvec::host::daemon
