// magvecd's operator commands; see commands.hpp.
#include "magvec/host/daemon/commands.hpp"

namespace magvec::host::daemon {

CommandOutcome run_command(const std::string& c, const CommandContext& ctx,
                           const CommandActions& act) {
  CommandOutcome r;
  if (c == "start") {
    r.state_changed = true;
    if (ctx.calibration_mode == "none") {
      r.message = "calibration mode is 'none': nothing to start";
      return r;
    }
    act.start_calibration();
    r.ok = true;
    r.message = "calibration started (" + ctx.calibration_mode + ")";
    return r;
  }
  if (c == "accept") {
    const CalibrationStatus& st = ctx.status;
    if (st.cal_id == 0) {
      r.message = "no calibration is active: nothing to accept";
    } else if (ctx.persisted.present && st.cal_id == ctx.persisted.cal_id) {
      r.ok = true;
      r.message = "calibration " + std::to_string(st.cal_id) + " is already persisted";
    } else {
      act.persist(st);
      r.ok = true;
      r.reply_when_persisted = true;
      r.message =
          "calibration " + std::to_string(st.cal_id) + " persisted to " + ctx.persisted_path;
    }
    return r;
  }
  if (c == "revert") {
    r.state_changed = true;
    const PersistedCalibration& p = ctx.persisted;
    const core::SensorModel<double> identity;
    act.set_active(p.present ? p.model : identity, p.present ? p.cal_id : 0,
                   p.present ? p.time_offset_s : 0, p.present ? p.output : OutputQuality{});
    r.ok = true;
    r.message = p.present ? "reverted to the persisted calibration " + std::to_string(p.cal_id)
                          : "no persisted calibration: reverted to the identity (uncalibrated)";
    return r;
  }
  if (c == "status") {
    r.state_changed = true;
    r.ok = true;
    r.message = "running, " + std::to_string(ctx.samples) + " samples";
    return r;
  }
  r.message = "unknown command '" + c + "' (start, accept, revert, status)";
  return r;
}

}  // namespace magvec::host::daemon
