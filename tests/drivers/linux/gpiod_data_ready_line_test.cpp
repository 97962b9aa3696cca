// GpiodDataReadyLine (drivers/linux/gpiod_data_ready_line.hpp). The error path runs everywhere;
// the edge tests need a gpio-sim chip and skip without one (the VM suite provides it):
//   MAGVEC_TEST_GPIOCHIP   chip name or path (e.g. gpiochip0)
//   MAGVEC_TEST_GPIO_LINE  line offset (default 0)
//   MAGVEC_TEST_GPIO_PULL  the sim's sysfs `pull` attribute of that line, e.g.
//                          /sys/devices/platform/gpio-sim.0/gpiochip0/sim_gpio0/pull
// Writing "pull-up"/"pull-down" to it makes the simulated input rise/fall.
#include "magvec/drivers/linux/gpiod_data_ready_line.hpp"

#include <glob.h>

#include <gtest/gtest.h>

#include <cerrno>
#include <cstdlib>
#include <fstream>
#include <string>

#include "magvec/drivers/linux/linux_clock.hpp"

namespace {

using namespace magvec;
using drivers::GpiodConfig;
using drivers::GpiodDataReadyLine;
using drivers::OsError;

std::string env(const char* name, const char* fallback = "") {
  const char* v = std::getenv(name);
  return v != nullptr && *v != '\0' ? v : fallback;
}

std::string gpio_unavailable() {
  glob_t g{};
  const bool any = ::glob("/dev/gpiochip*", 0, nullptr, &g) == 0 && g.gl_pathc > 0;
  ::globfree(&g);
  if (!any) return "no /dev/gpiochip* on this machine; the VM suite runs this test with gpio-sim";
  if (env("MAGVEC_TEST_GPIOCHIP").empty() || env("MAGVEC_TEST_GPIO_PULL").empty())
    return "MAGVEC_TEST_GPIOCHIP / MAGVEC_TEST_GPIO_PULL not set (gpio-sim chip and pull "
           "attribute)";
  return {};
}

#define MAGVEC_REQUIRE_GPIO()                   \
  do {                                          \
    const std::string why = gpio_unavailable(); \
    if (!why.empty()) GTEST_SKIP() << why;      \
  } while (0)

GpiodConfig sim_config() {
  GpiodConfig c;
  c.chip = env("MAGVEC_TEST_GPIOCHIP");
  c.line = static_cast<unsigned>(std::stoul(env("MAGVEC_TEST_GPIO_LINE", "0")));
  c.consumer = "magvec-test";
  return c;
}

void set_pull(bool up) {
  std::ofstream f(env("MAGVEC_TEST_GPIO_PULL"));
  ASSERT_TRUE(f.good()) << "cannot open " << env("MAGVEC_TEST_GPIO_PULL");
  f << (up ? "pull-up" : "pull-down");
  f.close();
  ASSERT_TRUE(f.good()) << "cannot write " << env("MAGVEC_TEST_GPIO_PULL");
}

TEST(GpiodErrors, MissingChipNamesItAndErrno) {
  GpiodConfig c;
  c.chip = "magvec-no-such-chip";
  c.line = 3;
  OsError err;
  EXPECT_EQ(GpiodDataReadyLine::open(c, &err), nullptr);
  EXPECT_NE(err.error_number, 0);
  EXPECT_NE(err.message.find("gpiod magvec-no-such-chip line 3: open chip"), std::string::npos)
      << err.message;
  EXPECT_NE(err.message.find("(errno " + std::to_string(err.error_number) + ")"), std::string::npos)
      << err.message;
}

TEST(Gpiod, BothEdgesArriveInOrderWithKernelTimestamps) {
  MAGVEC_REQUIRE_GPIO();
  set_pull(false);
  GpiodConfig c = sim_config();
  c.both_edges = true;
  OsError err;
  auto line = GpiodDataReadyLine::open(c, &err);
  ASSERT_NE(line, nullptr) << err.message;
  hal::EdgeEvent ev;
  EXPECT_EQ(line->wait_edge(ev, 20'000), hal::Status::kTimeout);
  std::uint64_t last = 0;
  for (int i = 0; i < 10; ++i) {
    const bool up = i % 2 == 0;
    const std::uint64_t t0 = drivers::monotonic_us();
    set_pull(up);
    ASSERT_EQ(line->wait_edge(ev, 1'000'000), hal::Status::kOk) << line->last_error().message;
    const std::uint64_t t1 = drivers::monotonic_us();
    EXPECT_EQ(ev.edge, up ? hal::Edge::kRising : hal::Edge::kFalling);
    EXPECT_GE(ev.t_us, t0);  // stamped by the kernel between the write and the read
    EXPECT_LE(ev.t_us, t1);
    EXPECT_GT(ev.t_us, last);
    last = ev.t_us;
  }
  EXPECT_EQ(line->events(), 10u);
  EXPECT_EQ(line->missed_edges(), 0u);
  EXPECT_EQ(line->wait_edge(ev, 0), hal::Status::kTimeout);
}

TEST(Gpiod, FallingEdgeConfigurationReportsOnlyFallingEdges) {
  MAGVEC_REQUIRE_GPIO();
  set_pull(false);
  GpiodConfig c = sim_config();
  c.edge = hal::Edge::kFalling;
  OsError err;
  auto line = GpiodDataReadyLine::open(c, &err);
  ASSERT_NE(line, nullptr) << err.message;
  hal::EdgeEvent ev;
  for (int i = 0; i < 3; ++i) {
    set_pull(true);
    EXPECT_EQ(line->wait_edge(ev, 20'000), hal::Status::kTimeout) << "a rising edge was reported";
    set_pull(false);
    ASSERT_EQ(line->wait_edge(ev, 1'000'000), hal::Status::kOk) << line->last_error().message;
    EXPECT_EQ(ev.edge, hal::Edge::kFalling);
  }
  EXPECT_EQ(line->wait_edge(ev, 20'000), hal::Status::kTimeout);
  EXPECT_EQ(line->events(), 3u);
}

TEST(Gpiod, MissingOrBusyLineGivesAClearError) {
  MAGVEC_REQUIRE_GPIO();
  GpiodConfig c = sim_config();
  OsError err;
  auto line = GpiodDataReadyLine::open(c, &err);
  ASSERT_NE(line, nullptr) << err.message;
  err = {};
  EXPECT_EQ(GpiodDataReadyLine::open(c, &err), nullptr);  // already requested
  EXPECT_EQ(err.error_number, EBUSY);
  EXPECT_NE(err.message.find("gpiod " + c.chip + " line " + std::to_string(c.line)),
            std::string::npos)
      << err.message;
  c.line = 9999;
  err = {};
  EXPECT_EQ(GpiodDataReadyLine::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, EINVAL);
  EXPECT_NE(err.message.find("line 9999: get line: no such line"), std::string::npos)
      << err.message;
}

}  // namespace
