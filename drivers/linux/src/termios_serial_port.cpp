// Linux transports: termios serial port (termios(3), tty_ioctl(4)) with unplug/re-plug handling.
#include "magvec/drivers/linux/termios_serial_port.hpp"

#include <fcntl.h>
#include <poll.h>
#include <termios.h>
#include <unistd.h>

#include <cerrno>

#include "magvec/drivers/linux/linux_clock.hpp"

namespace magvec::drivers {
namespace {

bool baud_constant(std::uint32_t baud, speed_t& out) noexcept {
  switch (baud) {
    // clang-format off
    case 50: out = B50; return true;
    case 75: out = B75; return true;
    case 110: out = B110; return true;
    case 134: out = B134; return true;
    case 150: out = B150; return true;
    case 200: out = B200; return true;
    case 300: out = B300; return true;
    case 600: out = B600; return true;
    case 1200: out = B1200; return true;
    case 1800: out = B1800; return true;
    case 2400: out = B2400; return true;
    case 4800: out = B4800; return true;
    case 9600: out = B9600; return true;
    case 19200: out = B19200; return true;
    case 38400: out = B38400; return true;
    case 57600: out = B57600; return true;
    case 115200: out = B115200; return true;
    case 230400: out = B230400; return true;
    case 460800: out = B460800; return true;
    case 500000: out = B500000; return true;
    case 576000: out = B576000; return true;
    case 921600: out = B921600; return true;
    case 1000000: out = B1000000; return true;
    case 1152000: out = B1152000; return true;
    case 1500000: out = B1500000; return true;
    case 2000000: out = B2000000; return true;
    case 2500000: out = B2500000; return true;
    case 3000000: out = B3000000; return true;
    case 3500000: out = B3500000; return true;
    case 4000000: out = B4000000; return true;
      // clang-format on
    default:
      return false;
  }
}

// Opens and configures the tty: raw 8N1, no flow control, non-blocking. -1 and `err` on failure.
int open_tty(const SerialConfig& config, const std::string& name, OsError& err) {
  speed_t speed{};
  if (!baud_constant(config.baud, speed)) {
    err = make_error(name, "configure",
                     "unsupported baud rate " + std::to_string(config.baud) +
                         " (use a standard termios rate, 50 .. 4000000)",
                     EINVAL);
    return -1;
  }
  const int fd = ::open(config.device.c_str(), O_RDWR | O_NOCTTY | O_NONBLOCK | O_CLOEXEC);
  if (fd < 0) {
    err = make_os_error(name, "open", errno);
    return -1;
  }
  termios tio{};
  const char* op = nullptr;
  if (::tcgetattr(fd, &tio) < 0) {
    op = "tcgetattr (not a tty?)";
  } else {
    ::cfmakeraw(&tio);
    tio.c_cflag &= ~static_cast<tcflag_t>(CSTOPB | CRTSCTS | PARENB | CSIZE);
    tio.c_cflag |= CS8 | CLOCAL | CREAD;
    tio.c_iflag &= ~static_cast<tcflag_t>(IXON | IXOFF | IXANY);
    tio.c_cc[VMIN] = 0;
    tio.c_cc[VTIME] = 0;
    if (::cfsetispeed(&tio, speed) < 0 || ::cfsetospeed(&tio, speed) < 0) {
      op = "cfsetspeed";
    } else if (::tcsetattr(fd, TCSANOW, &tio) < 0) {
      op = "tcsetattr";
    }
  }
  if (op != nullptr) {
    const int e = errno;
    ::close(fd);
    err = make_os_error(name, op, e);
    return -1;
  }
  return fd;
}

bool is_unplug_errno(int e) noexcept {
  return e == EIO || e == ENODEV || e == EBADF || e == ENXIO;
}

void sleep_us(std::uint64_t us) noexcept {
  const timespec ts = timespec_from_us(us);
  ::ppoll(nullptr, 0, &ts, nullptr);
}

}  // namespace

std::unique_ptr<TermiosSerialPort> TermiosSerialPort::open(const SerialConfig& config,
                                                           OsError* err) {
  const std::string name = "serial " + config.device;
  OsError e;
  const int fd = open_tty(config, name, e);
  if (fd < 0) {
    report_error(err, std::move(e));
    return nullptr;
  }
  return std::unique_ptr<TermiosSerialPort>(new TermiosSerialPort(fd, config));
}

TermiosSerialPort::TermiosSerialPort(int fd, SerialConfig config)
    : fd_(fd), config_(std::move(config)), name_("serial " + config_.device) {}

TermiosSerialPort::~TermiosSerialPort() {
  if (fd_ >= 0) ::close(fd_);
}

void TermiosSerialPort::disconnect(const char* operation, int error_number) noexcept {
  if (fd_ >= 0) ::close(fd_);
  fd_ = -1;
  ++disconnects_;
  if (error_number == 0) {
    assign_error(last_error_, name_, operation, "device hung up (end of file)");
  } else {
    assign_os_error(last_error_, name_, operation, error_number);
  }
  next_attempt_us_ = monotonic_us() + std::uint64_t{config_.reconnect_interval_ms} * 1000;
}

bool TermiosSerialPort::try_reconnect() noexcept {
  if (fd_ >= 0) return true;
  const std::uint64_t now = monotonic_us();
  if (now < next_attempt_us_) return false;
  next_attempt_us_ = now + std::uint64_t{config_.reconnect_interval_ms} * 1000;
  try {
    OsError e;
    const int fd = open_tty(config_, name_, e);
    if (fd < 0) {
      last_error_ = std::move(e);
      return false;
    }
    fd_ = fd;
    ++reconnects_;
    return true;
  } catch (...) {
    return false;  // out of memory while formatting the message: retry later
  }
}

hal::Status TermiosSerialPort::read(std::span<std::uint8_t> buf, std::size_t& n_read,
                                    std::uint32_t timeout_us) noexcept {
  n_read = 0;
  if (buf.empty()) return hal::Status::kInvalidArgument;
  const std::uint64_t deadline = monotonic_us() + timeout_us;
  for (;;) {
    const std::uint64_t now = monotonic_us();
    const std::uint64_t remaining = deadline > now ? deadline - now : 0;
    if (fd_ < 0 && !try_reconnect()) {
      // Disconnected: wait for the next re-open attempt or the deadline, whichever comes first.
      if (remaining == 0) return hal::Status::kBusError;
      const std::uint64_t until_attempt = next_attempt_us_ > now ? next_attempt_us_ - now : 0;
      sleep_us(until_attempt < remaining ? until_attempt : remaining);
      continue;
    }
    pollfd pfd{fd_, POLLIN, 0};
    const timespec ts = timespec_from_us(remaining);
    const int rc = ::ppoll(&pfd, 1, &ts, nullptr);
    if (rc < 0) {
      if (errno == EINTR) continue;
      assign_os_error(last_error_, name_, "poll", errno);
      return hal::Status::kBusError;
    }
    if (rc == 0) return hal::Status::kTimeout;
    if ((pfd.revents & POLLNVAL) != 0) {
      disconnect("poll", EBADF);
      return hal::Status::kBusError;
    }
    const ssize_t r = ::read(fd_, buf.data(), buf.size());
    if (r > 0) {
      n_read = static_cast<std::size_t>(r);
      return hal::Status::kOk;
    }
    if (r == 0) {  // readable but no bytes: the tty was hung up
      disconnect("read", 0);
      return hal::Status::kBusError;
    }
    const int e = errno;
    if (e == EAGAIN || e == EINTR) {
      if (remaining == 0) return hal::Status::kTimeout;
      continue;
    }
    if (is_unplug_errno(e)) {
      disconnect("read", e);
    } else {
      assign_os_error(last_error_, name_, "read", e);
    }
    return hal::Status::kBusError;
  }
}

hal::Status TermiosSerialPort::write(std::span<const std::uint8_t> data,
                                     std::size_t& n_written) noexcept {
  n_written = 0;
  if (fd_ < 0 && !try_reconnect()) return hal::Status::kBusError;
  const std::uint64_t deadline = monotonic_us() + std::uint64_t{config_.write_timeout_ms} * 1000;
  while (n_written < data.size()) {
    const ssize_t r = ::write(fd_, data.data() + n_written, data.size() - n_written);
    if (r > 0) {
      n_written += static_cast<std::size_t>(r);
      continue;
    }
    const int e = r < 0 ? errno : EAGAIN;
    if (e == EINTR) continue;
    if (e != EAGAIN) {
      if (is_unplug_errno(e)) {
        disconnect("write", e);
      } else {
        assign_os_error(last_error_, name_, "write", e);
      }
      return hal::Status::kBusError;
    }
    const std::uint64_t now = monotonic_us();
    if (now >= deadline) {
      assign_error(last_error_, name_, "write", "timed out (output buffer full)", ETIMEDOUT);
      return hal::Status::kTimeout;
    }
    pollfd pfd{fd_, POLLOUT, 0};
    const timespec ts = timespec_from_us(deadline - now);
    if (::ppoll(&pfd, 1, &ts, nullptr) < 0 && errno != EINTR) {
      assign_os_error(last_error_, name_, "poll", errno);
      return hal::Status::kBusError;
    }
  }
  return hal::Status::kOk;
}

}  // namespace magvec::drivers
