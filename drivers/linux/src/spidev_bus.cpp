// Linux transports: spidev SpiBus (Documentation/spi/spidev.rst, linux/spi/spidev.h).
#include "magvec/drivers/linux/spidev_bus.hpp"

#include <fcntl.h>
#include <linux/spi/spidev.h>
#include <sys/ioctl.h>
#include <unistd.h>

#include <cerrno>
#include <cstring>

namespace magvec::drivers {
namespace {

std::string device_name(const SpidevConfig& c) {
  return "spidev " + c.device;
}

}  // namespace

std::unique_ptr<SpidevBus> SpidevBus::open(const SpidevConfig& config, OsError* err) {
  const std::string dev = device_name(config);
  if (config.mode > 3) {
    report_error(err, make_error(dev, "configure", "SPI mode must be 0..3", EINVAL));
    return nullptr;
  }
  if (config.speed_hz == 0 || config.bits_per_word == 0 || config.bits_per_word > 32) {
    report_error(
        err, make_error(dev, "configure", "speed_hz must be > 0 and bits_per_word 1..32", EINVAL));
    return nullptr;
  }
  const int fd = ::open(config.device.c_str(), O_RDWR | O_CLOEXEC);
  if (fd < 0) {
    report_error(err, make_os_error(dev, "open", errno));
    return nullptr;
  }
  std::uint8_t mode = config.mode;
  std::uint8_t bits = config.bits_per_word;
  std::uint32_t speed = config.speed_hz;
  const char* op = nullptr;
  if (::ioctl(fd, SPI_IOC_WR_MODE, &mode) < 0) {
    op = "ioctl SPI_IOC_WR_MODE";
  } else if (::ioctl(fd, SPI_IOC_WR_BITS_PER_WORD, &bits) < 0) {
    op = "ioctl SPI_IOC_WR_BITS_PER_WORD";
  } else if (::ioctl(fd, SPI_IOC_WR_MAX_SPEED_HZ, &speed) < 0) {
    op = "ioctl SPI_IOC_WR_MAX_SPEED_HZ";
  }
  if (op != nullptr) {
    const int e = errno;
    ::close(fd);
    report_error(err, make_os_error(dev, op, e));
    return nullptr;
  }
  return std::unique_ptr<SpidevBus>(new SpidevBus(fd, config));
}

SpidevBus::SpidevBus(int fd, SpidevConfig config)
    : fd_(fd), config_(std::move(config)), name_(device_name(config_)) {}

SpidevBus::~SpidevBus() {
  if (fd_ >= 0) ::close(fd_);
}

hal::Status SpidevBus::transfer(std::span<const std::uint8_t> tx,
                                std::span<std::uint8_t> rx) noexcept {
  if (tx.size() != rx.size() || tx.size() > kMaxTransfer) return hal::Status::kInvalidArgument;
  if (tx.empty()) return hal::Status::kOk;
  spi_ioc_transfer xfer{};
  std::memset(&xfer, 0, sizeof xfer);
  xfer.tx_buf = reinterpret_cast<std::uintptr_t>(tx.data());
  xfer.rx_buf = reinterpret_cast<std::uintptr_t>(rx.data());
  xfer.len = static_cast<std::uint32_t>(tx.size());
  xfer.speed_hz = config_.speed_hz;
  xfer.bits_per_word = config_.bits_per_word;
  int rc = 0;
  do {
    rc = ::ioctl(fd_, SPI_IOC_MESSAGE(1), &xfer);
  } while (rc < 0 && errno == EINTR);
  if (rc < 0) {
    const int e = errno;
    ++errors_;
    assign_os_error(last_error_, name_, "ioctl SPI_IOC_MESSAGE", e);
    return e == EMSGSIZE || e == EINVAL ? hal::Status::kInvalidArgument : hal::Status::kBusError;
  }
  ++transfers_;
  return hal::Status::kOk;
}

}  // namespace magvec::drivers
