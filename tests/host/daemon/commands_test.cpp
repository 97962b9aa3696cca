// run_command (host/daemon commands.hpp): what each operator command does and answers.
#include "magvec/host/daemon/commands.hpp"

#include <gtest/gtest.h>

namespace magvec::host::daemon {
namespace {

struct Recorder {
  int starts{0};
  int persists{0};
  int set_actives{0};
  std::uint32_t set_active_id{999};
  double set_active_offset_s{-1};
  CommandActions actions() {
    CommandActions a;
    a.start_calibration = [this] { ++starts; };
    a.persist = [this](const CalibrationStatus&) { ++persists; };
    a.set_active = [this](const core::SensorModel<double>&, std::uint32_t id, double off,
                          const OutputQuality&) {
      ++set_actives;
      set_active_id = id;
      set_active_offset_s = off;
    };
    return a;
  }
};

CommandContext context() {
  CommandContext c;
  c.calibration_mode = "li";
  c.persisted_path = "/var/lib/magvecd/cal.json";
  c.samples = 42;
  return c;
}

TEST(Commands, StartStartsUnlessTheModeIsNone) {
  Recorder rec;
  CommandOutcome o = run_command("start", context(), rec.actions());
  EXPECT_TRUE(o.ok);
  EXPECT_EQ(o.message, "calibration started (li)");
  EXPECT_EQ(rec.starts, 1);
  CommandContext none = context();
  none.calibration_mode = "none";
  o = run_command("start", none, rec.actions());
  EXPECT_FALSE(o.ok);
  EXPECT_EQ(rec.starts, 1);
  EXPECT_NE(o.message.find("'none'"), std::string::npos);
}

TEST(Commands, AcceptPersistsOnlyANewActiveCalibration) {
  Recorder rec;
  CommandContext c = context();
  CommandOutcome o = run_command("accept", c, rec.actions());  // uncalibrated
  EXPECT_FALSE(o.ok);
  EXPECT_EQ(o.message, "no calibration is active: nothing to accept");
  c.status.cal_id = 2;
  c.persisted.present = true;
  c.persisted.cal_id = 2;
  o = run_command("accept", c, rec.actions());
  EXPECT_TRUE(o.ok);
  EXPECT_EQ(o.message, "calibration 2 is already persisted");
  EXPECT_FALSE(o.reply_when_persisted);
  EXPECT_EQ(rec.persists, 0);
  // A new one: the write starts, and the reply waits for its end (this message if it succeeds).
  c.status.cal_id = 3;
  o = run_command("accept", c, rec.actions());
  EXPECT_TRUE(o.ok);
  EXPECT_TRUE(o.reply_when_persisted);
  EXPECT_EQ(o.message, "calibration 3 persisted to /var/lib/magvecd/cal.json");
  EXPECT_EQ(rec.persists, 1);
}

TEST(Commands, RevertInstallsThePersistedCalibrationOrTheIdentity) {
  Recorder rec;
  CommandContext c = context();
  CommandOutcome o = run_command("revert", c, rec.actions());
  EXPECT_TRUE(o.ok);
  EXPECT_EQ(rec.set_active_id, 0u);
  EXPECT_NE(o.message.find("identity"), std::string::npos);
  c.persisted.present = true;
  c.persisted.cal_id = 5;
  c.persisted.time_offset_s = 0.02;
  o = run_command("revert", c, rec.actions());
  EXPECT_EQ(o.message, "reverted to the persisted calibration 5");
  EXPECT_EQ(rec.set_active_id, 5u);
  EXPECT_DOUBLE_EQ(rec.set_active_offset_s, 0.02);
  EXPECT_EQ(rec.set_actives, 2);
}

TEST(Commands, StatusAndUnknown) {
  Recorder rec;
  CommandOutcome o = run_command("status", context(), rec.actions());
  EXPECT_TRUE(o.ok);
  EXPECT_TRUE(o.state_changed);
  EXPECT_EQ(o.message, "running, 42 samples");
  o = run_command("reboot", context(), rec.actions());
  EXPECT_FALSE(o.ok);
  EXPECT_FALSE(o.state_changed);
  EXPECT_EQ(o.message, "unknown command 'reboot' (start, accept, revert, status)");
  EXPECT_EQ(rec.starts + rec.persists + rec.set_actives, 0);
}

}  // namespace
}  // namespace magvec::host::daemon
