// What `magvecd --sim` builds from the configuration: the simulated scenario (li2023 random
// attitudes running until stopped, or the survey pattern) at the configured magnetometer rate,
// and the SimRig (ADC transfer, INS rate/IDs/latency, seeds as `magvec run`), both with the
// configured faults (sim.faults). Shared with the tests so they drive exactly the daemon's rig.
#pragma once

#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/hil/loop_core.hpp"

namespace magvec::host::daemon {

drivers::sim::ScenarioConfig sim_scenario(const Config& c);
drivers::sim::SimRigConfig sim_rig_config(const Config& c);
// The LoopCore configuration of the pipeline (start_calibration is false: starting is an event).
hil::HilConfig hil_config(const Config& c);

}  // namespace magvec::host::daemon
