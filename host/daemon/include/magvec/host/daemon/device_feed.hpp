// DeviceFeed: how magvecd's real mode hands the events of its two devices (a magnetometer with a
// data-ready line or a serial line, an INS on CAN) to the pipeline. The time ordering is the
// pipeline's job (core::SamplePipeline: a magnetometer sample waits for the INS samples that
// bracket it, up to the fusion horizon), so the feed only has to deliver every INS sample as soon
// as it has been received and before the magnetometer samples read after it:
//   1. every INS sample already received;
//   2. one magnetometer read, waiting at most max_wait_us;
//   3. every INS sample received meanwhile, then the magnetometer sample.
// INS samples later than the magnetometer sample are fed too: they cannot disturb its
// interpolation (the buffer is ordered by time) and holding them back would leave the sample
// without the epoch that brackets it, i.e. with a held attitude.
// With a scalar magnetometer, its readings are drained with the INS samples and each
// magnetometer sample goes through a pipeline::ScalarAligner, which hands it on with F at its own
// time once the reading after it has arrived (or its horizon expired); without one, every sample
// carries the constant reference F at once.
// Only HAL interfaces: tests drive it with fake sources (INS late, early, in bursts).
#pragma once

#include <cstdint>
#include <memory>

#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/scalar_source.hpp"
#include "magvec/pipeline/scalar_aligner.hpp"

namespace magvec::host::daemon {

enum class FeedResult : std::uint8_t {
  kSample,  // a magnetometer sample was fed
  kIdle,    // no magnetometer sample within the wait
  kError,   // the magnetometer read failed (on_read_error was called)
};

class DeviceFeed {
 public:
  using Aligner = pipeline::ScalarAligner<64, 1024>;

  DeviceFeed(hal::MagnetometerSource& mag, hal::AttitudeSource& ins, double reference_nT) noexcept
      : mag_(mag), ins_(ins), reference_nT_(reference_nT) {}
  // F from `scalar` (align.fallback_nT where it has no reading near a sample).
  DeviceFeed(hal::MagnetometerSource& mag, hal::AttitudeSource& ins, hal::ScalarSource& scalar,
             const pipeline::ScalarAlignerConfig& align)
      : mag_(mag),
        ins_(ins),
        reference_nT_(align.fallback_nT),
        scalar_(&scalar),
        aligner_(std::make_unique<Aligner>(align)),
        max_gap_us_(align.max_gap_us) {}

  // Handler: on_attitude(const hal::AttitudeSample&), on_magnetometer(const
  // hal::MagnetometerSample&, double f_ref_nT), on_read_error(hal::Status).
  template <typename Handler>
  FeedResult poll(Handler& h, std::uint32_t max_wait_us) {
    drain_ins(h);
    drain_scalar(h);
    hal::MagnetometerSample s;
    const hal::Status st = mag_.read(s, max_wait_us);
    drain_ins(h);
    drain_scalar(h);
    if (st == hal::Status::kOk) {
      if (aligner_) {
        count_scalar_silence(s.t_us);
        aligner_->on_magnetometer(
            s, [&h](const hal::MagnetometerSample& m, double f) { h.on_magnetometer(m, f); });
      } else {
        h.on_magnetometer(s, reference_nT_);
      }
      return FeedResult::kSample;
    }
    if (st == hal::Status::kTimeout || st == hal::Status::kNoData) return FeedResult::kIdle;
    h.on_read_error(st);
    return FeedResult::kError;
  }

  // The samples still waiting for a scalar reading, with what F they can get now.
  template <typename Handler>
  void flush(Handler& h) {
    if (aligner_) {
      aligner_->flush(
          [&h](const hal::MagnetometerSample& m, double f) { h.on_magnetometer(m, f); });
    }
  }
  // The F of the samples read from now on, without a scalar magnetometer (the model's at the INS
  // position, position_reference.hpp).
  void set_reference_nT(double f_nT) noexcept { reference_nT_ = f_nT; }
  // nullptr without a scalar magnetometer.
  const pipeline::ScalarAlignerCounters* aligner_counters() const noexcept {
    return aligner_ ? &aligner_->counters() : nullptr;
  }
  // Scalar lines the source rejected (its counters say why) or transport failures.
  std::uint64_t scalar_read_errors() const noexcept { return scalar_read_errors_; }
  // Silences of the scalar magnetometer: every max_gap_us of magnetometer time (the longest gap
  // the aligner interpolates across) without a new reading counts once, so a stuck or
  // unplugged instrument shows as a growing count, not only as samples with the fallback F.
  std::uint64_t scalar_timeouts() const noexcept { return scalar_timeouts_; }

 private:
  // Every reading received so far; rejected lines are counted by the source (and here), a
  // transport failure ends the drain (the port reconnects on later reads).
  template <typename Handler>
  void drain_scalar(Handler& h) {
    if (scalar_ == nullptr) return;
    hal::ScalarSample r;
    for (int guard = 0; guard < kMaxPerDrain; ++guard) {
      const hal::Status st = scalar_->read(r, 0);
      if (st == hal::Status::kOk) {
        if (silence_from_us_ == kNoTime || r.t_us > silence_from_us_) silence_from_us_ = r.t_us;
        aligner_->on_scalar(
            r, [&h](const hal::MagnetometerSample& m, double f) { h.on_magnetometer(m, f); });
        continue;
      }
      if (st == hal::Status::kTimeout || st == hal::Status::kNoData) return;
      ++scalar_read_errors_;
      if (st == hal::Status::kBusError) return;
    }
  }
  void count_scalar_silence(std::uint64_t t_us) noexcept {
    if (silence_from_us_ == kNoTime) silence_from_us_ = t_us;
    const std::uint64_t gap_us = max_gap_us_ > 0 ? max_gap_us_ : 1;
    while (t_us >= silence_from_us_ + gap_us) {
      ++scalar_timeouts_;
      silence_from_us_ += gap_us;
    }
  }
  template <typename Handler>
  void drain_ins(Handler& h) {
    hal::AttitudeSample a;
    for (int guard = 0; guard < kMaxPerDrain && ins_.read(a, 0) == hal::Status::kOk; ++guard)
      h.on_attitude(a);
  }
  static constexpr int kMaxPerDrain = 256;

  hal::MagnetometerSource& mag_;
  hal::AttitudeSource& ins_;
  double reference_nT_;
  hal::ScalarSource* scalar_{nullptr};
  std::unique_ptr<Aligner> aligner_;
  std::uint64_t scalar_read_errors_{0};
  static constexpr std::uint64_t kNoTime = ~std::uint64_t{0};
  std::uint64_t max_gap_us_{0};
  std::uint64_t silence_from_us_{kNoTime};  // newest reading, or the first sample, or after a count
  std::uint64_t scalar_timeouts_{0};
};

}  // namespace magvec::host::daemon
