// The fault syntax of the simulated rig, one implementation for `magvec run --faults`, `magvec
// soak --faults` and magvecd's `[sim] faults`: comma-separated key=value items that set the
// simulator's and the simulated devices' fault injection (drivers/sim).
#pragma once

#include <stdexcept>
#include <string>

#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"

namespace magvec::host::hil {

// Every key, for help texts.
inline constexpr const char* kFaultsHelp =
    "Comma-separated faults: crc=P, saturation=P, adc-reset=P, stuck=START:LEN (SPI), "
    "dropout=P, spike=P (any), garbage=P, bad-checksum=P (serial), ins-corrupt=P, "
    "ins-duplicate=P, ins-gap=START:LEN, ins-invalid=START:LEN, ins-latency-us=N, "
    "clock-jump=AT:JUMP_S";

// A bad item; what() names the key and the problem.
class FaultSpecError : public std::invalid_argument {
 public:
  using std::invalid_argument::invalid_argument;
};

// Applies `spec` on top of the configurations; throws FaultSpecError on a bad item (the
// configurations may then be partly changed).
void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc);

}  // namespace magvec::host::hil
