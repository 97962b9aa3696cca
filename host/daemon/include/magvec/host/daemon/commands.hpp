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
  std::function<void()> start_calibration;  // START_CALIBRATION pipeline event
  // Starts writing cal.json (on the daemon's PersistWorker: the acquisition goes on meanwhile).
  std::function<void(const CalibrationStatus&)> persist;
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
  // accept: the reply waits for the end of the write it started; `message` is the reply when the
  // write succeeds (a failed one is answered with its error).
  bool reply_when_persisted{false};
};

CommandOutcome run_command(const std::string& command, const CommandContext& ctx,
                           const CommandActions& act);

}  // namespace magvec::host::daemon
