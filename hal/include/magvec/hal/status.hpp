// Common result codes of the HAL (docs/architecture.md#hal). Every HAL call reports failure through
// a Status value: no exceptions, no errno, no OS types. Drivers map their transport errors onto it.
#pragma once

#include <cstdint>

namespace magvec::hal {

enum class Status : std::uint8_t {
  kOk = 0,
  kTimeout,          // nothing arrived within the given timeout (not an error by itself)
  kNoData,           // non-blocking call found nothing to return
  kInvalidArgument,  // caller error: bad size, offset or configuration
  kBusError,         // transport failure (SPI/serial/CAN controller, kernel call)
  kCrcError,         // integrity check failed
  kMalformed,        // bytes arrived but do not form a valid message
  kOverflow,         // a bounded buffer could not take the data
  kNotReady,         // device not initialised or not in the required mode
  kPowerLoss,        // (simulated) supply interruption: the operation did not complete
  kCorrupt,          // stored data failed validation
  kNotFound,         // nothing valid stored
};

constexpr const char* to_string(Status s) noexcept {
  switch (s) {
    case Status::kOk:
      return "ok";
    case Status::kTimeout:
      return "timeout";
    case Status::kNoData:
      return "no data";
    case Status::kInvalidArgument:
      return "invalid argument";
    case Status::kBusError:
      return "bus error";
    case Status::kCrcError:
      return "crc error";
    case Status::kMalformed:
      return "malformed";
    case Status::kOverflow:
      return "overflow";
    case Status::kNotReady:
      return "not ready";
    case Status::kPowerLoss:
      return "power loss";
    case Status::kCorrupt:
      return "corrupt";
    case Status::kNotFound:
      return "not found";
  }
  return "unknown";
}

}  // namespace magvec::hal
