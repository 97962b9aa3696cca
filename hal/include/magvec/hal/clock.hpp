// HAL: monotonic time base (docs/conventions.md: uint64 microseconds, monotonic).
#pragma once

#include <cstdint>

namespace magvec::hal {

class Clock {
 public:
  // Microseconds on a monotonic clock (never steps backwards while the process/MCU runs).
  virtual std::uint64_t now_us() const noexcept = 0;

 protected:
  ~Clock() = default;  // never deleted through the interface (no heap)
};

}  // namespace magvec::hal
