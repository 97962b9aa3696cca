// TermiosSerialPort (drivers/linux/termios_serial_port.hpp) for real over pseudo-terminal pairs:
// the simulated serial fluxgate writes its lines into the master end, the driver reads the slave
// end through a symlink (as /dev/serial/by-id/... would be), and the real SerialFluxgate codec
// decodes them. Unplug = closing the master; re-plug = a new pty behind the same symlink.
#include "magvec/drivers/linux/termios_serial_port.hpp"

#include <fcntl.h>
#include <poll.h>
#include <pty.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <array>
#include <cerrno>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"

namespace {

using namespace magvec;
namespace fs = std::filesystem;
using drivers::OsError;
using drivers::SerialConfig;
using drivers::TermiosSerialPort;

// One pty pair; the slave is reachable through `link` (a symlink in a private temp directory).
class Pty {
 public:
  explicit Pty(const fs::path& link) {
    std::array<char, 128> name{};
    if (::openpty(&master_, &slave_, name.data(), nullptr, nullptr) != 0) std::abort();
    slave_name_ = name.data();
    const fs::path tmp = link.string() + ".new";
    fs::remove(tmp);
    fs::create_symlink(slave_name_, tmp);
    fs::rename(tmp, link);  // atomic replacement of the previous link
  }
  ~Pty() {
    close_master();
    close_slave();
  }
  Pty(const Pty&) = delete;
  Pty& operator=(const Pty&) = delete;

  void close_master() {
    if (master_ >= 0) ::close(master_);
    master_ = -1;
  }
  void close_slave() {  // the test's own handle; the driver opens the slave by path
    if (slave_ >= 0) ::close(slave_);
    slave_ = -1;
  }
  void write_all(std::span<const std::uint8_t> bytes) const {
    std::size_t done = 0;
    while (done < bytes.size()) {
      const ssize_t r = ::write(master_, bytes.data() + done, bytes.size() - done);
      ASSERT_GT(r, 0) << "write to pty master: errno " << errno;
      done += static_cast<std::size_t>(r);
    }
  }
  std::vector<std::uint8_t> read_exactly(std::size_t n) const {
    std::vector<std::uint8_t> out;
    while (out.size() < n) {
      pollfd pfd{master_, POLLIN, 0};
      if (::poll(&pfd, 1, 2000) <= 0) break;
      std::array<std::uint8_t, 512> buf{};
      const ssize_t r = ::read(master_, buf.data(), std::min(buf.size(), n - out.size()));
      if (r <= 0) break;
      out.insert(out.end(), buf.begin(), buf.begin() + r);
    }
    return out;
  }
  const std::string& slave_name() const { return slave_name_; }

 private:
  int master_{-1};
  int slave_{-1};
  std::string slave_name_;
};

class TermiosTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "magvec_tty_XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
    link_ = dir_ / "ttyFLUX";
  }
  void TearDown() override { fs::remove_all(dir_); }

  SerialConfig config(std::uint32_t reconnect_ms = 20) const {
    SerialConfig c;
    c.device = link_.string();
    c.baud = 115200;
    c.reconnect_interval_ms = reconnect_ms;
    return c;
  }

  fs::path dir_;
  fs::path link_;
};

std::vector<std::uint8_t> read_n(TermiosSerialPort& port, std::size_t n) {
  std::vector<std::uint8_t> out;
  for (int i = 0; i < 200 && out.size() < n; ++i) {
    std::array<std::uint8_t, 256> buf{};
    std::size_t got = 0;
    const hal::Status s = port.read(
        std::span<std::uint8_t>(buf.data(), std::min(buf.size(), n - out.size())), got, 100'000);
    if (s == hal::Status::kTimeout) break;
    EXPECT_EQ(s, hal::Status::kOk);
    if (s != hal::Status::kOk) break;
    out.insert(out.end(), buf.begin(), buf.begin() + static_cast<std::ptrdiff_t>(got));
  }
  return out;
}

TEST_F(TermiosTest, SimulatedFluxgateLinesDecodeThroughTheRealCodec) {
  Pty pty(link_);
  OsError err;
  auto port = TermiosSerialPort::open(config(), &err);
  ASSERT_NE(port, nullptr) << err.message;
  pty.close_slave();

  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.num_samples = 300;
  drivers::sim::Simulator sim(sc, 11);
  drivers::sim::SimSerialConfig simcfg;
  simcfg.line.checksum = drivers::ChecksumMode::kRequired;
  drivers::sim::SimSerialFluxgate instrument(simcfg);
  drivers::LinuxClock clock;
  drivers::SerialFluxgate<drivers::AsciiLineDecoder> fluxgate(
      *port, clock, drivers::AsciiLineDecoder(simcfg.line));

  drivers::sim::SimSample s{};
  std::uint32_t decoded = 0;
  std::uint32_t lines = 0;
  while (sim.next(&s)) {
    instrument.transmit(s);
    std::array<std::uint8_t, 256> line{};
    std::size_t n = 0;
    std::vector<std::uint8_t> bytes;
    while (instrument.read(line, n, 0) == hal::Status::kOk)
      bytes.insert(bytes.end(), line.begin(), line.begin() + static_cast<std::ptrdiff_t>(n));
    if (bytes.empty()) continue;  // a simulated dropout: nothing sent
    ++lines;
    const std::uint64_t t_before = clock.now_us();
    pty.write_all(bytes);
    hal::MagnetometerSample out;
    ASSERT_EQ(fluxgate.read(out, 1'000'000), hal::Status::kOk) << "sample " << s.index;
    const std::uint64_t t_after = clock.now_us();
    for (int i = 0; i < 3; ++i) {
      // The resolution bound of the line format (as in sim_devices_test).
      EXPECT_NEAR(out.m_nT[static_cast<std::size_t>(i)], s.m_nT[i], 0.0005 + 1e-9);
    }
    EXPECT_GE(out.t_us, t_before);
    EXPECT_LE(out.t_us, t_after);
    ++decoded;
  }
  EXPECT_GT(lines, 250u);
  EXPECT_EQ(decoded, lines);
  EXPECT_EQ(fluxgate.counters().crc_errors, 0u);
  EXPECT_EQ(fluxgate.counters().malformed, 0u);
  EXPECT_EQ(fluxgate.counters().garbage_bytes, 0u);
  EXPECT_EQ(fluxgate.counters().bus_errors, 0u);
}

TEST_F(TermiosTest, ReadTimesOutWithNothingAndPollsWithZeroTimeout) {
  Pty pty(link_);
  OsError err;
  auto port = TermiosSerialPort::open(config(), &err);
  ASSERT_NE(port, nullptr) << err.message;
  std::array<std::uint8_t, 16> buf{};
  std::size_t n = 99;
  EXPECT_EQ(port->read(buf, n, 0), hal::Status::kTimeout);
  EXPECT_EQ(n, 0u);
  const std::uint64_t t0 = drivers::monotonic_us();
  n = 99;
  EXPECT_EQ(port->read(buf, n, 30'000), hal::Status::kTimeout);
  EXPECT_EQ(n, 0u);
  EXPECT_GE(drivers::monotonic_us() - t0, 29'000u);  // waited (lower bound only)
  EXPECT_TRUE(port->connected());
  EXPECT_EQ(port->read(std::span<std::uint8_t>(), n, 0), hal::Status::kInvalidArgument);
}

TEST_F(TermiosTest, AllByteValuesPassUnchangedInBothDirections) {
  Pty pty(link_);
  OsError err;
  auto port = TermiosSerialPort::open(config(), &err);
  ASSERT_NE(port, nullptr) << err.message;
  pty.close_slave();
  // Every byte value, including NUL, CR/LF, ^C/^D/^Z, XON/XOFF and DEL, twice.
  std::vector<std::uint8_t> bytes;
  for (int rep = 0; rep < 2; ++rep)
    for (int b = 0; b < 256; ++b)
      bytes.push_back(static_cast<std::uint8_t>(b));
  pty.write_all(bytes);
  EXPECT_EQ(read_n(*port, bytes.size()), bytes);

  std::size_t written = 0;
  ASSERT_EQ(port->write(bytes, written), hal::Status::kOk) << port->last_error().message;
  EXPECT_EQ(written, bytes.size());
  EXPECT_EQ(pty.read_exactly(bytes.size()), bytes);  // no echo, no output processing
}

TEST_F(TermiosTest, UnplugReportsBusErrorAndReplugReconnects) {
  auto pty = std::make_unique<Pty>(link_);
  OsError err;
  auto port = TermiosSerialPort::open(config(20), &err);
  ASSERT_NE(port, nullptr) << err.message;
  pty->close_slave();
  const std::vector<std::uint8_t> hello{'h', 'e', 'l', 'l', 'o'};
  pty->write_all(hello);
  EXPECT_EQ(read_n(*port, hello.size()), hello);

  // Unplug: the device disappears (master closed, its node and our symlink target gone), and with
  // it the link, as udev removes a /dev/serial/by-id link. A stale link resolved to whatever pty
  // the kernel numbered alike next: under a parallel ctest another test's, to which the port then
  // "reconnected" (this test failed once that way).
  pty.reset();
  fs::remove(link_);
  std::array<std::uint8_t, 16> buf{};
  std::size_t n = 0;
  EXPECT_EQ(port->read(buf, n, 100'000), hal::Status::kBusError);
  EXPECT_FALSE(port->connected());
  EXPECT_EQ(port->disconnects(), 1u);
  EXPECT_NE(port->last_error().message.find(link_.string()), std::string::npos)
      << port->last_error().message;
  // While it is away every call reports kBusError (after waiting its timeout, not spinning).
  for (int i = 0; i < 3; ++i) {
    const std::uint64_t t0 = drivers::monotonic_us();
    EXPECT_EQ(port->read(buf, n, 30'000), hal::Status::kBusError);
    EXPECT_GE(drivers::monotonic_us() - t0, 29'000u);
    EXPECT_EQ(n, 0u);
  }
  std::size_t written = 0;
  EXPECT_EQ(port->write(hello, written), hal::Status::kBusError);
  EXPECT_EQ(port->reconnects(), 0u);
  EXPECT_NE(port->last_error().message.find("open"), std::string::npos)
      << port->last_error().message;

  // Re-plug: a new device behind the same path.
  Pty replugged(link_);
  for (int i = 0; i < 50 && !port->connected(); ++i)
    (void)port->read(buf, n, 20'000);
  ASSERT_TRUE(port->connected()) << port->last_error().message;
  replugged.close_slave();
  EXPECT_EQ(port->reconnects(), 1u);
  const std::vector<std::uint8_t> again{'a', 'g', 'a', 'i', 'n', 0, '\r', '\n'};
  replugged.write_all(again);
  EXPECT_EQ(read_n(*port, again.size()), again);
  ASSERT_EQ(port->write(hello, written), hal::Status::kOk);
  EXPECT_EQ(replugged.read_exactly(hello.size()), hello);
}

TEST(TermiosErrors, NonexistentDeviceNamesPathAndErrno) {
  SerialConfig c;
  c.device = "/nonexistent/ttyMAGVEC0";
  OsError err;
  EXPECT_EQ(TermiosSerialPort::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, ENOENT);
  EXPECT_NE(err.message.find("/nonexistent/ttyMAGVEC0"), std::string::npos) << err.message;
  EXPECT_NE(err.message.find("No such file or directory (errno 2)"), std::string::npos)
      << err.message;
  EXPECT_EQ(TermiosSerialPort::open(c, nullptr), nullptr);  // error output optional
}

TEST(TermiosErrors, NotATerminalAndUnsupportedBaudAreClear) {
  SerialConfig c;
  c.device = "/dev/null";
  OsError err;
  EXPECT_EQ(TermiosSerialPort::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, ENOTTY);
  EXPECT_NE(err.message.find("serial /dev/null: tcgetattr"), std::string::npos) << err.message;

  c.baud = 12345;
  err = {};
  EXPECT_EQ(TermiosSerialPort::open(c, &err), nullptr);
  EXPECT_EQ(err.error_number, EINVAL);
  EXPECT_NE(err.message.find("unsupported baud rate 12345"), std::string::npos) << err.message;
}

}  // namespace
