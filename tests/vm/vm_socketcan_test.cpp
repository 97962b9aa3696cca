// Guest test (VM): the SocketCAN driver (drivers/linux SocketCanBus) on a real kernel's
// vcan0 receives the frames of a simulated SBG INS (drivers/sim SimSbgIns) sent on another
// socket: kernel filters drop other IDs, kernel receive timestamps, error frames, a burst of
// 10 000 frames paced at 1 kHz without loss, and candump-format logs replayed by can-utils'
// canplayer / recorded by candump.
#include <fcntl.h>
#include <linux/can.h>
#include <linux/can/error.h>
#include <net/if.h>
#include <signal.h>
#include <sys/ioctl.h>
#include <sys/socket.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <atomic>
#include <cstdio>
#include <cstring>
#include <fstream>
#include <memory>
#include <thread>
#include <vector>

#include "candump_log.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/linux/socketcan_bus.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "vm_env.hpp"

namespace magvec {
namespace {

using drivers::CanFilterSpec;
using drivers::SocketCanBus;

std::string can_interface() {
  return vmtest::env("MAGVEC_TEST_CAN", "vcan0");
}

// The attitude messages magvecd subscribes to; with_position adds EKF_POS and EKF_ALTITUDE, which
// the simulated INS also sends (every tenth epoch), for the tests that expect every frame it sends.
std::vector<CanFilterSpec> sbg_filters(bool with_position = false) {
  const drivers::sbg::CanIds ids{};
  std::vector<CanFilterSpec> f = {
      {ids.status_01, 0x7FF, false}, {ids.status_03, 0x7FF, false},
      {ids.ekf_info, 0x7FF, false},  {ids.ekf_quat, 0x7FF, false},
      {ids.ekf_euler, 0x7FF, false}, {ids.ekf_orientation_acc, 0x7FF, false}};
  if (with_position) {
    f.push_back({ids.ekf_pos, 0x7FF, false});
    f.push_back({ids.ekf_altitude, 0x7FF, false});
  }
  return f;
}

std::unique_ptr<SocketCanBus> open_bus(std::vector<CanFilterSpec> filters,
                                       bool error_frames = true) {
  drivers::OsError err;
  auto bus = SocketCanBus::open({can_interface(), std::move(filters), error_frames}, &err);
  EXPECT_NE(bus, nullptr) << err.message;
  return bus;
}

// Frames of a simulated SBG INS over the survey scenario, in emission order.
std::vector<hal::CanFrame> sim_ins_frames(std::size_t min_frames, double rate_hz) {
  drivers::sim::Simulator sim(drivers::sim::scenario_survey(), 5);
  drivers::sim::SimSbgConfig config;
  config.rate_hz = rate_hz;
  drivers::sim::SimSbgIns ins(sim, config);
  std::vector<hal::CanFrame> out;
  for (std::size_t k = 0; out.size() < min_frames; ++k) {
    ins.run_until(static_cast<double>(k) / rate_hz);
    hal::CanFrame f;
    while (ins.receive(f, 0) == hal::Status::kOk) {
      f.t_us = 0;
      out.push_back(f);
    }
  }
  return out;
}

// Attitude samples the SBG decoder produces from `frames` without any transport (the reference).
std::vector<hal::AttitudeSample> decode_directly(const std::vector<hal::CanFrame>& frames) {
  drivers::sbg::CanDecoder decoder;
  std::vector<hal::AttitudeSample> out;
  for (const hal::CanFrame& f : frames) {
    if (decoder.feed(f) == drivers::sbg::FeedResult::kSample) out.push_back(decoder.sample());
  }
  return out;
}

bool same_payload(const hal::CanFrame& a, const hal::CanFrame& b) {
  return a.id == b.id && a.extended == b.extended && a.dlc == b.dlc && a.data == b.data;
}

hal::CanFrame frame(std::uint32_t id, std::uint8_t tag, bool extended = false) {
  hal::CanFrame f;
  f.id = id;
  f.extended = extended;
  f.dlc = 2;
  f.data[0] = tag;
  f.data[1] = 0xA5;
  return f;
}

TEST(SocketCanVm, SimulatedInsFramesArriveIntactWithKernelTimestamps) {
  auto rx = open_bus(sbg_filters(true));
  auto tx = open_bus({});
  ASSERT_TRUE(rx && tx);
  const auto frames = sim_ins_frames(400, 100.0);
  std::uint64_t last_t = 0;
  for (const hal::CanFrame& sent : frames) {
    const std::uint64_t before = drivers::monotonic_us();
    ASSERT_EQ(tx->send(sent), hal::Status::kOk) << tx->last_error().message;
    hal::CanFrame got;
    ASSERT_EQ(rx->receive(got, 1'000'000), hal::Status::kOk) << rx->last_error().message;
    const std::uint64_t after = drivers::monotonic_us();
    EXPECT_TRUE(same_payload(got, sent)) << "id " << got.id << " vs " << sent.id;
    // The kernel's receive timestamp lies between the send call and the end of receive().
    EXPECT_GE(got.t_us, before);
    EXPECT_LE(got.t_us, after);
    EXPECT_GE(got.t_us, last_t);
    last_t = got.t_us;
  }
  EXPECT_EQ(rx->dropped_frames(), 0u);
  EXPECT_EQ(rx->error_frames(), 0u);
}

TEST(SocketCanVm, AttitudeSourceOverSocketCanMatchesDirectDecode) {
  auto rx = open_bus(sbg_filters(true));
  auto tx = open_bus({});
  ASSERT_TRUE(rx && tx);
  const auto frames = sim_ins_frames(800, 100.0);
  const auto expected = decode_directly(frames);
  ASSERT_GE(expected.size(), 150u);
  drivers::sbg::CanAttitudeSource source(*rx);
  std::vector<hal::AttitudeSample> got;
  for (const hal::CanFrame& f : frames) {
    ASSERT_EQ(tx->send(f), hal::Status::kOk);
    hal::AttitudeSample s;
    // Each frame is read as it is sent; a sample completes at the quaternion frame.
    if (source.read(s, 20'000) == hal::Status::kOk) got.push_back(s);
  }
  ASSERT_EQ(got.size(), expected.size());
  for (std::size_t i = 0; i < got.size(); ++i) {
    EXPECT_EQ(got[i].t_ins_us, expected[i].t_ins_us) << i;
    EXPECT_EQ(got[i].q_nb, expected[i].q_nb) << i;
    EXPECT_EQ(got[i].flags, expected[i].flags) << i;
    if (i > 0) {
      EXPECT_GT(got[i].t_us, got[i - 1].t_us) << i;
    }
  }
  EXPECT_EQ(source.counters().malformed, 0u);
  EXPECT_EQ(source.counters().missing_time, 0u);
}

TEST(SocketCanVm, KernelFilterDropsOtherIds) {
  auto rx = open_bus(sbg_filters());
  auto tx = open_bus({});
  ASSERT_TRUE(rx && tx);
  const drivers::sbg::CanIds ids{};
  // Neighbours of the SBG IDs (one bit off, same high bits), an extended frame with an SBG
  // ID's number, and unrelated IDs: none may reach the process.
  const std::vector<hal::CanFrame> others = {
      frame(0x101, 1), frame(0x134, 2),       frame(0x1FF, 3), frame(0x030, 4),
      frame(0x731, 5), frame(0x131, 6, true), frame(0x000, 7), frame(0x7FF, 8)};
  const std::vector<hal::CanFrame> wanted = {frame(ids.ekf_info, 10), frame(ids.ekf_quat, 11),
                                             frame(ids.status_01, 12)};
  // Sent interleaved: three unwanted frames before each wanted one, the rest after the last.
  for (std::size_t i = 0; i < others.size(); ++i) {
    ASSERT_EQ(tx->send(others[i]), hal::Status::kOk);
    if (i % 3 == 2 && i / 3 < wanted.size()) {
      ASSERT_EQ(tx->send(wanted[i / 3]), hal::Status::kOk);
    }
  }
  ASSERT_EQ(tx->send(wanted[2]), hal::Status::kOk);
  ASSERT_EQ(tx->send(frame(0x100, 13, true)), hal::Status::kOk);  // extended twin of STATUS_01
  for (const hal::CanFrame& w : wanted) {
    hal::CanFrame got;
    ASSERT_EQ(rx->receive(got, 1'000'000), hal::Status::kOk);
    EXPECT_TRUE(same_payload(got, w))
        << "received id 0x" << std::hex << got.id << (got.extended ? " (extended)" : "");
  }
  hal::CanFrame extra;
  const hal::Status s = rx->receive(extra, 200'000);
  EXPECT_EQ(s, hal::Status::kTimeout) << "unexpected frame id 0x" << std::hex << extra.id;
}

TEST(SocketCanVm, ExtendedFilterPassesOnlyExtendedFrames) {
  // An INS configured for 29-bit IDs: 0x18FF0131 extended; the standard 0x131 must not match.
  auto rx = open_bus({{0x18FF0131, 0x1FFFFFFF, true}});
  auto tx = open_bus({});
  ASSERT_TRUE(rx && tx);
  ASSERT_EQ(tx->send(frame(0x131, 1)), hal::Status::kOk);
  ASSERT_EQ(tx->send(frame(0x18FF0130, 2, true)), hal::Status::kOk);
  ASSERT_EQ(tx->send(frame(0x18FF0131, 3, true)), hal::Status::kOk);
  hal::CanFrame got;
  ASSERT_EQ(rx->receive(got, 1'000'000), hal::Status::kOk);
  EXPECT_TRUE(got.extended);
  EXPECT_EQ(got.id, 0x18FF0131u);
  EXPECT_EQ(got.data[0], 3);
  EXPECT_EQ(rx->receive(got, 200'000), hal::Status::kTimeout) << "id 0x" << std::hex << got.id;
}

// Error frames cannot be produced by vcan itself; a raw socket sends one (CAN_ERR_FLAG), which
// the kernel delivers to sockets whose CAN_RAW_ERR_FILTER matches its class.
void send_error_frame(canid_t error_class) {
  const int fd = ::socket(PF_CAN, SOCK_RAW, CAN_RAW);
  ASSERT_GE(fd, 0) << std::strerror(errno);
  ifreq ifr{};
  std::strncpy(ifr.ifr_name, can_interface().c_str(), IFNAMSIZ - 1);
  ASSERT_EQ(::ioctl(fd, SIOCGIFINDEX, &ifr), 0) << std::strerror(errno);
  sockaddr_can addr{};
  addr.can_family = AF_CAN;
  addr.can_ifindex = ifr.ifr_ifindex;
  ASSERT_EQ(::bind(fd, reinterpret_cast<sockaddr*>(&addr), sizeof addr), 0);
  can_frame f{};
  f.can_id = CAN_ERR_FLAG | error_class;
  f.len = CAN_ERR_DLC;
  ASSERT_EQ(::write(fd, &f, sizeof f), static_cast<ssize_t>(sizeof f)) << std::strerror(errno);
  ::close(fd);
}

TEST(SocketCanVm, ErrorFramesAreReportedAsBusErrors) {
  auto rx = open_bus(sbg_filters(), true);
  auto quiet = open_bus(sbg_filters(), false);
  auto tx = open_bus({});
  ASSERT_TRUE(rx && quiet && tx);
  send_error_frame(CAN_ERR_BUSOFF);
  send_error_frame(CAN_ERR_CRTL);
  const drivers::sbg::CanIds ids{};
  ASSERT_EQ(tx->send(frame(ids.ekf_info, 1)), hal::Status::kOk);

  hal::CanFrame got;
  ASSERT_EQ(rx->receive(got, 1'000'000), hal::Status::kBusError);
  EXPECT_EQ(rx->last_error_class(), CAN_ERR_BUSOFF);
  EXPECT_NE(rx->last_error().message.find(can_interface()), std::string::npos)
      << rx->last_error().message;
  ASSERT_EQ(rx->receive(got, 1'000'000), hal::Status::kBusError);
  EXPECT_EQ(rx->last_error_class(), CAN_ERR_CRTL);
  EXPECT_EQ(rx->error_frames(), 2u);
  ASSERT_EQ(rx->receive(got, 1'000'000), hal::Status::kOk);  // data flows on after errors
  EXPECT_EQ(got.id, ids.ekf_info);

  // A socket that did not ask for error frames sees only the data frame.
  ASSERT_EQ(quiet->receive(got, 1'000'000), hal::Status::kOk);
  EXPECT_EQ(got.id, ids.ekf_info);
  EXPECT_EQ(quiet->error_frames(), 0u);
}

TEST(SocketCanVm, BurstOf10000FramesAt1kHzWithoutLoss) {
  constexpr std::size_t kFrames = 10'000;
  auto rx = open_bus(sbg_filters(true));
  auto tx = open_bus({});
  ASSERT_TRUE(rx && tx);
  auto frames = sim_ins_frames(kFrames, 250.0);
  frames.resize(kFrames);
  std::atomic<std::size_t> send_failures{0};
  std::atomic<std::size_t> resyncs{0};
  std::thread sender([&] {
    // 1 kHz on absolute deadlines (no drift). When the whole VM was descheduled by the host for
    // more than 20 ms, the schedule restarts from now instead of catching up with a burst the
    // real INS would never send.
    std::int64_t next = drivers::monotonic_ns();
    for (const hal::CanFrame& f : frames) {
      next += 1'000'000;
      if (drivers::monotonic_ns() > next + 20'000'000) {
        next = drivers::monotonic_ns();
        ++resyncs;
      }
      const timespec ts{static_cast<time_t>(next / 1'000'000'000),
                        static_cast<long>(next % 1'000'000'000)};
      ::clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr);
      if (tx->send(f) != hal::Status::kOk) ++send_failures;
    }
  });
  std::size_t received = 0;
  std::size_t mismatches = 0;
  std::size_t non_monotonic = 0;
  std::uint64_t last_t = 0;
  hal::CanFrame got;
  while (received < kFrames && rx->receive(got, 2'000'000) == hal::Status::kOk) {
    if (!same_payload(got, frames[received])) ++mismatches;
    if (got.t_us < last_t) ++non_monotonic;
    last_t = got.t_us;
    ++received;
  }
  sender.join();
  EXPECT_EQ(send_failures.load(), 0u);
  EXPECT_EQ(received, kFrames);
  EXPECT_EQ(mismatches, 0u);
  EXPECT_EQ(non_monotonic, 0u);
  EXPECT_EQ(rx->dropped_frames(), 0u);
  std::printf("burst: %zu frames received, %zu schedule restarts after VM stalls\n", received,
              resyncs.load());
  EXPECT_LT(resyncs.load(), kFrames / 100) << "the sender could not keep 1 kHz";
}

// Runs a program with stdout redirected to a file (empty = inherited); returns its pid.
pid_t spawn(const std::vector<std::string>& argv, const std::string& stdout_path) {
  const pid_t pid = ::fork();
  if (pid == 0) {
    if (!stdout_path.empty()) {
      const int fd = ::open(stdout_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
      if (fd < 0 || ::dup2(fd, 1) < 0) ::_exit(126);
    }
    std::vector<char*> args;
    for (const std::string& a : argv)
      args.push_back(const_cast<char*>(a.c_str()));
    args.push_back(nullptr);
    ::execvp(args[0], args.data());
    ::_exit(127);
  }
  return pid;
}

// Exit status of `pid`; a process still running after timeout_us is killed (status 128 + 9).
int wait_exit(pid_t pid, std::uint64_t timeout_us = 30'000'000) {
  const std::uint64_t deadline = drivers::monotonic_us() + timeout_us;
  int status = 0;
  pid_t r = 0;
  while ((r = ::waitpid(pid, &status, WNOHANG)) == 0) {
    if (drivers::monotonic_us() > deadline) {
      ::kill(pid, SIGKILL);
      r = ::waitpid(pid, &status, 0);
      break;
    }
    ::usleep(10'000);
  }
  if (r != pid) return -1;
  return WIFEXITED(status) ? WEXITSTATUS(status) : 128 + WTERMSIG(status);
}

// Receivers registered on the interface (/proc/net/can/rcvlist_all): tells when a freshly
// started candump has its socket bound, without guessing a delay.
int can_receivers() {
  std::ifstream f("/proc/net/can/rcvlist_all");
  std::string line;
  int n = 0;
  while (std::getline(f, line))
    if (line.find(can_interface()) != std::string::npos) ++n;
  return n;
}

TEST(SocketCanVm, CanplayerReplaysCandumpLogThroughDriver) {
  auto rx = open_bus(sbg_filters(true));
  ASSERT_TRUE(rx);
  // A 2 s recording at 100 Hz as candump -L writes it, with unrelated traffic interleaved.
  auto frames = sim_ins_frames(800, 100.0);
  const std::string path = "/tmp/sbg_replay.log";
  {
    std::ofstream log(path);
    std::uint64_t t = 1'700'000'000'000'000;
    for (std::size_t i = 0; i < frames.size(); ++i) {
      t += 2'500;
      log << vmtest::format_candump_line(frames[i], t, can_interface()) << '\n';
      if (i % 7 == 0)
        log << vmtest::format_candump_line(frame(0x3A0, 9), t, can_interface()) << '\n';
    }
  }
  const auto expected = decode_directly(frames);
  const pid_t player = spawn({"canplayer", "-I", path}, "");
  ASSERT_GT(player, 0);
  drivers::sbg::CanAttitudeSource source(*rx);
  std::vector<hal::AttitudeSample> got;
  hal::AttitudeSample s;
  // read() returns kTimeout as soon as the bus is momentarily empty between the frames of an
  // epoch, so it is called until the whole replay (about 2.3 s) has been consumed.
  const std::uint64_t deadline = drivers::monotonic_us() + 10'000'000;
  while (got.size() < expected.size() && drivers::monotonic_us() < deadline) {
    if (source.read(s, 100'000) == hal::Status::kOk) got.push_back(s);
  }
  EXPECT_EQ(wait_exit(player), 0) << "canplayer failed";
  ASSERT_EQ(got.size(), expected.size());
  for (std::size_t i = 0; i < got.size(); ++i) {
    EXPECT_EQ(got[i].q_nb, expected[i].q_nb) << i;
    EXPECT_EQ(got[i].t_ins_us, expected[i].t_ins_us) << i;
  }
  EXPECT_EQ(source.counters().malformed, 0u);
  EXPECT_EQ(source.counters().ignored, 0u);  // the kernel filter already dropped 0x3A0
}

TEST(SocketCanVm, CandumpRecordsWhatTheDriverSends) {
  auto tx = open_bus({});
  ASSERT_TRUE(tx);
  const std::string path = "/tmp/sbg_capture.log";
  const auto frames = sim_ins_frames(200, 100.0);
  const int receivers = can_receivers();
  // candump -n: it exits by itself after that many frames (a lost frame shows as a timeout).
  const pid_t dump =
      spawn({"candump", "-L", "-n", std::to_string(frames.size()), can_interface()}, path);
  ASSERT_GT(dump, 0);
  const std::uint64_t deadline = drivers::monotonic_us() + 10'000'000;
  while (can_receivers() <= receivers && drivers::monotonic_us() < deadline)
    ::usleep(5'000);
  ASSERT_GT(can_receivers(), receivers) << "candump did not bind its socket";
  for (const hal::CanFrame& f : frames)
    ASSERT_EQ(tx->send(f), hal::Status::kOk);
  EXPECT_EQ(wait_exit(dump, 10'000'000), 0) << "candump did not see all frames";
  std::ifstream log(path);
  std::string line;
  std::vector<vmtest::LoggedFrame> captured;
  while (std::getline(log, line)) {
    auto parsed = vmtest::parse_candump_line(line);
    ASSERT_TRUE(parsed.has_value()) << "unparsable candump line: " << line;
    captured.push_back(*parsed);
  }
  ASSERT_EQ(captured.size(), frames.size());
  for (std::size_t i = 0; i < frames.size(); ++i) {
    EXPECT_TRUE(same_payload(captured[i].frame, frames[i])) << i;
    EXPECT_EQ(captured[i].interface, can_interface());
  }
  EXPECT_EQ(decode_directly(frames).size(), [&] {
    std::vector<hal::CanFrame> back;
    for (const auto& c : captured)
      back.push_back(c.frame);
    return decode_directly(back).size();
  }());
}

}  // namespace
}  // namespace magvec
