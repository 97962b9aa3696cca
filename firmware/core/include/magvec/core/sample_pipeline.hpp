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
//   - Spike screen: a sample is a spike when it stands out from BOTH its neighbours (the last
//     sample that passed and the next one in the queue): its distance r from their time
//     interpolation exceeds spike_factor times the running RMS of r AND the distance c between
//     the neighbours (docs/equations.md E-Spike). A step (a real jump of the field, a new
//     attitude of a piecewise-constant run) moves the next sample too, so c > r and it passes.
//     The record is flagged kOutSpike and counted (spikes); the SensorLoop keeps it from the
//     calibrator. The screen needs the next sample: a sample waits for it as for its attitude
//     (within the horizon); one processed without it (horizon 0, flush) is not screened.
// Header-only, Scalar-templated, fixed memory, noexcept, no heap.
#pragma once

#include <algorithm>
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
  // Move time_offset_us by the step a calibration asks for (SensorLoop::take_time_offset_step_us:
  // the offset its candidate found in the data); off when the offset is configured as known.
  bool adopt_calibration_time_offset{true};
  std::uint32_t horizon_us{50'000};  // longest wait for bracketing INS samples
  // Expected cadences (missing/gap/jump counters), whole microseconds: integer arithmetic keeps
  // soft-float double off the M4F's per-sample path.
  std::uint32_t mag_period_us{5'000};
  std::uint32_t ins_period_us{10'000};
  // Spike screen: r > spike_factor * RMS(r) (0 switches it off). The RMS is learnt from the data
  // (the first kSpikeWarmup screened samples, then a running mean with outliers clipped), so the
  // screen follows the sensor's noise and the motion between samples, with no noise figure.
  Scalar spike_factor{10};
  // ... and r > spike_min_nT: below a nanotesla a lone jump is resolution and rounding (noise-free
  // or heavily quantised data would otherwise have an RMS near zero), not a spike.
  Scalar spike_min_nT{1};
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
  std::uint64_t horizon_expired{0};    // processed without a bracketing INS sample
  std::uint64_t extrapolated{0};       // records flagged kOutAttExtrapolated
  std::uint64_t queue_full{0};         // processed early because the queue was full
  std::uint64_t max_queued{0};         // deepest the queue has been
  std::uint64_t spikes{0};             // records flagged kOutSpike
  std::uint64_t spike_screened{0};     // samples the spike screen judged (had both neighbours)
  std::uint64_t time_offset_steps{0};  // time offset moved for a calibration (adopted or undone)
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
      if (s.t_us <= mag_newest_us_) {
        flush(emit);
        have_prev_ = false;  // the spike screen's neighbour is of the old time base too
      }
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
  // Off: the offset is known (configured or overridden); a calibration's own is not adopted.
  void set_adopt_calibration_time_offset(bool on) noexcept {
    config_.adopt_calibration_time_offset = on;
  }

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
      // The spike screen wants the next sample too (unless the horizon is up).
      const bool next_in = count_ >= 2 || !(config_.spike_factor > 0);
      if (!(bracketed && next_in) && !expired) return;
      process_front(emit);
    }
  }

  static bool screenable(const MagSample<Scalar>& s) noexcept {
    return !s.device_error && std::isfinite(s.m_nT(0)) && std::isfinite(s.m_nT(1)) &&
           std::isfinite(s.m_nT(2));
  }

  // E-Spike: judges s against the last sample that passed and the next one in the queue. Plain
  // scalar arithmetic: it runs on every sample of the M4F image (no expression temporaries).
  bool is_spike(const MagSample<Scalar>& s) noexcept {
    if (!(config_.spike_factor > 0) || !have_prev_ || count_ < 2 || !screenable(s)) return false;
    const MagSample<Scalar>& n = queue_[(head_ + 1) % QueueCapacity];
    if (!screenable(n) || !(prev_t_us_ < s.t_us && s.t_us < n.t_us)) return false;
    // Neighbours more than 10 periods apart are a gap: no judgement across it. The time
    // differences fit 32 bits then: no soft-float 64-bit conversion on the M4F.
    const std::uint64_t span = n.t_us - prev_t_us_;
    if (span > 10 * std::uint64_t{config_.mag_period_us > 0 ? config_.mag_period_us : 1})
      return false;
    // Uniform spacing (the usual case) needs no division.
    const auto before = static_cast<std::uint32_t>(s.t_us - prev_t_us_);
    const auto whole = static_cast<std::uint32_t>(span);
    const Scalar w = 2 * before == whole ? Scalar(0.5)
                                         : static_cast<Scalar>(before) / static_cast<Scalar>(whole);
    Scalar r2 = 0;
    Scalar c2 = 0;
    for (int i = 0; i < 3; ++i) {
      const Scalar step = n.m_nT(i) - prev_m_nT_(i);
      const Scalar d = s.m_nT(i) - prev_m_nT_(i) - w * step;
      r2 += d * d;
      c2 += step * step;
    }
    ++counters_.spike_screened;
    if (spike_warm_ < kSpikeWarmup) {
      // The first samples give the start through their median (a spike among them must not
      // inflate it): the median of r^2/E[r^2] (chi-square, 3 degrees of freedom, over 3) is 0.79.
      spike_warmup_r2_[spike_warm_++] = r2;
      if (spike_warm_ == kSpikeWarmup) {
        Scalar* mid = spike_warmup_r2_ + kSpikeWarmup / 2;
        std::nth_element(spike_warmup_r2_, mid, spike_warmup_r2_ + kSpikeWarmup);
        spike_ms_ = *mid / Scalar(0.79);
      }
      return false;
    }
    const Scalar k2 = config_.spike_factor * config_.spike_factor;
    const Scalar floor2 = config_.spike_min_nT * config_.spike_min_nT;
    if (r2 > k2 * spike_ms_ && r2 > c2 && r2 > floor2) return true;
    // Running mean square of r, each value clipped at 9x the mean (a step's large r barely
    // moves it; a lasting rise of the noise is followed within a few hundred samples).
    const Scalar cap = Scalar(9) * spike_ms_;
    spike_ms_ += ((r2 < cap ? r2 : cap) - spike_ms_) * Scalar(1.0 / 64);  // r2 is finite here
    return false;
  }

  template <typename Emit>
  void process_front(Emit& emit) noexcept {
    MagSample<Scalar> s = queue_[head_];
    s.spike = is_spike(s);
    if (s.spike) {
      ++counters_.spikes;
    } else if (config_.spike_factor > 0 && screenable(s)) {
      prev_m_nT_ = s.m_nT;
      prev_t_us_ = s.t_us;
      have_prev_ = true;
    }
    head_ = (head_ + 1) % QueueCapacity;
    --count_;
    // Paired as a candidate was fitted (or back, when refused) from the first sample after its
    // solve, whether the solve ran inline (in the previous sample) or was installed between.
    const std::int64_t step = loop_.take_time_offset_step_us();
    if (step != 0 && config_.adopt_calibration_time_offset) {
      config_.time_offset_us += step;
      ++counters_.time_offset_steps;
    }
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
  // Spike screen state.
  static constexpr std::uint32_t kSpikeWarmup = 16;
  Vec3<Scalar> prev_m_nT_ = Vec3<Scalar>::Zero();
  std::uint64_t prev_t_us_{0};
  bool have_prev_{false};
  std::uint32_t spike_warm_{0};
  Scalar spike_ms_{0};  // running mean square of r
  Scalar spike_warmup_r2_[kSpikeWarmup]{};
};

}  // namespace magvec::core
