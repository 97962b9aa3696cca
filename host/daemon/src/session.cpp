// magvecd's session start; see session.hpp.
#include "magvec/host/daemon/session.hpp"

namespace magvec::host::daemon {

SessionPlan plan_session(const Config& config, const std::string& config_text,
                         const PersistedCalibration& persisted, const Pipeline* running,
                         std::int64_t* sequence) {
  SessionPlan plan;
  PersistedCalibration install = persisted;
  if (running != nullptr) {
    const CalibrationStatus st = running->status();
    install.present = st.cal_id != 0;
    install.model = st.active;
    install.cal_id = st.cal_id;
    install.time_offset_s = running->time_offset_s();
    install.output = st.output;
    plan.calibration_restarted = st.state == core::CalState::kCollecting ||
                                 st.state == core::CalState::kSolving ||
                                 st.state == core::CalState::kValidating;
  }
  plan.events.push_back(session_start_event(++*sequence, config_text));
  if (config.calibration.solve_on_worker) plan.events.push_back(solve_on_worker_event(++*sequence));
  if (install.present)
    plan.events.push_back(set_active_event(++*sequence, install.model, install.cal_id,
                                           install.time_offset_s, install.output));
  const bool start =
      running == nullptr ? config.calibration.start_on_boot : plan.calibration_restarted;
  if (config.calibration.mode != "none" && start)
    plan.events.push_back(start_calibration_event(++*sequence));
  else
    plan.calibration_restarted = false;
  return plan;
}

}  // namespace magvec::host::daemon
