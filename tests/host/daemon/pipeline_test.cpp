// magvecd's Pipeline / EventPipeline / replay (host/daemon): the daemon pipeline driven by the
// LCM messages gives exactly the records of the HIL harness on the same rig; an LCM log written
// the way the daemon publishes replays bit-identically, and a changed sample is detected.
#include <gtest/gtest.h>

#include <unistd.h>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstring>
#include <deque>
#include <filesystem>
#include <lcm/lcm-cpp.hpp>
#include <limits>
#include <vector>

#include "logged_daemon.hpp"
#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/host/daemon/device_feed.hpp"
#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/daemon/replay.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/calibrators.hpp"
#include "magvec/host/hil/hil_session.hpp"

namespace magvec::host::daemon {
namespace {

using test::fast_config;
using test::fast_config_text;
using test::LoggedDaemon;
using test::VectorSink;

TEST(DaemonConfig, EmbeddedDefaultAndExampleFileParseAlike) {
  const Config d = parse_config(default_config_text(), "default");
  const Config e =
      parse_config(read_config_text(std::string(MAGVEC_SOURCE_DIR) + "/host/daemon/magvecd.toml"),
                   "magvecd.toml");
  EXPECT_EQ(d.lcm.url, e.lcm.url);
  EXPECT_EQ(d.lcm.channels.output, e.lcm.channels.output);
  EXPECT_EQ(d.lcm.channels.raw_mag_batch, e.lcm.channels.raw_mag_batch);
  EXPECT_EQ(d.lcm.raw_batch, e.lcm.raw_batch);
  EXPECT_EQ(d.magnetometer.rate_hz, e.magnetometer.rate_hz);
  EXPECT_EQ(d.magnetometer.adc.nT_per_volt, e.magnetometer.adc.nT_per_volt);
  EXPECT_EQ(d.ins.ids.ekf_quat, e.ins.ids.ekf_quat);
  EXPECT_EQ(d.calibration.mode, e.calibration.mode);
  EXPECT_EQ(d.calibration.li_min_samples, e.calibration.li_min_samples);
  EXPECT_TRUE(std::isnan(d.calibration.reference_field_nT));
  EXPECT_TRUE(std::isnan(e.calibration.reference_field_nT));
  EXPECT_EQ(d.sim.samples_per_attitude, e.sim.samples_per_attitude);
  EXPECT_EQ(d.sim.wake_period_us, e.sim.wake_period_us);
  EXPECT_EQ(d.daemon.state_dir, e.daemon.state_dir);
}

// A missing key takes the value the embedded default states.
TEST(DaemonConfig, EmptyFileEqualsTheEmbeddedDefault) {
  const Config d = parse_config(default_config_text(), "default");
  const Config e = parse_config("", "empty");
  EXPECT_EQ(d.daemon.state_dir, e.daemon.state_dir);
  EXPECT_EQ(d.daemon.log_level, e.daemon.log_level);
  EXPECT_EQ(d.daemon.realtime, e.daemon.realtime);
  EXPECT_EQ(d.daemon.rt_priority, e.daemon.rt_priority);
  EXPECT_EQ(d.daemon.health_period_s, e.daemon.health_period_s);
  EXPECT_EQ(d.daemon.status_period_s, e.daemon.status_period_s);
  EXPECT_EQ(d.lcm.url, e.lcm.url);
  const auto& dc = d.lcm.channels;
  const auto& ec = e.lcm.channels;
  EXPECT_EQ(dc.raw_mag + dc.attitude + dc.pipeline + dc.output + dc.cal_state + dc.health +
                dc.command + dc.reply,
            ec.raw_mag + ec.attitude + ec.pipeline + ec.output + ec.cal_state + ec.health +
                ec.command + ec.reply);
  EXPECT_EQ(dc.raw_mag_batch, ec.raw_mag_batch);
  EXPECT_EQ(d.lcm.raw_batch, e.lcm.raw_batch);
  const auto& dm = d.magnetometer;
  const auto& em = e.magnetometer;
  EXPECT_EQ(dm.link, em.link);
  EXPECT_EQ(dm.rate_hz, em.rate_hz);
  EXPECT_EQ(dm.spi_device, em.spi_device);
  EXPECT_EQ(dm.spi_speed_hz, em.spi_speed_hz);
  EXPECT_EQ(dm.drdy_chip, em.drdy_chip);
  EXPECT_EQ(dm.drdy_line, em.drdy_line);
  EXPECT_EQ(dm.serial_device, em.serial_device);
  EXPECT_EQ(dm.serial_baud, em.serial_baud);
  EXPECT_EQ(dm.serial_reconnect_ms, em.serial_reconnect_ms);
  EXPECT_EQ(dm.serial_latency_us, em.serial_latency_us);
  EXPECT_EQ(dm.adc.nT_per_volt, em.adc.nT_per_volt);
  EXPECT_EQ(dm.adc.channel_of_axis, em.adc.channel_of_axis);
  EXPECT_EQ(dm.adc.gain_code, em.adc.gain_code);
  EXPECT_EQ(dm.adc.stuck_count, em.adc.stuck_count);
  EXPECT_EQ(d.ins.can_interface, e.ins.can_interface);
  EXPECT_EQ(d.ins.rate_hz, e.ins.rate_hz);
  EXPECT_EQ(d.ins.latency_comp_us, e.ins.latency_comp_us);
  EXPECT_EQ(d.ins.require_attitude_valid, e.ins.require_attitude_valid);
  EXPECT_EQ(d.ins.ids.status_01, e.ins.ids.status_01);
  EXPECT_EQ(d.ins.ids.status_03, e.ins.ids.status_03);
  EXPECT_EQ(d.ins.ids.ekf_info, e.ins.ids.ekf_info);
  EXPECT_EQ(d.ins.ids.ekf_quat, e.ins.ids.ekf_quat);
  EXPECT_EQ(d.ins.ids.ekf_euler, e.ins.ids.ekf_euler);
  EXPECT_EQ(d.ins.ids.ekf_orientation_acc, e.ins.ids.ekf_orientation_acc);
  const auto& dk = d.calibration;
  const auto& ek = e.calibration;
  EXPECT_EQ(dk.mode, ek.mode);
  EXPECT_EQ(dk.start_on_boot, ek.start_on_boot);
  EXPECT_EQ(dk.auto_accept, ek.auto_accept);
  EXPECT_EQ(std::isnan(dk.noise_nT), std::isnan(ek.noise_nT));
  EXPECT_EQ(std::isnan(dk.attitude_noise_deg), std::isnan(ek.attitude_noise_deg));
  EXPECT_EQ(dk.validation_samples, ek.validation_samples);
  EXPECT_EQ(dk.validation_max_rms_factor, ek.validation_max_rms_factor);
  EXPECT_EQ(dk.validation_min_rms_nT, ek.validation_min_rms_nT);
  EXPECT_EQ(dk.validate_against_active, ek.validate_against_active);
  EXPECT_EQ(dk.ekf_align, ek.ekf_align);
  EXPECT_EQ(dk.li_min_samples, ek.li_min_samples);
  EXPECT_EQ(std::isnan(dk.reference_field_nT), std::isnan(ek.reference_field_nT));
  EXPECT_EQ(d.sim.scenario, e.sim.scenario);
  EXPECT_EQ(d.sim.seed, e.sim.seed);
  EXPECT_EQ(d.sim.samples_per_attitude, e.sim.samples_per_attitude);
  EXPECT_EQ(d.sim.wake_period_us, e.sim.wake_period_us);
}

TEST(DaemonConfig, ErrorsNameTheKey) {
  auto error_of = [](const std::string& text) {
    try {
      parse_config(text, "cfg.toml");
    } catch (const ConfigError& e) {
      return std::string(e.what());
    }
    return std::string("no error");
  };
  EXPECT_NE(error_of("[calibration]\nmode = \"magic\"\n").find("calibration.mode"),
            std::string::npos);
  EXPECT_NE(error_of("[calibration]\nnoise_nT = \"x\"\n").find("calibration.noise_nT"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.magnetometer]\nrate_hz = -5\n").find("rate_hz: out of range"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.ins]\ncan_interfce = \"can0\"\n").find("unknown key"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.magnetometer]\nnT_per_volt = [1, 2]\n").find("array of 3"),
            std::string::npos);
  // The SBG decoder takes standard (11-bit) identifiers only: a 29-bit one is refused here, not
  // later as a confusing CAN filter error when the device opens.
  EXPECT_NE(error_of("[devices.ins.can_ids]\nekf_quat = 0x1234\n").find("ekf_quat: out of range"),
            std::string::npos);
  EXPECT_NE(error_of("[daemon\nstate_dir=").find("cfg.toml:1"), std::string::npos);
  EXPECT_EQ(error_of(""), "no error");  // every key is optional
}

TEST(DaemonPipeline, SameRecordsAsTheHilHarnessThroughLcmMessages) {
  const Config c = fast_config("li");
  // HIL harness: its own calibrator, started at the first step.
  using LiCal = core::BatchLiCalibrator<double, 512>;
  hil::CalibratorSpec spec;
  spec.noise_nT = c.calibration.noise_nT;
  spec.attitude_noise_deg = c.calibration.attitude_noise_deg;
  spec.li_min_samples = c.calibration.li_min_samples;
  auto cal = std::make_unique<LiCal>(hil::li_config(spec));
  VectorSink hil_sink;
  hil::HilConfig hc = hil_config(c);
  hc.start_calibration = true;
  drivers::sim::Simulator sim_a(sim_scenario(c), c.sim.seed);
  auto hil = std::make_unique<hil::HilSession<LiCal>>(sim_a, sim_rig_config(c), *cal, hil_sink, hc);
  ASSERT_EQ(hil->init(), hal::Status::kOk);

  // Daemon path: SimFrontEnd -> LCM messages -> EventPipeline.
  drivers::sim::Simulator sim_b(sim_scenario(c), c.sim.seed);
  auto front = std::make_unique<hil::SimFrontEnd>(sim_b, sim_rig_config(c));
  ASSERT_EQ(front->init(), hal::Status::kOk);
  LoggedDaemon d;
  d.event(session_start_event(1, fast_config_text("li")));
  d.event(start_calibration_event(2));

  constexpr int kSteps = 1500;
  for (int i = 0; i < kSteps; ++i) {
    ASSERT_TRUE(hil->step());
    ASSERT_TRUE(front->rig().step());
    front->poll(d);
  }
  ASSERT_EQ(hil_sink.records.size(), d.sink.records.size());
  ASSERT_GT(d.sink.records.size(), 1000u);
  for (std::size_t i = 0; i < d.sink.records.size(); ++i)
    ASSERT_TRUE(bit_identical(hil_sink.records[i], d.sink.records[i])) << "record " << i;
  // The run calibrated: outputs switch to cal_id 1 and the pipeline reports it applied.
  EXPECT_EQ(d.sink.records.back().cal_id, 1u);
  const CalibrationStatus st = d.ep.pipeline()->status();
  EXPECT_EQ(st.state, core::CalState::kApplied);
  EXPECT_EQ(st.calibrator, "li");
  EXPECT_LT(st.validation_rms_nT, 1.0);
}

// A refused candidate names the figure and the bound it was judged by (the state message and
// the log carry it): a bound set below the noise refuses the good candidate of the run above.
TEST(DaemonPipeline, AValidationRefusalNamesItsFigures) {
  std::string text = fast_config_text("li");
  text.replace(text.find("validation_max_rms_factor = 3.0"), 31, "validation_max_rms_factor = 0.5");
  text.replace(text.find("validation_min_rms_nT = 1.0"), 27, "validation_min_rms_nT = 0.0");
  const Config c = parse_config(text, "test");
  drivers::sim::Simulator sim(sim_scenario(c), c.sim.seed);
  auto front = std::make_unique<hil::SimFrontEnd>(sim, sim_rig_config(c));
  ASSERT_EQ(front->init(), hal::Status::kOk);
  LoggedDaemon d;
  d.event(session_start_event(1, text));
  d.event(start_calibration_event(2));
  for (int i = 0; i < 1500 && d.ep.pipeline()->state() != core::CalState::kFailed; ++i) {
    ASSERT_TRUE(front->rig().step());
    front->poll(d);
  }
  const CalibrationStatus st = d.ep.pipeline()->status();
  ASSERT_EQ(st.state, core::CalState::kFailed);
  EXPECT_EQ(st.failure, core::CalFailure::kValidationFailed);
  EXPECT_NE(st.solver_reason.find("held-out |h| - F "), std::string::npos) << st.solver_reason;
  EXPECT_NE(st.solver_reason.find(" nT above the bound "), std::string::npos) << st.solver_reason;
  EXPECT_NE(st.solver_reason.find("(noise "), std::string::npos) << st.solver_reason;
  EXPECT_EQ(to_lcm(st, 0, 0).solver_reason, st.solver_reason);  // the state message carries it
  std::printf("refusal: %s %s\n", core::cal_failure_name(st.failure), st.solver_reason.c_str());
}

class DaemonReplay : public ::testing::Test {
 protected:
  void SetUp() override {
    dir_ = std::filesystem::temp_directory_path() /
           ("magvec_replay_test_" + std::to_string(::getpid()));
    std::filesystem::create_directories(dir_);
    path_ = (dir_ / "session.lcm").string();
  }
  void TearDown() override { std::filesystem::remove_all(dir_); }

  // Writes a log the way magvecd publishes: session, calibration install, start, samples,
  // outputs; a second session (reload) in the middle. Returns the live records.
  // raw_batch > 1 publishes the raw samples in batches (lcm.raw_batch); `batches` receives their
  // number.
  // mag_rate_hz: the magnetometer's rate (the INS runs at 100 Hz).
  std::vector<hal::OutputRecord> write_log(int steps, std::size_t raw_batch = 1,
                                           std::size_t* batches = nullptr,
                                           double mag_rate_hz = 100) {
    lcm::LogFile log(path_, "w");
    EXPECT_TRUE(log.good());
    const Config c = fast_config("li", mag_rate_hz);
    drivers::sim::Simulator sim(sim_scenario(c), c.sim.seed);
    auto front = std::make_unique<hil::SimFrontEnd>(sim, sim_rig_config(c));
    EXPECT_EQ(front->init(), hal::Status::kOk);
    LoggedDaemon d;
    d.log = &log;
    d.raw_batch = raw_batch;
    core::SensorModel<double> m;
    m.o = core::Vec3<double>(10, -20, 5);
    d.event(session_start_event(1, fast_config_text("li", mag_rate_hz)));
    d.event(set_active_event(2, m, 4));
    d.event(start_calibration_event(3));
    for (int i = 0; i < steps; ++i) {
      if (i == steps / 2) {  // SIGHUP-like new session, carrying the active calibration over
        const CalibrationStatus st = d.ep.pipeline()->status();
        d.event(session_start_event(4, fast_config_text("ekf", mag_rate_hz)));
        d.event(set_active_event(5, st.active, st.cal_id, 0.0, st.output));
      }
      EXPECT_TRUE(front->rig().step());
      front->poll(d);
    }
    d.stop();  // the daemon stops: the samples inside the horizon get their records
    if (batches != nullptr) *batches = d.batches;
    return d.sink.records;
  }

  std::filesystem::path dir_;
  std::string path_;
};

TEST_F(DaemonReplay, ReplayIsBitIdenticalToTheLiveRecords) {
  const std::vector<hal::OutputRecord> live = write_log(1600);
  VectorSink replayed, logged;
  const ReplayResult r = replay_log(path_, replayed, &logged);
  EXPECT_EQ(r.sessions, 2u);
  EXPECT_EQ(r.records, live.size());
  EXPECT_EQ(r.logged_records, live.size());
  EXPECT_EQ(r.compared, live.size());
  EXPECT_EQ(r.mismatches, 0u);
  EXPECT_EQ(r.uncompared, 0u);
  ASSERT_EQ(replayed.records.size(), live.size());
  for (std::size_t i = 0; i < live.size(); ++i)
    ASSERT_TRUE(bit_identical(replayed.records[i], live[i])) << i;
  // The first session calibrated on top of the installed cal_id 4; the second kept it.
  EXPECT_EQ(live.front().cal_id, 4u);
  EXPECT_EQ(live[800].cal_id, 5u);
  EXPECT_EQ(live.back().cal_id, 5u);
  EXPECT_EQ(r.final_status.calibrator, "ekf");
}

// lcm.raw_batch: the raw samples travel in mag_sample_batch messages, each published before its
// samples are fed; the replay feeds them in log order and is bit-identical to the live records,
// which are the records of the per-sample log (batching changes the messages, not the outputs).
TEST_F(DaemonReplay, BatchedRawSamplesReplayBitIdentically) {
  const std::vector<hal::OutputRecord> per_sample = write_log(1600, 1, nullptr, 1000);
  for (const std::size_t batch : {std::size_t{2}, std::size_t{10}, std::size_t{1000}}) {
    SCOPED_TRACE(batch);
    std::size_t batches = 0;
    const std::vector<hal::OutputRecord> live = write_log(1600, batch, &batches, 1000);
    // 1 kHz against a 100 Hz INS: batches of up to 10 samples between two attitudes.
    EXPECT_GE(batches, 1600u / std::min<std::size_t>(batch, 10));
    EXPECT_LT(batches, 1600u / 2u + 10u);
    VectorSink replayed, logged;
    const ReplayResult r = replay_log(path_, replayed, &logged);
    EXPECT_EQ(r.mag_batches, batches);
    EXPECT_EQ(r.mag_samples, 1600u);
    EXPECT_EQ(r.decode_errors, 0u);
    EXPECT_EQ(r.sessions, 2u);
    EXPECT_EQ(r.compared, live.size());
    EXPECT_EQ(r.mismatches, 0u);
    EXPECT_EQ(r.uncompared, 0u);
    ASSERT_EQ(live.size(), per_sample.size());
    ASSERT_EQ(replayed.records.size(), live.size());
    for (std::size_t i = 0; i < live.size(); ++i) {
      ASSERT_TRUE(bit_identical(replayed.records[i], live[i])) << i;
      ASSERT_TRUE(bit_identical(live[i], per_sample[i])) << i;
    }
  }
}

// A batch is cut by every other input event and never exceeds raw_batch samples: at 1 kHz with a
// 100 Hz INS and raw_batch = 4, batches of 4, 4 and 2 between two attitudes.
TEST_F(DaemonReplay, BatchesHoldAtMostRawBatchSamplesBetweenOtherEvents) {
  std::size_t batches = 0;
  (void)write_log(2000, 4, &batches, 1000);
  std::size_t max_count = 0, samples = 0, single = 0, prev_count = 0;
  lcm::LogFile log(path_, "r");
  std::string previous;
  const lcm::LogEvent* ev = nullptr;
  while ((ev = log.readNextEvent()) != nullptr) {
    if (ev->channel == "MAGVEC_RAW_MAG") ++single;
    if (ev->channel == "MAGVEC_RAW_MAG_BATCH") {
      magvec_lcm::mag_sample_batch b{};
      ASSERT_GE(b.decode(ev->data, 0, ev->datalen), 0);
      ASSERT_EQ(static_cast<std::size_t>(b.count), b.samples.size());
      ASSERT_FALSE(b.samples.empty());
      // Two batches in a row only when the first was full.
      if (previous == "MAGVEC_RAW_MAG_BATCH") {
        EXPECT_EQ(prev_count, 4u);
      }
      max_count = std::max(max_count, b.samples.size());
      samples += b.samples.size();
      prev_count = b.samples.size();
    }
    if (ev->channel != "MAGVEC_OUTPUT") previous = ev->channel;
  }
  EXPECT_EQ(single, 0u);
  EXPECT_EQ(samples, 2000u);
  EXPECT_EQ(max_count, 4u);
  // 4 + 4 + 2 per attitude period, plus the cuts of the reload's events and of the stop.
  EXPECT_GE(batches, 2000u / 10u * 3u);
  EXPECT_LE(batches, 2000u / 10u * 3u + 3u);
}

// A batch changed in one sample by one ulp no longer replays identically.
TEST_F(DaemonReplay, AChangedSampleInABatchIsDetected) {
  write_log(400, 10, nullptr, 1000);
  const std::string changed = (dir_ / "changed.lcm").string();
  {
    lcm::LogFile in(path_, "r");
    lcm::LogFile out(changed, "w");
    int batches = 0;
    const lcm::LogEvent* ev = nullptr;
    while ((ev = in.readNextEvent()) != nullptr) {
      lcm::LogEvent copy = *ev;
      std::vector<std::uint8_t> buf;
      if (ev->channel == "MAGVEC_RAW_MAG_BATCH" && ++batches == 20) {
        magvec_lcm::mag_sample_batch b{};
        ASSERT_GE(b.decode(ev->data, 0, ev->datalen), 0);
        ASSERT_FALSE(b.samples.empty());
        b.samples.back().m_nT[2] = std::nextafter(b.samples.back().m_nT[2], 1e9);
        buf.resize(static_cast<std::size_t>(b.getEncodedSize()));
        b.encode(buf.data(), 0, static_cast<int>(buf.size()));
        copy.data = buf.data();
        copy.datalen = static_cast<std::int32_t>(buf.size());
      }
      ASSERT_EQ(out.writeEvent(&copy), 0);
    }
    ASSERT_GE(batches, 20);
  }
  VectorSink replayed;
  const ReplayResult r = replay_log(changed, replayed);
  EXPECT_EQ(r.compared, 400u);
  EXPECT_GE(r.mismatches, 1u);
}

// A batch that does not decode (truncated, count beyond its bytes) is counted and skipped, never
// half-applied.
TEST_F(DaemonReplay, AMalformedBatchIsCountedAndSkipped) {
  write_log(400, 10, nullptr, 1000);
  const std::string broken = (dir_ / "broken.lcm").string();
  std::size_t lost = 0;
  {
    lcm::LogFile in(path_, "r");
    lcm::LogFile out(broken, "w");
    int batches = 0;
    const lcm::LogEvent* ev = nullptr;
    while ((ev = in.readNextEvent()) != nullptr) {
      lcm::LogEvent copy = *ev;
      std::vector<std::uint8_t> buf(ev->datalen > 0 ? static_cast<std::size_t>(ev->datalen) : 0);
      if (ev->channel == "MAGVEC_RAW_MAG_BATCH" && ++batches % 7 == 0) {
        magvec_lcm::mag_sample_batch b{};
        ASSERT_GE(b.decode(ev->data, 0, ev->datalen), 0);
        lost += b.samples.size();
        std::memcpy(buf.data(), ev->data, buf.size());
        if (batches % 14 == 0) {
          copy.datalen -= 1;  // truncated
        } else {
          buf[8] = 0x7F;  // count far beyond the bytes
        }
        copy.data = buf.data();
      }
      ASSERT_EQ(out.writeEvent(&copy), 0);
    }
  }
  ASSERT_GT(lost, 0u);
  VectorSink replayed;
  const ReplayResult r = replay_log(broken, replayed);
  EXPECT_GE(r.decode_errors, 2u);
  EXPECT_EQ(r.mag_samples, 400u - lost);
}

// --time-offset-s: the same offset as logged replays bit-identically; another one changes the
// attitude each sample is paired with (h_n), not the compensation (h_s) of the installed
// calibration.
TEST_F(DaemonReplay, TimeOffsetOverrideChangesOnlyTheAttitudePairing) {
  const std::vector<hal::OutputRecord> live = write_log(800);
  VectorSink same;
  const ReplayResult r0 = replay_log(path_, same, nullptr, "MAGVEC_PIPELINE", 0.0);
  ASSERT_EQ(same.records.size(), live.size());
  EXPECT_EQ(r0.mismatches, 0u);
  for (std::size_t i = 0; i < live.size(); ++i)
    ASSERT_TRUE(bit_identical(same.records[i], live[i])) << i;

  VectorSink shifted;
  replay_log(path_, shifted, nullptr, "MAGVEC_PIPELINE", 0.02);
  ASSERT_EQ(shifted.records.size(), live.size());
  std::size_t hn_differ = 0, compared = 0;
  for (std::size_t i = 0; i < live.size(); ++i) {
    const hal::OutputRecord& a = shifted.records[i];
    const hal::OutputRecord& b = live[i];
    if (a.cal_id != 4u || b.cal_id != 4u) continue;  // the installed calibration only
    ++compared;
    EXPECT_EQ(a.h_s_nT, b.h_s_nT) << i;
    if (std::isfinite(a.h_n_nT[0]) && a.h_n_nT != b.h_n_nT) ++hn_differ;
  }
  EXPECT_GT(compared, 100u);
  EXPECT_GT(hn_differ, compared / 2);
}

TEST_F(DaemonReplay, AChangedSampleIsDetected) {
  write_log(400);
  // Rewrite the log with one magnetometer sample changed by one ulp.
  const std::string changed = (dir_ / "changed.lcm").string();
  {
    lcm::LogFile in(path_, "r");
    lcm::LogFile out(changed, "w");
    int mags = 0;
    const lcm::LogEvent* ev = nullptr;
    while ((ev = in.readNextEvent()) != nullptr) {
      lcm::LogEvent copy = *ev;
      std::vector<std::uint8_t> buf;
      if (ev->channel == "MAGVEC_RAW_MAG" && ++mags == 200) {
        magvec_lcm::mag_sample m{};
        ASSERT_GE(m.decode(ev->data, 0, ev->datalen), 0);
        m.m_nT[1] = std::nextafter(m.m_nT[1], 1e9);
        buf.resize(static_cast<std::size_t>(m.getEncodedSize()));
        m.encode(buf.data(), 0, static_cast<int>(buf.size()));
        copy.data = buf.data();
        copy.datalen = static_cast<std::int32_t>(buf.size());
      }
      ASSERT_EQ(out.writeEvent(&copy), 0);
    }
  }
  VectorSink replayed;
  const ReplayResult r = replay_log(changed, replayed);
  EXPECT_EQ(r.compared, 400u);
  EXPECT_GE(r.mismatches, 1u);
}

TEST_F(DaemonReplay, LogWithoutSessionIsAnError) {
  {
    lcm::LogFile log(path_, "w");
    const auto m = to_lcm(hal::MagnetometerSample{}, 1.0);
    std::vector<std::uint8_t> buf(static_cast<std::size_t>(m.getEncodedSize()));
    m.encode(buf.data(), 0, static_cast<int>(buf.size()));
    lcm::LogEvent ev{0, 1, "MAGVEC_RAW_MAG", static_cast<std::int32_t>(buf.size()), buf.data()};
    ASSERT_EQ(log.writeEvent(&ev), 0);
  }
  VectorSink s;
  EXPECT_THROW(replay_log(path_, s), ReplayError);
  EXPECT_THROW(replay_log((dir_ / "missing.lcm").string(), s), ReplayError);
}

// ---------------------------------------------------------------- real-device ordering
// DeviceFeed with fake sources: a 200 Hz magnetometer and a 100 Hz INS whose frames arrive late
// (CAN latency after the epoch), early (ahead of the magnetometer samples they bracket) or in
// bursts. The platform turns at a constant rate about a fixed axis (slerp is exact), the model is
// the identity and there is no noise: every record whose attitude was interpolated must give h_n
// exactly.

constexpr std::uint64_t kMagPeriodUs = 5'000;
constexpr std::uint64_t kInsPeriodUs = 10'000;
const core::Vec3<double> kField(-4053.0, 25022.0, -47374.0);

core::Quat<double> attitude_at(std::uint64_t t_us) {
  const double angle = 1.5 * 1e-6 * static_cast<double>(t_us);  // 86 deg/s
  return core::Quat<double>(
      Eigen::AngleAxis<double>(angle, core::Vec3<double>(0.3, -0.4, 0.866).normalized()));
}

// Everything is scheduled by arrival time; `now` is the arrival time of the last magnetometer
// sample read (the daemon's clock).
struct FakeWorld {
  std::uint64_t now{0};
  struct Arrival {
    std::uint64_t at;
    hal::AttitudeSample a;
  };
  std::deque<Arrival> ins;
  std::deque<std::pair<std::uint64_t, hal::MagnetometerSample>> mag;
};

struct FakeMag final : hal::MagnetometerSource {
  FakeWorld& w;
  hal::MagCounters c{};
  explicit FakeMag(FakeWorld& world) : w(world) {}
  hal::Status read(hal::MagnetometerSample& out, std::uint32_t) noexcept override {
    if (w.mag.empty()) return hal::Status::kTimeout;
    w.now = w.mag.front().first;
    out = w.mag.front().second;
    w.mag.pop_front();
    return hal::Status::kOk;
  }
  const hal::MagCounters& counters() const noexcept override { return c; }
};

struct FakeIns final : hal::AttitudeSource {
  FakeWorld& w;
  hal::AttitudeCounters c{};
  explicit FakeIns(FakeWorld& world) : w(world) {}
  hal::Status read(hal::AttitudeSample& out, std::uint32_t) noexcept override {
    if (w.ins.empty() || w.ins.front().at > w.now) return hal::Status::kTimeout;
    out = w.ins.front().a;
    w.ins.pop_front();
    return hal::Status::kOk;
  }
  const hal::AttitudeCounters& counters() const noexcept override { return c; }
};

// kBursts: 5 epochs at once every 50 ms, in order; kBurstsReversed: the same, each burst in
// reverse order (frames swapped in transit: reordering, not a clock jump).
enum class InsDelivery { kLate, kEarly, kBursts, kBurstsReversed };

struct FeedOutcome {
  std::size_t records{0}, interpolated{0}, extrapolated{0}, no_attitude{0};
  std::uint64_t att_reordered{0}, att_time_jumps{0};
  double max_error_nT{0};
};

FeedOutcome run_feed(InsDelivery mode, std::uint32_t horizon_us) {
  constexpr std::uint64_t kT0 = 1'000'000;
  constexpr int kMagSamples = 2000;
  constexpr std::uint32_t kCanLatencyUs = 15'000;
  FakeWorld w;
  for (std::uint64_t t = kT0 - 50'000; t < kT0 + kMagSamples * kMagPeriodUs + 100'000;
       t += kInsPeriodUs) {
    hal::AttitudeSample a;
    const core::Quat<double> q = attitude_at(t);
    a.t_us = t + kCanLatencyUs;  // receive time, as the CAN driver stamps it
    a.q_nb = {q.w(), q.x(), q.y(), q.z()};
    a.flags = hal::kAttAttitudeValid | hal::kAttHeadingValid;
    std::uint64_t at = a.t_us;  // late: received its latency after the epoch
    if (mode == InsDelivery::kEarly) at = t > 30'000 ? t - 30'000 : 0;  // magnetometer lags
    if (mode == InsDelivery::kBursts || mode == InsDelivery::kBurstsReversed)
      at = (a.t_us / 50'000 + 1) * 50'000;
    w.ins.push_back({at, a});
  }
  const bool reverse = mode == InsDelivery::kBurstsReversed;
  std::stable_sort(w.ins.begin(), w.ins.end(),
                   [reverse](const FakeWorld::Arrival& x, const FakeWorld::Arrival& y) {
                     if (x.at != y.at) return x.at < y.at;
                     return reverse && x.a.t_us > y.a.t_us;
                   });
  for (int i = 0; i < kMagSamples; ++i) {
    const std::uint64_t t = kT0 + static_cast<std::uint64_t>(i) * kMagPeriodUs;
    hal::MagnetometerSample s;
    s.t_us = t;
    const core::Vec3<double> m = core::r_bn_from_quat(attitude_at(t)) * kField;
    s.m_nT = {m(0), m(1), m(2)};
    w.mag.push_back({t + 200, s});  // DRDY edge read 0.2 ms after the conversion
  }
  VectorSink sink;
  hil::HilConfig hc;
  hc.ins_latency_comp_us = kCanLatencyUs;
  hc.horizon_us = horizon_us;
  hc.start_calibration = false;
  hil::NullCalibrator cal;
  hil::LoopCore<hil::NullCalibrator> core(cal, sink, hc, 1e6 / kMagPeriodUs, 1e6 / kInsPeriodUs);
  core.loop().set_active(core::SensorModel<double>{}, 1);
  struct Handler {
    hil::LoopCore<hil::NullCalibrator>& c;
    void on_attitude(const hal::AttitudeSample& a) { c.on_attitude(a); }
    void on_magnetometer(const hal::MagnetometerSample& s, double f) { c.on_magnetometer(s, f); }
    void on_read_error(hal::Status) { c.on_read_error(); }
  } h{core};
  FakeMag mag(w);
  FakeIns ins(w);
  DeviceFeed feed(mag, ins, std::numeric_limits<double>::quiet_NaN());
  while (feed.poll(h, 0) == FeedResult::kSample) {
  }
  w.now = std::numeric_limits<std::uint64_t>::max();  // the INS goes on after the last sample
  EXPECT_EQ(feed.poll(h, 0), FeedResult::kIdle);
  core.flush();
  FeedOutcome o;
  o.records = sink.records.size();
  o.att_reordered = core.counters().att_reordered;
  o.att_time_jumps = core.counters().att_time_jumps;
  for (const hal::OutputRecord& r : sink.records) {
    if ((r.flags & core::kOutNoAttitude) != 0) {
      ++o.no_attitude;
      continue;
    }
    const double err = (core::Vec3<double>(r.h_n_nT[0], r.h_n_nT[1], r.h_n_nT[2]) - kField).norm();
    if ((r.flags & core::kOutAttExtrapolated) != 0) {
      ++o.extrapolated;
      continue;
    }
    ++o.interpolated;
    o.max_error_nT = std::max(o.max_error_nT, err);
  }
  return o;
}

// Bursts within the horizon (the last epoch of a burst arrives up to 65 ms after the sample it
// brackets): every sample waits for it. Reversed bursts used to clear the attitude buffer as a
// "clock jump" (27 of 2000 samples without attitude); they are reordering, counted as such.
TEST(DeviceFeed, InsLateEarlyOrInBurstsIsInterpolated) {
  for (const InsDelivery mode : {InsDelivery::kLate, InsDelivery::kEarly, InsDelivery::kBursts,
                                 InsDelivery::kBurstsReversed}) {
    const FeedOutcome o = run_feed(mode, 100'000);
    SCOPED_TRACE(static_cast<int>(mode));
    EXPECT_EQ(o.records, 2000u);
    EXPECT_EQ(o.no_attitude, 0u);
    EXPECT_EQ(o.extrapolated, 0u);
    EXPECT_EQ(o.interpolated, 2000u);
    EXPECT_LT(o.max_error_nT, 1e-6);
    EXPECT_EQ(o.att_time_jumps, 0u);
    if (mode == InsDelivery::kBurstsReversed) {
      EXPECT_GE(o.att_reordered, 800u);  // 4 of every 5 epochs arrive after a later one
    } else {
      EXPECT_EQ(o.att_reordered, 0u);
    }
  }
}

// The old behaviour (each sample processed on arrival) holds the attitude with late INS frames.
TEST(DeviceFeed, ProcessingOnArrivalHoldsTheAttitude) {
  const FeedOutcome o = run_feed(InsDelivery::kLate, 0);
  EXPECT_EQ(o.records, 2000u);
  EXPECT_LT(o.interpolated, 10u);
}

// A silent scalar magnetometer (stuck or unplugged) is counted: one timeout per max_gap_us of
// magnetometer time without a reading, and the samples of the silence take the fallback F.
TEST(DeviceFeed, AScalarSilenceIsCountedAsTimeouts) {
  struct FakeScalar final : hal::ScalarSource {
    FakeWorld& w;
    std::deque<std::pair<std::uint64_t, hal::ScalarSample>> lines;  // arrival time, reading
    hal::ScalarCounters c{};
    explicit FakeScalar(FakeWorld& world) : w(world) {}
    hal::Status read(hal::ScalarSample& out, std::uint32_t) noexcept override {
      if (lines.empty() || lines.front().first > w.now) return hal::Status::kTimeout;
      out = lines.front().second;
      lines.pop_front();
      ++c.samples;
      return hal::Status::kOk;
    }
    const hal::ScalarCounters& counters() const noexcept override { return c; }
  };
  struct Handler {
    std::vector<double> f;
    void on_attitude(const hal::AttitudeSample&) {}
    void on_magnetometer(const hal::MagnetometerSample&, double f_nT) { f.push_back(f_nT); }
    void on_read_error(hal::Status) {}
  };
  auto run = [](bool silence, std::uint64_t* timeouts, std::uint64_t* fallback) {
    constexpr std::uint64_t kT0 = 1'000'000;
    FakeWorld w;
    FakeMag mag(w);
    FakeIns ins(w);
    FakeScalar scalar(w);
    for (std::uint64_t t = kT0; t < kT0 + 2'000'000; t += kMagPeriodUs) {
      hal::MagnetometerSample s;
      s.t_us = t;
      w.mag.push_back({t, s});
    }
    // 10 Hz readings, each arriving 20 ms after its time; silent from 0.5 s to 1.4 s.
    for (std::uint64_t t = kT0; t < kT0 + 2'100'000; t += 100'000) {
      if (silence && t > kT0 + 500'000 && t < kT0 + 1'400'000) continue;
      hal::ScalarSample r;
      r.t_us = t;
      r.f_nT = 50'000;
      scalar.lines.push_back({t + 20'000, r});
    }
    pipeline::ScalarAlignerConfig align;  // max_gap_us 250 ms
    align.fallback_nT = 49'000;
    DeviceFeed feed(mag, ins, scalar, align);
    Handler h;
    while (feed.poll(h, 0) == FeedResult::kSample) {
    }
    w.now = std::numeric_limits<std::uint64_t>::max();
    (void)feed.poll(h, 0);
    feed.flush(h);
    EXPECT_EQ(h.f.size(), 400u);
    *timeouts = feed.scalar_timeouts();
    *fallback = feed.aligner_counters()->fallback;
  };
  std::uint64_t timeouts = 0, fallback = 0;
  run(false, &timeouts, &fallback);
  EXPECT_EQ(timeouts, 0u);
  EXPECT_EQ(fallback, 0u);
  // 0.9 s without a reading (0.5 s to 1.4 s): counted at 0.75, 1.0 and 1.25 s.
  run(true, &timeouts, &fallback);
  EXPECT_EQ(timeouts, 3u);
  EXPECT_GT(fallback, 0u);
}

// The time offset of an installed calibration reaches the pipeline through SET_ACTIVE (logged,
// so a replay applies it too); a configured devices.ins.time_offset_s fixes it.
TEST(DaemonPipeline, TimeOffsetFromSetActiveUnlessConfigured) {
  VectorSink sink;
  EventPipeline ep(sink);
  ep.apply(session_start_event(1, fast_config_text("none")));
  EXPECT_EQ(ep.pipeline()->time_offset_s(), 0.0);
  ep.apply(set_active_event(2, core::SensorModel<double>{}, 3, -0.025));
  EXPECT_DOUBLE_EQ(ep.pipeline()->time_offset_s(), -0.025);
  std::string text = fast_config_text("none");
  text.replace(text.find("time_offset_s = nan"), 19, "time_offset_s = 0.004");
  ep.apply(session_start_event(3, text));
  EXPECT_DOUBLE_EQ(ep.pipeline()->time_offset_s(), 0.004);
  ep.apply(set_active_event(4, core::SensorModel<double>{}, 3, -0.025));
  EXPECT_DOUBLE_EQ(ep.pipeline()->time_offset_s(), 0.004);
}

// REFERENCE (the geomagnetic model's F from now on, real mode without a scalar magnetometer):
// the loop validates and flags by the model's sigma, and a calibration in progress starts over;
// SET_ACTIVE carries the flag of a model-referenced calibration (cal.json after a restart).
TEST(DaemonPipeline, ReferenceEventAndModelReferencedActiveCalibration) {
  const magvec_lcm::pipeline_event e = reference_event(7, "WMM2025", 138.0);
  EXPECT_TRUE(e.kind == magvec_lcm::pipeline_event::REFERENCE);
  EXPECT_DOUBLE_EQ(reference_sigma_from(e), 138.0);
  magvec_lcm::pipeline_event corrupt = e;
  corrupt.config_toml = "model = WMM2025\nreference_sigma_nT = -5\n";
  EXPECT_TRUE(std::isnan(reference_sigma_from(corrupt)));

  VectorSink sink;
  EventPipeline ep(sink);
  ep.apply(session_start_event(1, fast_config_text("li")));
  ep.apply(start_calibration_event(2));
  ep.apply(corrupt);  // ignored: no sigma
  EXPECT_EQ(ep.pipeline()->state(), core::CalState::kCollecting);
  ep.apply(e);
  EXPECT_EQ(ep.pipeline()->state(), core::CalState::kCollecting);

  OutputQuality q;
  q.sigma_f_nT = 138.5;
  q.model_reference = true;
  const magvec_lcm::pipeline_event active =
      set_active_event(3, core::SensorModel<double>{}, 4, 0, q);
  EXPECT_TRUE(output_quality_from(active).model_reference);
  EXPECT_FALSE(
      output_quality_from(set_active_event(3, core::SensorModel<double>{}, 4)).model_reference);
  ep.apply(active);
  EXPECT_TRUE(ep.pipeline()->status().output.model_reference);
  hal::MagnetometerSample s;
  s.t_us = 1000;
  s.m_nT = {20000.0, 10000.0, -40000.0};
  ep.pipeline()->on_magnetometer(s, 49000.0);
  ep.pipeline()->flush();
  ASSERT_FALSE(sink.records.empty());
  EXPECT_NE(sink.records.back().flags & core::kOutModelReference, 0u);
  EXPECT_DOUBLE_EQ(sink.records.back().sigma_f_nT, 138.5);
}

}  // namespace
}  // namespace magvec::host::daemon
