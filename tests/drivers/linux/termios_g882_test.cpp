// The G-882 scalar magnetometer's Linux source (TermiosSerialPort + SerialScalarSource) for real
// over a pseudo-terminal: the simulated G-882 writes its lines into the master end, the driver
// reads the slave end at the instrument's 9600 baud and decodes them; then bad lines.
#include <gtest/gtest.h>

#include <cstdlib>
#include <filesystem>
#include <string>
#include <vector>

#include "magvec/drivers/g882.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/linux/termios_serial_port.hpp"
#include "magvec/drivers/sim/sim_g882.hpp"
#include "support/pty_pair.hpp"

namespace {

using namespace magvec;
namespace fs = std::filesystem;

class TermiosG882 : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "magvec_g882_XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
    link_ = dir_ / "ttyG882";
    pty_ = std::make_unique<test::PtyPair>(link_);
    drivers::SerialConfig c;
    c.device = link_.string();
    c.baud = 9600;  // the G-882 default (a pty ignores the rate)
    drivers::OsError err;
    port_ = drivers::TermiosSerialPort::open(c, &err);
    ASSERT_NE(port_, nullptr) << err.message;
    pty_->close_slave();
  }
  void TearDown() override {
    port_.reset();
    pty_.reset();
    fs::remove_all(dir_);
  }
  void write(const std::string& s) {
    ASSERT_TRUE(pty_->write_all(
        std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(s.data()), s.size())));
  }

  fs::path dir_;
  fs::path link_;
  std::unique_ptr<test::PtyPair> pty_;
  std::unique_ptr<drivers::TermiosSerialPort> port_;
  drivers::LinuxClock clock_;
};

TEST_F(TermiosG882, SimulatedInstrumentLinesDecodeWithReceiveTimes) {
  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.num_samples = 600;
  drivers::sim::Simulator sim(sc, 3);
  drivers::sim::SimG882Config cfg;
  cfg.noise_nT = 0;
  drivers::sim::SimG882 instrument(cfg);
  drivers::SerialScalarSource source(*port_, clock_, drivers::G882LineDecoder(cfg.line), 1000);
  drivers::sim::SimSample s{};
  std::uint32_t lines = 0;
  while (sim.next(&s)) {
    if (!instrument.transmit(s)) continue;
    std::array<std::uint8_t, 64> buf{};
    std::size_t n = 0;
    std::vector<std::uint8_t> bytes;
    while (instrument.read(buf, n, 0) == hal::Status::kOk)
      bytes.insert(bytes.end(), buf.begin(), buf.begin() + static_cast<std::ptrdiff_t>(n));
    ++lines;
    const std::uint64_t t_before = clock_.now_us();
    ASSERT_TRUE(pty_->write_all(bytes));
    hal::ScalarSample out;
    ASSERT_EQ(source.read(out, 1'000'000), hal::Status::kOk) << "line " << lines;
    const std::uint64_t t_after = clock_.now_us();
    EXPECT_NEAR(out.f_nT, s.h_n_true_nT.norm(), 0.0005 + 1e-9);
    EXPECT_GE(out.t_us + 1000, t_before);  // receive time minus the 1-ms latency
    EXPECT_LE(out.t_us + 1000, t_after);
  }
  EXPECT_GE(lines, 20u);
  EXPECT_EQ(source.counters().samples, lines);
  EXPECT_EQ(source.counters().malformed + source.counters().garbage_bytes +
                source.counters().bus_errors + source.counters().out_of_range,
            0u);
}

TEST_F(TermiosG882, BadLinesAreCountedRejectedAndTheStreamRecovers) {
  drivers::SerialScalarSource source(*port_, clock_,
                                     drivers::G882LineDecoder(drivers::G882LineConfig{}));
  write("noise\r\n$ 48123.45x,0721\r\n$ 12000.000,0721\r\n$ 4812$ 48123.456,0721\r\n");
  write("$ 48123.456" + std::string(80, '9') + "\r\n$ 48200.000,0800\r\n");
  std::vector<hal::Status> got;
  std::vector<double> f;
  for (int i = 0; i < 20; ++i) {
    hal::ScalarSample out;
    const hal::Status st = source.read(out, 200'000);
    if (st == hal::Status::kTimeout) break;
    got.push_back(st);
    if (st == hal::Status::kOk) f.push_back(out.f_nT);
  }
  const std::vector<hal::Status> expected{
      hal::Status::kMalformed,  // 4812x
      hal::Status::kMalformed,  // 12000 nT: out of range
      hal::Status::kMalformed,  // "$ 4812" cut by the next preamble
      hal::Status::kOk,        hal::Status::kOverflow, hal::Status::kOk};
  EXPECT_EQ(got, expected);
  EXPECT_EQ(f, (std::vector<double>{48123.456, 48200.0}));
  const hal::ScalarCounters& c = source.counters();
  EXPECT_EQ(c.samples, 2u);
  EXPECT_EQ(c.malformed, 2u);
  EXPECT_EQ(c.out_of_range, 1u);
  EXPECT_EQ(c.overflows, 1u);
  EXPECT_EQ(c.garbage_bytes, 7u + 6u + (11u + 80u + 2u - 1u));
}

}  // namespace
