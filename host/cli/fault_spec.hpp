// The --faults option of `magvec run` and `magvec soak`: the simulated rig's fault syntax
// (magvec/host/hil/fault_spec.hpp, shared with magvecd), its errors as CLI11 validation errors.
#pragma once

#include <string>

#include "magvec/host/hil/fault_spec.hpp"

namespace magvec::host::cli {

inline constexpr const char* kFaultsHelp = hil::kFaultsHelp;

// hil::apply_faults; a bad item throws CLI::ValidationError naming `option` and the item.
void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc, const std::string& option = "--faults");

}  // namespace magvec::host::cli
