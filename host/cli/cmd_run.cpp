// `magvec run --sim SCENARIO`: host-in-the-loop run (host/hil): simulated devices speaking the
// real bytes -> real drivers -> AttitudeBuffer -> SensorLoop -> record CSV, in simulated time (as
// fast as possible, deterministic from --seed). Prints a summary with every health counter next
// to the number of faults injected.
// --calibrator: only `none` exists today (no calibration runs; the output uses the calibration
// given with --calibration FILE, or the identity model, and is flagged uncalibrated while
// cal_id = 0). The EKF (`ekf`) and the batch Li calibrator (`li`) plug into HilSession<Calibrator>
// when they land.
#include <CLI/CLI.hpp>
#include <cmath>
#include <iostream>
#include <memory>
#include <sstream>
#include <string>

#include "calibration/calibration_file.hpp"
#include "commands.hpp"
#include "magvec/host/hil/csv_record_sink.hpp"
#include "magvec/host/hil/hil_session.hpp"
#include "sim_csv.hpp"

namespace magvec::host::cli {
namespace {

struct RunOptions {
  std::string scenario;
  double duration_s = 0;
  std::uint64_t seed = 1;
  std::string faults;
  std::string link = "spi";
  std::string calibrator = "none";
  std::string calibration;
  std::string out;
};

double number(const std::string& key, const std::string& text) {
  std::size_t used = 0;
  double v = 0;
  try {
    v = std::stod(text, &used);
  } catch (const std::exception&) {
    used = 0;
  }
  if (used != text.size() || !std::isfinite(v))
    throw CLI::ValidationError("--faults", key + ": not a number: '" + text + "'");
  return v;
}

double probability(const std::string& key, const std::string& text) {
  const double p = number(key, text);
  if (p < 0 || p > 1)
    throw CLI::ValidationError("--faults", key + ": probability must be in [0, 1]");
  return p;
}

// "a:b" -> (a, b)
std::pair<double, double> pair_of(const std::string& key, const std::string& text) {
  const auto colon = text.find(':');
  if (colon == std::string::npos)
    throw CLI::ValidationError("--faults",
                               key + " needs START:LENGTH (seconds), got '" + text + "'");
  return {number(key, text.substr(0, colon)), number(key, text.substr(colon + 1))};
}

// --faults key=value,...; keys documented in the option help.
void apply_faults(const std::string& spec, drivers::sim::ScenarioConfig* sc,
                  drivers::sim::SimRigConfig* rc) {
  std::stringstream ss(spec);
  std::string item;
  while (std::getline(ss, item, ',')) {
    if (item.empty()) continue;
    const auto eq = item.find('=');
    if (eq == std::string::npos)
      throw CLI::ValidationError("--faults", "expected key=value, got '" + item + "'");
    const std::string key = item.substr(0, eq);
    const std::string val = item.substr(eq + 1);
    if (key == "crc") {
      rc->adc.faults.crc_error_probability = probability(key, val);
    } else if (key == "saturation") {
      rc->adc.faults.saturation_probability = probability(key, val);
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
    } else if (key == "ins-gap") {
      std::tie(rc->ins.faults.gap_start_s, rc->ins.faults.gap_length_s) = pair_of(key, val);
    } else if (key == "ins-invalid") {
      std::tie(rc->ins.faults.invalid_start_s, rc->ins.faults.invalid_length_s) = pair_of(key, val);
    } else if (key == "ins-latency-us") {
      const double v = number(key, val);
      if (v < 0 || v > 1e6)
        throw CLI::ValidationError("--faults", "ins-latency-us must be in [0, 1e6]");
      rc->ins.can_latency_us = static_cast<std::uint32_t>(v);
    } else if (key == "clock-jump") {
      const auto [at, jump_s] = pair_of(key, val);
      if (std::fabs(jump_s) > 5.0)
        throw CLI::ValidationError("--faults", "clock-jump: |jump| must be <= 5 s");
      rc->time.jump_at_s = at;
      rc->time.jump_us = std::llround(jump_s * 1e6);
    } else {
      throw CLI::ValidationError("--faults", "unknown fault '" + key + "'");
    }
  }
}

template <typename Calibrator>
void run_session(const RunOptions& o, drivers::sim::Simulator& sim,
                 const drivers::sim::SimRigConfig& rc, Calibrator& cal,
                 const host::hil::HilConfig& hc) {
  host::hil::CsvRecordSink sink(
      o.out,
      {"magvec run --sim " + o.scenario + " seed " + std::to_string(o.seed) + " link " + o.link +
       " calibrator " + o.calibrator + (o.faults.empty() ? "" : " faults " + o.faults)});
  auto session = std::make_unique<host::hil::HilSession<Calibrator>>(sim, rc, cal, sink, hc);
  if (!o.calibration.empty()) {
    const CalibrationFile file = read_calibration_file(o.calibration);
    session->loop().set_active(file.model, 1);
  }
  if (const hal::Status s = session->init(); s != hal::Status::kOk)
    throw std::runtime_error(std::string("device initialisation failed: ") + hal::to_string(s));
  session->run();
  if (session->counters().sink_errors != 0)
    throw std::runtime_error("writing " + o.out + " failed: " + sink.last_error());
  sink.commit();

  const auto& c = session->counters();
  const auto& h = session->loop().health();
  const auto& mc = session->mag_counters();
  const auto& ac = session->attitude_counters();
  auto& rig = session->rig();
  const auto& adc = rig.adc().injected();
  const auto& ser = rig.serial().injected();
  const auto& ins = rig.ins().injected();
  std::cout << "magvec run: " << sim.config().name << ", seed " << o.seed << ", link " << o.link
            << ", calibrator " << o.calibrator << ": " << c.records << " records -> " << o.out
            << "\n";
  std::cout << "  magnetometer: steps " << c.steps << ", samples " << mc.samples << ", crc errors "
            << mc.crc_errors << ", malformed " << mc.malformed << ", garbage bytes "
            << mc.garbage_bytes << ", saturated " << mc.saturated << ", stuck " << mc.stuck
            << ", not fresh (dropouts) " << c.mag_not_fresh << ", missing " << c.mag_missing
            << ", time jumps " << c.mag_time_jumps << "\n";
  std::cout << "  attitude: samples " << ac.samples << ", malformed frames " << ac.malformed
            << ", missing time " << ac.missing_time << ", invalid " << c.att_invalid << ", gaps "
            << c.att_gaps << ", time jumps " << c.att_time_jumps << ", buffer rejected "
            << c.att_rejected << "\n";
  std::cout << "  loop: samples " << h.samples << ", dropouts " << h.dropouts << ", device errors "
            << h.device_errors << ", no attitude " << h.no_attitude << ", calibrations applied "
            << h.calibrations_applied << ", failed " << h.calibrations_failed << ", final cal_id "
            << session->loop().cal_id() << "\n";
  std::cout << "  injected: ";
  if (rc.link == drivers::sim::MagLink::kSpi) {
    std::cout << "crc " << adc.crc_corrupted << ", saturation " << adc.saturated << " (frames "
              << adc.saturated_frames << "), dropouts " << adc.not_fresh << ", range clipped "
              << adc.range_clipped;
  } else {
    std::cout << "garbage bytes " << ser.garbage_bytes << ", bad checksums " << ser.bad_checksums
              << ", dropouts " << ser.dropouts;
  }
  std::cout << ", ins corrupted frames " << ins.corrupted_frames << ", ins gap epochs "
            << ins.gap_epochs << ", ins invalid epochs " << ins.invalid_epochs << ", clock jumps "
            << rig.clock_jumps_injected() << "\n";
}

void run(const RunOptions& o) {
  drivers::sim::ScenarioConfig sc =
      scenario_by_name(o.scenario, drivers::sim::Fixture::kPlaneNormal);
  if (o.duration_s > 0) {
    sc.num_samples = static_cast<std::uint32_t>(std::llround(o.duration_s * sc.rate_hz));
    if (sc.num_samples == 0)
      throw CLI::ValidationError("--duration", "shorter than one sample period");
  }
  drivers::sim::SimRigConfig rc;
  rc.link = o.link == "serial" ? drivers::sim::MagLink::kSerial : drivers::sim::MagLink::kSpi;
  // Fluxgate electronics 100 uT/V into the ADC at gain 1: +/-120 uT range, 0.014 nT per code.
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  rc.adc.seed = o.seed ^ 0xA1;
  rc.serial.seed = o.seed ^ 0xB2;
  rc.ins.seed = o.seed ^ 0xC3;
  apply_faults(o.faults, &sc, &rc);
  host::hil::HilConfig hc;
  hc.loop.noise_nT = sc.mag_noise_nT > 0 ? sc.mag_noise_nT : 1.0;
  hc.ins_latency_comp_us = rc.ins.can_latency_us;
  drivers::sim::Simulator sim(sc, o.seed);
  // Only "none" exists (see the file comment).
  host::hil::NullCalibrator cal;
  hc.start_calibration = false;
  run_session(o, sim, rc, cal, hc);
}

}  // namespace

void register_run(CLI::App& app) {
  auto opt = std::make_shared<RunOptions>();
  CLI::App* sub = app.add_subcommand(
      "run", "Host-in-the-loop run: simulated devices -> drivers -> sensor loop -> record CSV");
  sub->add_option("--sim", opt->scenario, "Simulated scenario")
      ->required()
      ->check(CLI::IsMember(scenario_names()));
  sub->add_option("--duration", opt->duration_s, "Simulated seconds (default: the scenario's)")
      ->check(CLI::Range(1e-3, 1e7));
  sub->add_option("--seed", opt->seed, "Random seed")->capture_default_str();
  sub->add_option("--faults", opt->faults,
                  "Comma-separated faults: crc=P, saturation=P, dropout=P, spike=P (SPI/any), "
                  "garbage=P, bad-checksum=P (serial), ins-corrupt=P, ins-gap=START:LEN, "
                  "ins-invalid=START:LEN, ins-latency-us=N, clock-jump=AT:JUMP_S");
  sub->add_option("--link", opt->link, "Magnetometer link")
      ->check(CLI::IsMember({"spi", "serial"}))
      ->capture_default_str();
  sub->add_option("--calibrator", opt->calibrator,
                  "In-loop calibrator (only 'none' so far; 'ekf' and 'li' to come)")
      ->check(CLI::IsMember({"none"}))
      ->capture_default_str();
  sub->add_option("--calibration", opt->calibration,
                  "Calibration file (cal.json) installed as the active calibration (cal_id 1)")
      ->check(CLI::ExistingFile);
  sub->add_option("--out", opt->out, "Record CSV (written atomically)")->required();
  sub->callback([opt] { run(*opt); });
}

}  // namespace magvec::host::cli
