// magvecd's error-streak exit (Daemon::on_read_error): magnetometer read errors and nothing else
// for more than 10 s end the daemon with the device exit code and a message naming the cause,
// leaving the persisted calibration byte-identical, and the restart systemd then makes loads it;
// errors among good samples never end it. The daemon runs in process in --sim mode with its
// simulated ADC's frames corrupted ([sim] faults = "crc=P"), LCM in memory (memq://). Each run
// takes ~11 s of wall time: the limit is the daemon's real 10 s on its monotonic clock.
#include <gtest/gtest.h>
#include <spdlog/sinks/ostream_sink.h>
#include <spdlog/spdlog.h>
#include <stdlib.h>

#include <csignal>
#include <filesystem>
#include <fstream>
#include <optional>
#include <sstream>
#include <string>
#include <thread>

#include "logged_daemon.hpp"
#include "magvec/host/daemon/daemon.hpp"
#include "magvec/host/daemon/daemon_error.hpp"
#include "magvec/host/daemon/persistence.hpp"

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

std::string file_text(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::ostringstream os;
  os << in.rdbuf();
  return os.str();
}

// The daemon's log while the object lives (spdlog's default logger into a string).
class CapturedLog {
 public:
  CapturedLog()
      : previous_(spdlog::default_logger()),
        logger_(std::make_shared<spdlog::logger>(
            "test", std::make_shared<spdlog::sinks::ostream_sink_mt>(text_))) {
    spdlog::set_default_logger(logger_);
  }
  ~CapturedLog() { spdlog::set_default_logger(previous_); }
  CapturedLog(const CapturedLog&) = delete;
  CapturedLog& operator=(const CapturedLog&) = delete;
  std::string text() const { return text_.str(); }

 private:
  std::ostringstream text_;
  std::shared_ptr<spdlog::logger> previous_;
  std::shared_ptr<spdlog::logger> logger_;
};

// Runs a daemon until a stop request (SIGTERM's flag) after `for_time`: its exit code, or the
// error that ended it first.
struct StoppedRun {
  int code{-1};
  std::string error;
};
StoppedRun run_until_stopped(const DaemonOptions& options, std::chrono::milliseconds for_time) {
  volatile std::sig_atomic_t stop = 0, reload = 0;
  Daemon d(options, DaemonSignals{&stop, &reload});
  std::thread stopper([&stop, for_time] {
    std::this_thread::sleep_for(for_time);
    stop = 1;
  });
  StoppedRun r;
  try {
    r.code = d.run();
  } catch (const DaemonError& e) {
    r.error = e.what();
  }
  stopper.join();
  return r;
}

TEST_F(DaemonErrorStreak, OnlyReadErrorsForTenSecondsExitWithTheDeviceCode) {
  // The calibration in force before the device fails (as magvecd persisted it).
  const DaemonOptions opt = options("crc=1");
  fs::create_directories(opt.state_dir);
  CalibrationStatus st;
  st.calibrator = "li";
  st.cal_id = 7;
  st.validation_rms_nT = 0.3;
  st.active.w = core::Mat3<double>::Identity() * 1.002;
  st.active.o = core::Vec3<double>(12.5, -3.25, 4.0);
  std::string save_error;
  ASSERT_TRUE(CalibrationStore(opt.state_dir).save(st, 0, "before the fault", &save_error))
      << save_error;
  const fs::path cal = fs::path(opt.state_dir) / "cal.json";
  const std::string last_good = file_text(cal);

  volatile std::sig_atomic_t stop = 0, reload = 0;
  Daemon d(opt, DaemonSignals{&stop, &reload});
  std::optional<DaemonError> error;
  try {
    d.run();
  } catch (const DaemonError& e) {
    error = e;
  }
  ASSERT_TRUE(error.has_value()) << "the daemon kept running on nothing but read errors";
  EXPECT_EQ(file_text(cal), last_good) << "the failing device changed the persisted calibration";
  EXPECT_EQ(error->code(), kExitDevice);
  const std::string what = error->what();
  EXPECT_NE(what.find("magnetometer: only read errors for 10 s (last: crc error"),
            std::string::npos)
      << what;
  // The streak is timed, not counted: at 100 Hz it holds hundreds of errors, not the first one.
  const auto n = what.rfind(", ");
  ASSERT_NE(n, std::string::npos) << what;
  EXPECT_GT(std::stoull(what.substr(n + 2)), 100u) << what;

  // systemd restarts it (Restart=on-failure); the device works again. The new daemon starts with
  // the last calibration (its load, logged) and leaves the file as it was.
  {
    CapturedLog log;
    const StoppedRun restart = run_until_stopped(options(""), std::chrono::milliseconds(800));
    EXPECT_EQ(restart.error, "");
    EXPECT_EQ(restart.code, kExitOk);
    const std::string text = log.text();
    EXPECT_NE(text.find("loaded persisted calibration " + cal.string() + " (cal_id 7"),
              std::string::npos)
        << text;
  }
  EXPECT_EQ(file_text(cal), last_good);
}

TEST_F(DaemonErrorStreak, ErrorsAmongGoodSamplesDoNotStopTheDaemon) {
  // 90 % of the frames corrupted: streaks of errors, each ended by a good sample.
  const StoppedRun run = run_until_stopped(options("crc=0.9"), std::chrono::seconds(12));
  EXPECT_EQ(run.error, "");  // past the 10-s limit
  EXPECT_EQ(run.code, kExitOk);
}

}  // namespace
}  // namespace magvec::host::daemon
