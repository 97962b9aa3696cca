// magvecd's sessions: a session is one configuration applied to one pipeline, started at boot
// and again on every SIGHUP reload. plan_session() decides the pipeline events that start it, in
// order (each is published and then applied by the daemon, so a replay rebuilds the same state):
//   SESSION_START (the configuration text as read: command-line overrides of the state directory
//   and the LCM URLs do not reach the pipeline), SOLVE_ON_WORKER when configured, SET_ACTIVE with
//   the persisted calibration (boot) or the running one (reload: carried over), and
//   START_CALIBRATION at boot when start_on_boot, or on a reload that interrupted a calibration
//   (its data belong to the old configuration: it starts again).
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/daemon/persistence.hpp"
#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

struct SessionPlan {
  std::vector<magvec_lcm::pipeline_event> events;
  bool calibration_restarted{false};  // a reload interrupted a calibration
};

// `running`: the pipeline of the session being replaced (nullptr at boot). `sequence` numbers
// the events (incremented per event).
SessionPlan plan_session(const Config& config, const std::string& config_text,
                         const PersistedCalibration& persisted, const Pipeline* running,
                         std::int64_t* sequence);

}  // namespace magvec::host::daemon
