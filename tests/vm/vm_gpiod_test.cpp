// Guest test (VM): the libgpiod data-ready driver (drivers/linux GpiodDataReadyLine) on
// a real kernel's gpio-sim chip (built out of tree by toolchain/vm/prepare-kernel, created by the
// guest's /init through configfs). Edges are produced by writing pull-up / pull-down to the sim
// line's `pull` attribute; they must arrive as events with kernel timestamps on the
// CLOCK_MONOTONIC base, and a missing chip, line or busy line must give a clear error.
#include <cerrno>
#include <memory>
#include <string>

#include "magvec/drivers/linux/gpiod_data_ready_line.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "vm_env.hpp"

namespace magvec {
namespace {

using drivers::GpiodConfig;
using drivers::GpiodDataReadyLine;

std::string chip() {
  return vmtest::env("MAGVEC_TEST_GPIOCHIP");
}
std::string pull_path() {
  return vmtest::env("MAGVEC_TEST_GPIO_PULL");
}
unsigned line_offset() {
  return static_cast<unsigned>(std::stoul(vmtest::env("MAGVEC_TEST_GPIO_LINE", "0")));
}

void set_pull(bool up) {
  ASSERT_TRUE(vmtest::write_sysfs(pull_path(), up ? "pull-up" : "pull-down")) << pull_path();
}

std::unique_ptr<GpiodDataReadyLine> open_line(bool both, hal::Edge edge = hal::Edge::kFalling) {
  drivers::OsError err;
  GpiodConfig c;
  c.chip = chip();
  c.line = line_offset();
  c.both_edges = both;
  c.edge = edge;
  c.consumer = "magvec-vm-test";
  auto line = GpiodDataReadyLine::open(c, &err);
  EXPECT_NE(line, nullptr) << err.message;
  return line;
}

TEST(GpiodVm, GuestProvidesTheSimChip) {
  ASSERT_FALSE(chip().empty()) << "MAGVEC_TEST_GPIOCHIP not set by /init";
  ASSERT_FALSE(pull_path().empty()) << "MAGVEC_TEST_GPIO_PULL not set by /init";
}

TEST(GpiodVm, PullChangesArriveAsTimestampedEdgesInOrder) {
  set_pull(false);
  auto line = open_line(true);
  ASSERT_TRUE(line);
  hal::EdgeEvent ev;
  std::uint64_t last_t = 0;
  for (int i = 0; i < 50; ++i) {
    const bool up = i % 2 == 0;
    const std::uint64_t before = drivers::monotonic_us();
    set_pull(up);
    ASSERT_EQ(line->wait_edge(ev, 1'000'000), hal::Status::kOk) << line->last_error().message;
    const std::uint64_t after = drivers::monotonic_us();
    EXPECT_EQ(ev.edge, up ? hal::Edge::kRising : hal::Edge::kFalling) << i;
    // The kernel stamps the edge in its interrupt handler: inside the write() .. return window.
    EXPECT_GE(ev.t_us, before) << i;
    EXPECT_LE(ev.t_us, after) << i;
    EXPECT_GT(ev.t_us, last_t) << i;
    last_t = ev.t_us;
  }
  EXPECT_EQ(line->events(), 50u);
  EXPECT_EQ(line->missed_edges(), 0u);
  EXPECT_EQ(line->wait_edge(ev, 100'000), hal::Status::kTimeout);
  set_pull(false);
}

TEST(GpiodVm, FallingEdgeRequestSeesOnlyFallingEdges) {
  set_pull(false);
  auto line = open_line(false, hal::Edge::kFalling);
  ASSERT_TRUE(line);
  for (int i = 0; i < 10; ++i) {
    set_pull(true);
    set_pull(false);
  }
  hal::EdgeEvent ev;
  int falling = 0;
  while (line->wait_edge(ev, 200'000) == hal::Status::kOk) {
    EXPECT_EQ(ev.edge, hal::Edge::kFalling);
    ++falling;
  }
  EXPECT_EQ(falling, 10);
}

TEST(GpiodVm, QueuedEdgesAreDeliveredOldestFirst) {
  set_pull(false);
  auto line = open_line(true);
  ASSERT_TRUE(line);
  std::uint64_t t_first = drivers::monotonic_us();
  for (int i = 0; i < 6; ++i)
    set_pull(i % 2 == 0);
  hal::EdgeEvent ev;
  std::uint64_t last = 0;
  for (int i = 0; i < 6; ++i) {
    ASSERT_EQ(line->wait_edge(ev, 1'000'000), hal::Status::kOk);
    EXPECT_EQ(ev.edge, i % 2 == 0 ? hal::Edge::kRising : hal::Edge::kFalling);
    EXPECT_GE(ev.t_us, t_first);
    EXPECT_GT(ev.t_us, last);
    last = ev.t_us;
  }
  set_pull(false);
}

// The v1 uAPI keeps 16 events per line and drops newer ones when full, without telling. With
// both edges requested the driver still notices: after the overflow the next event has the same
// direction as the last one delivered.
TEST(GpiodVm, LostEdgesAreDetectedWithBothEdges) {
  set_pull(false);
  auto line = open_line(true);
  ASSERT_TRUE(line);
  for (int i = 0; i < 41; ++i)  // R F R ... R: 41 edges, the kernel keeps the first 16
    set_pull(i % 2 == 0);
  hal::EdgeEvent ev;
  int delivered = 0;
  while (line->wait_edge(ev, 200'000) == hal::Status::kOk) {
    EXPECT_EQ(ev.edge, delivered % 2 == 0 ? hal::Edge::kRising : hal::Edge::kFalling);
    ++delivered;
  }
  EXPECT_EQ(delivered, 16);
  EXPECT_EQ(line->missed_edges(), 0u);
  set_pull(false);  // the line was high: a falling edge follows the delivered falling edge
  ASSERT_EQ(line->wait_edge(ev, 1'000'000), hal::Status::kOk);
  EXPECT_EQ(ev.edge, hal::Edge::kFalling);
  EXPECT_EQ(line->missed_edges(), 1u);
}

TEST(GpiodVm, MissingLineGivesClearError) {
  drivers::OsError err;
  GpiodConfig c;
  c.chip = chip();
  c.line = 57;  // the sim chip has 8 lines
  EXPECT_EQ(GpiodDataReadyLine::open(c, &err), nullptr);
  EXPECT_NE(err.message.find("57"), std::string::npos) << err.message;
  EXPECT_NE(err.message.find(chip().substr(chip().rfind('/') + 1)), std::string::npos)
      << err.message;

  drivers::OsError err2;
  c.chip = "/dev/gpiochip97";
  c.line = 0;
  EXPECT_EQ(GpiodDataReadyLine::open(c, &err2), nullptr);
  EXPECT_NE(err2.message.find("gpiochip97"), std::string::npos) << err2.message;
  EXPECT_NE(err2.error_number, 0) << err2.message;
}

TEST(GpiodVm, BusyLineGivesClearError) {
  auto first = open_line(true);
  ASSERT_TRUE(first);
  drivers::OsError err;
  GpiodConfig c;
  c.chip = chip();
  c.line = line_offset();
  EXPECT_EQ(GpiodDataReadyLine::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, EBUSY) << err.message;
  EXPECT_FALSE(err.message.empty());
}

}  // namespace
}  // namespace magvec
