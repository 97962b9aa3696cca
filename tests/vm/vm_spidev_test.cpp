// Guest test (VM): the spidev driver (drivers/linux SpidevBus) talks to the project's
// virtual ADS131M04 (toolchain/vm/magvec_vspi.c, a kernel SPI controller; spidev binds to its
// device as /dev/spidev0.0) through the ADS131M04 codec and the Ads131Fluxgate driver, with the
// data-ready line on gpio-sim. The model's samples are deterministic (ch0 = 2^22 cos(n deg),
// ch1 = 2^22 sin(n deg), ch2 = 0x100000, ch3 = n for conversion n), CRC errors are injected
// through the module parameter crc_error_every. The feed (/dev/magvec_adc_feed, used by the
// magvecd end-to-end test) serves written conversions instead of the pattern.
#include <fcntl.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <cmath>
#include <cstdint>
#include <memory>
#include <numbers>
#include <span>
#include <string>
#include <thread>
#include <vector>

#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/ads131m04.hpp"
#include "magvec/drivers/linux/gpiod_data_ready_line.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/linux/spidev_bus.hpp"
#include "vm_env.hpp"

namespace magvec {
namespace {

using drivers::SpidevBus;
namespace ads = drivers::ads131;

std::string param(const char* name) {
  return vmtest::env("MAGVEC_TEST_VSPI_PARAMS", "/sys/module/magvec_vspi/parameters") + "/" + name;
}

// Restores crc_error_every = 0 whatever the test outcome.
struct CrcInjection {
  explicit CrcInjection(unsigned every) {
    EXPECT_TRUE(vmtest::write_sysfs(param("crc_error_every"), std::to_string(every)));
  }
  ~CrcInjection() { vmtest::write_sysfs(param("crc_error_every"), "0"); }
  CrcInjection(const CrcInjection&) = delete;
  CrcInjection& operator=(const CrcInjection&) = delete;
};

std::unique_ptr<SpidevBus> open_spi() {
  drivers::OsError err;
  drivers::SpidevConfig c;
  c.device = vmtest::env("MAGVEC_TEST_SPIDEV", "/dev/spidev0.0");
  auto bus = SpidevBus::open(c, &err);
  EXPECT_NE(bus, nullptr) << err.message;
  return bus;
}

ads::ParseResult null_frame(SpidevBus& spi, ads::Response& r) {
  ads::Frame tx{};
  ads::Frame rx{};
  EXPECT_TRUE(ads::build_command_frame(ads::kCmdNull, {}, false, tx));
  EXPECT_EQ(spi.transfer(tx, rx), hal::Status::kOk) << spi.last_error().message;
  return ads::parse_response_frame(rx, r);
}

// Expected channel codes of conversion n (fixp_sin32 table, 1 degree steps, >> 9).
void expect_model(const ads::Response& r, int n) {
  const double a = std::ldexp(1.0, 22);
  const double deg = std::numbers::pi / 180.0 * (n % 360);
  EXPECT_NEAR(r.codes[0], a * std::cos(deg), 2.0) << "n=" << n;
  EXPECT_NEAR(r.codes[1], a * std::sin(deg), 2.0) << "n=" << n;
  EXPECT_EQ(r.codes[2], 0x100000);
}

TEST(SpidevVm, NullFramesCarryCrcCheckedModelData) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  ads::Response r;
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);  // first frame: previous command's
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  int n = r.codes[3];
  for (int i = 0; i < 400; ++i) {
    ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk) << i;
    ++n;
    EXPECT_EQ(r.codes[3], n) << "lost or repeated conversion";
    EXPECT_EQ(r.response & ads::kStatusWlengthMask, ads::kStatusWlength24);
    EXPECT_EQ(r.response & ads::kStatusDrdyMask, ads::kStatusDrdyMask);
    expect_model(r, n);
  }
  EXPECT_EQ(spi->errors(), 0u);
}

TEST(SpidevVm, ResetAndGainHandshakeThroughFluxgateDriver) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  drivers::OsError err;
  drivers::GpiodConfig gc;
  gc.chip = vmtest::env("MAGVEC_TEST_GPIOCHIP");
  auto drdy = drivers::GpiodDataReadyLine::open(gc, &err);
  ASSERT_TRUE(drdy) << err.message;
  drivers::Ads131FluxgateConfig config;
  config.gain_code = {1, 2, 3, 0};
  drivers::Ads131Fluxgate fluxgate(*spi, *drdy, config);
  ASSERT_EQ(fluxgate.init(), hal::Status::kOk);
  EXPECT_TRUE(fluxgate.initialised());
  EXPECT_EQ(vmtest::read_sysfs_number(param("gain1")), ads::gain1_register(config.gain_code));
}

ads::ParseResult command_frame(SpidevBus& spi, std::uint16_t command,
                               std::span<const std::uint16_t> data, ads::Response& r) {
  ads::Frame tx{};
  ads::Frame rx{};
  EXPECT_TRUE(ads::build_command_frame(command, data, false, tx));
  EXPECT_EQ(spi.transfer(tx, rx), hal::Status::kOk) << spi.last_error().message;
  return ads::parse_response_frame(rx, r);
}

// STATUS.RESET reads MODE.RESET: set by a reset, still set after the reset acknowledge (FF24h)
// has been read and after other registers were written, cleared only by writing MODE with the
// bit 0 (and set again by writing it 1).
TEST(SpidevVm, StatusResetStaysUntilModeResetIsWrittenZero) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  ads::Response r;
  ASSERT_EQ(command_frame(*spi, ads::kCmdReset, {}, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_EQ(r.response, ads::kResetResponse);
  EXPECT_EQ(vmtest::read_sysfs_number(param("mode")), ads::kModeResetValue);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_NE(r.response & ads::kStatusReset, 0) << "cleared by reading the acknowledge";
  const std::array<std::uint16_t, 1> gain{ads::gain1_register({1, 1, 1, 1})};
  ASSERT_EQ(command_frame(*spi, ads::wreg(ads::kRegGain1, 1), gain, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_EQ(r.response, ads::wreg_response(ads::kRegGain1, 1));
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_NE(r.response & ads::kStatusReset, 0) << "cleared by writing another register";
  const std::array<std::uint16_t, 1> still_set{ads::kModeResetValue};
  ASSERT_EQ(command_frame(*spi, ads::wreg(ads::kRegMode, 1), still_set, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_NE(r.response & ads::kStatusReset, 0) << "cleared by writing MODE.RESET = 1";
  const std::array<std::uint16_t, 1> cleared{
      static_cast<std::uint16_t>(ads::kModeResetValue & ~ads::kModeReset)};
  ASSERT_EQ(command_frame(*spi, ads::wreg(ads::kRegMode, 1), cleared, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_EQ(r.response & ads::kStatusReset, 0) << "MODE.RESET written 0";
  EXPECT_EQ(vmtest::read_sysfs_number(param("mode")), cleared[0]);
}

// The driver under that rule: init() clears MODE.RESET, so its samples are not flagged; a reset
// mid-stream (inject_reset: the registers back to their defaults) flags exactly the sample that
// shows it, is counted, and the driver configures the device again (gain and MODE), after which
// the samples are clean.
TEST(SpidevVm, ADeviceResetMidStreamIsFlaggedOnceAndTheDriverConfiguresAgain) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  const std::string pull = vmtest::env("MAGVEC_TEST_GPIO_PULL");
  ASSERT_TRUE(vmtest::write_sysfs(pull, "pull-up"));
  drivers::OsError err;
  drivers::GpiodConfig gc;
  gc.chip = vmtest::env("MAGVEC_TEST_GPIOCHIP");
  gc.edge = hal::Edge::kFalling;
  auto drdy = drivers::GpiodDataReadyLine::open(gc, &err);
  ASSERT_TRUE(drdy) << err.message;
  drivers::Ads131FluxgateConfig config;
  config.gain_code = {2, 2, 2, 0};
  drivers::Ads131Fluxgate fluxgate(*spi, *drdy, config);
  ASSERT_EQ(fluxgate.init(), hal::Status::kOk);
  EXPECT_EQ(vmtest::read_sysfs_number(param("mode")) & ads::kModeReset, 0);
  const long long resets_before = vmtest::read_sysfs_number(param("resets"));
  auto read_one = [&](hal::MagnetometerSample& s) {
    EXPECT_TRUE(vmtest::write_sysfs(pull, "pull-down"));
    const hal::Status st = fluxgate.read(s, 1'000'000);
    EXPECT_TRUE(vmtest::write_sysfs(pull, "pull-up"));
    return st;
  };
  std::vector<std::uint32_t> flags;
  for (int i = 0; i < 30; ++i) {
    if (i == 10) {
      ASSERT_TRUE(vmtest::write_sysfs(param("inject_reset"), "1"));
    }
    hal::MagnetometerSample s;
    ASSERT_EQ(read_one(s), hal::Status::kOk) << i;
    flags.push_back(s.flags);
  }
  for (int i = 0; i < 30; ++i)
    EXPECT_EQ((flags[static_cast<std::size_t>(i)] & hal::kMagDeviceReset) != 0, i == 10) << i;
  EXPECT_EQ(fluxgate.counters().device_resets, 1u);
  // The injected reset and the driver's own RESET command when it configured the device again.
  EXPECT_EQ(vmtest::read_sysfs_number(param("resets")) - resets_before, 2);
  EXPECT_TRUE(fluxgate.initialised());
  EXPECT_EQ(vmtest::read_sysfs_number(param("gain1")), ads::gain1_register(config.gain_code));
  EXPECT_EQ(vmtest::read_sysfs_number(param("mode")) & ads::kModeReset, 0);
  ASSERT_TRUE(vmtest::write_sysfs(pull, "pull-down"));
}

TEST(SpidevVm, InjectedCrcErrorsAreDetectedExactly) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  ads::Response r;
  null_frame(*spi, r);
  const long long injected_before = vmtest::read_sysfs_number(param("crc_errors_injected"));
  ASSERT_GE(injected_before, 0);
  int crc_errors = 0;
  int ok = 0;
  {
    CrcInjection every7(7);
    for (int i = 0; i < 70; ++i) {
      if (null_frame(*spi, r) == ads::ParseResult::kOk) {
        ++ok;
      } else {
        ++crc_errors;
        EXPECT_NE(r.crc_received, r.crc_computed);
      }
    }
  }
  EXPECT_EQ(crc_errors, 10);
  EXPECT_EQ(ok, 60);
  EXPECT_EQ(vmtest::read_sysfs_number(param("crc_errors_injected")) - injected_before, 10);
  // Injection off again: clean frames.
  for (int i = 0; i < 20; ++i)
    EXPECT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
}

TEST(SpidevVm, FluxgateReadsOnGpioSimDataReadyAndCountsCrcErrors) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  const std::string pull = vmtest::env("MAGVEC_TEST_GPIO_PULL");
  ASSERT_TRUE(vmtest::write_sysfs(pull, "pull-up"));  // DRDY idles high, a conversion pulls it low
  drivers::OsError err;
  drivers::GpiodConfig gc;
  gc.chip = vmtest::env("MAGVEC_TEST_GPIOCHIP");
  gc.edge = hal::Edge::kFalling;
  auto drdy = drivers::GpiodDataReadyLine::open(gc, &err);
  ASSERT_TRUE(drdy) << err.message;
  drivers::Ads131FluxgateConfig config;  // gain 1, 1e4 nT/V on channels 0, 1, 2
  drivers::Ads131Fluxgate fluxgate(*spi, *drdy, config);
  ASSERT_EQ(fluxgate.init(), hal::Status::kOk);

  CrcInjection every5(5);
  int ok = 0;
  int crc = 0;
  for (int i = 0; i < 40; ++i) {
    const std::uint64_t before = drivers::monotonic_us();
    ASSERT_TRUE(vmtest::write_sysfs(pull, "pull-down"));  // DRDY falling edge
    hal::MagnetometerSample s;
    const hal::Status st = fluxgate.read(s, 1'000'000);
    ASSERT_TRUE(vmtest::write_sysfs(pull, "pull-up"));
    if (st == hal::Status::kOk) {
      ++ok;
      EXPECT_GE(s.t_us, before);  // the sample is stamped with the DRDY edge time
      EXPECT_LE(s.t_us, drivers::monotonic_us());
      // code / 2^23 * 1.2 V * 1e4 nT/V
      const double nT_per_code = 1.2 * 1e4 / 8388608.0;
      for (std::size_t axis = 0; axis < 3; ++axis)
        EXPECT_DOUBLE_EQ(s.m_nT[axis], s.raw[axis] * nT_per_code);
      EXPECT_EQ(s.raw[2], 0x100000);
      EXPECT_NEAR(std::hypot(s.m_nT[0], s.m_nT[1]), 4194304.0 * nT_per_code, 0.01);
    } else {
      EXPECT_EQ(st, hal::Status::kCrcError) << static_cast<int>(st);
      ++crc;
    }
  }
  EXPECT_EQ(crc, 8);
  EXPECT_EQ(ok, 32);
  EXPECT_EQ(fluxgate.counters().crc_errors, 8u);
  EXPECT_EQ(fluxgate.counters().timeouts, 0u);
  ASSERT_TRUE(vmtest::write_sysfs(pull, "pull-down"));
}

// The feed: written conversions are served in order, one per data frame, with DRDY set; with
// the FIFO empty the last one is repeated with DRDY clear (not new data); a partial record is
// refused; closing the feed restores the rotating pattern.
TEST(SpidevVm, FeedServesWrittenConversionsInOrderAndFlagsRepeatsNotNew) {
  auto spi = open_spi();
  ASSERT_TRUE(spi);
  const std::string path = vmtest::env("MAGVEC_TEST_ADC_FEED", "/dev/magvec_adc_feed");
  const int fd = ::open(path.c_str(), O_WRONLY);
  ASSERT_GE(fd, 0) << path;
  EXPECT_LT(::open(path.c_str(), O_WRONLY), 0) << "a second feeder must be refused (EBUSY)";
  ads::Response r;
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);  // flush the previous command's answer
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_EQ(r.response & ads::kStatusDrdyMask, 0) << "nothing fed yet: not new";
  const std::array<std::array<std::int32_t, 4>, 3> codes = {
      {{-8388608, 8388607, 123456, -1}, {1, -2, 3, -4}, {5, 6, 7, 8}}};
  // One conversion per write, then two in one write.
  std::array<std::int32_t, 12> flat{};
  for (std::size_t k = 0; k < 12; ++k)
    flat[k] = codes[k / 4][k % 4];
  const ssize_t record = 4 * sizeof(std::int32_t);
  ASSERT_EQ(::write(fd, flat.data(), record), record);
  ASSERT_EQ(::write(fd, flat.data() + 4, 2 * record), 2 * record);
  EXPECT_LT(::write(fd, codes[0].data(), 5), 0) << "partial conversion accepted";
  for (std::size_t k = 0; k < 4; ++k) {
    const std::size_t expect = std::min<std::size_t>(k, 2);
    ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
    EXPECT_EQ(r.response & ads::kStatusDrdyMask, k < 3 ? ads::kStatusDrdyMask : 0)
        << "frame " << k << (k < 3 ? ": new data" : ": a repeat must be flagged not new");
    for (std::size_t ch = 0; ch < 4; ++ch)
      EXPECT_EQ(r.codes[ch], codes[expect][ch]) << "frame " << k << " ch " << ch;
  }
  ::close(fd);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  ASSERT_EQ(null_frame(*spi, r), ads::ParseResult::kOk);
  EXPECT_EQ(r.response & ads::kStatusDrdyMask, ads::kStatusDrdyMask);
  expect_model(r, r.codes[3]);  // the pattern is back
}

TEST(SpidevVm, MissingDeviceGivesClearError) {
  drivers::OsError err;
  drivers::SpidevConfig c;
  c.device = "/dev/spidev7.3";
  EXPECT_EQ(SpidevBus::open(c, &err), nullptr);
  EXPECT_NE(err.message.find("/dev/spidev7.3"), std::string::npos) << err.message;
  EXPECT_EQ(err.error_number, ENOENT) << err.message;
}

}  // namespace
}  // namespace magvec
