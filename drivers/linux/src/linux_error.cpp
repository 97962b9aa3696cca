// Linux transports: OS error messages naming the device and the errno.
#include "magvec/drivers/linux/linux_error.hpp"

#include <cstring>

namespace magvec::drivers {

OsError make_os_error(std::string_view device, std::string_view operation, int error_number) {
  std::string detail = std::strerror(error_number);
  detail += " (errno ";
  detail += std::to_string(error_number);
  detail += ')';
  return make_error(device, operation, detail, error_number);
}

OsError make_error(std::string_view device, std::string_view operation, std::string_view detail,
                   int error_number) {
  OsError e;
  e.error_number = error_number;
  e.message.reserve(device.size() + operation.size() + detail.size() + 4);
  e.message.append(device).append(": ").append(operation).append(": ").append(detail);
  return e;
}

void assign_os_error(OsError& dst, std::string_view device, std::string_view operation,
                     int error_number) noexcept {
  try {
    dst = make_os_error(device, operation, error_number);
  } catch (...) {
    dst.error_number = error_number;
  }
}

void assign_error(OsError& dst, std::string_view device, std::string_view operation,
                  std::string_view detail, int error_number) noexcept {
  try {
    dst = make_error(device, operation, detail, error_number);
  } catch (...) {
    dst.error_number = error_number;
  }
}

}  // namespace magvec::drivers
