// Host-in-the-loop harness (DESIGN.md "Host-in-the-loop simulation", issue 5 item 7):
//   simulated devices (drivers/sim SimRig: ADS131M04 on SPI + DRDY or serial ASCII fluxgate, SBG
//   INS on CAN) -> the REAL drivers (Ads131Fluxgate / SerialFluxgate / CanAttitudeSource, i.e.
//   the byte codecs) -> core::AttitudeBuffer (every valid INS sample inserted; queried at every
//   magnetometer time, slerp) -> core::SensorLoop<double, Calibrator> -> hal::RecordSink.
// Simulated time only: each step() advances the rig by one magnetometer sample, no sleeping, so a
// run is as fast as the CPU allows and deterministic from the scenario seed.
//
// Plugging a calibrator: HilSession is templated on the SensorLoop's Calibrator concept
// (sensor_loop.hpp: begin/add/progress/ready/solve). Construct the calibrator yourself and pass it
// by reference; HilConfig::start_calibration starts a calibration at the first sample (the loop's
// state machine then collects, solves, validates on held-out samples and applies). A calibration
// loaded from a file is installed with session.loop().set_active(model, id) before running.
//
// Scalar reference: the calibrators need |h| per sample (f_ref_nT). The harness takes it from the
// simulator (SimSample::f_nT: a simulated scalar magnetometer, or NaN in scenarios without one);
// it is not part of the HAL path.
//
// Health (HilCounters), on top of the drivers' counters and LoopHealth:
//   - mag_read_errors: reads that returned a driver error (CRC, malformed...): no record;
//   - mag_not_fresh: samples the device marked not new (ADC dropout decision, sim_devices.hpp):
//     passed to the loop as a dropout (NaN, never as a device error), so the record carries
//     kOutDropout;
//   - mag_missing: samples missing from the regular cadence (time step of k periods, 1.5 < k <= 10:
//     k - 1 missing): frames lost to CRC errors, lines skipped or rejected on the serial link;
//   - mag_time_jumps: time steps < 0.5 period or > 10 periods (clock jumps);
//   - att_invalid: INS samples without ATTITUDE_VALID (not inserted: the buffer shows a gap);
//   - att_gaps: INS sample spacing > 1.5 INS periods (missing INS);
//   - att_time_jumps: INS time going backwards (buffer cleared: it must not mix time bases);
//   - att_rejected: inserts the buffer refused (duplicates, invalid quaternions, too old).
// Zero heap allocations per step after construction (proved by tests/host/hil/hil_session_test).
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/hal/record_sink.hpp"

namespace magvec::host::hil {

struct HilConfig {
  core::LoopConfig<double> loop{};
  core::AttitudeBufferConfig buffer{};
  // Subtracted from CAN receive times to get the attitude validity time on the host clock
  // (known transport latency; the sim's default CAN latency).
  std::uint32_t ins_latency_comp_us{500};
  bool require_attitude_valid{true};
  bool start_calibration{true};
};

struct HilCounters {
  std::uint64_t steps{0};
  std::uint64_t mag_samples{0};
  std::uint64_t mag_read_errors{0};
  std::uint64_t mag_not_fresh{0};
  std::uint64_t mag_missing{0};
  std::uint64_t mag_time_jumps{0};
  std::uint64_t att_samples{0};
  std::uint64_t att_invalid{0};
  std::uint64_t att_gaps{0};
  std::uint64_t att_time_jumps{0};
  std::uint64_t att_rejected{0};
  std::uint64_t records{0};
  std::uint64_t sink_errors{0};
};

// core::OutputRecord -> hal::OutputRecord (NaN for values that do not exist for this record).
inline hal::OutputRecord to_hal_record(const core::OutputRecord<double>& r) noexcept {
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  hal::OutputRecord o;
  o.t_us = r.t_us;
  const bool dropout = (r.flags & core::kOutDropout) != 0;
  const bool no_att = dropout || (r.flags & core::kOutNoAttitude) != 0;
  for (int i = 0; i < 3; ++i) {
    const auto k = static_cast<std::size_t>(i);
    o.raw_nT[k] = r.raw_nT[i];
    o.h_s_nT[k] = dropout ? kNaN : r.h_s_nT[i];
    o.h_n_nT[k] = no_att ? kNaN : r.h_n_nT[i];
  }
  o.f_nT = dropout ? kNaN : r.intensity_nT;
  o.sigma_f_nT = dropout ? kNaN : r.sigma_f_nT;
  o.flags = r.flags;
  o.cal_id = r.cal_id;
  return o;
}

template <typename Calibrator, std::size_t BufferCapacity = 64>
class HilSession {
 public:
  HilSession(drivers::sim::Simulator& sim, const drivers::sim::SimRigConfig& rig_config,
             Calibrator& calibrator, hal::RecordSink& sink, const HilConfig& config) noexcept
      : config_(config),
        rig_(sim, rig_config),
        ads_(rig_.adc(), rig_.adc(), rig_config.adc.transfer),
        serial_(rig_.serial(), rig_.clock(), drivers::AsciiLineDecoder(rig_config.serial.line)),
        can_(rig_.ins()),
        buffer_(config.buffer),
        loop_(calibrator, config.loop),
        sink_(sink),
        mag_period_us_(1e6 / sim.config().rate_hz),
        ins_period_us_(1e6 / rig_config.ins.rate_hz) {
    if (rig_config.link == drivers::sim::MagLink::kSpi) {
      mag_ = &ads_;
    } else {
      mag_ = &serial_;
    }
  }

  // Device start-up (ADC reset + gain configuration on SPI). kOk or the driver's status.
  hal::Status init() noexcept {
    if (mag_ == &ads_) return ads_.init();
    return hal::Status::kOk;
  }

  // One magnetometer sample period of simulated time; false when the scenario has ended.
  bool step() noexcept {
    if (!rig_.step()) return false;
    ++counters_.steps;
    if (config_.start_calibration && !started_) {
      loop_.start_calibration();
      started_ = true;
    }
    drain_attitude();
    for (int guard = 0; guard < 8; ++guard) {
      hal::MagnetometerSample s;
      const hal::Status st = mag_->read(s, 0);
      if (st == hal::Status::kTimeout || st == hal::Status::kNoData) break;
      if (st != hal::Status::kOk) {
        ++counters_.mag_read_errors;
        continue;
      }
      process(s);
    }
    return true;
  }

  std::uint64_t run(std::uint64_t max_steps = std::numeric_limits<std::uint64_t>::max()) noexcept {
    std::uint64_t n = 0;
    while (n < max_steps && step())
      ++n;
    return n;
  }

  drivers::sim::SimRig& rig() noexcept { return rig_; }
  core::SensorLoop<double, Calibrator>& loop() noexcept { return loop_; }
  const core::AttitudeBuffer<double, BufferCapacity>& buffer() const noexcept { return buffer_; }
  const HilCounters& counters() const noexcept { return counters_; }
  const hal::MagCounters& mag_counters() const noexcept { return mag_->counters(); }
  const hal::AttitudeCounters& attitude_counters() const noexcept { return can_.counters(); }

 private:
  void drain_attitude() noexcept {
    hal::AttitudeSample a;
    for (int guard = 0; guard < 256 && can_.read(a, 0) == hal::Status::kOk; ++guard) {
      ++counters_.att_samples;
      if (config_.require_attitude_valid && (a.flags & hal::kAttAttitudeValid) == 0) {
        ++counters_.att_invalid;
        continue;
      }
      const std::uint64_t t =
          a.t_us > config_.ins_latency_comp_us ? a.t_us - config_.ins_latency_comp_us : 0;
      if (have_att_) {
        if (t < last_att_us_) {
          ++counters_.att_time_jumps;
          buffer_.clear();
        } else if (static_cast<double>(t - last_att_us_) > 1.5 * ins_period_us_) {
          ++counters_.att_gaps;
        }
      }
      have_att_ = true;
      last_att_us_ = t;
      const core::Quat<double> q(a.q_nb[0], a.q_nb[1], a.q_nb[2], a.q_nb[3]);
      const core::AttitudeInsert r = buffer_.insert(t, q);
      if (r == core::AttitudeInsert::kDuplicate || r == core::AttitudeInsert::kTooOld ||
          r == core::AttitudeInsert::kInvalid) {
        ++counters_.att_rejected;
      }
    }
  }

  void process(const hal::MagnetometerSample& s) noexcept {
    ++counters_.mag_samples;
    if (have_mag_) {
      const double ratio =
          (static_cast<double>(s.t_us) - static_cast<double>(last_mag_us_)) / mag_period_us_;
      if (ratio < 0.5 || ratio > 10.0) {
        ++counters_.mag_time_jumps;
      } else if (ratio > 1.5) {
        counters_.mag_missing += static_cast<std::uint64_t>(std::llround(ratio)) - 1;
      }
    }
    have_mag_ = true;
    last_mag_us_ = s.t_us;

    core::MagSample<double> m;
    m.t_us = s.t_us;
    m.m_nT = core::Vec3<double>(s.m_nT[0], s.m_nT[1], s.m_nT[2]);
    m.f_ref_nT = rig_.last().f_nT;
    m.device_error = (s.flags & hal::kMagInvalidMask) != 0;
    if ((s.flags & hal::kMagNotFresh) != 0) {
      // Not new data: a dropout, whatever the held codes look like (a held full-scale code was
      // already counted as saturated on its fresh frame by the driver).
      ++counters_.mag_not_fresh;
      m.device_error = false;
      m.m_nT.setConstant(std::numeric_limits<double>::quiet_NaN());
    }
    const core::AttitudeQuery<double> q = buffer_.at(s.t_us);
    core::Mat3<double> r_bn;
    const bool usable = core::attitude_usable(q.status);
    if (usable) r_bn = core::r_bn_from_quat(q.q_nb);
    const core::OutputRecord<double> rec = loop_.process(m, usable ? &r_bn : nullptr);
    ++counters_.records;
    if (sink_.emit(to_hal_record(rec)) != hal::Status::kOk) ++counters_.sink_errors;
  }

  HilConfig config_;
  drivers::sim::SimRig rig_;
  drivers::Ads131Fluxgate ads_;
  drivers::SerialFluxgate<drivers::AsciiLineDecoder> serial_;
  drivers::sbg::CanAttitudeSource can_;
  hal::MagnetometerSource* mag_{nullptr};
  core::AttitudeBuffer<double, BufferCapacity> buffer_;
  core::SensorLoop<double, Calibrator> loop_;
  hal::RecordSink& sink_;
  double mag_period_us_;
  double ins_period_us_;
  HilCounters counters_{};
  std::uint64_t last_mag_us_{0};
  std::uint64_t last_att_us_{0};
  bool have_mag_{false};
  bool have_att_{false};
  bool started_{false};
};

// A calibrator that never calibrates (the `--calibrator none` choice): the loop outputs with the
// active calibration (identity, or one installed with set_active) and flags kOutUncalibrated
// while cal_id is 0. It exists so the harness runs before an estimator is plugged in; it is not
// started (HilConfig::start_calibration = false).
struct NullCalibrator {
  void begin() noexcept {}
  core::CalibratorAdd add(const core::Vec3<double>&, double, const core::Mat3<double>*) noexcept {
    return core::CalibratorAdd::kRejected;
  }
  double progress() const noexcept { return 0; }
  bool ready() const noexcept { return false; }
  core::CalibratorSolve solve(core::SensorModel<double>*) noexcept { return {false, 1}; }
};

}  // namespace magvec::host::hil
