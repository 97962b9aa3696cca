// Host-in-the-loop harness: minutes of simulated survey through simulated devices, the real
// drivers, the AttitudeBuffer and the SensorLoop with a scripted (fake) calibrator; record count,
// timestamps, flags, counters for every injected fault, and zero heap allocations per step.
#include "magvec/host/hil/hil_session.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

#include "support/alloc_counter.hpp"

namespace {

using namespace magvec;
using drivers::sim::MagLink;
using drivers::sim::ScenarioConfig;
using drivers::sim::SimRigConfig;
using drivers::sim::Simulator;
using host::hil::HilConfig;
using host::hil::HilSession;

// Test double: collects `needed` samples that have an attitude and a scalar reference, then
// "solves" to the model it was given (the truth, or a wrong one). Not an estimator.
struct ScriptedCalibrator {
  core::SensorModel<double> result;
  std::uint32_t needed{2000};
  std::uint32_t used{0};
  std::uint32_t begins{0};
  void begin() noexcept {
    used = 0;
    ++begins;
  }
  core::CalibratorAdd add(const core::Vec3<double>& m, double f,
                          const core::Mat3<double>* r) noexcept {
    if (!m.allFinite() || !std::isfinite(f) || r == nullptr) return core::CalibratorAdd::kRejected;
    ++used;
    return core::CalibratorAdd::kUsed;
  }
  double progress() const noexcept { return static_cast<double>(used) / needed; }
  bool ready() const noexcept { return used >= needed; }
  std::uint32_t solves{0};
  core::CalibratorSolve solve(core::SensorModel<double>* out) noexcept {
    ++solves;
    *out = result;
    return {true, 0};
  }
};

struct MemorySink final : hal::RecordSink {
  std::vector<hal::OutputRecord> records;
  explicit MemorySink(std::size_t capacity) { records.reserve(capacity); }
  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    if (records.size() == records.capacity())
      return hal::Status::kOverflow;  // never grow inside the loop
    records.push_back(r);
    return hal::Status::kOk;
  }
};

ScenarioConfig survey_minutes(double minutes) {
  ScenarioConfig c = drivers::sim::scenario_survey();  // 200 Hz, 0.3 nT, 0.015 deg
  c.num_samples = static_cast<std::uint32_t>(minutes * 60.0 * c.rate_hz);
  return c;
}

SimRigConfig spi_rig() {
  SimRigConfig r;
  r.link = MagLink::kSpi;
  r.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  return r;
}

HilConfig hil_config() {
  HilConfig h;
  h.loop.noise_nT = 0.3;
  return h;
}

double sim_time(const hal::OutputRecord& r, const SimRigConfig& rc) {
  return (static_cast<double>(r.t_us) - static_cast<double>(rc.time.epoch_us)) * 1e-6;
}

TEST(HilSession, ThreeMinutesWithFaultsThroughTheWholeChain) {
  ScenarioConfig sc = survey_minutes(3.0);
  sc.dropout_probability = 0.01;
  Simulator sim(sc, 42);
  SimRigConfig rc = spi_rig();
  rc.adc.faults.crc_error_probability = 0.01;
  rc.adc.faults.saturation_probability = 0.005;
  rc.ins.faults.corrupt_probability = 0.01;
  rc.ins.faults.gap_start_s = 100.0;
  rc.ins.faults.gap_length_s = 1.0;
  rc.ins.faults.invalid_start_s = 120.0;
  rc.ins.faults.invalid_length_s = 2.0;
  ScriptedCalibrator cal;
  cal.result = sc.truth;
  MemorySink sink(40000);
  HilSession<ScriptedCalibrator> hil(sim, rc, cal, sink, hil_config());
  ASSERT_EQ(hil.init(), hal::Status::kOk);
  EXPECT_EQ(hil.run(), 36000u);

  const auto& adc = hil.rig().adc().injected();
  const auto& ins = hil.rig().ins().injected();
  const auto& hc = hil.counters();
  const auto& health = hil.loop().health();
  // Record count: one per conversion except those lost to CRC errors.
  EXPECT_GT(adc.crc_corrupted, 250u);
  EXPECT_EQ(hil.mag_counters().crc_errors, adc.crc_corrupted);
  EXPECT_EQ(hc.mag_read_errors, adc.crc_corrupted);
  EXPECT_EQ(sink.records.size(), 36000u - adc.crc_corrupted);
  EXPECT_EQ(hc.records, sink.records.size());
  EXPECT_EQ(hc.sink_errors, 0u);
  // Dropouts (not-fresh conversions) -> dropout records; saturation -> device-error records.
  EXPECT_GT(adc.not_fresh, 250u);
  // A not-fresh frame can itself be lost to a CRC error; every other one reaches the loop.
  EXPECT_LE(hc.mag_not_fresh, adc.not_fresh);
  EXPECT_GE(hc.mag_not_fresh + adc.crc_corrupted, adc.not_fresh);
  std::uint64_t dropout_records = 0, device_error_records = 0, no_att_records = 0;
  std::uint64_t prev_t = 0;
  for (const auto& r : sink.records) {
    ASSERT_GT(r.t_us, prev_t);
    ASSERT_EQ((r.t_us - rc.time.epoch_us) % 5000u, 0u);  // on the 200 Hz grid
    prev_t = r.t_us;
    const bool dropout = (r.flags & core::kOutDropout) != 0;
    dropout_records += dropout && (r.flags & core::kOutDeviceError) == 0 ? 1u : 0u;
    device_error_records += (r.flags & core::kOutDeviceError) != 0 ? 1u : 0u;
    if (dropout) {
      EXPECT_TRUE(std::isnan(r.f_nT));
      continue;
    }
    const double t = sim_time(r, rc);
    const bool in_window = (t > 99.99 && t < 101.01) || (t > 119.99 && t < 122.01);
    if ((r.flags & core::kOutNoAttitude) != 0) {
      ++no_att_records;
      EXPECT_TRUE(in_window) << "no attitude at t = " << t;
      EXPECT_TRUE(std::isnan(r.h_n_nT[0]));
    } else {
      EXPECT_FALSE((t >= 100.01 && t < 100.99) || (t >= 120.01 && t < 121.99))
          << "attitude inside an INS outage at t = " << t;
      EXPECT_TRUE(std::isfinite(r.h_n_nT[0]));
    }
  }
  EXPECT_EQ(dropout_records, health.dropouts);
  EXPECT_EQ(hc.mag_not_fresh, health.dropouts);
  EXPECT_GT(device_error_records, 100u);
  EXPECT_EQ(device_error_records, health.device_errors);
  EXPECT_EQ(hil.mag_counters().saturated, adc.saturated_frames);
  // Saturated frames are device errors, except a full-scale code held through a dropout (then
  // the sample is a dropout).
  EXPECT_LE(device_error_records, adc.saturated_frames);
  EXPECT_GE(device_error_records + hc.mag_not_fresh, adc.saturated_frames);
  EXPECT_EQ(no_att_records, health.no_attitude);
  EXPECT_GE(no_att_records, 3u * 200u - 20u);  // 3 s of outage at 200 Hz, minus dropouts
  EXPECT_LE(no_att_records, 3u * 200u + 20u);
  // INS: corrupted frames, invalid epochs, the gap.
  EXPECT_GT(ins.corrupted_frames, 50u);
  EXPECT_EQ(hil.attitude_counters().malformed, ins.corrupted_frames);
  EXPECT_EQ(hc.att_samples, ins.epochs - ins.corrupted_epochs);
  EXPECT_EQ(ins.gap_epochs, 100u);
  EXPECT_EQ(ins.invalid_epochs, 200u);
  EXPECT_LE(hc.att_invalid, ins.invalid_epochs);
  EXPECT_GE(hc.att_invalid + ins.corrupted_epochs, ins.invalid_epochs);
  EXPECT_GE(hc.att_gaps, 2u);  // the gap and the invalid window (plus lost epochs)
  EXPECT_EQ(hc.mag_time_jumps, 0u);
  // The ADC never skips a DRDY edge: the only holes in the cadence are frames lost to CRC errors
  // (the last sample of the run has no successor to reveal a hole after it).
  EXPECT_LE(hc.mag_missing, adc.crc_corrupted);
  EXPECT_GE(hc.mag_missing + 1, adc.crc_corrupted);
  // Calibration in the loop: uncalibrated until the scripted solve validates, then cal_id 1.
  EXPECT_EQ(hil.loop().state(), core::CalState::kApplied)
      << core::cal_failure_name(hil.loop().failure()) << ", validation rms "
      << hil.loop().last_validation_rms_nT() << " nT";
  EXPECT_EQ(health.calibrations_applied, 1u);
  EXPECT_EQ(sink.records.front().cal_id, 0u);
  EXPECT_NE(sink.records.front().flags & core::kOutUncalibrated, 0u);
  EXPECT_NE(sink.records.front().flags & core::kOutCalibrating, 0u);
  EXPECT_EQ(sink.records.back().cal_id, 1u);
  EXPECT_EQ(sink.records.back().flags & (core::kOutUncalibrated | core::kOutCalibrating), 0u);
  // With the (scripted) true model, calibrated intensity is the true |h| within the noise.
  double sum_sq = 0;
  std::uint64_t n = 0;
  const double f_true = sc.h_n_nT.norm();
  for (const auto& r : sink.records) {
    if (r.cal_id != 1 || (r.flags & (core::kOutDropout | core::kOutDeviceError)) != 0) continue;
    sum_sq += (r.f_nT - f_true) * (r.f_nT - f_true);
    ++n;
  }
  ASSERT_GT(n, 30000u);
  const double rms = std::sqrt(sum_sq / static_cast<double>(n));
  EXPECT_LT(rms, 0.3 * 1.1);  // ~ noise / sqrt(1) along the field direction
  EXPECT_GT(rms, 0.3 * 0.8);
}

TEST(HilSession, WrongCandidateFailsValidationAndStaysUncalibrated) {
  ScenarioConfig sc = survey_minutes(0.5);
  Simulator sim(sc, 5);
  const SimRigConfig rc = spi_rig();
  ScriptedCalibrator cal;
  cal.result = sc.truth;
  cal.result.o = cal.result.o + core::Vec3<double>(50, 0, 0);  // a wrong offset
  MemorySink sink(7000);
  HilSession<ScriptedCalibrator> hil(sim, rc, cal, sink, hil_config());
  ASSERT_EQ(hil.init(), hal::Status::kOk);
  hil.run();
  EXPECT_EQ(hil.loop().state(), core::CalState::kFailed);
  EXPECT_EQ(hil.loop().failure(), core::CalFailure::kValidationFailed);
  EXPECT_EQ(sink.records.back().cal_id, 0u);
  EXPECT_NE(sink.records.back().flags & core::kOutUncalibrated, 0u);
}

// The MCU image's rule (HilConfig::solve_install_records, pipeline::SolveSchedule): the loop
// raises a ticket on one record, keeps compensating with the active (identity) model for exactly
// N more records and installs the solve's result on the N-th; the held-out validation then
// applies it. Inline (0), the loop solves on the record after the ticket's.
TEST(HilSession, SolveResultGoesInAFixedNumberOfRecordsAfterTheTicket) {
  for (const std::uint32_t n : {0u, 8u, 40u}) {
    SCOPED_TRACE(n);
    ScenarioConfig sc = survey_minutes(0.5);
    Simulator sim(sc, 5);
    const SimRigConfig rc = spi_rig();
    ScriptedCalibrator cal;
    cal.result = sc.truth;
    cal.needed = 1500;
    // Record by record: the loop's state and ticket as each record reached the sink.
    struct StateSink final : hal::RecordSink {
      const core::SensorLoop<double, ScriptedCalibrator>* loop{nullptr};
      std::vector<core::CalState> states;
      std::uint32_t ticket_record{0};
      hal::Status emit(const hal::OutputRecord&) noexcept override {
        states.push_back(loop->state());
        if (ticket_record == 0 && loop->solve_ticket() == 1)
          ticket_record = static_cast<std::uint32_t>(states.size());
        return hal::Status::kOk;
      }
    } sink;
    sink.states.reserve(7000);
    HilConfig hc = hil_config();
    hc.solve_install_records = n;
    HilSession<ScriptedCalibrator> hil(sim, rc, cal, sink, hc);
    sink.loop = &hil.loop();
    ASSERT_EQ(hil.init(), hal::Status::kOk);
    hil.run();
    const std::vector<core::CalState>& states = sink.states;
    const std::uint32_t ticket_record = sink.ticket_record;
    ASSERT_GT(ticket_record, 0u);
    ASSERT_GT(states.size(), ticket_record + n);
    EXPECT_EQ(cal.solves, 1u);
    EXPECT_EQ(hil.loop().state(), core::CalState::kApplied);
    if (n == 0) {
      // Inline: the loop solves on the sample after the ticket's.
      EXPECT_EQ(states[ticket_record - 1], core::CalState::kSolving);
      EXPECT_EQ(states[ticket_record], core::CalState::kValidating);
      continue;
    }
    // Records ticket .. ticket + n - 1 (1-based) leave in kSolving, the next ones validating.
    for (std::uint32_t k = ticket_record; k < ticket_record + n; ++k)
      EXPECT_EQ(states[k - 1], core::CalState::kSolving) << "record " << k;
    EXPECT_EQ(states[ticket_record + n - 1], core::CalState::kValidating);
  }
}

TEST(HilSession, SerialLinkCountsGarbageChecksumsAndMissingLines) {
  ScenarioConfig sc = survey_minutes(1.0);
  sc.dropout_probability = 0.01;
  Simulator sim(sc, 8);
  SimRigConfig rc;
  rc.link = MagLink::kSerial;
  rc.serial.faults.garbage_probability = 0.02;
  rc.serial.faults.bad_checksum_probability = 0.01;
  host::hil::NullCalibrator cal;
  MemorySink sink(13000);
  HilConfig hc = hil_config();
  hc.start_calibration = false;
  HilSession<host::hil::NullCalibrator> hil(sim, rc, cal, sink, hc);
  ASSERT_EQ(hil.init(), hal::Status::kOk);
  EXPECT_EQ(hil.run(), 12000u);
  const auto& inj = hil.rig().serial().injected();
  EXPECT_EQ(hil.mag_counters().garbage_bytes, inj.garbage_bytes);
  EXPECT_EQ(hil.mag_counters().crc_errors, inj.bad_checksums);
  EXPECT_EQ(sink.records.size(), inj.lines - inj.bad_checksums);
  // A missing line (dropout or bad checksum) shows as a gap in the 200 Hz cadence.
  EXPECT_EQ(hil.counters().mag_missing, inj.dropouts + inj.bad_checksums);
  EXPECT_EQ(hil.loop().state(), core::CalState::kIdle);
  for (const auto& r : sink.records) {
    ASSERT_EQ(r.cal_id, 0u);
    ASSERT_NE(r.flags & core::kOutUncalibrated, 0u);
  }
}

TEST(HilSession, ClockJumpIsDetectedOnBothStreams) {
  ScenarioConfig sc = survey_minutes(0.25);
  Simulator sim(sc, 9);
  SimRigConfig rc = spi_rig();
  rc.time.jump_at_s = 5.0;
  rc.time.jump_us = -300'000;
  host::hil::NullCalibrator cal;
  MemorySink sink(4000);
  HilConfig hc = hil_config();
  hc.start_calibration = false;
  HilSession<host::hil::NullCalibrator> hil(sim, rc, cal, sink, hc);
  ASSERT_EQ(hil.init(), hal::Status::kOk);
  hil.run();
  EXPECT_EQ(hil.rig().clock_jumps_injected(), 1u);
  EXPECT_EQ(hil.counters().mag_time_jumps, 1u);
  EXPECT_EQ(hil.counters().att_time_jumps, 1u);
  // After the jump the buffer restarted on the new time base: attitude is usable again.
  EXPECT_EQ(sink.records.back().flags & core::kOutNoAttitude, 0u);
}

TEST(HilSession, NoHeapAllocationPerStepAfterStartUp) {
  ScenarioConfig sc = survey_minutes(1.0);
  sc.dropout_probability = 0.01;
  Simulator sim(sc, 10);
  SimRigConfig rc = spi_rig();
  rc.adc.faults.crc_error_probability = 0.01;
  rc.ins.faults.corrupt_probability = 0.01;
  ScriptedCalibrator cal;
  cal.result = sc.truth;
  MemorySink sink(13000);
  HilSession<ScriptedCalibrator> hil(sim, rc, cal, sink, hil_config());
  ASSERT_EQ(hil.init(), hal::Status::kOk);
  hil.run(1000);
  const magvec::test::AllocationScope scope;
  const std::uint64_t steps = hil.run(10000);
  EXPECT_EQ(scope.count(), 0u);
  EXPECT_EQ(steps, 10000u);
  EXPECT_EQ(hil.loop().state(), core::CalState::kApplied);  // calibration ran inside the scope
}

}  // namespace
