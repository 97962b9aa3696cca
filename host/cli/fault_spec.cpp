// --faults (fault_spec.hpp): the shared parser, with CLI11's error type.
#include "fault_spec.hpp"

#include <CLI/CLI.hpp>

namespace magvec::host::cli {

void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc, const std::string& option) {
  try {
    hil::apply_faults(spec, sc, rc);
  } catch (const hil::FaultSpecError& e) {
    throw CLI::ValidationError(option, e.what());
  }
}

}  // namespace magvec::host::cli
