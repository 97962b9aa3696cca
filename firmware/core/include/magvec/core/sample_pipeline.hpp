// SamplePipeline: the per-sample pipeline shared by the MCU image, `magvec run`/`demo`, `magvec
// replay` and magvecd: INS samples -> AttitudeBuffer; magnetometer samples -> a bounded queue ->
// (attitude at the sample's time) -> SensorLoop -> one OutputRecord per magnetometer sample, in
// sample order, handed to an emit callback.
//
// Delayed fusion horizon (as PX4 EKF2 fuses on a delayed time horizon): on real hardware the INS
// epoch that brackets a magnetometer sample arrives after it (CAN latency, the INS's own output
// delay), so a sample is not processed when it arrives. It waits in the queue until
//   - an INS sample at or after its attitude time has arrived (valid or not): the attitude is
//     interpolated between the two bracketing INS samples (or refused across an INS gap), or
//   - the horizon expires: a magnetometer sample horizon_us newer has arrived, the queue is full,
//     or the caller flushes (end of the stream). The attitude is then extrapolated past the newest
//     INS sample (AttitudeBuffer: held or constant rate, within max_extrapolation_us) and the
//     record carries kOutAttExtrapolated; farther, it has no attitude (kOutNoAttitude).
// horizon_us = 0 processes every sample at once (the attitude is whatever the buffer holds then).
//
// Times. INS sample times are receive times on the host clock: the configured transport latency
// ins_latency_us is subtracted to get the attitude validity time. A magnetometer sample stamped t
// pairs with the attitude at t - time_offset_us (time_offset = magnetometer time stamp minus the
// INS time of the attitude it belongs to; positive when the magnetometer lags).
//
// One set of rules for time jumps, reordering and dropouts:
//   - INS time going backwards by more than the buffer's max_gap_us: a clock jump; the buffer is
//     cleared (it must not mix time bases) and counted (att_time_jumps). Less than that:
//     reordering in transit (att_reordered); the buffer inserts the sample in time order. INS
//     spacing above 1.5 periods is counted as a gap (att_gaps).
//     An INS sample without attitude validity is not inserted (att_invalid) but still tells the
//     queue how far the INS has got. Inserts the buffer refuses are att_rejected.
//   - Magnetometer time going backwards: a clock jump (mag_time_jumps); the queue is flushed first
//     (those samples belong to the old time base). A step of < 0.5 or > 10 periods is a jump; of
//     k periods, 1.5 < k <= 10, k - 1 samples are missing (mag_missing).
//   - A sample the device marked not fresh is a dropout (NaN, kOutDropout, never a device error);
//     a device error is passed on (kOutDeviceError). Both still get their record, in order.
// Header-only, Scalar-templated, fixed memory, noexcept, no heap.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

template <typename Scalar>
struct PipelineConfig {
  LoopConfig<Scalar> loop{};
  AttitudeBufferConfig buffer{};
  std::uint32_t ins_latency_us{500};  // subtracted from INS receive times
  std::int64_t time_offset_us{0};     // magnetometer stamp - INS time of its attitude
  std::uint32_t horizon_us{50'000};   // longest wait for bracketing INS samples
  // Expected cadences (missing/gap/jump counters), whole microseconds: integer arithmetic keeps
  // soft-float double off the M4F's per-sample path.
  std::uint32_t mag_period_us{5'000};
  std::uint32_t ins_period_us{10'000};
};

struct PipelineCounters {
  std::uint64_t mag_samples{0};
  std::uint64_t mag_not_fresh{0};
  std::uint64_t mag_missing{0};
  std::uint64_t mag_time_jumps{0};
  std::uint64_t att_samples{0};
  std::uint64_t att_invalid{0};
  std::uint64_t att_gaps{0};
  std::uint64_t att_time_jumps{0};
  std::uint64_t att_reordered{0};
  std::uint64_t att_rejected{0};
  std::uint64_t records{0};
  std::uint64_t horizon_expired{0};  // processed without a bracketing INS sample
  std::uint64_t extrapolated{0};     // records flagged kOutAttExtrapolated
  std::uint64_t queue_full{0};       // processed early because the queue was full
  std::uint64_t max_queued{0};       // deepest the queue has been
};

template <typename Scalar, typename Calibrator, std::size_t BufferCapacity = 64,
          std::size_t QueueCapacity = 64>
class SamplePipeline {
  static_assert(QueueCapacity >= 1, "the queue holds at least one sample");

 public:
  using Loop = SensorLoop<Scalar, Calibrator>;
  using Buffer = AttitudeBuffer<Scalar, BufferCapacity>;

  SamplePipeline(Calibrator& calibrator, const PipelineConfig<Scalar>& config) noexcept
      : config_(config), buffer_(config.buffer), loop_(calibrator, config.loop) {}

  // One INS sample: receive time on the host clock, attitude q_nb, validity flag. Emit is called
  // for every queued magnetometer sample this sample makes ready.
  template <typename Emit>
  void on_attitude(std::uint64_t t_rx_us, const Quat<Scalar>& q_nb, bool valid,
                   Emit&& emit) noexcept {
    ++counters_.att_samples;
    const std::uint64_t t = t_rx_us > config_.ins_latency_us ? t_rx_us - config_.ins_latency_us : 0;
    if (!have_ins_) {
      ins_seen_us_ = t;
    } else if (t < ins_seen_us_ && ins_seen_us_ - t > config_.buffer.max_gap_us) {
      // A clock jump: the buffer must not mix time bases.
      ++counters_.att_time_jumps;
      buffer_.clear();
      ins_seen_us_ = t;
    } else if (t < ins_seen_us_) {
      // Reordered by less than the longest interpolation gap (frames of one burst swapped in
      // transit): the buffer inserts it in time order; the INS has still got as far as before.
      ++counters_.att_reordered;
    } else {
      if (2 * (t - ins_seen_us_) > 3 * std::uint64_t{config_.ins_period_us}) ++counters_.att_gaps;
      ins_seen_us_ = t;
    }
    have_ins_ = true;
    if (!valid) {
      ++counters_.att_invalid;
    } else {
      const AttitudeInsert r = buffer_.insert(t, q_nb);
      if (r == AttitudeInsert::kDuplicate || r == AttitudeInsert::kTooOld ||
          r == AttitudeInsert::kInvalid) {
        ++counters_.att_rejected;
      }
    }
    drain(emit);
  }

  // One magnetometer sample (not_fresh: the device said the conversion is not new). Emit is
  // called for every sample that becomes ready, this one included when it is.
  template <typename Emit>
  void on_magnetometer(const MagSample<Scalar>& s, bool not_fresh, Emit&& emit) noexcept {
    ++counters_.mag_samples;
    if (have_mag_) {
      // Step of k periods: < 0.5 or > 10 is a jump; 1.5 < k <= 10 means round(k) - 1 missing.
      const std::uint64_t p = config_.mag_period_us > 0 ? config_.mag_period_us : 1;
      if (s.t_us < mag_newest_us_ || 2 * (s.t_us - mag_newest_us_) < p ||
          s.t_us - mag_newest_us_ > 10 * p) {
        ++counters_.mag_time_jumps;
      } else if (2 * (s.t_us - mag_newest_us_) > 3 * p) {
        counters_.mag_missing += (s.t_us - mag_newest_us_ + p / 2) / p - 1;
      }
      // The pending samples belong to the old time base: out before the new one goes in.
      if (s.t_us <= mag_newest_us_) flush(emit);
    }
    have_mag_ = true;
    mag_newest_us_ = s.t_us;
    MagSample<Scalar> m = s;
    if (not_fresh) {
      // Not new data: a dropout, whatever the held codes look like.
      ++counters_.mag_not_fresh;
      m.device_error = false;
      m.m_nT.setConstant(std::numeric_limits<Scalar>::quiet_NaN());
    }
    if (count_ == QueueCapacity) {
      ++counters_.queue_full;
      process_front(emit);
    }
    queue_[(head_ + count_) % QueueCapacity] = m;
    ++count_;
    if (count_ > counters_.max_queued) counters_.max_queued = count_;
    drain(emit);
  }

  // Processes every pending sample now (end of the stream, or before a new session).
  template <typename Emit>
  void flush(Emit&& emit) noexcept {
    while (count_ > 0)
      process_front(emit);
  }

  // Changes the magnetometer<->INS time offset (e.g. with a new calibration).
  void set_time_offset_us(std::int64_t offset_us) noexcept { config_.time_offset_us = offset_us; }
  std::int64_t time_offset_us() const noexcept { return config_.time_offset_us; }

  std::size_t pending() const noexcept { return count_; }
  Loop& loop() noexcept { return loop_; }
  const Loop& loop() const noexcept { return loop_; }
  const Buffer& buffer() const noexcept { return buffer_; }
  const PipelineCounters& counters() const noexcept { return counters_; }
  const PipelineConfig<Scalar>& config() const noexcept { return config_; }

  // The attitude time of a magnetometer sample stamped t_us.
  std::uint64_t attitude_time_us(std::uint64_t t_us) const noexcept {
    const std::int64_t off = config_.time_offset_us;
    if (off >= 0) {
      const auto o = static_cast<std::uint64_t>(off);
      return t_us > o ? t_us - o : 0;
    }
    return t_us + static_cast<std::uint64_t>(-off);
  }

 private:
  template <typename Emit>
  void drain(Emit& emit) noexcept {
    while (count_ > 0) {
      const MagSample<Scalar>& f = queue_[head_];
      const bool bracketed = have_ins_ && ins_seen_us_ >= attitude_time_us(f.t_us);
      const bool expired = mag_newest_us_ - f.t_us >= config_.horizon_us;
      if (!bracketed && !expired) return;
      process_front(emit);
    }
  }

  template <typename Emit>
  void process_front(Emit& emit) noexcept {
    const MagSample<Scalar> s = queue_[head_];
    head_ = (head_ + 1) % QueueCapacity;
    --count_;
    const std::uint64_t tq = attitude_time_us(s.t_us);
    if (!(have_ins_ && ins_seen_us_ >= tq)) ++counters_.horizon_expired;
    const AttitudeQuery<Scalar> q = buffer_.at(tq);
    const bool usable = attitude_usable(q.status);
    Mat3<Scalar> r_bn;
    if (usable) r_bn = r_bn_from_quat(q.q_nb);
    OutputRecord<Scalar> rec = loop_.process(s, usable ? &r_bn : nullptr);
    if (q.status == AttitudeQueryStatus::kExtrapolated && (rec.flags & kOutNoAttitude) == 0 &&
        (rec.flags & kOutDropout) == 0) {
      rec.flags |= kOutAttExtrapolated;
      ++counters_.extrapolated;
    }
    ++counters_.records;
    emit(rec);
  }

  PipelineConfig<Scalar> config_;
  Buffer buffer_;
  Loop loop_;
  PipelineCounters counters_{};
  MagSample<Scalar> queue_[QueueCapacity];
  std::size_t head_{0};
  std::size_t count_{0};
  std::uint64_t mag_newest_us_{0};
  std::uint64_t ins_seen_us_{0};
  bool have_mag_{false};
  bool have_ins_{false};
};

}  // namespace magvec::core
