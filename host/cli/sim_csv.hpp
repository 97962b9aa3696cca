// Shared by `magvec simulate` and `magvec demo`: scenario selection by name, the simulation CSV
// layout (docs/conventions.md#file-formats columns plus truth columns the reader ignores) and the
// '#' header that states scenario, seed and the truth parameters in canonical, Li, Ge and sine
// form.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "magvec/drivers/sim/simulator.hpp"

namespace magvec::host::cli {

// li2023 | ge2017 | sine-xy | sine-xz | survey; fixture is used for sine-xz only.
drivers::sim::ScenarioConfig scenario_by_name(const std::string& name,
                                              drivers::sim::Fixture fixture);
const std::vector<std::string>& scenario_names();

// Column names of a simulation CSV, in order.
const std::vector<std::string>& sim_csv_columns();
// Header comment lines (without '#').
std::vector<std::string> sim_csv_comments(const drivers::sim::ScenarioConfig& cfg,
                                          std::uint64_t seed);
// Runs the simulator to its end and writes the CSV atomically; returns the number of rows.
std::uint64_t write_sim_csv(drivers::sim::Simulator* sim, const std::string& path);

}  // namespace magvec::host::cli
