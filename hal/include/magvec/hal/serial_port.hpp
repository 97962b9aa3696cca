// HAL: a byte stream (UART, termios tty, pty, simulated). No framing: codecs do that.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

class SerialPort {
 public:
  // Reads up to buf.size() bytes that are available, waiting at most timeout_us (0 = poll) for
  // the first one. n_read is set in every case. kOk if n_read > 0, kTimeout if nothing arrived.
  virtual Status read(std::span<std::uint8_t> buf, std::size_t& n_read,
                      std::uint32_t timeout_us) noexcept = 0;
  // Writes all bytes or reports why not; n_written is the number actually accepted.
  virtual Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept = 0;

 protected:
  ~SerialPort() = default;
};

}  // namespace magvec::hal
