// Linux transports: hal::SerialPort over a termios tty (USB serial adapter, UART, pty).
// Raw 8N1 (cfmakeraw, CLOCAL | CREAD, no flow control), non-blocking fd with poll()-based
// timeouts. Unplug handling: when the kernel reports the device gone (read returns 0 after
// POLLIN/POLLHUP, or EIO / ENODEV / EBADF / ENXIO), the fd is closed and re-opened by path every
// reconnect_interval_ms; meanwhile read()/write() return kBusError (read() waits out its timeout
// while retrying, so a caller's loop does not spin). Re-opening by path follows symlinks such as
// /dev/serial/by-id/..., so a re-plugged adapter is found again even under a new ttyUSBn.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>

#include "magvec/drivers/linux/linux_error.hpp"
#include "magvec/hal/serial_port.hpp"

namespace magvec::drivers {

struct SerialConfig {
  std::string device;
  std::uint32_t baud{115200};  // one of the standard termios rates (50 .. 4000000)
  std::uint32_t reconnect_interval_ms{1000};
  std::uint32_t write_timeout_ms{1000};  // write() gives up (kTimeout) after this long
};

class TermiosSerialPort final : public hal::SerialPort {
 public:
  // Opens and configures the device; nullptr and *err if it cannot (missing device, not a tty,
  // unsupported baud rate).
  static std::unique_ptr<TermiosSerialPort> open(const SerialConfig& config, OsError* err);
  ~TermiosSerialPort();
  TermiosSerialPort(const TermiosSerialPort&) = delete;
  TermiosSerialPort& operator=(const TermiosSerialPort&) = delete;

  // kOk (n_read > 0), kTimeout, kBusError (disconnected or a read error; see last_error()).
  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n_read,
                   std::uint32_t timeout_us) noexcept override;
  // kOk when all bytes were written, kTimeout after write_timeout_ms, kBusError when disconnected.
  hal::Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept override;

  bool connected() const noexcept { return fd_ >= 0; }
  std::uint32_t reconnects() const noexcept { return reconnects_; }    // successful re-opens
  std::uint32_t disconnects() const noexcept { return disconnects_; }  // unplugs detected
  const OsError& last_error() const noexcept { return last_error_; }
  const SerialConfig& config() const noexcept { return config_; }

 private:
  TermiosSerialPort(int fd, SerialConfig config);
  void disconnect(const char* operation, int error_number) noexcept;
  bool try_reconnect() noexcept;  // true when connected afterwards

  int fd_{-1};
  SerialConfig config_;
  std::string name_;  // "serial <device>", for messages
  OsError last_error_;
  std::uint64_t next_attempt_us_{0};
  std::uint32_t reconnects_{0};
  std::uint32_t disconnects_{0};
};

}  // namespace magvec::drivers
