// Linux transports: CLOCK_MONOTONIC time base and kernel timestamp conversion.
#include "magvec/drivers/linux/linux_clock.hpp"

#include <cstdint>
#include <cstdlib>

namespace magvec::drivers {
namespace {

std::int64_t clock_ns(clockid_t id) noexcept {
  timespec ts{};
  ::clock_gettime(id, &ts);
  return timespec_ns(ts);
}

std::uint64_t to_us(std::int64_t ns) noexcept {
  return ns <= 0 ? 0u : static_cast<std::uint64_t>(ns / 1000);
}

}  // namespace

std::int64_t timespec_ns(const timespec& ts) noexcept {
  return static_cast<std::int64_t>(ts.tv_sec) * 1'000'000'000 +
         static_cast<std::int64_t>(ts.tv_nsec);
}

timespec timespec_from_us(std::uint64_t us) noexcept {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(us / 1'000'000);
  ts.tv_nsec = static_cast<long>((us % 1'000'000) * 1000);
  return ts;
}
std::int64_t monotonic_ns() noexcept {
  return clock_ns(CLOCK_MONOTONIC);
}
std::int64_t realtime_ns() noexcept {
  return clock_ns(CLOCK_REALTIME);
}
std::uint64_t monotonic_us() noexcept {
  return to_us(monotonic_ns());
}

std::uint64_t realtime_to_monotonic_us(const timespec& ts) noexcept {
  // Offset sampled as real - mono with the monotonic reading taken on both sides, so that a
  // preemption between the two calls does not bias it by more than half the gap; the tightest of
  // three brackets is used, because one preemption can last milliseconds (seen in the VM tests:
  // a frame stamped 2.8 ms before it was sent).
  std::int64_t best_gap = INT64_MAX;
  std::int64_t offset = 0;
  for (int i = 0; i < 3; ++i) {
    const std::int64_t m0 = monotonic_ns();
    const std::int64_t r = realtime_ns();
    const std::int64_t m1 = monotonic_ns();
    if (m1 - m0 < best_gap) {
      best_gap = m1 - m0;
      offset = r - (m0 + (m1 - m0) / 2);
    }
  }
  return to_us(timespec_ns(ts) - offset);
}

std::uint64_t kernel_event_to_monotonic_us(const timespec& ts) noexcept {
  const std::int64_t t = timespec_ns(ts);
  const std::int64_t m = monotonic_ns();
  const std::int64_t r = realtime_ns();
  if (std::llabs(t - m) <= std::llabs(t - r)) return to_us(t);
  return realtime_to_monotonic_us(ts);
}

}  // namespace magvec::drivers
