// magvecd's error-streak exit (Daemon::on_read_error): magnetometer read errors and nothing else
// for more than 10 s end the daemon with the device exit code and a message naming the cause;
// errors among good samples never do. The daemon runs in process in --sim mode with its simulated
// ADC's frames corrupted ([sim] faults = "crc=P"), LCM in memory (memq://). Each run takes ~11 s
// of wall time: the limit is the daemon's real 10 s on its monotonic clock.
#include <gtest/gtest.h>
#include <stdlib.h>

#include <csignal>
#include <filesystem>
#include <fstream>
#include <optional>
#include <string>
#include <thread>

#include "logged_daemon.hpp"
#include "magvec/host/daemon/daemon.hpp"
#include "magvec/host/daemon/daemon_error.hpp"

namespace magvec::host::daemon {
namespace {

namespace fs = std::filesystem;

class DaemonErrorStreak : public ::testing::Test {
 protected:
  void SetUp() override {
    char tmpl[] = "/tmp/magvec_error_streak_XXXXXX";
    ASSERT_NE(::mkdtemp(tmpl), nullptr);
    dir_ = tmpl;
  }
  void TearDown() override { fs::remove_all(dir_); }

  // The test configuration (100 Hz) with the simulated ADC's faults; no real-time hints.
  DaemonOptions options(const std::string& faults) {
    std::string text = test::fast_config_text();
    auto patch = [&text](const std::string& from, const std::string& to) {
      const auto at = text.find(from);
      ASSERT_NE(at, std::string::npos) << from;
      text.replace(at, from.size(), to);
    };
    patch("faults = \"\"", "faults = \"" + faults + "\"");
    patch("realtime = true", "realtime = false");
    const fs::path config = dir_ / "magvecd.toml";
    std::ofstream(config) << text;
    DaemonOptions o;
    o.config_path = config.string();
    o.sim = true;
    o.state_dir = (dir_ / "state").string();
    o.lcm_url = "memq://";
    return o;
  }

  fs::path dir_;
};

TEST_F(DaemonErrorStreak, OnlyReadErrorsForTenSecondsExitWithTheDeviceCode) {
  volatile std::sig_atomic_t stop = 0, reload = 0;
  Daemon d(options("crc=1"), DaemonSignals{&stop, &reload});
  std::optional<DaemonError> error;
  try {
    d.run();
  } catch (const DaemonError& e) {
    error = e;
  }
  ASSERT_TRUE(error.has_value()) << "the daemon kept running on nothing but read errors";
  EXPECT_EQ(error->code(), kExitDevice);
  const std::string what = error->what();
  EXPECT_NE(what.find("magnetometer: only read errors for 10 s (last: crc error"),
            std::string::npos)
      << what;
  // The streak is timed, not counted: at 100 Hz it holds hundreds of errors, not the first one.
  const auto n = what.rfind(", ");
  ASSERT_NE(n, std::string::npos) << what;
  EXPECT_GT(std::stoull(what.substr(n + 2)), 100u) << what;
}

TEST_F(DaemonErrorStreak, ErrorsAmongGoodSamplesDoNotStopTheDaemon) {
  // 90 % of the frames corrupted: streaks of errors, each ended by a good sample.
  volatile std::sig_atomic_t stop = 0, reload = 0;
  Daemon d(options("crc=0.9"), DaemonSignals{&stop, &reload});
  std::thread stopper([&stop] {
    std::this_thread::sleep_for(std::chrono::seconds(12));  // past the 10-s limit
    stop = 1;
  });
  int code = -1;
  std::string error;
  try {
    code = d.run();
  } catch (const DaemonError& e) {
    error = e.what();
  }
  stopper.join();
  EXPECT_EQ(error, "");
  EXPECT_EQ(code, kExitOk);
}

}  // namespace
}  // namespace magvec::host::daemon
