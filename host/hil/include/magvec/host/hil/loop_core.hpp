// LoopCore: the host's binding of pipeline::DevicePipeline<double> (the one per-sample pipeline
// of the MCU image, HilSession, magvecd and `magvec replay`) to a hal::RecordSink, configured
// from the host's HilConfig. It consumes raw input events only - INS attitude samples
// (hal::AttitudeSample as a driver delivers them) and magnetometer samples
// (hal::MagnetometerSample + the scalar reference) - and the core's SamplePipeline decides when
// each sample is processed (delayed fusion horizon, time offset, jumps, dropouts).
// A record is emitted when its sample is processed: when INS samples bracket it or the horizon
// expires, so on_attitude can emit records too, and flush() emits what is still pending at the
// end of a stream. Feeding the same events in the same order gives bit-identical records (no
// clock, no I/O, no randomness here), which is what makes `magvec replay` of an LCM log exact.
// Health: pipeline::DeviceCounters (the core's PipelineCounters + failed reads, sink errors,
// steps). Zero heap allocations per event.
#pragma once

#include <cmath>
#include <cstdint>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/sample_pipeline.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/record_sink.hpp"
#include "magvec/pipeline/device_pipeline.hpp"
#include "magvec/pipeline/solve_schedule.hpp"

namespace magvec::host::hil {

struct HilConfig {
  core::LoopConfig<double> loop{};
  core::AttitudeBufferConfig buffer{};
  // Subtracted from CAN receive times to get the attitude validity time on the host clock
  // (known transport latency; the sim's default CAN latency).
  std::uint32_t ins_latency_comp_us{500};
  // Longest wait of a magnetometer sample for INS samples that bracket it (delayed fusion
  // horizon, magnetometer time); 0 processes each sample at once.
  std::uint32_t horizon_us{50'000};
  // Magnetometer time stamp minus the INS time of the attitude it belongs to (cal.json
  // time_offset_s): a sample stamped t pairs with the attitude at t - time_offset.
  std::int64_t time_offset_us{0};
  // Adopt the time offset an in-loop calibration finds (core::PipelineConfig); off when
  // time_offset_us is known.
  bool adopt_calibration_time_offset{true};
  bool require_attitude_valid{true};
  bool start_calibration{true};
  // 0: the loop runs its calibrator's solve inline. N > 0: the MCU image's rule
  // (pipeline::SolveSchedule): the solve's result goes in N records after the one that raised the
  // ticket, so a run reproduces the image's records (`magvec run --profile mcu`).
  std::uint32_t solve_install_records{0};
};

using HilCounters = pipeline::DeviceCounters;

// The HilConfig of a pipeline configuration (the MCU image's, `magvec run --profile mcu`): the
// inverse of LoopCore's pipeline_config(), whose sample periods come from the rig's rates.
inline HilConfig hil_config_from(const core::PipelineConfig<double>& p) noexcept {
  HilConfig h;
  h.loop = p.loop;
  h.buffer = p.buffer;
  h.ins_latency_comp_us = p.ins_latency_us;
  h.horizon_us = p.horizon_us;
  h.time_offset_us = p.time_offset_us;
  h.adopt_calibration_time_offset = p.adopt_calibration_time_offset;
  return h;
}

// Seconds -> whole microseconds (the time offset of cal.json and the CLI options).
inline std::int64_t offset_us_from_s(double s) noexcept {
  return static_cast<std::int64_t>(std::llround(s * 1e6));
}

template <typename Calibrator, std::size_t BufferCapacity = 64, std::size_t QueueCapacity = 256>
class LoopCore {
 public:
  using Device = pipeline::DevicePipeline<double, Calibrator, BufferCapacity, QueueCapacity>;
  using Core = typename Device::Core;

  LoopCore(Calibrator& calibrator, hal::RecordSink& sink, const HilConfig& config,
           double mag_rate_hz, double ins_rate_hz) noexcept
      : config_(config),
        calibrator_(calibrator),
        device_(calibrator, pipeline_config(config, mag_rate_hz, ins_rate_hz),
                config.require_attitude_valid),
        sink_(sink),
        schedule_(config.solve_install_records) {}

  // One INS sample as the attitude driver delivered it (may emit records it makes ready).
  void on_attitude(const hal::AttitudeSample& a) noexcept { device_.on_attitude(a, emit()); }

  // A magnetometer read that failed (CRC, malformed...): counted, no record.
  void on_read_error() noexcept { device_.on_read_error(); }

  // One magnetometer sample as the driver delivered it, with the scalar reference |h| (NaN when
  // none). Exactly one record per sample reaches the sink, once the sample is processed.
  void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) noexcept {
    device_.on_magnetometer(s, f_ref_nT, emit());
  }

  // Emits every pending record (end of the stream, before a new session).
  void flush() noexcept { device_.flush(emit()); }

  void set_time_offset_us(std::int64_t offset_us) noexcept {
    device_.set_time_offset_us(offset_us);
  }
  void set_adopt_calibration_time_offset(bool on) noexcept {
    device_.set_adopt_calibration_time_offset(on);
  }

  void count_step() noexcept { device_.count_step(); }

  core::SensorLoop<double, Calibrator>& loop() noexcept { return device_.loop(); }
  const core::SensorLoop<double, Calibrator>& loop() const noexcept { return device_.loop(); }
  const core::AttitudeBuffer<double, BufferCapacity>& buffer() const noexcept {
    return device_.core().buffer();
  }
  const Core& pipeline() const noexcept { return device_.core(); }
  const HilCounters& counters() const noexcept { return device_.counters(); }
  const HilConfig& config() const noexcept { return config_; }

 private:
  static core::PipelineConfig<double> pipeline_config(const HilConfig& c, double mag_rate_hz,
                                                      double ins_rate_hz) noexcept {
    core::PipelineConfig<double> p;
    p.loop = c.loop;
    p.buffer = c.buffer;
    p.ins_latency_us = c.ins_latency_comp_us;
    p.time_offset_us = c.time_offset_us;
    p.adopt_calibration_time_offset = c.adopt_calibration_time_offset;
    p.horizon_us = c.horizon_us;
    p.mag_period_us = pipeline::period_us_from_hz(mag_rate_hz);
    p.ins_period_us = pipeline::period_us_from_hz(ins_rate_hz);
    if (c.solve_install_records > 0) p.loop.external_solve = true;
    return p;
  }

  // The emit callback: each record to the sink; with solve_install_records, the schedule's
  // ticket and install checks first, on every record as the MCU image makes them.
  auto emit() noexcept {
    return [this](const core::OutputRecord<double>& r) noexcept {
      ++records_;
      if (schedule_.install_after_records() > 0) run_schedule();
      device_.emit_to(sink_)(r);
    };
  }
  void run_schedule() noexcept {
    auto& lp = device_.loop();
    (void)schedule_.raised(lp, records_);
    if (!schedule_.due(records_)) return;
    core::SensorModel<double> model;
    const core::CalibratorSolve r = calibrator_.solve(&model);
    schedule_.installed();
    (void)lp.install_solve(schedule_.ticket(), r, model);
  }

  HilConfig config_;
  Calibrator& calibrator_;
  Device device_;
  hal::RecordSink& sink_;
  pipeline::SolveSchedule schedule_;
  std::uint32_t records_{0};
};

// The `--calibrator none` choice; it is not started (HilConfig::start_calibration = false).
using NullCalibrator = pipeline::NullCalibrator<double>;

}  // namespace magvec::host::hil
