// Linux transports: hal::SpiBus over spidev (Documentation/spi/spidev.rst): one full-duplex
// SPI_IOC_MESSAGE(1) per transfer with chip select held for the whole transfer; mode, speed and
// word size set with SPI_IOC_WR_MODE / SPI_IOC_WR_MAX_SPEED_HZ / SPI_IOC_WR_BITS_PER_WORD at open.
// The ADS131M04 front end uses SPI mode 1 (CPOL 0, CPHA 1), hence the default.
#pragma once

#include <cstdint>
#include <memory>
#include <span>
#include <string>

#include "magvec/drivers/linux/linux_error.hpp"
#include "magvec/hal/spi_bus.hpp"

namespace magvec::drivers {

struct SpidevConfig {
  std::string device{"/dev/spidev0.0"};
  std::uint32_t speed_hz{8'000'000};
  std::uint8_t mode{1};  // SPI mode 0..3 (CPOL << 1 | CPHA)
  std::uint8_t bits_per_word{8};
};

class SpidevBus final : public hal::SpiBus {
 public:
  // spidev's default transfer buffer (module parameter bufsiz); larger transfers are rejected
  // with kInvalidArgument before reaching the kernel.
  static constexpr std::size_t kMaxTransfer = 4096;

  // Opens the device and applies the configuration; nullptr and *err on failure.
  static std::unique_ptr<SpidevBus> open(const SpidevConfig& config, OsError* err);
  ~SpidevBus();
  SpidevBus(const SpidevBus&) = delete;
  SpidevBus& operator=(const SpidevBus&) = delete;

  // kOk, kInvalidArgument (size mismatch / too long), kBusError (ioctl failed: see last_error()).
  hal::Status transfer(std::span<const std::uint8_t> tx,
                       std::span<std::uint8_t> rx) noexcept override;

  const SpidevConfig& config() const noexcept { return config_; }
  const OsError& last_error() const noexcept { return last_error_; }
  std::uint32_t transfers() const noexcept { return transfers_; }
  std::uint32_t errors() const noexcept { return errors_; }

 private:
  SpidevBus(int fd, SpidevConfig config);

  int fd_{-1};
  SpidevConfig config_;
  std::string name_;  // "spidev <device>", for messages
  OsError last_error_;
  std::uint32_t transfers_{0};
  std::uint32_t errors_{0};
};

}  // namespace magvec::drivers
