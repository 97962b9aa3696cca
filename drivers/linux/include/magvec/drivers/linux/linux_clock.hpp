// Linux transports: the hal::Clock of magvecd. CLOCK_MONOTONIC in microseconds; every Linux
// driver converts its kernel timestamps (SocketCAN receive time, GPIO line events) onto this base
// so that attitude and magnetometer samples can be matched (docs/conventions.md: uint64 us).
#pragma once

#include <cstdint>
#include <ctime>

#include "magvec/hal/clock.hpp"

namespace magvec::drivers {

// CLOCK_MONOTONIC / CLOCK_REALTIME now, in microseconds / nanoseconds.
std::uint64_t monotonic_us() noexcept;
std::int64_t monotonic_ns() noexcept;
std::int64_t realtime_ns() noexcept;
std::int64_t timespec_ns(const timespec& ts) noexcept;
// A duration in microseconds as a timespec (for ppoll/pselect/gpiod waits).
timespec timespec_from_us(std::uint64_t us) noexcept;

// Converts a CLOCK_REALTIME kernel timestamp onto the CLOCK_MONOTONIC base by the current
// offset between the two clocks (sampled now; a later NTP step between the event and this call is
// the residual error, normally microseconds). Results before the epoch of CLOCK_MONOTONIC clamp to
// 0.
std::uint64_t realtime_to_monotonic_us(const timespec& ts) noexcept;

// A kernel event timestamp whose clock is not known in advance (GPIO v1 line events were
// CLOCK_REALTIME before Linux 5.7 and CLOCK_MONOTONIC since): the clock whose "now" is nearer is
// taken (the two differ by decades, so the choice is unambiguous), converted to monotonic us.
std::uint64_t kernel_event_to_monotonic_us(const timespec& ts) noexcept;

class LinuxClock final : public hal::Clock {
 public:
  std::uint64_t now_us() const noexcept override { return monotonic_us(); }
};

}  // namespace magvec::drivers
