// The fault syntax (fault_spec.hpp) of `magvec run`, `magvec soak` and magvecd's [sim] faults.
#include "magvec/host/hil/fault_spec.hpp"

#include <cmath>
#include <sstream>
#include <tuple>
#include <utility>

namespace magvec::host::hil {
namespace {

double number(const std::string& key, const std::string& text) {
  std::size_t used = 0;
  double v = 0;
  try {
    v = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used != text.size() || !std::isfinite(v))
    throw FaultSpecError(key + ": not a number: '" + text + "'");
  return v;
}

double probability(const std::string& key, const std::string& text) {
  const double p = number(key, text);
  if (p < 0 || p > 1) throw FaultSpecError(key + ": probability must be in [0, 1]");
  return p;
}

// "a:b" -> (a, b)
std::pair<double, double> pair_of(const std::string& key, const std::string& text) {
  const auto colon = text.find(':');
  if (colon == std::string::npos)
    throw FaultSpecError(key + " needs START:LENGTH (seconds), got '" + text + "'");
  return {number(key, text.substr(0, colon)), number(key, text.substr(colon + 1))};
}

}  // namespace

void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc) {
  std::stringstream ss(spec);
  std::string item;
  while (std::getline(ss, item, ',')) {
    if (item.empty()) continue;
    const auto eq = item.find('=');
    if (eq == std::string::npos) throw FaultSpecError("expected key=value, got '" + item + "'");
    const std::string key = item.substr(0, eq);
    const std::string val = item.substr(eq + 1);
    if (key == "crc") {
      rc->adc.faults.crc_error_probability = probability(key, val);
    } else if (key == "saturation") {
      rc->adc.faults.saturation_probability = probability(key, val);
    } else if (key == "adc-reset") {
      rc->adc.faults.reset_probability = probability(key, val);
    } else if (key == "stuck") {
      std::tie(rc->adc.faults.stuck_start_s, rc->adc.faults.stuck_length_s) = pair_of(key, val);
      if (rc->adc.faults.stuck_length_s < 0) throw FaultSpecError("stuck: LENGTH must be >= 0");
    } else if (key == "dropout") {
      sc->dropout_probability = probability(key, val);
    } else if (key == "spike") {
      sc->spike_probability = probability(key, val);
      if (sc->spike_amplitude_nT == 0) sc->spike_amplitude_nT = 1000;
    } else if (key == "garbage") {
      rc->serial.faults.garbage_probability = probability(key, val);
    } else if (key == "bad-checksum") {
      rc->serial.faults.bad_checksum_probability = probability(key, val);
    } else if (key == "ins-corrupt") {
      rc->ins.faults.corrupt_probability = probability(key, val);
    } else if (key == "ins-duplicate") {
      rc->ins.faults.duplicate_probability = probability(key, val);
    } else if (key == "ins-gap") {
      std::tie(rc->ins.faults.gap_start_s, rc->ins.faults.gap_length_s) = pair_of(key, val);
    } else if (key == "ins-invalid") {
      std::tie(rc->ins.faults.invalid_start_s, rc->ins.faults.invalid_length_s) = pair_of(key, val);
    } else if (key == "ins-latency-us") {
      const double v = number(key, val);
      if (v < 0 || v > 1e6) throw FaultSpecError("ins-latency-us must be in [0, 1e6]");
      rc->ins.can_latency_us = static_cast<std::uint32_t>(v);
    } else if (key == "clock-jump") {
      const auto [at, jump_s] = pair_of(key, val);
      if (std::fabs(jump_s) > 5.0) throw FaultSpecError("clock-jump: |jump| must be <= 5 s");
      rc->time.jump_at_s = at;
      rc->time.jump_us = std::llround(jump_s * 1e6);
    } else {
      throw FaultSpecError("unknown fault '" + key + "'");
    }
  }
}

}  // namespace magvec::host::hil
