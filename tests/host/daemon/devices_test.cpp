// open_sim_devices (host/daemon devices.hpp): magvecd --sim steps the rig once per magnetometer
// period of its clock (a fake clock here), waits in between, reschedules after a stall, and opening
// a real device that does not exist names it with the device exit code.
#include "magvec/host/daemon/devices.hpp"

#include <gtest/gtest.h>

#include <vector>

#include "magvec/host/daemon/daemon_error.hpp"

namespace magvec::host::daemon {
namespace {

struct Counter final : EventHandler {
  int mags{0};
  int atts{0};
  std::vector<std::uint64_t> mag_t_us;
  void on_attitude(const hal::AttitudeSample&) override { ++atts; }
  void on_magnetometer(const hal::MagnetometerSample& s, double) override {
    ++mags;
    mag_t_us.push_back(s.t_us);
  }
  void on_read_error(hal::Status) override {}
};

TEST(SimDevices, OneStepPerPeriodOfTheClock) {
  Config c = parse_config("", "test");
  c.magnetometer.rate_hz = 1000;  // 1 ms period
  std::uint64_t now = 5'000'000;
  std::vector<std::uint32_t> waits;
  auto d = open_sim_devices(
      c, [&](std::uint32_t us) { waits.push_back(us); }, [&] { return now; });
  Counter h;
  // At t0 the first step is due.
  EXPECT_TRUE(d->poll(h, 20'000));
  const int first = h.mags;
  EXPECT_TRUE(waits.empty());
  // Not due yet: waits for the rest of the period (never longer than asked).
  now += 400;
  EXPECT_TRUE(d->poll(h, 20'000));
  ASSERT_EQ(waits.size(), 1u);
  EXPECT_EQ(waits.back(), 600u);
  EXPECT_TRUE(d->poll(h, 100));
  EXPECT_EQ(waits.back(), 100u);
  EXPECT_EQ(h.mags, first);
  // 10 periods later: ten steps are due, one per poll, without waiting.
  now += 600 + 9'000;
  const std::size_t waited = waits.size();
  for (int i = 0; i < 10; ++i)
    EXPECT_TRUE(d->poll(h, 20'000));
  EXPECT_EQ(waits.size(), waited);
  EXPECT_TRUE(d->poll(h, 20'000));
  EXPECT_EQ(waits.size(), waited + 1);  // caught up: waits again
  EXPECT_EQ(d->mag_counters().samples, static_cast<std::uint64_t>(11));
}

// sim.wake_period_us: one wait per wake period instead of one per conversion, and the very same
// samples in the same order (a fake clock that jumps to the end of each wait).
TEST(SimDevices, AWakePeriodDeliversTheSameSamplesWithFewerWaits) {
  auto run = [](std::uint32_t wake_period_us, int* waits) {
    Config c = parse_config("", "test");
    c.magnetometer.rate_hz = 1000;
    c.sim.wake_period_us = wake_period_us;
    std::uint64_t now = 2'000'000;
    *waits = 0;
    auto d = open_sim_devices(
        c,
        [&](std::uint32_t us) {
          ++*waits;
          now += us;
        },
        [&] { return now; });
    Counter h;
    while (h.mags < 1000)
      EXPECT_TRUE(d->poll(h, 20'000));
    return h;
  };
  int waits_each = 0, waits_10ms = 0, waits_2500us = 0;
  const Counter each = run(0, &waits_each);
  const Counter every_10ms = run(10'000, &waits_10ms);
  const Counter every_2500us = run(2'500, &waits_2500us);
  EXPECT_EQ(each.mag_t_us, every_10ms.mag_t_us);
  EXPECT_EQ(each.mag_t_us, every_2500us.mag_t_us);
  EXPECT_EQ(each.atts, every_10ms.atts);
  EXPECT_GE(waits_each, 999);
  EXPECT_LE(waits_10ms, 101);
  EXPECT_GE(waits_10ms, 99);
  EXPECT_LE(waits_2500us, 401);
  EXPECT_GE(waits_2500us, 399);
}

TEST(SimDevices, AStallOfMoreThanASecondIsNotReplayedAtFullSpeed) {
  Config c = parse_config("", "test");
  c.magnetometer.rate_hz = 100;
  std::uint64_t now = 1'000'000;
  int waits = 0;
  auto d = open_sim_devices(
      c, [&](std::uint32_t) { ++waits; }, [&] { return now; });
  Counter h;
  EXPECT_TRUE(d->poll(h, 20'000));
  now += 5'000'000;                 // the process stalled for 5 s
  EXPECT_TRUE(d->poll(h, 20'000));  // one step, rescheduled from now
  EXPECT_EQ(waits, 0);
  EXPECT_TRUE(d->poll(h, 20'000));  // the next is one period later: a wait
  EXPECT_EQ(waits, 1);
  EXPECT_EQ(d->mag_counters().samples, 2u);
}

TEST(RealDevices, AMissingDeviceIsNamedWithTheDeviceExitCode) {
  Config c = parse_config("", "test");
  c.magnetometer.spi_device = "/nonexistent/spidev9.9";
  try {
    (void)open_real_devices(c, [](std::uint32_t) {});
    FAIL() << "opened a device that does not exist";
  } catch (const DaemonError& e) {
    EXPECT_EQ(e.code(), kExitDevice);
    EXPECT_NE(std::string(e.what()).find("/nonexistent/spidev9.9"), std::string::npos);
  }
}

}  // namespace
}  // namespace magvec::host::daemon
