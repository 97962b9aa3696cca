// LoopCore: the driver-independent half of the host sensor pipeline (DESIGN.md "Host-in-the-loop
// simulation"; shared by HilSession and magvecd's Pipeline): it consumes raw input events only -
// INS attitude samples (hal::AttitudeSample as a driver delivers them) and magnetometer samples
// (hal::MagnetometerSample + the scalar reference) - and runs core::AttitudeBuffer (every valid INS
// sample inserted; queried at every magnetometer time, slerp) -> core::SensorLoop -> RecordSink.
// Feeding the same events in the same order gives bit-identical records (no clock, no I/O, no
// randomness here), which is what makes `magvec replay` of an LCM log exact.
//
// Health (HilCounters), on top of the drivers' counters and LoopHealth:
//   - mag_read_errors: reads that returned a driver error (CRC, malformed...): no record
//     (counted by the caller through on_read_error());
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
// Zero heap allocations per event.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
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
class LoopCore {
 public:
  LoopCore(Calibrator& calibrator, hal::RecordSink& sink, const HilConfig& config,
           double mag_rate_hz, double ins_rate_hz) noexcept
      : config_(config),
        buffer_(config.buffer),
        loop_(calibrator, config.loop),
        sink_(sink),
        mag_period_us_(1e6 / mag_rate_hz),
        ins_period_us_(1e6 / ins_rate_hz) {}

  // One INS sample as the attitude driver delivered it.
  void on_attitude(const hal::AttitudeSample& a) noexcept {
    ++counters_.att_samples;
    if (config_.require_attitude_valid && (a.flags & hal::kAttAttitudeValid) == 0) {
      ++counters_.att_invalid;
      return;
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

  // A magnetometer read that failed (CRC, malformed...): counted, no record.
  void on_read_error() noexcept { ++counters_.mag_read_errors; }

  // One magnetometer sample as the driver delivered it, with the scalar reference |h| (NaN when
  // none); emits exactly one record to the sink and returns it.
  hal::OutputRecord on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) noexcept {
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
    m.f_ref_nT = f_ref_nT;
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
    const hal::OutputRecord out = to_hal_record(loop_.process(m, usable ? &r_bn : nullptr));
    ++counters_.records;
    if (sink_.emit(out) != hal::Status::kOk) ++counters_.sink_errors;
    return out;
  }

  void count_step() noexcept { ++counters_.steps; }

  core::SensorLoop<double, Calibrator>& loop() noexcept { return loop_; }
  const core::SensorLoop<double, Calibrator>& loop() const noexcept { return loop_; }
  const core::AttitudeBuffer<double, BufferCapacity>& buffer() const noexcept { return buffer_; }
  const HilCounters& counters() const noexcept { return counters_; }
  const HilConfig& config() const noexcept { return config_; }

 private:
  HilConfig config_;
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
