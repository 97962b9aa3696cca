// The counted fault matrix: every fault the simulated rig can inject, alone, through the one
// sample pipeline (HilSession: simulated devices -> real codecs -> LoopCore -> SensorLoop), with
// the simulator's true calibration installed. For each fault:
//   - every counter equals what the FaultLedger derives from the injection (counter_checks);
//   - the counters that move against a fault-free run of the same seed are exactly the declared
//     ones (nothing else moves);
//   - the outputs stay right: one record per delivered sample, dropouts NaN + kOutDropout, and
//     every record the fault did not touch bit-identical to the fault-free run (magnetometer
//     faults), or with h_s and |h| bit-identical (attitude and clock faults touch only h_n), or
//     every record bit-identical (faults the drivers must absorb: INS duplicates).
// FaultMatrix.Table runs them all once more and prints the README's table (markdown); with
// MAGVEC_FAULT_TABLE=FILE it also writes it there.
#include <gtest/gtest.h>

#include <cctype>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <functional>
#include <iostream>
#include <map>
#include <memory>
#include <set>
#include <sstream>
#include <string>
#include <vector>

#include "magvec/core/sensor_loop.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/hil/fault_ledger.hpp"
#include "magvec/host/hil/hil_session.hpp"

namespace magvec::host::hil {
namespace {

using drivers::sim::MagLink;
using Session = HilSession<NullCalibrator>;

constexpr std::uint32_t kSamples = 20'000;  // 20 s at 1 kHz, 2000 INS epochs
constexpr double kRateHz = 1000;
constexpr std::size_t kCases = 15;  // rows of the matrix (cases())

class StoreSink final : public hal::RecordSink {
 public:
  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    records.push_back(r);
    return hal::Status::kOk;
  }
  std::vector<hal::OutputRecord> records;
};

enum class Touches : std::uint8_t {
  kMagnetometer,  // records of untouched samples bit-identical to the fault-free run
  kAttitude,      // every record's raw, h_s and |h| bit-identical; h_n may change
  kNothing,       // every record bit-identical to the fault-free run
};

struct FaultCase {
  std::string name;
  std::string item;  // the --faults item of `magvec run` / `magvec soak`
  MagLink link;
  std::function<void(drivers::sim::ScenarioConfig&, drivers::sim::SimRigConfig&)> inject;
  std::function<std::uint64_t(Session&, const ExpectedCounts&)> injected;
  std::set<std::string> moves;  // every counter that differs from the fault-free run
  Touches touches;
  std::string behaviour;
  // A channel held at one code in [held_start_s, held_start_s + held_length_s) (stuck): records
  // there that are not flagged carry the held code on that axis, the other axes untouched.
  std::uint8_t held_axis{0};
  double held_start_s{0};
  double held_length_s{0};
  // A counter that must move by exactly the injected count (one count per injected fault), an
  // independent check of the ledger, which derives its counts from what the devices delivered.
  std::string exact_counter{};
};

struct RunResult {
  std::map<std::string, std::uint64_t> counters;
  std::vector<CounterCheck> checks;
  std::vector<hal::OutputRecord> records;
  std::vector<std::uint32_t> sample_flags;  // simulator flags of each record's sample
  std::vector<double> sample_t_s;           // simulation time of each record's sample
  std::uint64_t injected{0};
};

drivers::sim::ScenarioConfig scenario() {
  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.rate_hz = kRateHz;
  sc.num_samples = kSamples;
  return sc;
}

drivers::sim::SimRigConfig rig_config(MagLink link) {
  drivers::sim::SimRigConfig rc;
  rc.link = link;
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  rc.adc.seed = 11;
  rc.serial.seed = 12;
  rc.ins.seed = 13;
  return rc;
}

RunResult run_case(const FaultCase* fc, MagLink link) {
  drivers::sim::ScenarioConfig sc = scenario();
  drivers::sim::SimRigConfig rc = rig_config(link);
  if (fc != nullptr) fc->inject(sc, rc);
  drivers::sim::Simulator sim(sc, 7);
  HilConfig hc;
  hc.loop.noise_nT = sc.mag_noise_nT;
  hc.start_calibration = false;
  NullCalibrator cal;
  StoreSink sink;
  sink.records.reserve(kSamples);
  auto session = std::make_unique<Session>(sim, rc, cal, sink, hc);
  session->loop().set_active(sc.truth, 1);
  EXPECT_EQ(session->init(), hal::Status::kOk);
  FaultLedger ledger(rc, sc.rate_hz, hc);
  std::map<std::uint64_t, drivers::sim::SimSample> sample_by_t;
  while (session->step()) {
    ledger.observe(session->rig());
    sample_by_t[session->rig().host_us(session->rig().last().t_s)] = session->rig().last();
  }
  RunResult r;
  r.checks = counter_checks(*session, ledger.expected());
  for (const CounterCheck& c : r.checks)
    r.counters[c.counter] = c.counted;
  const auto& pc = session->counters();
  r.counters["horizon_expired"] = pc.horizon_expired;
  r.counters["extrapolated"] = pc.extrapolated;
  r.counters["max_queued"] = pc.max_queued;
  r.counters["loop.no_attitude"] = session->loop().health().no_attitude;
  r.counters["att.ignored"] = session->attitude_counters().ignored;
  r.records = std::move(sink.records);
  for (const hal::OutputRecord& rec : r.records) {
    const auto it = sample_by_t.find(rec.t_us);
    r.sample_flags.push_back(it == sample_by_t.end() ? 0u : it->second.flags);
    r.sample_t_s.push_back(it == sample_by_t.end() ? -1.0 : it->second.t_s);
  }
  if (fc != nullptr) r.injected = fc->injected(*session, ledger.expected());
  return r;
}

bool same(double a, double b) {
  return a == b || (std::isnan(a) && std::isnan(b));
}

bool same_field(const hal::OutputRecord& a, const hal::OutputRecord& b) {
  bool s = same(a.f_nT, b.f_nT);
  for (std::size_t k = 0; k < 3; ++k)
    s = s && same(a.raw_nT[k], b.raw_nT[k]) && same(a.h_s_nT[k], b.h_s_nT[k]);
  return s;
}

bool same_record(const hal::OutputRecord& a, const hal::OutputRecord& b) {
  bool s = same_field(a, b) && a.t_us == b.t_us && a.flags == b.flags && a.cal_id == b.cal_id;
  for (std::size_t k = 0; k < 3; ++k)
    s = s && same(a.h_n_nT[k], b.h_n_nT[k]);
  return s;
}

std::vector<FaultCase> cases() {
  using drivers::sim::ScenarioConfig;
  using drivers::sim::SimRigConfig;
  const std::set<std::string> lost_sample = {"records",        "loop.samples",    "mag.samples",
                                             "mag.crc_errors", "mag_read_errors", "mag_missing"};
  std::vector<FaultCase> v;
  v.push_back(
      {"ADC frame CRC error", "crc=2e-3", MagLink::kSpi,
       [](ScenarioConfig&, SimRigConfig& rc) { rc.adc.faults.crc_error_probability = 2e-3; },
       [](Session& s, const ExpectedCounts&) { return s.rig().adc().injected().crc_corrupted; },
       lost_sample, Touches::kMagnetometer,
       "no record for the sample (read error); the next step counts it missing"});
  v.push_back(
      {"ADC channel saturated",
       "saturation=2e-3",
       MagLink::kSpi,
       [](ScenarioConfig&, SimRigConfig& rc) { rc.adc.faults.saturation_probability = 2e-3; },
       [](Session& s, const ExpectedCounts&) { return s.rig().adc().injected().saturated_frames; },
       {"mag.saturated", "loop.device_errors"},
       Touches::kMagnetometer,
       "record flagged kOutDeviceError + kOutDropout, values NaN"});
  v.push_back({"ADC channel stuck (x repeats its code 0.5 s)",
               "stuck=5:0.5",
               MagLink::kSpi,
               [](ScenarioConfig&, SimRigConfig& rc) {
                 rc.adc.faults.stuck_start_s = 5;
                 rc.adc.faults.stuck_length_s = 0.5;
               },
               [](Session& s, const ExpectedCounts&) {
                 return std::uint64_t{s.rig().adc().injected().stuck_conversions};
               },
               {"mag.stuck", "loop.device_errors"},
               Touches::kMagnetometer,
               "from the 64th equal code on (stuck_count; the last good conversion is the run's "
               "first) flagged kOutDeviceError + kOutDropout, values NaN; the 62 records before "
               "cannot be told from a steady field and carry the held code on x",
               0,
               5,
               0.5});
  v.push_back({"ADC reset mid-stream",
               "adc-reset=2e-3",
               MagLink::kSpi,
               [](ScenarioConfig&, SimRigConfig& rc) { rc.adc.faults.reset_probability = 2e-3; },
               [](Session& s, const ExpectedCounts&) {
                 return std::uint64_t{s.rig().adc().injected().resets};
               },
               {"mag.device_resets", "loop.device_errors"},
               Touches::kMagnetometer,
               "the sample with STATUS.RESET flagged kOutDeviceError + kOutDropout, values NaN "
               "(converted at the default gain); the driver re-initialises the ADC (RESET, GAIN1, "
               "MODE.RESET cleared) in the same read: the next conversion is good",
               0,
               0,
               0,
               "mag.device_resets"});
  v.push_back({"fluxgate dropout (ADC not fresh)",
               "dropout=2e-3",
               MagLink::kSpi,
               [](ScenarioConfig& sc, SimRigConfig&) { sc.dropout_probability = 2e-3; },
               [](Session& s, const ExpectedCounts&) { return s.rig().adc().injected().not_fresh; },
               {"mag_not_fresh", "loop.dropouts"},
               Touches::kMagnetometer,
               "record with NaN h_s, h_n, \\|h\\| and kOutDropout"});
  v.push_back({"spike on one axis (1000 nT)",
               "spike=2e-3",
               MagLink::kSpi,
               [](ScenarioConfig& sc, SimRigConfig&) {
                 sc.spike_probability = 2e-3;
                 sc.spike_amplitude_nT = 1000;
               },
               [](Session&, const ExpectedCounts& e) { return e.spikes + e.spikes_ambiguous; },
               {"spikes"},
               Touches::kMagnetometer,
               "record flagged kOutSpike, values kept (the spike screen: the sample stands out "
               "from both neighbours); never fed to a calibrator"});
  v.push_back(
      {"serial garbage before a line",
       "garbage=5e-2",
       MagLink::kSerial,
       [](ScenarioConfig&, SimRigConfig& rc) { rc.serial.faults.garbage_probability = 5e-2; },
       [](Session& s, const ExpectedCounts&) { return s.rig().serial().injected().garbage_bytes; },
       {"mag.garbage_bytes"},
       Touches::kMagnetometer,
       "skipped by the decoder; every record unchanged"});
  v.push_back(
      {"serial line checksum wrong", "bad-checksum=2e-3", MagLink::kSerial,
       [](ScenarioConfig&, SimRigConfig& rc) { rc.serial.faults.bad_checksum_probability = 2e-3; },
       [](Session& s, const ExpectedCounts&) { return s.rig().serial().injected().bad_checksums; },
       lost_sample, Touches::kMagnetometer,
       "no record (read() returns kCrcError, as for an ADC frame); the next step counts it "
       "missing"});
  v.push_back(
      {"serial fluxgate dropout (line not sent)",
       "dropout=2e-3 (serial)",
       MagLink::kSerial,
       [](ScenarioConfig& sc, SimRigConfig&) { sc.dropout_probability = 2e-3; },
       [](Session& s, const ExpectedCounts&) { return s.rig().serial().injected().dropouts; },
       {"records", "loop.samples", "mag.samples", "mag_missing"},
       Touches::kMagnetometer,
       "no record; the next step counts it missing"});
  v.push_back(
      {"INS CAN frame truncated",
       "ins-corrupt=2e-3",
       MagLink::kSpi,
       [](ScenarioConfig&, SimRigConfig& rc) { rc.ins.faults.corrupt_probability = 2e-3; },
       [](Session& s, const ExpectedCounts&) { return s.rig().ins().injected().corrupted_frames; },
       {"att.malformed", "att.missing_time", "att.samples", "att_samples", "att_gaps",
        "max_queued"},
       Touches::kAttitude,
       "epoch lost when its time or attitude frame is hit: attitude interpolated across "
       "the 20-ms gap"});
  v.push_back(
      {"INS frame received twice or epoch repeated",
       "ins-duplicate=5e-2",
       MagLink::kSpi,
       [](ScenarioConfig&, SimRigConfig& rc) { rc.ins.faults.duplicate_probability = 5e-2; },
       [](Session& s, const ExpectedCounts&) {
         const auto& i = s.rig().ins().injected();
         return std::uint64_t{i.duplicated_frames} + i.repeated_epochs;
       },
       {"att.duplicates"},
       Touches::kNothing,
       "dropped by the SBG decoder (a frame identical to the previous one; an epoch whose "
       "INS time was sampled already): every record bit-identical",
       0,
       0,
       0,
       "att.duplicates"});
  v.push_back(
      {"INS outage (no CAN frames)",
       "ins-gap=8:1",
       MagLink::kSpi,
       [](ScenarioConfig&, SimRigConfig& rc) {
         rc.ins.faults.gap_start_s = 8;
         rc.ins.faults.gap_length_s = 1;
       },
       [](Session& s, const ExpectedCounts&) { return s.rig().ins().injected().gap_epochs; },
       {"att.samples", "att_samples", "att_gaps", "horizon_expired", "extrapolated", "max_queued",
        "loop.no_attitude"},
       Touches::kAttitude,
       "records wait the 50-ms horizon, then kOutAttExtrapolated, then kOutNoAttitude "
       "(h_n NaN) until the INS is back"});
  v.push_back(
      {"INS attitude invalid",
       "ins-invalid=12:1",
       MagLink::kSpi,
       [](ScenarioConfig&, SimRigConfig& rc) {
         rc.ins.faults.invalid_start_s = 12;
         rc.ins.faults.invalid_length_s = 1;
       },
       [](Session& s, const ExpectedCounts&) { return s.rig().ins().injected().invalid_epochs; },
       {"att_invalid", "extrapolated", "loop.no_attitude"},
       Touches::kAttitude,
       "the last valid attitude is extrapolated briefly, then kOutNoAttitude (h_n NaN) for "
       "the window; h_s and \\|h\\| unchanged"});
  v.push_back({"clock steps back 1 s",
               "clock-jump=10:-1",
               MagLink::kSpi,
               [](ScenarioConfig&, SimRigConfig& rc) {
                 rc.time.jump_at_s = 10;
                 rc.time.jump_us = -1'000'000;
               },
               [](Session& s, const ExpectedCounts&) { return s.rig().clock_jumps_injected(); },
               {"mag_time_jumps", "att_time_jumps", "horizon_expired", "extrapolated"},
               Touches::kAttitude,
               "queue flushed, INS buffer cleared: a few records extrapolated until the next INS "
               "epoch"});
  v.push_back({"clock steps forward 0.5 s",
               "clock-jump=10:0.5",
               MagLink::kSpi,
               [](ScenarioConfig&, SimRigConfig& rc) {
                 rc.time.jump_at_s = 10;
                 rc.time.jump_us = 500'000;
               },
               [](Session& s, const ExpectedCounts&) { return s.rig().clock_jumps_injected(); },
               {"mag_time_jumps", "att_gaps", "horizon_expired", "extrapolated"},
               Touches::kAttitude,
               "counted; the records across the step are extrapolated"});
  return v;
}

std::set<std::string> moved(const RunResult& base, const RunResult& r) {
  std::set<std::string> m;
  for (const auto& [name, value] : r.counters)
    if (base.counters.at(name) != value) m.insert(name);
  return m;
}

std::string join(const std::set<std::string>& s) {
  std::string out;
  for (const std::string& x : s)
    out += (out.empty() ? "" : ", ") + x;
  return out.empty() ? "(none)" : out;
}

class FaultMatrix : public ::testing::TestWithParam<std::size_t> {};

TEST(FaultMatrixBaseline, FaultFreeRunsCountNothing) {
  for (MagLink link : {MagLink::kSpi, MagLink::kSerial}) {
    const RunResult base = run_case(nullptr, link);
    for (const CounterCheck& c : base.checks)
      EXPECT_TRUE(c.ok()) << c.counter << ": " << c.counted << " vs " << c.expected;
    EXPECT_EQ(base.records.size(), kSamples);
    EXPECT_EQ(base.counters.at("records"), kSamples);
    for (const hal::OutputRecord& r : base.records)
      ASSERT_EQ(r.flags & (core::kOutDropout | core::kOutDeviceError), 0u);
  }
}

// The checker must be able to fail: a wrong expectation is flagged, on that counter only.
TEST(FaultMatrixBaseline, CounterChecksFlagAWrongExpectation) {
  FaultCase crc = cases().front();
  drivers::sim::ScenarioConfig sc = scenario();
  drivers::sim::SimRigConfig rc = rig_config(MagLink::kSpi);
  crc.inject(sc, rc);
  drivers::sim::Simulator sim(sc, 7);
  HilConfig hc;
  hc.start_calibration = false;
  NullCalibrator cal;
  StoreSink sink;
  auto session = std::make_unique<Session>(sim, rc, cal, sink, hc);
  ASSERT_EQ(session->init(), hal::Status::kOk);
  FaultLedger ledger(rc, sc.rate_hz, hc);
  while (session->step())
    ledger.observe(session->rig());
  ASSERT_TRUE(all_ok(counter_checks(*session, ledger.expected())));
  ExpectedCounts wrong = ledger.expected();
  wrong.mag_missing += 1;
  const std::vector<CounterCheck> checks = counter_checks(*session, wrong);
  EXPECT_FALSE(all_ok(checks));
  for (const CounterCheck& c : checks)
    EXPECT_EQ(c.ok(), c.counter != "mag_missing") << c.counter;
}

TEST_P(FaultMatrix, CountedExactlyNothingElseMovesOutputsRight) {
  const FaultCase fc = cases()[GetParam()];
  SCOPED_TRACE(fc.name);
  const RunResult base = run_case(nullptr, fc.link);
  const RunResult r = run_case(&fc, fc.link);
  EXPECT_GT(r.injected, 0u) << "the fault was not injected: the row would prove nothing";
  for (const CounterCheck& c : r.checks)
    EXPECT_TRUE(c.ok()) << c.counter << " (" << c.fault << "): counted " << c.counted
                        << ", expected " << c.expected;
  EXPECT_EQ(moved(base, r), fc.moves);
  if (!fc.exact_counter.empty()) {
    EXPECT_EQ(r.counters.at(fc.exact_counter) - base.counters.at(fc.exact_counter), r.injected)
        << fc.exact_counter;
  }

  // Outputs.
  std::map<std::uint64_t, const hal::OutputRecord*> base_by_t;
  for (const hal::OutputRecord& b : base.records)
    base_by_t[b.t_us] = &b;
  std::uint64_t dropouts = 0, device_errors = 0, spikes = 0, spikes_flagged = 0, untouched = 0;
  std::uint64_t held = 0;
  double held_nT = 0;
  for (std::size_t i = 0; i < r.records.size(); ++i) {
    const hal::OutputRecord& rec = r.records[i];
    const double t_s = r.sample_t_s[i];
    if (fc.held_length_s > 0 && t_s >= fc.held_start_s &&
        t_s < fc.held_start_s + fc.held_length_s &&
        (rec.flags & (core::kOutDropout | core::kOutDeviceError)) == 0) {
      // Not yet detected: the held code on its axis, the other axes as without the fault.
      const auto it = base_by_t.find(rec.t_us);
      ASSERT_NE(it, base_by_t.end());
      if (held == 0) held_nT = rec.raw_nT[fc.held_axis];
      EXPECT_EQ(rec.raw_nT[fc.held_axis], held_nT) << "not the held code at t_us " << rec.t_us;
      for (std::size_t k = 0; k < 3; ++k) {
        if (k != fc.held_axis) {
          EXPECT_EQ(rec.raw_nT[k], it->second->raw_nT[k]);
        }
      }
      ++held;
      continue;
    }
    if ((rec.flags & (core::kOutDropout | core::kOutDeviceError)) != 0) {
      // A dropout or a device error (then also kOutDropout) has no output values.
      ++((rec.flags & core::kOutDeviceError) != 0 ? device_errors : dropouts);
      EXPECT_TRUE(std::isnan(rec.f_nT) && std::isnan(rec.h_s_nT[0]) && std::isnan(rec.h_n_nT[0]))
          << "dropout record with a number at t_us " << rec.t_us;
      continue;
    }
    if ((rec.flags & core::kOutNoAttitude) != 0) {
      EXPECT_TRUE(std::isnan(rec.h_n_nT[0]) && std::isnan(rec.h_n_nT[1]) &&
                  std::isnan(rec.h_n_nT[2]));
    }
    const bool flagged = (rec.flags & core::kOutSpike) != 0;
    if ((r.sample_flags[i] & drivers::sim::kFlagSpike) != 0) {
      ++spikes;
      spikes_flagged += flagged ? 1u : 0u;
      continue;
    }
    EXPECT_FALSE(flagged) << "a clean sample flagged as a spike at t_us " << rec.t_us;
    if (fc.touches == Touches::kNothing) {
      ASSERT_EQ(r.records.size(), base.records.size());
      EXPECT_TRUE(same_record(rec, base.records[i])) << "record changed at record " << i;
    } else if (fc.touches == Touches::kMagnetometer) {
      const auto it = base_by_t.find(rec.t_us);
      ASSERT_NE(it, base_by_t.end()) << "record at a time the fault-free run has none";
      EXPECT_TRUE(same_record(rec, *it->second)) << "record changed at t_us " << rec.t_us;
    } else {
      // No magnetometer sample is lost: record i belongs to sample i in both runs.
      ASSERT_EQ(r.records.size(), base.records.size());
      EXPECT_TRUE(same_field(rec, base.records[i])) << "h_s or |h| changed at record " << i;
    }
    ++untouched;
  }
  EXPECT_EQ(spikes, fc.item.rfind("spike", 0) == 0 ? r.injected : 0u);
  EXPECT_EQ(spikes_flagged, r.counters.at("spikes"));
  EXPECT_EQ(dropouts, r.counters.at("loop.dropouts"));
  EXPECT_EQ(device_errors, r.counters.at("loop.device_errors"));
  EXPECT_GT(untouched, r.records.size() / 2);
  if (fc.held_length_s > 0) {
    // The run starts with the last good conversion: stuck_count - 2 stuck ones pass unflagged.
    const std::uint32_t stuck_count = drivers::Ads131FluxgateConfig{}.stuck_count;
    EXPECT_EQ(held, stuck_count - 2);
    EXPECT_EQ(r.counters.at("mag.stuck"), r.injected - held);
  }
}

INSTANTIATE_TEST_SUITE_P(EveryFault, FaultMatrix, ::testing::Range<std::size_t>(0, kCases),
                         [](const ::testing::TestParamInfo<std::size_t>& p) {
                           std::string n = cases()[p.param].name;
                           std::string out;
                           for (char ch : n)
                             if (std::isalnum(static_cast<unsigned char>(ch)) != 0) out += ch;
                           return out;
                         });

TEST(FaultMatrixTable, CasesAreAllInstantiated) {
  EXPECT_EQ(cases().size(), kCases);
}

// The README table, from the runs themselves.
TEST(FaultMatrixTable, Markdown) {
  std::ostringstream md;
  md << "| fault | `--faults` | injected (20 s, 1 kHz) | counted by (= the ledger's count) | "
        "also moves | output |\n|---|---|---|---|---|---|\n";
  for (const FaultCase& fc : cases()) {
    const RunResult base = run_case(nullptr, fc.link);
    const RunResult r = run_case(&fc, fc.link);
    std::set<std::string> counted_by, consequences;
    for (const std::string& m : moved(base, r)) {
      const bool flow = m == "records" || m == "loop.samples" || m == "mag.samples" ||
                        m == "att.samples" || m == "att_samples" || m == "horizon_expired" ||
                        m == "extrapolated" || m == "max_queued" || m == "loop.no_attitude";
      (flow ? consequences : counted_by).insert(m);
    }
    std::string counted;
    for (const std::string& m : counted_by) {
      const std::uint64_t delta = r.counters.at(m) - base.counters.at(m);
      counted += (counted.empty() ? "" : ", ") + m + " " + std::to_string(delta);
    }
    if (counted.empty()) counted = "**none**";
    md << "| " << fc.name << " | `" << fc.item << "` | " << r.injected << " | " << counted << " | "
       << join(consequences) << " | " << fc.behaviour << " |\n";
    EXPECT_TRUE(all_ok(r.checks)) << fc.name;
  }
  std::cout << md.str();
  if (const char* path = std::getenv("MAGVEC_FAULT_TABLE"); path != nullptr) {
    std::ofstream f(path);
    f << md.str();
    EXPECT_TRUE(f.good()) << path;
  }
}

}  // namespace
}  // namespace magvec::host::hil
