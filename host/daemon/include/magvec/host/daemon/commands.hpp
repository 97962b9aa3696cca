// magvecd's operator commands (`magvec ctl`): start | accept | revert | status. The decision and
// the reply text are here; what a command does to the daemon goes through CommandActions, so the
// rules are tested without LCM or devices.
#pragma once

#include <cstdint>
#include <functional>
#include <string>

#include "magvec/host/daemon/persistence.hpp"
#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

struct CommandActions {
  std::function<void()> start_calibration;                // START_CALIBRATION pipeline event
  std::function<bool(const CalibrationStatus&)> persist;  // write cal.json; false on failure
  // SET_ACTIVE pipeline event (model, cal_id, time_offset_s, output quality)
  std::function<void(const core::SensorModel<double>&, std::uint32_t, double, const OutputQuality&)>
      set_active;
};

struct CommandContext {
  std::string calibration_mode;  // li | ekf | none
  CalibrationStatus status;      // of the running pipeline
  PersistedCalibration persisted;
  std::string persisted_path;
  std::uint64_t samples{0};
};

struct CommandOutcome {
  bool ok{false};
  std::string message;
  bool state_changed{false};  // start/revert/status: publish the calibration state
};

CommandOutcome run_command(const std::string& command, const CommandContext& ctx,
                           const CommandActions& act);

}  // namespace magvec::host::daemon
