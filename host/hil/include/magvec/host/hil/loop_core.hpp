// LoopCore: the driver-independent half of the host sensor pipeline (shared by HilSession and
// magvecd's Pipeline): it consumes raw input events only - INS attitude samples
// (hal::AttitudeSample as a driver delivers them) and magnetometer samples
// (hal::MagnetometerSample + the scalar reference) - converts them and runs core::SamplePipeline
// (AttitudeBuffer with the delayed fusion horizon -> SensorLoop; its rules for time jumps,
// reordering, dropouts and horizon expiry are the core's) -> RecordSink.
// A record is emitted when its sample is processed: when INS samples bracket it or the horizon
// expires, so on_attitude can emit records too, and flush() emits what is still pending at the
// end of a stream. Feeding the same events in the same order gives bit-identical records (no
// clock, no I/O, no randomness here), which is what makes `magvec replay` of an LCM log exact.
//
// Health (HilCounters), on top of the drivers' counters and LoopHealth:
//   - mag_read_errors: reads that returned a driver error (CRC, malformed...): no record
//     (counted by the caller through on_read_error());
//   - the rest come from core::PipelineCounters (sample_pipeline.hpp): mag_not_fresh (dropout
//     records), mag_missing, mag_time_jumps, att_invalid, att_gaps, att_time_jumps, att_rejected,
//     and the horizon figures (horizon_expired, extrapolated, queue_full, max_queued).
// Zero heap allocations per event.
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sample_pipeline.hpp"
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
  // Longest wait of a magnetometer sample for INS samples that bracket it (delayed fusion
  // horizon, magnetometer time); 0 processes each sample at once.
  std::uint32_t horizon_us{50'000};
  // Magnetometer time stamp minus the INS time of the attitude it belongs to (cal.json
  // time_offset_s): a sample stamped t pairs with the attitude at t - time_offset.
  std::int64_t time_offset_us{0};
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
  std::uint64_t horizon_expired{0};
  std::uint64_t extrapolated{0};
  std::uint64_t queue_full{0};
  std::uint64_t max_queued{0};
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

// Seconds -> whole microseconds (the time offset of cal.json and the CLI options).
inline std::int64_t offset_us_from_s(double s) noexcept {
  return static_cast<std::int64_t>(std::llround(s * 1e6));
}

template <typename Calibrator, std::size_t BufferCapacity = 64, std::size_t QueueCapacity = 256>
class LoopCore {
 public:
  using Core = core::SamplePipeline<double, Calibrator, BufferCapacity, QueueCapacity>;

  LoopCore(Calibrator& calibrator, hal::RecordSink& sink, const HilConfig& config,
           double mag_rate_hz, double ins_rate_hz) noexcept
      : config_(config),
        core_(calibrator, pipeline_config(config, mag_rate_hz, ins_rate_hz)),
        sink_(sink) {}

  // One INS sample as the attitude driver delivered it (may emit records it makes ready).
  void on_attitude(const hal::AttitudeSample& a) noexcept {
    const bool valid = !config_.require_attitude_valid || (a.flags & hal::kAttAttitudeValid) != 0;
    const core::Quat<double> q(a.q_nb[0], a.q_nb[1], a.q_nb[2], a.q_nb[3]);
    core_.on_attitude(a.t_us, q, valid, Emitter{*this});
  }

  // A magnetometer read that failed (CRC, malformed...): counted, no record.
  void on_read_error() noexcept { ++counters_.mag_read_errors; }

  // One magnetometer sample as the driver delivered it, with the scalar reference |h| (NaN when
  // none). Exactly one record per sample reaches the sink, once the sample is processed.
  void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) noexcept {
    core::MagSample<double> m;
    m.t_us = s.t_us;
    m.m_nT = core::Vec3<double>(s.m_nT[0], s.m_nT[1], s.m_nT[2]);
    m.f_ref_nT = f_ref_nT;
    m.device_error = (s.flags & hal::kMagInvalidMask) != 0;
    core_.on_magnetometer(m, (s.flags & hal::kMagNotFresh) != 0, Emitter{*this});
  }

  // Emits every pending record (end of the stream, before a new session).
  void flush() noexcept { core_.flush(Emitter{*this}); }

  void set_time_offset_us(std::int64_t offset_us) noexcept { core_.set_time_offset_us(offset_us); }

  void count_step() noexcept { ++counters_.steps; }

  core::SensorLoop<double, Calibrator>& loop() noexcept { return core_.loop(); }
  const core::SensorLoop<double, Calibrator>& loop() const noexcept { return core_.loop(); }
  const core::AttitudeBuffer<double, BufferCapacity>& buffer() const noexcept {
    return core_.buffer();
  }
  const Core& pipeline() const noexcept { return core_; }
  const HilCounters& counters() const noexcept {
    const core::PipelineCounters& c = core_.counters();
    counters_.mag_samples = c.mag_samples;
    counters_.mag_not_fresh = c.mag_not_fresh;
    counters_.mag_missing = c.mag_missing;
    counters_.mag_time_jumps = c.mag_time_jumps;
    counters_.att_samples = c.att_samples;
    counters_.att_invalid = c.att_invalid;
    counters_.att_gaps = c.att_gaps;
    counters_.att_time_jumps = c.att_time_jumps;
    counters_.att_rejected = c.att_rejected;
    counters_.horizon_expired = c.horizon_expired;
    counters_.extrapolated = c.extrapolated;
    counters_.queue_full = c.queue_full;
    counters_.max_queued = c.max_queued;
    counters_.records = c.records;
    return counters_;
  }
  const HilConfig& config() const noexcept { return config_; }

 private:
  struct Emitter {
    LoopCore& self;
    void operator()(const core::OutputRecord<double>& r) const noexcept {
      if (self.sink_.emit(to_hal_record(r)) != hal::Status::kOk) ++self.counters_.sink_errors;
    }
  };

  static core::PipelineConfig<double> pipeline_config(const HilConfig& c, double mag_rate_hz,
                                                      double ins_rate_hz) noexcept {
    core::PipelineConfig<double> p;
    p.loop = c.loop;
    p.buffer = c.buffer;
    p.ins_latency_us = c.ins_latency_comp_us;
    p.time_offset_us = c.time_offset_us;
    p.horizon_us = c.horizon_us;
    p.mag_period_us = 1e6 / mag_rate_hz;
    p.ins_period_us = 1e6 / ins_rate_hz;
    return p;
  }

  HilConfig config_;
  Core core_;
  hal::RecordSink& sink_;
  mutable HilCounters counters_{};
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
