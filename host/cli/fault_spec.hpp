// The --faults syntax shared by `magvec run` and `magvec soak`: comma-separated key=value items
// that set the simulator's and the simulated devices' fault injection (drivers/sim).
#pragma once

#include <string>

#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"

namespace magvec::host::cli {

// Help text of the option (every key).
inline constexpr const char* kFaultsHelp =
    "Comma-separated faults: crc=P, saturation=P, adc-reset=P, stuck=START:LEN (SPI), "
    "dropout=P, spike=P (any), garbage=P, "
    "bad-checksum=P (serial), ins-corrupt=P, ins-duplicate=P, ins-gap=START:LEN, "
    "ins-invalid=START:LEN, "
    "ins-latency-us=N, clock-jump=AT:JUMP_S";

// Applies `spec` on top of the configurations; a bad item throws CLI::ValidationError naming
// `option` and the item.
void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc, const std::string& option = "--faults");

}  // namespace magvec::host::cli
