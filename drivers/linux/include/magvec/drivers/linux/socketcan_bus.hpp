// Linux transports: hal::CanBus over a SocketCAN raw socket (Documentation/networking/can.rst).
// - CAN_RAW_FILTER: only the configured IDs reach the process (the kernel drops the rest).
// - Receive time: the kernel's software receive timestamp (SO_TIMESTAMPNS, CLOCK_REALTIME, taken
//   when the driver hands the frame to the stack), converted onto the CLOCK_MONOTONIC base of
//   LinuxClock. Frames without a timestamp get the time of the recvmsg() call.
// - Error frames (CAN_RAW_ERR_FILTER, all classes): receive() returns kBusError for each, with the
//   frame in `out` (id = error class bits), and counts it in error_frames().
// - SO_RXQ_OVFL: the kernel's count of frames dropped because the socket queue was full.
// Classic CAN only (no CAN FD); RTR frames are delivered with their DLC and zero data.
#pragma once

#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "magvec/drivers/linux/linux_error.hpp"
#include "magvec/hal/can_bus.hpp"

namespace magvec::drivers {

struct CanFilterSpec {
  std::uint32_t id{0};
  std::uint32_t mask{0x7FF};  // bits of `id` that must match (use 0x1FFFFFFF for extended IDs)
  bool extended{false};       // match only extended (true) or only standard (false) frames
};

struct SocketCanConfig {
  std::string interface { "can0" };
  std::vector<CanFilterSpec> filters;  // empty = receive every frame
  bool receive_error_frames{true};
};

class SocketCanBus final : public hal::CanBus {
 public:
  // Opens and binds the socket; nullptr and *err if AF_CAN is unavailable, the interface does
  // not exist, or a filter is invalid.
  static std::unique_ptr<SocketCanBus> open(const SocketCanConfig& config, OsError* err);
  ~SocketCanBus();
  SocketCanBus(const SocketCanBus&) = delete;
  SocketCanBus& operator=(const SocketCanBus&) = delete;

  // kOk, kTimeout, kBusError (error frame received, or a socket error: see last_error()).
  hal::Status receive(hal::CanFrame& out, std::uint32_t timeout_us) noexcept override;
  // kOk, kInvalidArgument (dlc > 8, id out of range), kOverflow (tx queue full), kBusError.
  hal::Status send(const hal::CanFrame& frame) noexcept override;

  std::uint32_t error_frames() const noexcept { return error_frames_; }
  std::uint32_t dropped_frames() const noexcept { return dropped_frames_; }      // SO_RXQ_OVFL
  std::uint32_t last_error_class() const noexcept { return last_error_class_; }  // CAN_ERR_* bits
  const OsError& last_error() const noexcept { return last_error_; }
  const SocketCanConfig& config() const noexcept { return config_; }

 private:
  SocketCanBus(int fd, SocketCanConfig config);

  int fd_{-1};
  SocketCanConfig config_;
  std::string name_;  // "socketcan <interface>", for messages
  OsError last_error_;
  std::uint32_t error_frames_{0};
  std::uint32_t dropped_frames_{0};
  std::uint32_t last_error_class_{0};
};

}  // namespace magvec::drivers
