// --faults parsing (fault_spec.hpp), moved out of cmd_run.cpp so `magvec soak` takes the same
// syntax.
#include "fault_spec.hpp"

#include <CLI/CLI.hpp>
#include <cmath>
#include <sstream>
#include <tuple>
#include <utility>

namespace magvec::host::cli {
namespace {

double number(const std::string& option, const std::string& key, const std::string& text) {
  std::size_t used = 0;
  double v = 0;
  try {
    v = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used != text.size() || !std::isfinite(v))
    throw CLI::ValidationError(option, key + ": not a number: '" + text + "'");
  return v;
}

double probability(const std::string& option, const std::string& key, const std::string& text) {
  const double p = number(option, key, text);
  if (p < 0 || p > 1) throw CLI::ValidationError(option, key + ": probability must be in [0, 1]");
  return p;
}

// "a:b" -> (a, b)
std::pair<double, double> pair_of(const std::string& option, const std::string& key,
                                  const std::string& text) {
  const auto colon = text.find(':');
  if (colon == std::string::npos)
    throw CLI::ValidationError(option, key + " needs START:LENGTH (seconds), got '" + text + "'");
  return {number(option, key, text.substr(0, colon)), number(option, key, text.substr(colon + 1))};
}

}  // namespace

void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc, const std::string& option) {
  std::stringstream ss(spec);
  std::string item;
  while (std::getline(ss, item, ',')) {
    if (item.empty()) continue;
    const auto eq = item.find('=');
    if (eq == std::string::npos)
      throw CLI::ValidationError(option, "expected key=value, got '" + item + "'");
    const std::string key = item.substr(0, eq);
    const std::string val = item.substr(eq + 1);
    if (key == "crc") {
      rc->adc.faults.crc_error_probability = probability(option, key, val);
    } else if (key == "saturation") {
      rc->adc.faults.saturation_probability = probability(option, key, val);
    } else if (key == "adc-reset") {
      rc->adc.faults.reset_probability = probability(option, key, val);
    } else if (key == "stuck") {
      std::tie(rc->adc.faults.stuck_start_s, rc->adc.faults.stuck_length_s) =
          pair_of(option, key, val);
      if (rc->adc.faults.stuck_length_s < 0)
        throw CLI::ValidationError(option, "stuck: LENGTH must be >= 0");
    } else if (key == "dropout") {
      sc->dropout_probability = probability(option, key, val);
    } else if (key == "spike") {
      sc->spike_probability = probability(option, key, val);
      if (sc->spike_amplitude_nT == 0) sc->spike_amplitude_nT = 1000;
    } else if (key == "garbage") {
      rc->serial.faults.garbage_probability = probability(option, key, val);
    } else if (key == "bad-checksum") {
      rc->serial.faults.bad_checksum_probability = probability(option, key, val);
    } else if (key == "ins-corrupt") {
      rc->ins.faults.corrupt_probability = probability(option, key, val);
    } else if (key == "ins-duplicate") {
      rc->ins.faults.duplicate_probability = probability(option, key, val);
    } else if (key == "ins-gap") {
      std::tie(rc->ins.faults.gap_start_s, rc->ins.faults.gap_length_s) = pair_of(option, key, val);
    } else if (key == "ins-invalid") {
      std::tie(rc->ins.faults.invalid_start_s, rc->ins.faults.invalid_length_s) =
          pair_of(option, key, val);
    } else if (key == "ins-latency-us") {
      const double v = number(option, key, val);
      if (v < 0 || v > 1e6)
        throw CLI::ValidationError(option, "ins-latency-us must be in [0, 1e6]");
      rc->ins.can_latency_us = static_cast<std::uint32_t>(v);
    } else if (key == "clock-jump") {
      const auto [at, jump_s] = pair_of(option, key, val);
      if (std::fabs(jump_s) > 5.0)
        throw CLI::ValidationError(option, "clock-jump: |jump| must be <= 5 s");
      rc->time.jump_at_s = at;
      rc->time.jump_us = std::llround(jump_s * 1e6);
    } else {
      throw CLI::ValidationError(option, "unknown fault '" + key + "'");
    }
  }
}

}  // namespace magvec::host::cli
