// `magvec run --sim SCENARIO`: host-in-the-loop run (host/hil): simulated devices speaking the
// real bytes -> real drivers -> AttitudeBuffer -> SensorLoop -> record CSV, in simulated time (as
// fast as possible, deterministic from --seed). Prints a summary with every health counter next
// to the number of faults injected.
// --calibrator (the calibration starts at the first sample; the loop's state machine collects,
// solves, validates on held-out samples and applies; the previous calibration, from
// --calibration FILE or the identity, stays active until then):
//   li    core::BatchLiCalibrator (Li et al. 2023 one-step fit, docs/equations.md E-Li),
//   motion-decimated store; ekf   core::EkfCalibrator (Ge et al. 2017 EKF, docs/equations.md E-Ge)
//   + misalignment fit for the INS
//         alignment (--ekf-no-align: EKF model only, Rm = I; then h_n is NOT aligned to the INS and
//         the summary says so);
//   vector-ekf  core::VectorCalibrator: the online vector calibration filter (docs/equations.md
//         E-VF: W, o, Rm, field, time offset, temperature coefficients from every sample; the noise
//         is estimated first unless --noise-nT and --ins-noise-deg are both given);
//   none  no calibration runs (flagged uncalibrated while cal_id = 0).
// --profile mcu, instead of --sim and the options that configure a run: the MCU image's run
// (firmware/app/include/magvec/app/image_profile.hpp: its scenario and seed, rig, EKF calibrator,
// pipeline, and its rule of installing a solve a fixed number of records after the ticket). The
// host build has the images' numerics (docs/architecture.md#numerics), so the records are
// bit-identical to the M7 double image's and its host twin's (tests/mcu/compare_app_runs.py).
#include <CLI/CLI.hpp>
#include <cmath>
#include <iostream>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "commands.hpp"
#include "fault_spec.hpp"
#include "magvec/app/image_profile.hpp"
#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/vector_calibrator.hpp"
#include "magvec/host/hil/calibrators.hpp"
#include "magvec/host/hil/csv_record_sink.hpp"
#include "magvec/host/hil/hil_session.hpp"
#include "sim_csv.hpp"

namespace magvec::host::cli {
namespace {

struct RunOptions {
  std::string profile;
  std::string scenario;
  double duration_s = 0;
  std::uint64_t seed = 1;
  std::string faults;
  std::string link = "spi";
  std::string calibrator = "none";
  std::string calibration;
  std::string out;
  bool ekf_no_align = false;
  std::uint32_t ins_latency_comp_us = 500;
  std::uint32_t fusion_horizon_us = 50'000;
  double time_offset_s = std::numeric_limits<double>::quiet_NaN();
  // Known noise figures for the in-loop calibrator and validation (NaN: estimated from the data;
  // never the simulator's own figures, which the code under test must not know).
  double noise_nT = std::numeric_limits<double>::quiet_NaN();
  double ins_noise_deg = std::numeric_limits<double>::quiet_NaN();
};

using LiCal = host::hil::LiCalibrator;
using VecCal = host::hil::VectorLoopCalibrator;

// Calibrator-specific part of the summary.
std::string solver_reason(const host::hil::NullCalibrator&, std::uint8_t) {
  return "none";
}
std::string solver_reason(const LiCal&, std::uint8_t code) {
  return core::verdict_name(static_cast<core::Verdict>(code));
}
template <std::size_t AlignCapacity, int InitCapacity>
std::string solver_reason(const core::EkfCalibrator<double, AlignCapacity, InitCapacity>&,
                          std::uint8_t code) {
  return core::ekf_cal_code_name(code);
}
std::string solver_reason(const VecCal&, std::uint8_t code) {
  return core::vec_cal_code_name(code);
}

void describe(const host::hil::NullCalibrator&, std::ostream&) {}
void describe(const LiCal& cal, std::ostream& os) {
  const auto& c = cal.counts();
  os << "  li calibrator: seen " << c.seen << ", kept " << c.kept << ", decimated " << c.decimated
     << ", rejected " << c.rejected << ", store full " << c.full << ", coverage " << cal.coverage()
     << "\n";
  if (!cal.solved()) return;
  const auto& r = cal.last_result();
  os << "  li solve: verdict " << core::verdict_name(r.verdict) << ", used " << r.counts.used
     << ", outliers " << r.counts.outliers << ", intensity rms " << r.quality.intensity_rms_nT
     << " nT, chi2/dof " << r.quality.chi2_per_dof << "\n";
  if (!r.ok()) return;
  const double deg = 180.0 / core::kPi<double>;
  os << "    Ks " << r.li.ks.transpose() << ", O [deg] " << (r.li.o_rad * deg).transpose()
     << ", Kof [nT] " << r.li.kof.transpose() << ", Rm [deg] " << (r.li.rm_rad * deg).transpose()
     << ", h_n [nT] " << r.h_n_nT.transpose() << "\n";
}
template <std::size_t AlignCapacity, int InitCapacity>
void describe(const core::EkfCalibrator<double, AlignCapacity, InitCapacity>& cal,
              std::ostream& os) {
  const auto& c = cal.filter().counters();
  os << "  ekf calibrator: updates " << c.updates << ", gated " << c.gated << ", rejected "
     << c.rejected_nonfinite + c.rejected_reference << ", reinitialisations " << c.reinitialisations
     << ", sigma_F " << cal.sigma_f_nT() << " nT, alignment samples " << cal.align_samples()
     << "\n";
  if (!cal.config().align) {
    os << "  WARNING: --ekf-no-align: the EKF gives W only up to a rotation and Rm = I; h_n "
          "(hE/hN/hU) is NOT aligned to the INS\n";
  } else if (cal.aligned()) {
    const double deg = 180.0 / core::kPi<double>;
    os << "  alignment: Rm [deg] " << (cal.alignment().rm_rad * deg).transpose() << ", h_n [nT] "
       << cal.alignment().h_n.transpose() << "\n";
  }
}

void describe(const VecCal& cal, std::ostream& os) {
  const VecCal::Diagnostics d = cal.diagnostics();
  const auto& c = d.counts;
  const auto& fc = d.filter_counters;
  os << "  vector-ekf calibrator: seen " << c.seen << ", rejected non-finite " << c.nonfinite
     << ", no attitude " << c.no_attitude << ", no reference " << c.no_reference << ", gated "
     << c.gated << "; filter updates " << fc.updates << ", resets " << fc.resets
     << ", starts tried " << fc.init_attempts << " (refused " << fc.init_failures << ")\n";
  if (d.noise_known) {
    const auto& n = d.noise;
    os << "  noise" << (n.estimated ? " estimated" : " given") << ": magnetometer " << n.mag_nT
       << " +- " << n.mag_sigma_nT << " nT, INS " << n.attitude_deg << " +- "
       << n.attitude_sigma_deg << " deg\n";
  }
  if (!d.initialised) return;
  const double deg = 180.0 / core::kPi<double>;
  core::LiParams<double> li;
  if (core::to_li(d.model, &li) == core::ConversionStatus::kOk) {
    os << "    Ks " << li.ks.transpose() << ", O [deg] " << (li.o_rad * deg).transpose()
       << ", Kof [nT] " << li.kof.transpose() << ", Rm [deg] " << (li.rm_rad * deg).transpose()
       << ", h_n [nT] " << d.h_n_nT.transpose() << "\n";
  }
  os << "    time offset " << d.time_offset_s * 1e3 << " +- " << d.sigmas.dt_s * 1e3
     << " ms, heading " << (d.heading_held ? "held" : "estimated") << ", readiness ratio "
     << d.readiness_ratio << " (ready at 1; per parameter " << d.parameter_ratio << ")"
     << "\n    calibration 1-sigma over the survey envelope (every heading, the tilts seen): E/N/U "
     << d.output.vector_nT << " nT per axis (per-sample noise " << d.output.vector_noise_nT
     << " nT), |h| " << d.output.intensity_nT << " nT (noise " << d.output.intensity_noise_nT
     << " nT)\n";
}

template <typename Calibrator>
void run_session(const RunOptions& o, std::uint64_t seed, drivers::sim::Simulator& sim,
                 const drivers::sim::SimRigConfig& rc, Calibrator& cal,
                 const host::hil::HilConfig& hc) {
  host::hil::CsvRecordSink sink(
      o.out,
      {o.profile.empty() ? "magvec run --sim " + o.scenario + " seed " + std::to_string(seed) +
                               " link " + o.link + " calibrator " + o.calibrator +
                               (o.faults.empty() ? "" : " faults " + o.faults)
                         : "magvec run --profile " + o.profile + " (scenario " + sim.config().name +
                               " seed " + std::to_string(seed) + " link spi calibrator ekf)"});
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
  std::cout << "magvec run: " << sim.config().name << ", seed " << seed << ", link "
            << (rc.link == drivers::sim::MagLink::kSpi ? "spi" : "serial") << ", calibrator "
            << (o.profile.empty() ? o.calibrator : "ekf (profile " + o.profile + ")") << ": "
            << c.records << " records -> " << o.out << "\n";
  std::cout << "  magnetometer: steps " << c.steps << ", samples " << mc.samples << ", crc errors "
            << mc.crc_errors << ", malformed " << mc.malformed << ", garbage bytes "
            << mc.garbage_bytes << ", saturated " << mc.saturated << ", stuck " << mc.stuck
            << ", device resets " << mc.device_resets << ", not fresh (dropouts) "
            << c.mag_not_fresh << ", missing " << c.mag_missing << ", time jumps "
            << c.mag_time_jumps << "\n";
  std::cout << "  attitude: samples " << ac.samples << ", malformed frames " << ac.malformed
            << ", missing time " << ac.missing_time << ", duplicates " << ac.duplicates
            << ", invalid " << c.att_invalid << ", gaps " << c.att_gaps << ", time jumps "
            << c.att_time_jumps << ", buffer rejected " << c.att_rejected << "\n";
  std::cout << "  loop: samples " << h.samples << ", dropouts " << h.dropouts << ", device errors "
            << h.device_errors << ", no attitude " << h.no_attitude << ", calibrations applied "
            << h.calibrations_applied << ", failed " << h.calibrations_failed << ", final cal_id "
            << session->loop().cal_id() << "\n";
  const auto& lp = session->loop();
  std::cout << "  calibration: state " << core::cal_state_name(lp.state()) << ", progress "
            << lp.progress() << ", cal_id " << lp.cal_id();
  if (lp.state() == core::CalState::kFailed) {
    std::cout << ", failure " << core::cal_failure_name(lp.failure());
    if (lp.failure() == core::CalFailure::kSolverRejected)
      std::cout << " (" << solver_reason(cal, lp.solver_code()) << ")";
  }
  if (lp.state() == core::CalState::kApplied || lp.failure() == core::CalFailure::kValidationFailed)
    std::cout << ", validation intensity rms " << lp.last_validation_rms_nT() << " nT";
  std::cout << "; calibrator used " << h.cal_used << ", gated " << h.cal_gated << ", rejected "
            << h.cal_rejected << "\n";
  const auto& pipe = session->core().pipeline();
  std::cout << "  magnetometer-INS time offset of the pairing: "
            << 1e-3 * static_cast<double>(pipe.time_offset_us()) << " ms ("
            << (pipe.config().adopt_calibration_time_offset
                    ? std::to_string(pipe.counters().time_offset_steps) +
                          " steps adopted from the in-loop calibration"
                    : std::string("given, not adopted"))
            << ")\n";
  describe(cal, std::cout);
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

// The MCU image's run (see the top): its configuration, one definition with the image's.
void run_mcu_profile(const RunOptions& o) {
  const drivers::sim::ScenarioConfig sc = app::make_scenario();
  const drivers::sim::SimRigConfig rc = app::make_rig_config();
  drivers::sim::Simulator sim(sc, app::kSeed);
  host::hil::HilConfig hc = host::hil::hil_config_from(app::pipeline_config<double>(sc, false));
  hc.solve_install_records = app::kSolveInstallRecords;
  hc.start_calibration = true;
  auto cal =
      std::make_unique<app::EkfImageCalibrator<double>>(app::ekf_calibrator_config<double>(sc));
  run_session(o, app::kSeed, sim, rc, *cal, hc);
}

void run(const RunOptions& o) {
  if (o.profile == "mcu") {
    run_mcu_profile(o);
    return;
  }
  if (o.scenario.empty()) throw CLI::RequiredError("--sim or --profile");
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
  hc.loop.noise_nT = o.noise_nT;
  hc.loop.attitude_noise_deg = o.ins_noise_deg;
  // Configured, never taken from the injected fault: the loop does not know the true latency.
  hc.ins_latency_comp_us = o.ins_latency_comp_us;
  hc.horizon_us = o.fusion_horizon_us;
  if (std::isfinite(o.time_offset_s)) {
    hc.time_offset_us = host::hil::offset_us_from_s(o.time_offset_s);
    hc.adopt_calibration_time_offset = false;  // known: an in-loop calibration's is not taken
  } else if (!o.calibration.empty()) {
    hc.time_offset_us =
        host::hil::offset_us_from_s(read_calibration_file(o.calibration).time_offset_s);
  }
  drivers::sim::Simulator sim(sc, o.seed);
  host::hil::CalibratorSpec spec;
  spec.mode = o.calibrator;
  spec.noise_nT = hc.loop.noise_nT;
  spec.attitude_noise_deg = hc.loop.attitude_noise_deg;
  spec.ekf_align = !o.ekf_no_align;
  host::hil::with_calibrator(spec, [&](auto cal) {
    using Cal = typename decltype(cal)::element_type;
    hc.start_calibration = host::hil::kCalibrates<Cal>;
    run_session(o, o.seed, sim, rc, *cal, hc);
  });
}

}  // namespace

void register_run(CLI::App& app) {
  auto opt = std::make_shared<RunOptions>();
  CLI::App* sub = app.add_subcommand(
      "run", "Host-in-the-loop run: simulated devices -> drivers -> sensor loop -> record CSV");
  CLI::Option* sim_opt = sub->add_option("--sim", opt->scenario, "Simulated scenario")
                             ->check(CLI::IsMember(scenario_names()));
  CLI::Option* profile =
      sub->add_option("--profile", opt->profile,
                      "Instead of --sim and the run's options: mcu = the MCU image's scenario, "
                      "seed, devices, EKF calibrator and pipeline (bit-identical to the M7 image)")
          ->check(CLI::IsMember({"mcu"}))
          ->excludes(sim_opt);
  // What --profile fixes cannot also be given (each is rejected by name).
  std::vector<CLI::Option*> configures;
  configures.push_back(
      sub->add_option("--duration", opt->duration_s, "Simulated seconds (default: the scenario's)")
          ->check(CLI::Range(1e-3, 1e7)));
  configures.push_back(sub->add_option("--seed", opt->seed, "Random seed")->capture_default_str());
  configures.push_back(sub->add_option("--faults", opt->faults, kFaultsHelp));
  configures.push_back(sub->add_option("--link", opt->link, "Magnetometer link")
                           ->check(CLI::IsMember({"spi", "serial"}))
                           ->capture_default_str());
  configures.push_back(
      sub->add_option(
             "--calibrator", opt->calibrator,
             "In-loop calibrator: li (batch one-step), ekf (online scalar EKF + misalignment "
             "fit), vector-ekf (online vector calibration filter), none")
          ->check(CLI::IsMember({"none", "li", "ekf", "vector-ekf"}))
          ->capture_default_str());
  configures.push_back(
      sub->add_flag("--ekf-no-align", opt->ekf_no_align,
                    "ekf: skip the misalignment fit (Rm = I; h_n not aligned to the INS)"));
  configures.push_back(
      sub->add_option("--calibration", opt->calibration,
                      "Calibration file (cal.json) installed as the active calibration (cal_id 1)")
          ->check(CLI::ExistingFile));
  configures.push_back(
      sub->add_option("--ins-latency-comp-us", opt->ins_latency_comp_us,
                      "Known INS transport latency subtracted from CAN receive times "
                      "(configuration; the ins-latency-us fault is not known to the loop)")
          ->check(CLI::Range(0, 1'000'000))
          ->capture_default_str());
  configures.push_back(
      sub->add_option("--fusion-horizon-us", opt->fusion_horizon_us,
                      "Longest wait of a sample for the INS samples that bracket it, then its "
                      "attitude is extrapolated and flagged (0: process on arrival)")
          ->check(CLI::Range(0, 1'000'000))
          ->capture_default_str());
  configures.push_back(sub->add_option("--time-offset-s", opt->time_offset_s,
                                       "Magnetometer stamp minus INS time of its attitude (s); "
                                       "overrides the --calibration file's time_offset_s")
                           ->check(CLI::Range(-10.0, 10.0)));
  configures.push_back(
      sub->add_option("--noise-nT", opt->noise_nT,
                      "Known magnetometer noise SD per axis for the in-loop calibrator and its "
                      "validation (default: estimated from the data)")
          ->check(CLI::Range(1e-6, 1e5)));
  configures.push_back(
      sub->add_option("--ins-noise-deg", opt->ins_noise_deg,
                      "Known INS attitude noise SD per angle for the in-loop calibrator and the "
                      "vector check (default: estimated from the data)")
          ->check(CLI::Range(1e-6, 10.0)));
  for (CLI::Option* c : configures)
    profile->excludes(c);
  sub->add_option("--out", opt->out, "Record CSV (written atomically)")->required();
  sub->callback([opt] { run(*opt); });
}

}  // namespace magvec::host::cli
