// DevicePipeline: core::SamplePipeline fed with samples as the HAL drivers deliver them, the one
// per-sample composition of the MCU image (firmware/app), `magvec run`/`demo` (HilSession),
// `magvec replay` and magvecd (LoopCore). It owns only what sits between the HAL types and the
// core: converting hal::AttitudeSample / hal::MagnetometerSample to the core's types, counting
// failed reads, and converting each core::OutputRecord to a hal::OutputRecord (NaN for values a
// record does not have). Timing rules (delayed fusion horizon, time offset, jumps, dropouts) are
// the core's (sample_pipeline.hpp, docs/architecture.md#sample-pipeline).
// Records go to an emit callback with the core record (the MCU image scores and thins them) or
// to a hal::RecordSink (emit_to). Header-only, Scalar-templated, fixed memory, noexcept, no heap:
// it may include only the core and the HAL (interfaces).
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/frames.hpp"
#include "magvec/core/sample_pipeline.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/record_sink.hpp"

namespace magvec::pipeline {

// Health on top of the core's PipelineCounters (which count samples, dropouts, gaps, jumps and
// the horizon figures): reads that failed in the driver (CRC, malformed frame: no sample, no
// record), records the sink refused, and loop steps of a simulated rig.
struct DeviceCounters : core::PipelineCounters {
  std::uint64_t steps{0};
  std::uint64_t mag_read_errors{0};
  std::uint64_t sink_errors{0};
};

// core::OutputRecord -> hal::OutputRecord. A dropout has no output values and a record without
// attitude no h_n: NaN, never a stale or zero number that looks like a measurement.
template <typename Scalar>
hal::OutputRecord to_hal_record(const core::OutputRecord<Scalar>& r) noexcept {
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  hal::OutputRecord o;
  o.t_us = r.t_us;
  const bool dropout = (r.flags & core::kOutDropout) != 0;
  const bool no_att = dropout || (r.flags & core::kOutNoAttitude) != 0;
  for (int i = 0; i < 3; ++i) {
    const auto k = static_cast<std::size_t>(i);
    o.raw_nT[k] = static_cast<double>(r.raw_nT(i));
    o.h_s_nT[k] = dropout ? kNaN : static_cast<double>(r.h_s_nT(i));
    o.h_n_nT[k] = no_att ? kNaN : static_cast<double>(r.h_n_nT(i));
  }
  o.f_nT = dropout ? kNaN : static_cast<double>(r.intensity_nT);
  o.sigma_f_nT = dropout ? kNaN : static_cast<double>(r.sigma_f_nT);
  o.sigma_enu_nT = no_att ? kNaN : static_cast<double>(r.sigma_enu_nT);
  o.flags = r.flags;
  o.cal_id = r.cal_id;
  return o;
}

// A calibrator that never calibrates (the calibrator mode "none"): the loop outputs with the
// active calibration (identity, or one installed with set_active) and flags kOutUncalibrated
// while cal_id is 0. For running the pipeline before, or without, an estimator.
template <typename Scalar>
struct NullCalibrator {
  void begin() noexcept {}
  core::CalibratorAdd add(const core::Vec3<Scalar>&, Scalar, const core::Mat3<Scalar>*) noexcept {
    return core::CalibratorAdd::kRejected;
  }
  Scalar progress() const noexcept { return 0; }
  bool ready() const noexcept { return false; }
  core::CalibratorSolve solve(core::SensorModel<Scalar>*) noexcept { return {false, 1}; }
};

// Expected sample period in whole microseconds from a rate (the pipeline's missing/gap counters).
constexpr std::uint32_t period_us_from_hz(double rate_hz) noexcept {
  return rate_hz > 0 ? static_cast<std::uint32_t>(1e6 / rate_hz + 0.5) : 0;
}

template <typename Scalar, typename Calibrator, std::size_t BufferCapacity = 64,
          std::size_t QueueCapacity = 64>
class DevicePipeline {
 public:
  using Core = core::SamplePipeline<Scalar, Calibrator, BufferCapacity, QueueCapacity>;
  using Loop = typename Core::Loop;

  // require_attitude_valid: only INS samples flagged kAttAttitudeValid enter the buffer.
  DevicePipeline(Calibrator& calibrator, const core::PipelineConfig<Scalar>& config,
                 bool require_attitude_valid = true) noexcept
      : core_(calibrator, config), require_valid_(require_attitude_valid) {}

  // One INS sample as the driver delivered it (t_us = receive time). May emit records it makes
  // ready.
  template <typename Emit>
  void on_attitude(const hal::AttitudeSample& a, Emit&& emit) noexcept {
    const bool valid = !require_valid_ || (a.flags & hal::kAttAttitudeValid) != 0;
    const core::Quat<Scalar> q(static_cast<Scalar>(a.q_nb[0]), static_cast<Scalar>(a.q_nb[1]),
                               static_cast<Scalar>(a.q_nb[2]), static_cast<Scalar>(a.q_nb[3]));
    core_.on_attitude(a.t_us, q, valid, emit);
  }

  // One magnetometer sample as the driver delivered it, with the scalar reference |h| (NaN when
  // there is none). Exactly one record per sample is emitted, once the sample is processed.
  template <typename Emit>
  void on_magnetometer(const hal::MagnetometerSample& s, Scalar f_ref_nT, Emit&& emit) noexcept {
    core::MagSample<Scalar> m;
    m.t_us = s.t_us;
    m.m_nT = core::Vec3<Scalar>(static_cast<Scalar>(s.m_nT[0]), static_cast<Scalar>(s.m_nT[1]),
                                static_cast<Scalar>(s.m_nT[2]));
    m.f_ref_nT = f_ref_nT;
    m.temperature_degC = static_cast<Scalar>(s.temperature_degC);
    m.device_error = (s.flags & hal::kMagInvalidMask) != 0;
    core_.on_magnetometer(m, (s.flags & hal::kMagNotFresh) != 0, emit);
  }

  // A magnetometer read that failed in the driver: counted, no record.
  void on_read_error() noexcept { ++extra_.mag_read_errors; }
  void count_step() noexcept { ++extra_.steps; }
  void count_sink_error() noexcept { ++extra_.sink_errors; }

  // Processes every pending sample (end of the stream, before a new session).
  template <typename Emit>
  void flush(Emit&& emit) noexcept {
    core_.flush(emit);
  }

  // An emit callback that converts each record and hands it to a hal::RecordSink, counting the
  // records the sink refuses.
  auto emit_to(hal::RecordSink& sink) noexcept {
    return [this, &sink](const core::OutputRecord<Scalar>& r) noexcept {
      if (sink.emit(to_hal_record(r)) != hal::Status::kOk) ++extra_.sink_errors;
    };
  }

  void set_time_offset_us(std::int64_t offset_us) noexcept { core_.set_time_offset_us(offset_us); }
  void set_adopt_calibration_time_offset(bool on) noexcept {
    core_.set_adopt_calibration_time_offset(on);
  }

  Loop& loop() noexcept { return core_.loop(); }
  const Loop& loop() const noexcept { return core_.loop(); }
  const Core& core() const noexcept { return core_; }
  std::size_t pending() const noexcept { return core_.pending(); }

  const DeviceCounters& counters() const noexcept {
    static_cast<core::PipelineCounters&>(extra_) = core_.counters();
    return extra_;
  }

 private:
  Core core_;
  bool require_valid_;
  mutable DeviceCounters extra_{};
};

}  // namespace magvec::pipeline
