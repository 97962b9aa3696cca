// `magvec soak --hours H`: a long run through the one sample pipeline (host::hil::HilSession:
// simulated ADS131M04 + SBG INS speaking the real bytes -> the real codecs -> LoopCore /
// DevicePipeline -> SensorLoop), in simulated time as fast as the CPU allows, with faults at
// realistic rates, that checks what a survey of many hours needs:
//   - no drift: per interval (an hour by default) the mean and RMS error of E, N, U and |h|
//     against the simulator's TRUE field of each record's own sample (records leave the pipeline
//     after the delayed fusion horizon, so the truth waits in a ring keyed by the sample's host
//     time), hourly means within a statistical bound of the first hour's (soak_checks.hpp);
//   - flat memory: VmRSS at the end of every interval, growth after the first within a slack;
//   - flat time per sample: wall and CPU time per sample over the first and last 10 % (reported,
//     not judged: the machine is shared);
//   - every counter equal to what was injected (host/hil/fault_ledger.hpp).
// The simulator's true calibration is installed at the start (cal_id 1, no calibrator runs), so
// the output error is the pipeline's, not a calibration's. Exit 0 when every check passes, 3
// when one fails; --json FILE writes the whole report (atomically).
#include <time.h>

#include <CLI/CLI.hpp>
#include <algorithm>
#include <array>
#include <chrono>
#include <cmath>
#include <cstdio>
#include <fstream>
#include <iomanip>
#include <iostream>
#include <limits>
#include <memory>
#include <nlohmann/json.hpp>
#include <sstream>
#include <string>
#include <vector>

#include "commands.hpp"
#include "fault_spec.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/hil/fault_ledger.hpp"
#include "magvec/host/hil/hil_session.hpp"
#include "magvec/host/io/csv.hpp"
#include "soak_checks.hpp"

namespace magvec::host::cli {
namespace {

struct SoakOptions {
  double hours = 24;
  double rate_hz = 1000;
  std::uint64_t seed = 1;
  std::string faults = "default";
  std::string link = "spi";  // spi: ADS131M04 frames; serial: ASCII fluxgate lines
  double interval_s = 3600;
  std::string json;
};

using Session = hil::HilSession<hil::NullCalibrator>;

// Realistic rates for a day on a survey platform: an ADC CRC error about every 100 s, a fluxgate
// dropout as often, a saturated conversion every 17 min, a spike every 100 s, a truncated CAN
// frame every ~20 s; one 2-s INS outage, one 10-s attitude-invalid window and one backwards clock
// step (NTP) of 1 s at a quarter, half and three quarters of the run. Over the serial link the
// ADC faults give way to the line's: garbage before a line about every 10 s, a wrong checksum
// about every 100 s.
std::string default_faults(double duration_s, bool serial) {
  std::ostringstream os;
  os << std::setprecision(10)
     << (serial ? "garbage=1e-4,bad-checksum=1e-5" : "crc=1e-5,saturation=1e-6")
     << ",dropout=1e-5,spike=1e-5,ins-corrupt=1e-5"
     << ",ins-gap=" << 0.25 * duration_s << ":2"
     << ",ins-invalid=" << 0.5 * duration_s << ":10"
     << ",clock-jump=" << 0.75 * duration_s << ":-1";
  return os.str();
}

std::int64_t rss_kib() {
  std::ifstream f("/proc/self/status");
  std::string line;
  while (std::getline(f, line)) {
    if (line.rfind("VmRSS:", 0) == 0) return std::stoll(line.substr(6));
  }
  return -1;
}

double cpu_s() {
  timespec ts{};
  clock_gettime(CLOCK_PROCESS_CPUTIME_ID, &ts);
  return static_cast<double>(ts.tv_sec) + 1e-9 * static_cast<double>(ts.tv_nsec);
}

double wall_s() {
  using Clock = std::chrono::steady_clock;
  return std::chrono::duration<double>(Clock::now().time_since_epoch()).count();
}

// Scores every record against the truth of its own sample and checks the output of the records a
// fault produced (dropouts: NaN values and kOutDropout).
class SoakSink final : public hal::RecordSink {
 public:
  SoakSink(double interval_s, std::size_t intervals) : interval_s_(interval_s) {
    stats.resize(intervals);
  }
  void attach(Session* s) noexcept { session_ = s; }

  // After every step: the truth of the sample just simulated, until its record leaves.
  void remember(const drivers::sim::SimSample& s, std::uint64_t t_us) noexcept {
    if (count_ == kRing) {  // more pending than the pipeline can hold: a bug, counted
      head_ = (head_ + 1) % kRing;
      --count_;
      ++ring_overflows;
    }
    ring_[(head_ + count_) % kRing] = Truth{t_us, s.t_s, s.h_n_true_nT, s.flags};
    ++count_;
  }

  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    ++records;
    Truth t{};
    if (!take(r.t_us, &t)) {
      const drivers::sim::SimSample& last = session_->rig().last();
      if (session_->rig().host_us(last.t_s) != r.t_us) {
        ++unmatched;
        return hal::Status::kOk;
      }
      t = Truth{r.t_us, last.t_s, last.h_n_true_nT, last.flags};  // emitted within its own step
    }
    score(r, t);
    return hal::Status::kOk;
  }

  std::vector<IntervalStats> stats;
  std::uint64_t records{0};
  std::uint64_t unmatched{0};  // records without the truth of their sample
  std::uint64_t ring_overflows{0};
  std::uint64_t dropout_records{0};  // kOutDropout without kOutDeviceError
  std::uint64_t dropout_not_nan{0};  // kOutDropout with a number in an output: wrong
  std::uint64_t device_error_records{0};
  std::uint64_t no_attitude_records{0};
  std::uint64_t extrapolated_records{0};
  std::uint64_t spike_records{0};
  std::uint64_t wrong_cal_records{0};   // cal_id other than the installed 1
  std::uint64_t not_finite_records{0};  // scored records with a NaN/inf value
  std::uint64_t scored{0};

 private:
  struct Truth {
    std::uint64_t t_us;
    double t_s;
    core::Vec3<double> h_n;
    std::uint32_t flags;
  };
  static constexpr std::size_t kRing = 1024;  // > the pipeline's queue (256)

  // Records leave in sample order; samples without a record (rejected frames) are skipped.
  bool take(std::uint64_t t_us, Truth* out) noexcept {
    for (std::size_t i = 0; i < count_; ++i) {
      const Truth& t = ring_[(head_ + i) % kRing];
      if (t.t_us != t_us) continue;
      *out = t;
      head_ = (head_ + i + 1) % kRing;
      count_ -= i + 1;
      return true;
    }
    return false;
  }

  void score(const hal::OutputRecord& r, const Truth& t) noexcept {
    if (r.cal_id != 1) ++wrong_cal_records;
    if ((r.flags & (core::kOutDropout | core::kOutDeviceError)) != 0) {
      // A dropout or a device error (then also kOutDropout) has no output values: all NaN.
      bool nan = std::isnan(r.f_nT);
      for (std::size_t k = 0; k < 3; ++k)
        nan = nan && std::isnan(r.h_s_nT[k]) && std::isnan(r.h_n_nT[k]);
      if (!nan) ++dropout_not_nan;
      ++((r.flags & core::kOutDeviceError) != 0 ? device_error_records : dropout_records);
      return;
    }
    if ((r.flags & core::kOutNoAttitude) != 0) {
      ++no_attitude_records;
      return;
    }
    if ((r.flags & core::kOutAttExtrapolated) != 0) {
      ++extrapolated_records;  // an INS outage, not the steady state the means describe
      return;
    }
    if ((t.flags & drivers::sim::kFlagSpike) != 0) {
      ++spike_records;
      return;
    }
    const double e[kComponents] = {r.h_n_nT[0] - t.h_n(0), r.h_n_nT[1] - t.h_n(1),
                                   r.h_n_nT[2] - t.h_n(2), r.f_nT - t.h_n.norm()};
    for (double x : e) {
      if (!std::isfinite(x)) {
        ++not_finite_records;
        return;
      }
    }
    auto i = static_cast<std::size_t>(t.t_s / interval_s_);
    if (i >= stats.size()) i = stats.size() - 1;
    for (std::size_t c = 0; c < kComponents; ++c)
      stats[i].err[c].add(e[c]);
    ++scored;
  }

  double interval_s_;
  Session* session_{nullptr};
  std::array<Truth, kRing> ring_{};
  std::size_t head_{0};
  std::size_t count_{0};
};

// Seconds per sample of the simulator alone and of the simulated devices (simulator + byte
// encoding), over n samples of the same scenario: tells whether the simulation is the bottleneck.
struct SimCost {
  double sim_us{0};
  double rig_us{0};
};

SimCost measure_sim_cost(const drivers::sim::ScenarioConfig& sc,
                         const drivers::sim::SimRigConfig& rc, std::uint64_t seed,
                         std::uint32_t n) {
  drivers::sim::ScenarioConfig short_sc = sc;
  short_sc.num_samples = n;
  SimCost c;
  {
    drivers::sim::Simulator sim(short_sc, seed);
    drivers::sim::SimSample s;
    const double t0 = cpu_s();
    while (sim.next(&s)) {
    }
    c.sim_us = (cpu_s() - t0) / n * 1e6;
  }
  {
    drivers::sim::Simulator sim(short_sc, seed);
    auto rig = std::make_unique<drivers::sim::SimRig>(sim, rc);
    hal::CanFrame f;
    hal::EdgeEvent e;
    const double t0 = cpu_s();
    while (rig->step()) {
      // Drain what the devices produced so their queues do not fill (no decoding).
      while (rig->ins().receive(f, 0) == hal::Status::kOk) {
      }
      while (rig->adc().wait_edge(e, 0) == hal::Status::kOk) {
      }
    }
    c.rig_us = (cpu_s() - t0) / n * 1e6;
  }
  return c;
}

std::string fixed(double v, int digits) {
  std::ostringstream os;
  os << std::fixed << std::setprecision(digits) << v;
  return os.str();
}

nlohmann::json stats_json(const ErrorStats& s) {
  return {{"n", s.count()}, {"mean_nT", s.mean()}, {"rms_nT", s.rms()}, {"sd_nT", s.sd()}};
}

void run(const SoakOptions& o) {
  const double duration_s = o.hours * 3600.0;
  const double samples_d = std::round(duration_s * o.rate_hz);
  if (samples_d < 10) throw CLI::ValidationError("--hours", "shorter than 10 samples at --rate-hz");
  if (samples_d > 4e9) throw CLI::ValidationError("--hours", "more than 4e9 samples");
  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.name = "soak (survey racetrack)";
  sc.rate_hz = o.rate_hz;
  sc.num_samples = static_cast<std::uint32_t>(samples_d);
  drivers::sim::SimRigConfig rc;
  const bool serial = o.link == "serial";
  rc.link = serial ? drivers::sim::MagLink::kSerial : drivers::sim::MagLink::kSpi;
  // Fluxgate electronics 100 uT/V into the ADC at gain 1, as `magvec run`.
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  rc.adc.seed = o.seed ^ 0xA1;
  rc.serial.seed = o.seed ^ 0xB2;
  rc.ins.seed = o.seed ^ 0xC3;
  const std::string faults = o.faults == "default" ? default_faults(duration_s, serial)
                             : o.faults == "none"  ? std::string()
                                                   : o.faults;
  apply_faults(faults, &sc, &rc);
  if (o.rate_hz <= rc.ins.rate_hz)
    throw CLI::ValidationError("--rate-hz", "must exceed the INS rate (100 Hz)");

  hil::HilConfig hc;
  hc.loop.noise_nT = sc.mag_noise_nT;
  hc.start_calibration = false;

  const auto intervals =
      static_cast<std::size_t>(std::max(1.0, std::ceil(duration_s / o.interval_s - 1e-9)));
  SoakSink sink(o.interval_s, intervals);
  // The measurement of the simulation's own cost runs first, on the same scenario (1 % of the
  // run, at most 10^6 samples), so it does not disturb the soak's time series.
  const auto probe_n =
      static_cast<std::uint32_t>(std::clamp(samples_d / 100.0, std::min(samples_d, 1000.0), 1e6));
  const SimCost sim_cost = measure_sim_cost(sc, rc, o.seed, probe_n);

  drivers::sim::Simulator sim(sc, o.seed);
  hil::NullCalibrator cal;
  auto session = std::make_unique<Session>(sim, rc, cal, sink, hc);
  sink.attach(session.get());
  session->loop().set_active(sc.truth, 1);
  if (const hal::Status s = session->init(); s != hal::Status::kOk)
    throw std::runtime_error(std::string("device initialisation failed: ") + hal::to_string(s));
  hil::FaultLedger ledger(rc, o.rate_hz, hc);

  const std::uint64_t total = sc.num_samples;
  const std::uint64_t tenth = std::max<std::uint64_t>(1, total / 10);
  const auto per_interval = static_cast<std::uint64_t>(std::llround(o.interval_s * o.rate_hz));
  std::vector<std::int64_t> rss(intervals, -1);
  std::cout << "magvec soak: " << o.hours << " h at " << o.rate_hz << " Hz = " << total
            << " samples, " << o.link << " link, seed " << o.seed << ", faults "
            << (faults.empty() ? "none" : faults) << "\n"
            << std::flush;

  const double wall0 = wall_s();
  const double cpu0 = cpu_s();
  double wall_a = 0, cpu_a = 0, wall_b = 0, cpu_b = 0;
  std::uint64_t k = 0;
  while (session->step()) {
    ledger.observe(session->rig());
    sink.remember(session->rig().last(), session->rig().host_us(session->rig().last().t_s));
    ++k;
    if (k == tenth) {
      wall_a = wall_s();
      cpu_a = cpu_s();
    }
    if (k == total - tenth) {
      wall_b = wall_s();
      cpu_b = cpu_s();
    }
    if (per_interval > 0 && k % per_interval == 0 && k / per_interval <= intervals) {
      rss[k / per_interval - 1] = rss_kib();
      if (k / per_interval < intervals || k == total) {
        std::cerr << "soak: " << fixed(static_cast<double>(k) / o.rate_hz / 3600.0, 2)
                  << " h simulated, " << fixed(wall_s() - wall0, 0) << " s\n";
      }
    }
  }
  const double wall1 = wall_s();
  const double cpu1 = cpu_s();
  if (rss.back() < 0) rss.back() = rss_kib();  // the last, partial interval

  // ---- checks
  std::vector<hil::CounterCheck> counters = hil::counter_checks(*session, ledger.expected());
  const hil::ExpectedCounts& e = ledger.expected();
  counters.push_back(
      {"sink: kOutDropout records", "simulator dropout", sink.dropout_records, e.mag_not_fresh});
  counters.push_back(
      {"sink: dropout/error records not NaN", "(must not happen)", sink.dropout_not_nan, 0});
  counters.push_back({"sink: kOutDeviceError records", "saturated samples (also kOutDropout)",
                      sink.device_error_records, e.mag_device_errors});
  counters.push_back({"sink: records", "one per delivered sample", sink.records, e.mag_delivered});
  counters.push_back({"sink: records without their truth", "(must not happen)", sink.unmatched, 0});
  counters.push_back({"sink: truth ring overflows", "(must not happen)", sink.ring_overflows, 0});
  counters.push_back(
      {"sink: records not on cal_id 1", "(must not happen)", sink.wrong_cal_records, 0});
  counters.push_back(
      {"sink: scored records not finite", "(must not happen)", sink.not_finite_records, 0});
  const auto& hc_counters = session->counters();
  const auto& health = session->loop().health();
  counters.push_back({"sink: kOutNoAttitude records", "loop.no_attitude", sink.no_attitude_records,
                      health.no_attitude});
  counters.push_back({"sink: kOutAttExtrapolated records", "extrapolated",
                      sink.extrapolated_records, hc_counters.extrapolated});

  for (std::size_t i = 0; i < intervals; ++i)
    sink.stats[i].rss_kib = rss[i];
  const double ins_rate = rc.ins.rate_hz;
  const std::vector<DriftCheck> drift = drift_checks(sink.stats, o.rate_hz, ins_rate);
  const RssCheck rss_result = rss_check(rss);
  bool drift_ok = true;
  for (const DriftCheck& d : drift)
    drift_ok = drift_ok && d.ok();
  const bool counters_ok = hil::all_ok(counters);
  const bool ok = drift_ok && counters_ok && rss_result.ok();

  const double n_first = static_cast<double>(tenth);
  const double wall_first_us = (wall_a - wall0) / n_first * 1e6;
  const double cpu_first_us = (cpu_a - cpu0) / n_first * 1e6;
  const double wall_last_us = (wall1 - wall_b) / n_first * 1e6;
  const double cpu_last_us = (cpu1 - cpu_b) / n_first * 1e6;
  const double cpu_total_us = (cpu1 - cpu0) / static_cast<double>(k) * 1e6;
  const double samples_per_s = static_cast<double>(k) / (wall1 - wall0);

  // ---- human summary
  const bool hourly = o.interval_s == 3600;
  std::cout << "\nper " << (hourly ? "hour" : fixed(o.interval_s, 3) + " s")
            << ": error vs the true field, mean / RMS [nT] (scored records: calibrated, with "
               "attitude, no fault flag)\n";
  std::cout << std::setw(6) << "#" << std::setw(11) << "records";
  for (const char* n : kComponentNames)
    std::cout << std::setw(20) << (std::string(n) + " mean/rms");
  std::cout << std::setw(12) << "RSS [KiB]\n";
  for (std::size_t i = 0; i < intervals; ++i) {
    const IntervalStats& st = sink.stats[i];
    std::cout << std::setw(6) << i + 1 << std::setw(11) << st.err[0].count();
    for (const ErrorStats& s : st.err)
      std::cout << std::setw(20) << (fixed(s.mean(), 4) + " / " + fixed(s.rms(), 3));
    std::cout << std::setw(11) << st.rss_kib << "\n";
  }
  double worst_ratio = 0;
  const DriftCheck* worst = nullptr;
  for (const DriftCheck& d : drift) {
    const double r = d.bound_nT > 0 ? std::fabs(d.diff_nT) / d.bound_nT : 1e9;
    if (r >= worst_ratio) {
      worst_ratio = r;
      worst = &d;
    }
  }
  std::cout << "drift (mean of each interval - first; bound " << kDriftSigmas
            << " sigma of the difference from the noise and sample count): ";
  if (worst == nullptr) {
    std::cout << "one interval only, nothing to compare\n";
  } else {
    std::cout << (drift_ok ? "PASS" : "FAIL") << ", worst " << kComponentNames[worst->component]
              << " interval " << worst->interval + 1 << ": " << fixed(worst->diff_nT, 4)
              << " nT vs bound " << fixed(worst->bound_nT, 4) << " nT (" << fixed(worst_ratio, 2)
              << " of the bound)\n";
    for (std::size_t c = 0; c < kComponents; ++c) {
      double max_diff = 0, bound = 0;
      for (const DriftCheck& d : drift) {
        if (d.component != c) continue;
        if (std::fabs(d.diff_nT) >= max_diff) {
          max_diff = std::fabs(d.diff_nT);
          bound = d.bound_nT;
        }
      }
      std::cout << "  " << kComponentNames[c] << ": largest |diff| " << fixed(max_diff, 4)
                << " nT (bound there " << fixed(bound, 4) << " nT)\n";
    }
    for (const DriftCheck& d : drift) {
      if (!d.ok())
        std::cout << "  FAIL " << kComponentNames[d.component] << " interval " << d.interval + 1
                  << ": " << d.diff_nT << " nT, bound " << d.bound_nT << " nT\n";
    }
  }
  std::cout << "memory: VmRSS " << rss_result.first_kib << " KiB after the first interval, "
            << rss_result.last_kib << " KiB at the end, largest growth " << rss_result.growth_kib
            << " KiB (slack " << rss_result.slack_kib
            << "): " << (rss_result.ok() ? "PASS" : "FAIL") << "\n";
  std::cout << "time per sample: first 10 % " << fixed(wall_first_us, 3) << " us wall / "
            << fixed(cpu_first_us, 3) << " us CPU, last 10 % " << fixed(wall_last_us, 3)
            << " us wall / " << fixed(cpu_last_us, 3) << " us CPU (last/first CPU "
            << fixed(cpu_last_us / cpu_first_us, 3) << "); " << fixed(samples_per_s, 0)
            << " samples/s overall, " << fixed(cpu_total_us, 3) << " us CPU/sample\n";
  std::cout << "  of which simulation: simulator " << fixed(sim_cost.sim_us, 3)
            << " us/sample, simulated devices incl. simulator " << fixed(sim_cost.rig_us, 3)
            << " us/sample (" << fixed(100.0 * sim_cost.rig_us / cpu_total_us, 0)
            << " % of the CPU time per sample; measured on " << probe_n << " samples)\n";
  std::cout << "counters (counted vs expected from the injection):\n";
  for (const hil::CounterCheck& c : counters) {
    std::cout << "  " << (c.ok() ? "ok  " : "FAIL") << " " << std::left << std::setw(38)
              << c.counter << std::right << std::setw(12) << c.counted << std::setw(12)
              << c.expected << "  " << c.fault << "\n";
  }
  std::cout << "  info: horizon_expired " << hc_counters.horizon_expired << ", extrapolated "
            << hc_counters.extrapolated << ", no_attitude " << health.no_attitude
            << ", spikes the screen may or may not flag (next to another fault) "
            << e.spikes_ambiguous << ", clock jumps " << session->rig().clock_jumps_injected()
            << ", max_queued " << hc_counters.max_queued << ", scored records " << sink.scored
            << "\n";
  std::cout << "soak: " << (ok ? "PASS" : "FAIL") << " (drift " << (drift_ok ? "ok" : "FAIL")
            << ", memory " << (rss_result.ok() ? "ok" : "FAIL") << ", counters "
            << (counters_ok ? "ok" : "FAIL") << ")\n";

  if (!o.json.empty()) {
    nlohmann::json j;
    j["command"] = "magvec soak";
    j["hours"] = o.hours;
    j["rate_hz"] = o.rate_hz;
    j["samples"] = k;
    j["seed"] = o.seed;
    j["faults"] = faults;
    j["interval_s"] = o.interval_s;
    j["ok"] = ok;
    nlohmann::json iv = nlohmann::json::array();
    for (std::size_t i = 0; i < intervals; ++i) {
      nlohmann::json x;
      x["index"] = i + 1;
      x["rss_kib"] = sink.stats[i].rss_kib;
      for (std::size_t c = 0; c < kComponents; ++c)
        x["error"][kComponentNames[c]] = stats_json(sink.stats[i].err[c]);
      iv.push_back(x);
    }
    j["intervals"] = iv;
    nlohmann::json dj = nlohmann::json::array();
    for (const DriftCheck& d : drift)
      dj.push_back({{"interval", d.interval + 1},
                    {"component", kComponentNames[d.component]},
                    {"diff_nT", d.diff_nT},
                    {"bound_nT", d.bound_nT},
                    {"ok", d.ok()}});
    j["drift"] = {{"sigmas", kDriftSigmas}, {"ok", drift_ok}, {"checks", dj}};
    j["rss"] = {{"first_kib", rss_result.first_kib},
                {"last_kib", rss_result.last_kib},
                {"growth_kib", rss_result.growth_kib},
                {"slack_kib", rss_result.slack_kib},
                {"ok", rss_result.ok()}};
    j["timing"] = {{"wall_us_per_sample_first_10pct", wall_first_us},
                   {"cpu_us_per_sample_first_10pct", cpu_first_us},
                   {"wall_us_per_sample_last_10pct", wall_last_us},
                   {"cpu_us_per_sample_last_10pct", cpu_last_us},
                   {"cpu_us_per_sample", cpu_total_us},
                   {"samples_per_s", samples_per_s},
                   {"wall_s", wall1 - wall0},
                   {"simulator_cpu_us_per_sample", sim_cost.sim_us},
                   {"sim_devices_cpu_us_per_sample", sim_cost.rig_us}};
    nlohmann::json cj = nlohmann::json::array();
    for (const hil::CounterCheck& c : counters)
      cj.push_back({{"counter", c.counter},
                    {"fault", c.fault},
                    {"counted", c.counted},
                    {"expected", c.expected},
                    {"slack", c.slack},
                    {"ok", c.ok()}});
    j["counters"] = cj;
    j["info"] = {{"horizon_expired", hc_counters.horizon_expired},
                 {"extrapolated", hc_counters.extrapolated},
                 {"no_attitude", health.no_attitude},
                 {"spikes_ambiguous", e.spikes_ambiguous},
                 {"clock_jumps", session->rig().clock_jumps_injected()},
                 {"scored_records", sink.scored}};
    io::AtomicFile file(o.json);
    file.write(j.dump(2) + "\n");
    file.commit();
  }
  if (!ok) throw CommandExit(3, "soak: a check failed (see above)");
}

}  // namespace

void register_soak(CLI::App& app) {
  auto opt = std::make_shared<SoakOptions>();
  CLI::App* sub = app.add_subcommand(
      "soak",
      "Long accelerated run through the sample pipeline with faults: drift, memory, time per "
      "sample and every counter against the injection (exit 3 when a check fails)");
  sub->add_option("--hours", opt->hours, "Simulated hours (fractional allowed)")
      ->check(CLI::Range(1e-4, 1000.0))
      ->capture_default_str();
  sub->add_option("--rate-hz", opt->rate_hz, "Magnetometer rate")
      ->check(CLI::Range(200.0, 10000.0))
      ->capture_default_str();
  sub->add_option("--seed", opt->seed, "Random seed")->capture_default_str();
  sub->add_option(
         "--faults", opt->faults,
         std::string("'default' (realistic rates, see the summary), 'none', or ") + kFaultsHelp)
      ->capture_default_str();
  sub->add_option("--link", opt->link, "Magnetometer link (the default faults follow it)")
      ->check(CLI::IsMember({"spi", "serial"}))
      ->capture_default_str();
  sub->add_option("--interval-s", opt->interval_s,
                  "Length of a reporting interval (drift and memory are judged per interval)")
      ->check(CLI::Range(1.0, 1e6))
      ->capture_default_str();
  sub->add_option("--json", opt->json, "Report file (JSON, written atomically)");
  sub->callback([opt] { run(*opt); });
}

}  // namespace magvec::host::cli
