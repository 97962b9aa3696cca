// HAL: classic CAN 2.0 (up to 8 data bytes), as SocketCAN raw sockets or an MCU bxCAN/FDCAN.
#pragma once

#include <array>
#include <cstdint>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

struct CanFrame {
  std::uint32_t id{0};  // 11-bit standard or 29-bit extended identifier
  bool extended{false};
  std::uint8_t dlc{0};                 // 0..8 data bytes
  std::array<std::uint8_t, 8> data{};  // bytes beyond dlc are zero
  std::uint64_t t_us{0};               // receive time (kernel timestamp) on the hal::Clock base
};

class CanBus {
 public:
  // Waits up to timeout_us (0 = poll) for one frame. kOk, kTimeout, or kBusError.
  virtual Status receive(CanFrame& out, std::uint32_t timeout_us) noexcept = 0;
  // Queues one frame for transmission (t_us ignored).
  virtual Status send(const CanFrame& frame) noexcept = 0;

 protected:
  ~CanBus() = default;
};

}  // namespace magvec::hal
