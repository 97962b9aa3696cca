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
// Only HAL interfaces: tests drive it with fake sources (INS late, early, in bursts).
#pragma once

#include <cstdint>

#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"

namespace magvec::host::daemon {

enum class FeedResult : std::uint8_t {
  kSample,  // a magnetometer sample was fed
  kIdle,    // no magnetometer sample within the wait
  kError,   // the magnetometer read failed (on_read_error was called)
};

class DeviceFeed {
 public:
  DeviceFeed(hal::MagnetometerSource& mag, hal::AttitudeSource& ins, double reference_nT) noexcept
      : mag_(mag), ins_(ins), reference_nT_(reference_nT) {}

  // Handler: on_attitude(const hal::AttitudeSample&), on_magnetometer(const
  // hal::MagnetometerSample&, double f_ref_nT), on_read_error(hal::Status).
  template <typename Handler>
  FeedResult poll(Handler& h, std::uint32_t max_wait_us) {
    drain_ins(h);
    hal::MagnetometerSample s;
    const hal::Status st = mag_.read(s, max_wait_us);
    drain_ins(h);
    if (st == hal::Status::kOk) {
      h.on_magnetometer(s, reference_nT_);
      return FeedResult::kSample;
    }
    if (st == hal::Status::kTimeout || st == hal::Status::kNoData) return FeedResult::kIdle;
    h.on_read_error(st);
    return FeedResult::kError;
  }

 private:
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
};

}  // namespace magvec::host::daemon
