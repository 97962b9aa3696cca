// SpidevBus (drivers/linux/spidev_bus.hpp). Error paths run everywhere; the device test needs a
// spidev node answering like an ADS131M04 (env MAGVEC_TEST_SPIDEV, e.g. /dev/spidev0.0; the VM
// suite provides a virtual one) and skips without it. The real Ads131Fluxgate driver initialises
// the device and reads frames over it, checking every frame's CRC. Set MAGVEC_TEST_SPIDEV_CRC=1
// when the device injects CRC errors: they must then be detected and counted.
// MAGVEC_TEST_SPIDEV_LOOPBACK names a spidev node whose controller returns what it receives
// (rx = tx): a check of the transfer path itself, independent of any device protocol.
#include "magvec/drivers/linux/spidev_bus.hpp"

#include <glob.h>

#include <gtest/gtest.h>

#include <array>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <string>
#include <vector>

#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"

namespace {

using namespace magvec;
using drivers::OsError;
using drivers::SpidevBus;
using drivers::SpidevConfig;

std::string env(const char* name) {
  const char* v = std::getenv(name);
  return v != nullptr ? v : "";
}

std::string spidev_unavailable() {
  glob_t g{};
  const bool any = ::glob("/dev/spidev*", 0, nullptr, &g) == 0 && g.gl_pathc > 0;
  ::globfree(&g);
  if (!any) return "no /dev/spidev* on this machine; the VM suite runs this test";
  if (env("MAGVEC_TEST_SPIDEV").empty())
    return "MAGVEC_TEST_SPIDEV not set (spidev node of an ADS131M04-compatible device)";
  return {};
}

// Data ready without a GPIO: the device always has a conversion (the virtual ADC answers at once).
class AlwaysReady final : public hal::DataReadyLine {
 public:
  hal::Status wait_edge(hal::EdgeEvent& out, std::uint32_t) noexcept override {
    out.t_us = drivers::monotonic_us();
    out.edge = hal::Edge::kFalling;
    return hal::Status::kOk;
  }
  std::uint32_t missed_edges() const noexcept override { return 0; }
};

TEST(SpidevErrors, MissingDeviceNamesItAndErrno) {
  SpidevConfig c;
  c.device = "/dev/spidev-magvec9.9";
  OsError err;
  EXPECT_EQ(SpidevBus::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, ENOENT);
  EXPECT_EQ(err.message, "spidev /dev/spidev-magvec9.9: open: No such file or directory (errno 2)");
}

TEST(SpidevErrors, NonSpiDeviceAndBadConfigurationAreClear) {
  SpidevConfig c;
  c.device = "/dev/null";
  OsError err;
  EXPECT_EQ(SpidevBus::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, ENOTTY);
  EXPECT_NE(err.message.find("spidev /dev/null: ioctl SPI_IOC_WR_MODE"), std::string::npos)
      << err.message;
  c.mode = 4;
  EXPECT_EQ(SpidevBus::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, EINVAL);
  EXPECT_NE(err.message.find("SPI mode"), std::string::npos) << err.message;
}

TEST(Spidev, LoopbackReturnsEveryByteUpToTheTransferLimit) {
  if (spidev_unavailable().rfind("no /dev", 0) == 0) GTEST_SKIP() << spidev_unavailable();
  if (env("MAGVEC_TEST_SPIDEV_LOOPBACK").empty())
    GTEST_SKIP() << "MAGVEC_TEST_SPIDEV_LOOPBACK not set (spidev node of a loopback controller)";
  SpidevConfig c;
  c.device = env("MAGVEC_TEST_SPIDEV_LOOPBACK");
  OsError err;
  auto spi = SpidevBus::open(c, &err);
  ASSERT_NE(spi, nullptr) << err.message;
  std::vector<std::uint8_t> tx(SpidevBus::kMaxTransfer);
  for (std::size_t i = 0; i < tx.size(); ++i)
    tx[i] = static_cast<std::uint8_t>(i * 13u + 7u);
  std::vector<std::uint8_t> rx(tx.size(), 0);
  ASSERT_EQ(spi->transfer(tx, rx), hal::Status::kOk) << spi->last_error().message;
  EXPECT_EQ(rx, tx);
  const std::array<std::uint8_t, 6> frame{0x00, 0x00, 0x00, 0x11, 0x22, 0x33};
  std::array<std::uint8_t, 6> back{};
  ASSERT_EQ(spi->transfer(frame, back), hal::Status::kOk);
  EXPECT_EQ(back, frame);
  EXPECT_EQ(spi->transfers(), 2u);
  std::vector<std::uint8_t> too_long(SpidevBus::kMaxTransfer + 1);
  EXPECT_EQ(spi->transfer(too_long, too_long), hal::Status::kInvalidArgument);
  EXPECT_EQ(spi->transfer({}, {}), hal::Status::kOk);
  EXPECT_EQ(spi->errors(), 0u);
}

TEST(Spidev, Ads131FramesReadWithValidCrc) {
  if (const std::string why = spidev_unavailable(); !why.empty()) GTEST_SKIP() << why;
  SpidevConfig c;
  c.device = env("MAGVEC_TEST_SPIDEV");
  c.speed_hz = 1'000'000;
  OsError err;
  auto spi = SpidevBus::open(c, &err);
  ASSERT_NE(spi, nullptr) << err.message;
  std::array<std::uint8_t, 4> tx{};
  std::array<std::uint8_t, 3> rx_short{};
  EXPECT_EQ(spi->transfer(tx, rx_short), hal::Status::kInvalidArgument);

  AlwaysReady drdy;
  drivers::Ads131Fluxgate adc(*spi, drdy, drivers::Ads131FluxgateConfig{});
  ASSERT_EQ(adc.init(), hal::Status::kOk) << spi->last_error().message;
  constexpr int kFrames = 200;
  int ok = 0;
  int crc = 0;
  for (int i = 0; i < kFrames; ++i) {
    hal::MagnetometerSample s;
    const hal::Status st = adc.read(s, 100'000);
    if (st == hal::Status::kOk) {
      ++ok;
      for (const double v : s.m_nT)
        EXPECT_TRUE(std::isfinite(v));
    } else {
      EXPECT_EQ(st, hal::Status::kCrcError) << spi->last_error().message;
      ++crc;
    }
  }
  EXPECT_EQ(ok + crc, kFrames);
  EXPECT_EQ(static_cast<int>(adc.counters().crc_errors), crc);
  EXPECT_EQ(spi->errors(), 0u);
  if (env("MAGVEC_TEST_SPIDEV_CRC") == "1") {
    EXPECT_GT(crc, 0) << "the device injects CRC errors, none was detected";
    EXPECT_GT(ok, 0);
  } else {
    EXPECT_EQ(crc, 0);
  }
}

}  // namespace
