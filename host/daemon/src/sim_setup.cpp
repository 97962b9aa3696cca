// magvecd --sim rig and the pipeline's loop configuration; see sim_setup.hpp.
#include "magvec/host/daemon/sim_setup.hpp"

#include <cmath>
#include <limits>

#include "magvec/host/hil/fault_spec.hpp"

namespace magvec::host::daemon {

drivers::sim::ScenarioConfig sim_scenario(const Config& c) {
  drivers::sim::ScenarioConfig sc = c.sim.scenario == "survey" ? drivers::sim::scenario_survey()
                                                               : drivers::sim::scenario_li2023();
  const double rate = c.magnetometer.rate_hz;
  if (c.sim.scenario == "survey") {
    sc.num_samples = static_cast<std::uint32_t>(
        std::lround(drivers::sim::survey_duration_s(sc.survey, 4) * rate));
  } else {
    sc.num_samples = std::numeric_limits<std::uint32_t>::max();  // runs until stopped
    sc.samples_per_attitude = c.sim.samples_per_attitude;
  }
  sc.rate_hz = rate;
  drivers::sim::SimRigConfig unused;
  hil::apply_faults(c.sim.faults, &sc, &unused);  // valid: parse_config checked it
  return sc;
}

drivers::sim::SimRigConfig sim_rig_config(const Config& c) {
  drivers::sim::SimRigConfig rc;
  rc.link = c.magnetometer.link == "serial" ? drivers::sim::MagLink::kSerial
                                            : drivers::sim::MagLink::kSpi;
  rc.adc.transfer = c.magnetometer.adc;
  rc.adc.seed = c.sim.seed ^ 0xA1;
  rc.serial.seed = c.sim.seed ^ 0xB2;
  rc.ins.seed = c.sim.seed ^ 0xC3;
  rc.ins.rate_hz = c.ins.rate_hz;
  rc.ins.ids = c.ins.ids;
  rc.ins.can_latency_us = c.ins.latency_comp_us;
  drivers::sim::ScenarioConfig unused;
  hil::apply_faults(c.sim.faults, &unused, &rc);
  return rc;
}

hil::HilConfig hil_config(const Config& c) {
  const CalibrationConfig& cc = c.calibration;
  hil::HilConfig hc;
  hc.loop.noise_nT = cc.noise_nT;
  hc.loop.attitude_noise_deg = cc.attitude_noise_deg;
  hc.loop.validation_samples = cc.validation_samples;
  hc.loop.validation_max_rms_factor = cc.validation_max_rms_factor;
  hc.loop.validation_min_rms_nT = cc.validation_min_rms_nT;
  hc.loop.validate_against_active = cc.validate_against_active;
  hc.ins_latency_comp_us = c.ins.latency_comp_us;
  hc.horizon_us = c.ins.fusion_horizon_us;
  // A configured offset is fixed; otherwise the installed calibration's applies (SET_ACTIVE).
  hc.time_offset_us =
      std::isfinite(c.ins.time_offset_s) ? hil::offset_us_from_s(c.ins.time_offset_s) : 0;
  hc.require_attitude_valid = c.ins.require_attitude_valid;
  hc.start_calibration = false;  // start is a pipeline event (logged), never implicit
  return hc;
}

}  // namespace magvec::host::daemon
