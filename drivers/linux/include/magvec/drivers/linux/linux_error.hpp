// Linux transports: OS error reporting. The HAL methods return hal::Status only; each Linux
// driver additionally keeps the last OS error as a human-readable message that names the device
// and the errno, e.g. "spidev /dev/spidev0.0: open: No such file or directory (errno 2)".
#pragma once

#include <string>
#include <string_view>

namespace magvec::drivers {

struct OsError {
  std::string message;
  int error_number{0};  // errno value (0 when the error is not an OS error, e.g. a bad config)
};

// "<device>: <operation>: <strerror(error_number)> (errno <error_number>)".
OsError make_os_error(std::string_view device, std::string_view operation, int error_number);
// Same without an errno: "<device>: <operation>: <detail>".
OsError make_error(std::string_view device, std::string_view operation, std::string_view detail,
                   int error_number = 0);

// noexcept variants for the HAL methods: on allocation failure only error_number is updated.
void assign_os_error(OsError& dst, std::string_view device, std::string_view operation,
                     int error_number) noexcept;
void assign_error(OsError& dst, std::string_view device, std::string_view operation,
                  std::string_view detail, int error_number = 0) noexcept;

// Stores `e` into *out when out is not null (the factories' optional error output).
inline void report_error(OsError* out, OsError e) {
  if (out != nullptr) *out = std::move(e);
}

}  // namespace magvec::drivers
