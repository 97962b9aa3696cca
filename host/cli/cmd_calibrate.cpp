// `magvec calibrate`: calibrates a recording with one of the estimators and writes cal.json.
//   auto      li-ml when the recording has attitude columns, else ellipsoid (default)
//   li-ml     one-step 14-parameter weighted fit (Li et al. 2023, docs/equations.md E-Li-6)
//   li        ellipsoid fit + plane compression (Li's two-step method, E-Li-2/3)
//   li-joint  ellipsoid fit + joint fit of Rm and h_n (E-Li-5)
//   ellipsoid ellipsoid fit only (no attitude needed; W up to a rotation, Rm identity)
//   sine      turntable sine fitting from an XY and an XZ sweep (docs/equations.md E-Sine)
//   ekf       the 12-state scalar EKF of Ge et al. 2017 (E-Ge)
//   vector-ekf  the online vector calibration filter (E-VF): W, o, Rm, h_n, time offset and
//             temperature coefficients in one pass over a recording with attitude
// Noise figures, the magnetometer-INS time offset and (without an F column) the field are taken
// from the data unless given; cal.json records what was used. --site/--date take the reference
// field of a recording without F from the WMM2025 model (host/geomag); a measured F_nT column wins
// over the model unless --model-f replaces it (the model then only checks the measured F).
// The estimators run through the host/calibration runners (shared with the daemon and reports);
// this file parses options and prints the human summary. Exit status: 0 ok, 2 bad input (the
// message names file, line and column), 3 calibration refused (verdict not ok). cal.json is written
// only for verdict ok, or with --force-write when a solution exists (never without one).
#include <CLI/CLI.hpp>
#include <cmath>
#include <iostream>
#include <limits>
#include <map>
#include <memory>
#include <optional>
#include <sstream>
#include <string>
#include <system_error>
#include <vector>

#include "calibration/batch_runner.hpp"
#include "calibration/calibration_file.hpp"
#include "calibration/ekf_runner.hpp"
#include "calibration/sine_runner.hpp"
#include "calibration/vector_ekf_runner.hpp"
#include "commands.hpp"
#include "magvec/host/geomag/reference_field.hpp"
#include "magvec/host/io/csv.hpp"
#include "magvec/version.hpp"
#include "stats.hpp"

namespace magvec::host::cli {
namespace {

constexpr double kDeg = 180.0 / core::kPi<double>;

struct CalibrateOptions {
  std::string method = "auto";
  std::string in_path;
  std::string sweep_xz;
  std::string out_path;
  std::string fixture;
  std::string trace;
  double field_nT = std::numeric_limits<double>::quiet_NaN();
  double noise_nT = std::numeric_limits<double>::quiet_NaN();
  double ins_noise_deg = std::numeric_limits<double>::quiet_NaN();
  double time_offset_s = std::numeric_limits<double>::quiet_NaN();
  double max_time_offset_s = 0.1;
  std::string prior_path;
  double fix_heading_deg = std::numeric_limits<double>::quiet_NaN();
  int passes = 1;
  bool paper_settings = false;
  bool float32 = false;
  bool force_write = false;
  std::string site;      // --site LAT,LON,ALT
  std::string date;      // --date YYYY-MM-DD
  bool model_f = false;  // --model-f: the model's F replaces a measured F_nT column
};

// "v +- s" with the given decimals.
std::string pm(double v, double s, int decimals) {
  return fixed(v, decimals) + " +- " + fixed(s, decimals);
}
std::string pm3(const core::Vec3<double>& v, const core::Vec3<double>& s, int decimals) {
  return "[" + pm(v(0), s(0), decimals) + ", " + pm(v(1), s(1), decimals) + ", " +
         pm(v(2), s(2), decimals) + "]";
}
std::string vec3(const core::Vec3<double>& v, int decimals) {
  return "[" + fixed(v(0), decimals) + ", " + fixed(v(1), decimals) + ", " + fixed(v(2), decimals) +
         "]";
}
std::string mat3(const core::Mat3<double>& m, int decimals) {
  return "[" + vec3(m.row(0).transpose(), decimals) + ", " + vec3(m.row(1).transpose(), decimals) +
         ", " + vec3(m.row(2).transpose(), decimals) + "]";
}

// no_enu: why there are no E/N/U figures when e.has_enu is false.
void print_evaluation(const Evaluation& e, const std::string& no_enu) {
  if (e.n_intensity > 0) {
    std::cout << "  intensity residual |h| - F, RMS over " << e.n_intensity << " samples: before "
              << fixed(e.intensity_rms_before_nT, 3) << " nT, after "
              << fixed(e.intensity_rms_after_nT, 3) << " nT (mean "
              << fixed(e.intensity_mean_after_nT, 3) << " nT)\n";
  } else {
    std::cout << "  intensity residual: no reference total field\n";
  }
  if (e.has_enu) {
    std::cout << "  E/N/U component spread (SD over " << e.n_enu << " samples): before "
              << vec3(e.enu_sd_before_nT, 1) << " nT (raw m rotated by R_bn^T), after "
              << vec3(e.enu_sd_after_nT, 3) << " nT\n";
  } else {
    std::cout << "  E/N/U component spread: not available (" << no_enu << ")\n";
  }
}

void print_li(const core::LiParams<double>& li, const core::LiSigmas<double>* s, bool with_rm) {
  const core::LiSigmas<double> zero{};
  const core::LiSigmas<double>& sg = s != nullptr ? *s : zero;
  const char* note = s != nullptr ? "" : " (1-sigma not available for this method)";
  std::cout << "  Li 2023 form" << note << ":\n"
            << "    ks             " << pm3(li.ks, sg.ks, 6) << "\n"
            << "    O1..O3 deg     " << pm3(li.o_rad * kDeg, sg.o_rad * kDeg, 5) << "\n"
            << "    Kof nT         " << pm3(li.kof, sg.kof, 3) << "\n";
  if (with_rm) {
    std::cout << "    am,bm,gm deg   " << pm3(li.rm_rad * kDeg, sg.rm_rad * kDeg, 5) << "\n";
  }
}

void print_counts(const CalibrationCounts& c, const std::string& extra) {
  std::cout << "  rows " << c.samples << ", used " << c.used << ", skipped (nan) "
            << c.skipped_nonfinite << ", rejected (outliers/gated) " << c.rejected_outliers << extra
            << "\n";
}

void print_verdict(const CalibrationQuality& q) {
  std::cout << "  coverage " << fixed(100.0 * q.coverage, 1) << " % of the sphere (32 cells)";
  if (q.condition > 0) {
    char buf[64];
    std::snprintf(buf, sizeof(buf), "%.3g", q.condition);
    std::cout << ", condition number " << buf;
  }
  std::cout << "\n  verdict: " << q.verdict << " (" << q.reason << ")\n";
}

// The prior (--prior cal.json): a previous calibration with the 1-sigmas of its Li parameters.
core::OneStepPrior<double> read_prior(const std::string& path) {
  const CalibrationFile pc = read_calibration_file(path);
  core::OneStepPrior<double> prior;
  if (core::to_li(pc.model, &prior.mean) != core::ConversionStatus::kOk)
    throw CommandExit(2, path + ": --prior: its W/Rm do not convert to the Li parameters");
  auto take = [&](const char* key, double scale, core::Vec3<double>* out) {
    const auto it = pc.sigma.find(key);
    if (it == pc.sigma.end() || it->second.size() != 3) {
      throw CommandExit(2, path + ": --prior needs the 1-sigmas sigma." + key +
                               " (a li-ml calibration has them)");
    }
    *out = core::Vec3<double>(it->second[0], it->second[1], it->second[2]) * scale;
  };
  take("ks", 1.0, &prior.sigma.ks);
  take("O_deg", 1.0 / kDeg, &prior.sigma.o_rad);
  take("Kof_nT", 1.0, &prior.sigma.kof);
  take("Rm_deg", 1.0 / kDeg, &prior.sigma.rm_rad);
  return prior;
}

std::string names_or_none(std::uint32_t bits) {
  const std::string s = parameter_names(bits);
  return s.empty() ? "none" : s;
}

CalibrationFile run_batch_method(const CalibrateOptions& o, core::BatchMethod method) {
  io::CsvReaderOptions ropt;
  if (std::isfinite(o.field_nT)) ropt.f_nT = o.field_nT;
  ropt.f_replaces_column = o.model_f;
  ropt.require_time = false;  // only the time-offset estimate uses t_s
  io::CsvReader reader(o.in_path, ropt);
  const bool need_att = method != core::BatchMethod::kEllipsoidOnly;
  if (need_att && reader.attitude_columns() == io::AttitudeColumns::kNone) {
    throw CommandExit(2, o.in_path +
                             ": no attitude columns (alpha/beta/gamma_deg, "
                             "yaw/pitch/roll_deg or qw..qz): --method " +
                             o.method + " needs the INS attitude; use --method ellipsoid");
  }
  BatchRunOptions bo;
  bo.method = method;
  bo.method_name = batch_method_name(method);
  bo.config.field_nT = o.field_nT;
  bo.mag_noise_given = std::isfinite(o.noise_nT);
  bo.ins_noise_given = std::isfinite(o.ins_noise_deg);
  if (bo.mag_noise_given) bo.config.mag_noise_nT = o.noise_nT;
  if (bo.ins_noise_given) bo.config.attitude_noise_deg = o.ins_noise_deg;
  if (std::isfinite(o.time_offset_s)) bo.fixed_time_offset_s = o.time_offset_s;
  bo.max_time_offset_s = o.max_time_offset_s;
  if (reader.attitude_columns() == io::AttitudeColumns::kQuaternion)
    bo.config.attitude_model = core::AttitudeNoiseModel::kIsotropic;
  if (std::isfinite(o.fix_heading_deg)) {
    bo.config.fix_heading_misalignment = true;
    bo.config.fixed_heading_misalignment_deg = o.fix_heading_deg;
  }
  core::OneStepPrior<double> prior;
  if (!o.prior_path.empty()) {
    if (method != core::BatchMethod::kOneStep)
      throw CommandExit(2, "--prior applies only to --method li-ml");
    prior = read_prior(o.prior_path);
    bo.config.prior = &prior;
  }
  const BatchRun run = run_batch(reader, bo);
  const core::BatchResult<double>& r = run.result;
  static const std::map<std::string, std::string> kTitle = {
      {"li-ml", "one-step 14-parameter weighted fit (Li 2023, docs/equations.md E-Li-6)"},
      {"li", "ellipsoid + plane compression (Li 2023 two-step, E-Li-2/3)"},
      {"li-joint", "ellipsoid + joint Rm/h_n fit (E-Li-5)"},
      {"ellipsoid", "ellipsoid fit only (W up to a rotation, no misalignment)"}};
  std::cout << "magvec calibrate: method " << bo.method_name << ": " << kTitle.at(bo.method_name)
            << "\n"
            << "  input " << o.in_path << "\n";
  const core::BatchNoise<double>& nz = r.noise;
  std::cout << "  noise: magnetometer " << fixed(nz.mag_nT, 3);
  if (nz.estimated) std::cout << " +- " << fixed(nz.mag_sigma_nT, 3);
  std::cout << " nT/axis (" << (nz.estimated ? "estimated from the data" : "given") << ")";
  if (nz.has_attitude) {
    std::cout << ", INS " << fixed(nz.attitude_deg, 4);
    if (nz.estimated) std::cout << " +- " << fixed(nz.attitude_sigma_deg, 4);
    std::cout << " deg/angle";
  }
  std::cout << "\n";
  if (!nz.estimated) {
    std::cout << "  the data's own estimate: " << fixed(run.data_noise.mag_nT, 3) << " nT";
    if (run.data_noise.has_attitude)
      std::cout << ", " << fixed(run.data_noise.attitude_deg, 4) << " deg";
    std::cout << "\n";
  }
  for (const std::string& w : run.warnings)
    std::cout << "  warning: " << w << "\n";
  if (run.field_from_data) {
    std::cout << "  no reference field (no F_nT column, no --field-nT): the median |m| "
              << fixed(run.field_nT, 1)
              << " nT stands for it, so scale factors and offsets are relative to it\n";
  }
  if (need_att) {
    const TimeOffsetEstimate& to = run.time_offset;
    std::cout << "  time offset (magnetometer minus INS): ";
    if (to.estimated) {
      std::cout << fixed(to.offset_s * 1e3, 2) << " +- " << fixed(to.sigma_s * 1e3, 2) << " ms ("
                << to.note << ")\n";
    } else {
      std::cout << fixed(to.offset_s * 1e3, 2) << " ms, " << to.note << "\n";
    }
  }
  print_counts(run.cal.counts,
               need_att ? ", without attitude " + std::to_string(run.rows_without_attitude) : "");
  if (run.keep_stride > 1) {
    std::cout << "  kept every " << run.keep_stride << "th row (" << run.rows_kept << " of "
              << run.rows << ") to bound memory\n";
  }
  if (bo.config.prior != nullptr && r.has_model) {
    std::cout << "  prior " << o.prior_path << ": the data determine "
              << names_or_none(r.quality.updated)
              << "; moved from the prior: " << names_or_none(r.quality.moved) << "\n";
  }
  if (r.has_model && r.quality.undetermined != 0 && bo.config.prior == nullptr) {
    std::cout << "  not determined by the data: " << parameter_names(r.quality.undetermined)
              << "\n";
  }
  if (r.has_model) {
    print_li(r.li, method == core::BatchMethod::kOneStep ? &r.sigma : nullptr, need_att);
    if (method == core::BatchMethod::kPlaneCompression || method == core::BatchMethod::kJoint) {
      std::cout << "    (two-step: 1-sigma of the misalignment only)\n"
                << "    am,bm,gm sigma " << vec3(r.sigma.rm_rad * kDeg, 5) << " deg\n";
    }
    if (r.heading_fixed) {
      std::cout << "    am held at " << fixed(o.fix_heading_deg, 4)
                << " deg (--fix-heading-misalignment-deg)\n";
    }
    if (r.has_h_n) {
      std::cout << "    h_n nT (E,N,U) " << pm3(r.h_n_nT, r.h_n_sigma_nT, 2) << ", |h_n| "
                << fixed(r.h_n_nT.norm(), 2) << "\n";
    }
    if (std::isfinite(r.calibration_sigma_enu_nT)) {
      std::cout << "    calibration's own 1-sigma over the survey envelope (every heading at the "
                   "data's tilts): E/N/U "
                << fixed(r.calibration_sigma_enu_nT, 3) << " nT per axis, |h| "
                << fixed(r.calibration_sigma_f_nT, 3) << " nT\n";
    }
    const core::GeParams<double> ge = core::to_ge(r.model);
    std::cout << "  Ge 2017 form: C^-1 = " << mat3(ge.c_inv, 6) << ", b = " << vec3(ge.b, 3)
              << " nT\n";
  }
  print_evaluation(run.eval, need_att ? "no attitude in the input"
                                      : "the ellipsoid fit determines W only up to a rotation");
  if (need_att) {
    std::cout << "  pitch/roll spread " << fixed(r.quality.tilt_spread_deg, 2) << " deg";
    if (method == core::BatchMethod::kOneStep)
      std::cout << ", chi2/dof " << fixed(r.quality.chi2_per_dof, 3);
    std::cout << ", residual tail ratio " << fixed(r.quality.tail_ratio, 2) << "\n";
  }
  return run.cal;
}

CalibrationFile run_sine_method(const CalibrateOptions& o) {
  io::CsvReaderOptions ropt;
  if (std::isfinite(o.field_nT)) ropt.f_nT = o.field_nT;
  ropt.f_replaces_column = o.model_f;
  io::CsvReader xy(o.in_path, ropt);
  io::CsvReader xz(o.sweep_xz, ropt);
  SineRunOptions so;
  so.fixture =
      o.fixture == "housing-y" ? core::SineFixture::kHousingY : core::SineFixture::kPlaneNormal;
  if (std::isfinite(o.field_nT)) so.field_nT = o.field_nT;
  so.noise_nT = std::isfinite(o.noise_nT) ? o.noise_nT : 5.0;
  SineRun run;
  try {
    run = run_sine(xy, xz, so);
  } catch (const std::invalid_argument& e) {
    throw CommandExit(2, e.what());
  }
  std::cout << "magvec calibrate: method sine: turntable sine fitting (docs/equations.md E-Sine), "
               "fixture "
            << o.fixture << "\n"
            << "  input XY sweep " << o.in_path << " (" << run.rows_xy << " rows), XZ sweep "
            << o.sweep_xz << " (" << run.rows_xz << " rows); |B| " << fixed(run.field_nT, 1)
            << " nT; noise " << fixed(so.noise_nT, 2) << " nT/axis\n";
  print_counts(run.cal.counts, "");
  if (run.solution.status == core::SineStatus::kOk) {
    const core::SineParams<double>& p = run.solution.params;
    const SineParamSigmas& s = run.sigma;
    std::cout << "  sine-fit parameters (1-sigma from the fit residuals):\n"
              << "    k              " << pm3(p.k, s.k, 6) << "\n"
              << "    alpha deg      " << pm(p.alpha_rad * kDeg, s.alpha_rad * kDeg, 5) << "\n"
              << "    beta deg       " << pm(p.beta_rad * kDeg, s.beta_rad * kDeg, 4) << "\n"
              << "    gamma deg      " << pm(p.gamma_rad * kDeg, s.gamma_rad * kDeg, 4) << "\n"
              << "    B0 nT          " << pm3(p.b0, s.b0, 2) << "\n"
              << "    inclination    "
              << pm(run.solution.inclination_rad * kDeg, s.inclination_rad * kDeg, 4) << " deg\n"
              << "  sweep fit RMS per axis: XY " << vec3(run.solution.xy.rms, 2) << " nT, XZ "
              << vec3(run.solution.xz.rms, 2) << " nT\n";
  }
  print_evaluation(run.eval, "the sine fit works in the fixture frame, not the INS frame");
  return run.cal;
}

CalibrationFile run_ekf_method(const CalibrateOptions& o) {
  io::CsvReaderOptions ropt;
  if (std::isfinite(o.field_nT)) ropt.f_nT = o.field_nT;
  ropt.f_replaces_column = o.model_f;
  {
    io::CsvReader probe(o.in_path, ropt);
    if (!probe.has_f() && !std::isfinite(o.field_nT)) {
      throw CommandExit(2, o.in_path + ": no F_nT column: give the total field with --field-nT");
    }
  }
  EkfRunOptions eo;
  eo.paper_settings = o.paper_settings;
  eo.float32 = o.float32;
  eo.passes = o.passes;
  if (std::isfinite(o.noise_nT)) eo.noise_nT = o.noise_nT;  // else estimated from the data
  if (std::isfinite(o.field_nT)) eo.field_nT = o.field_nT;
  eo.trace_path = o.trace;
  const EkfRun run = run_ekf(o.in_path, ropt, eo);
  std::cout
      << "magvec calibrate: method ekf: 12-state scalar EKF (Ge 2017, docs/equations.md E-Ge), "
      << (o.float32 ? "float32" : "float64") << ", "
      << (o.paper_settings
              ? "paper settings (printed x0/P0/Q/R; known to fail, docs/equations.md E-Ge-3)"
              : "default settings (start from a fit of a well-spread start-up set)")
      << ", " << o.passes << (o.passes == 1 ? " pass" : " passes") << "\n"
      << "  input " << o.in_path << "; magnetometer noise ";
  if (run.noise_estimated) {
    std::cout << pm(run.noise_estimate_nT, run.noise_estimate_sigma_nT, 2)
              << " nT/axis (estimated from the data)\n";
  } else {
    std::cout << fixed(run.noise_nT, 2) << " nT/axis (given; the data say "
              << pm(run.noise_estimate_nT, run.noise_estimate_sigma_nT, 2) << ")\n";
  }
  for (const std::string& w : run.warnings)
    std::cout << "  warning: " << w << "\n";
  print_counts(run.cal.counts, " (last pass)");
  std::cout << "  filter: " << run.counters.updates << " updates, " << run.counters.gated
            << " gated, " << run.counters.reinitialisations << " re-initialisations (last reason "
            << run.last_reset << "), " << run.counters.init_attempts << " initial fits tried ("
            << run.counters.init_failures << " failed, " << run.counters.init_exchanges
            << " start-up set exchanges), " << run.counters.init_outliers
            << " initial-fit outliers (all passes)\n";
  if (!run.initialised) {
    std::cout << "  filter not running at the end: last initial fit "
              << ekf_init_failure_name(run.init_report.failure) << " on " << run.init_report.samples
              << " samples; start-up set " << run.startup_samples << " samples\n";
  }
  if (run.initialised) {
    const core::Mat3<double> c_inv = run.model.w;
    std::cout << "  Ge 2017 parameters (1-sigma):\n    C^-1           [";
    for (int r = 0; r < 3; ++r) {
      std::cout << (r > 0 ? ", " : "") << "[";
      for (int c = 0; c < 3; ++c) {
        std::cout << (c > 0 ? ", " : "") << pm(c_inv(r, c), run.sigma(3 * r + c), 6);
      }
      std::cout << "]";
    }
    std::cout
        << "]\n    b nT           " << pm3(run.model.o, run.sigma.tail<3>(), 2) << "\n"
        << "    G = C^-T C^-1  " << mat3(run.model.g(), 6) << "\n"
        << "  note: a scalar (|H|) observation determines G and b only; C^-1 is known up to a "
           "rotation (docs/equations.md E-Ge-2): cal.json holds W = C^-1, Rm = identity, and its "
           "li "
           "block's Rm_deg is that rotation, not a misalignment\n";
    if (run.li_ok) print_li(run.li, &run.li_sigma, false);
  }
  if (!o.trace.empty())
    std::cout << "  trace: " << run.trace_rows << " rows -> " << o.trace << "\n";
  print_evaluation(run.eval, "the EKF determines W only up to a rotation");
  return run.cal;
}

CalibrationFile run_vector_ekf_method(const CalibrateOptions& o) {
  io::CsvReaderOptions ropt;
  if (std::isfinite(o.field_nT)) ropt.f_nT = o.field_nT;
  ropt.f_replaces_column = o.model_f;
  VectorEkfRunOptions vo;
  vo.float32 = o.float32;
  if (std::isfinite(o.noise_nT)) vo.noise_nT = o.noise_nT;
  if (std::isfinite(o.ins_noise_deg)) vo.ins_noise_deg = o.ins_noise_deg;
  if (std::isfinite(o.field_nT)) vo.field_nT = o.field_nT;
  if (std::isfinite(o.time_offset_s)) vo.time_offset_s = o.time_offset_s;
  vo.trace_path = o.trace;
  VectorEkfRun run;
  try {
    run = run_vector_ekf(o.in_path, ropt, vo);
  } catch (const std::invalid_argument& e) {
    throw CommandExit(2, e.what());
  } catch (const std::system_error& e) {
    throw CommandExit(2,
                      (o.trace.empty() ? std::string() : "--trace " + o.trace + ": ") + e.what());
  }
  std::cout << "magvec calibrate: method vector-ekf: online vector calibration filter "
               "(docs/equations.md E-VF), "
            << (o.float32 ? "float32" : "float64") << ", one pass\n"
            << "  input " << o.in_path << "\n";
  std::cout << "  noise: magnetometer " << fixed(run.noise_nT, 3);
  if (run.noise_estimated) std::cout << " +- " << fixed(run.noise_sigma_nT, 3);
  std::cout << " nT/axis (" << (run.noise_estimated ? "estimated by the one-step fit" : "given")
            << "), INS " << fixed(run.ins_noise_deg, 4);
  if (run.ins_noise_estimated) std::cout << " +- " << fixed(run.ins_noise_sigma_deg, 4);
  std::cout << " deg/angle (" << (run.ins_noise_estimated ? "estimated" : "given") << ")\n";
  for (const std::string& w : run.warnings)
    std::cout << "  warning: " << w << "\n";
  if (run.field_from_data) {
    std::cout << "  no reference field (no F_nT column, no --field-nT): the median |m| "
              << fixed(run.field_nT, 1)
              << " nT stands for it, so scale factors and offsets are relative to it\n";
  }
  std::cout << "  temperature: "
            << (run.rows_with_temperature > 0
                    ? std::to_string(run.rows_with_temperature) + " rows with temperature_degC"
                    : std::string("none in the recording (temperature coefficients keep their "
                                  "prior)"))
            << "\n";
  print_counts(run.cal.counts, ", without attitude " + std::to_string(run.rows_without_attitude));
  const core::VfCounters& k = run.counters;
  std::cout << "  filter: " << k.updates << " updates, " << k.reference_updates
            << " reference updates, " << k.gated << " gated, " << k.resets
            << " resets (last reason " << run.last_reset << "), " << k.field_reopens
            << " field re-opens, " << k.init_attempts << " starts from data tried ("
            << k.init_failures << " refused), heading held in " << k.heading_held << " updates\n";
  if (run.initialised) {
    if (run.li_ok) print_li(run.li, &run.li_sigma, true);
    std::cout << "    h_n nT (E,N,U) " << pm3(run.h_n_nT, run.h_n_sigma_nT, 2) << ", |h_n| "
              << fixed(run.h_n_nT.norm(), 2) << "\n"
              << "  time offset (magnetometer minus INS): ";
    if (std::isfinite(o.time_offset_s)) {
      std::cout << fixed(run.time_offset_s * 1e3, 3) << " ms (fixed by --time-offset-s)\n";
    } else {
      std::cout << pm(run.time_offset_s * 1e3, run.time_offset_sigma_s * 1e3, 3)
                << " ms (estimated by the filter)\n";
    }
    std::cout << "  offset temperature coefficients nT/degC "
              << pm3(run.tc_nT_per_degC, run.tc_sigma_nT_per_degC, 4);
    if (std::isfinite(run.temperature_ref_degC))
      std::cout << " (reference " << fixed(run.temperature_ref_degC, 2) << " degC)";
    std::cout << "\n  aligned to the INS: "
              << (run.heading_held ? "no (the heading misalignment was held: too little tilt)"
                                   : "yes")
              << "\n";
  } else {
    std::cout << "  filter not running at the end of the data (" << run.startup_samples
              << " start-up samples kept; last start's batch verdict " << run.last_init_verdict
              << ")\n";
  }
  if (!o.trace.empty())
    std::cout << "  trace: " << run.trace_rows << " rows (every " << run.trace_stride
              << "th row) -> " << o.trace << "\n";
  print_evaluation(run.eval, run.initialised ? "no reference" : "the filter is not running");
  std::cout << "  pitch/roll spread " << fixed(run.tilt_spread_deg, 2) << " deg\n";
  return run.cal;
}

// The model's field at --site/--date, or nothing; option errors exit 2 with the option named.
std::optional<geomag::ReferenceField> model_reference(const CalibrateOptions& o,
                                                      geomag::Site* site) {
  if (o.site.empty() && o.date.empty()) {
    if (o.model_f) throw CommandExit(2, "--model-f needs --site and --date");
    return std::nullopt;
  }
  if (o.site.empty() || o.date.empty())
    throw CommandExit(2, "--site and --date go together (the model field depends on both)");
  if (std::isfinite(o.field_nT))
    throw CommandExit(2, "--field-nT and --site/--date both give the reference field: give one");
  try {
    *site = geomag::parse_site(o.site);
  } catch (const geomag::GeomagError& e) {
    throw CommandExit(2, std::string("--site: ") + e.what());
  }
  geomag::Date date;
  try {
    date = geomag::parse_date(o.date);
  } catch (const geomag::GeomagError& e) {
    throw CommandExit(2, std::string("--date: ") + e.what());
  }
  try {
    return geomag::MagneticModel::wmm2025().field(*site, date);
  } catch (const geomag::GeomagError& e) {
    throw CommandExit(2, std::string("--site/--date: ") + e.what());
  }
}

ModelReference to_model_reference(const geomag::ReferenceField& f, const geomag::Site& site,
                                  const std::string& date) {
  ModelReference m;
  m.name = f.model;
  m.lat_deg = site.lat_deg;
  m.lon_deg = site.lon_deg;
  m.height_m = site.height_m;
  m.date = date;
  m.decimal_year = f.decimal_year;
  m.enu_nT = f.enu_nT;
  m.sigma_enu_nT = f.sigma.enu_nT;
  m.f_nT = f.total_nT;
  m.sigma_f_nT = f.sigma.total_nT;
  m.declination_deg = f.declination_deg;
  m.sigma_declination_deg = f.sigma.declination_deg;
  m.inclination_deg = f.inclination_deg;
  m.sigma_inclination_deg = f.sigma.inclination_deg;
  return m;
}

// Prints the reference the calibration used and, with a model, checks the fitted field vector
// (and a measured F) against it in units of the model's stated 1-sigma; the figures go to
// quality.extra. A departure beyond ~3 sigma points at the site, the date, the INS heading or a
// local anomaly; it is reported, not a refusal (the model's error is not the calibration's).
void report_reference(CalibrationFile* cal, bool has_f_column, bool model_f, double field_nT,
                      const std::optional<geomag::ReferenceField>& model, const geomag::Site& site,
                      const std::string& date) {
  ReferenceInfo ref;
  const bool measured = has_f_column && !model_f;
  ref.source = measured ? "measured" : model ? "model" : std::isfinite(field_nT) ? "given" : "data";
  if (model) {
    ref.model = to_model_reference(*model, site, date);
    if (!measured) {
      ref.f_nT = model->total_nT;
      ref.sigma_f_nT = model->sigma.total_nT;
    }
    std::cout << "  reference field: " << model->model << " at " << fixed(site.lat_deg, 5) << ", "
              << fixed(site.lon_deg, 5) << ", " << fixed(site.height_m, 1) << " m on " << date
              << ": E/N/U " << vec3(model->enu_nT, 1) << " nT +- " << vec3(model->sigma.enu_nT, 0)
              << ", F " << pm(model->total_nT, model->sigma.total_nT, 1) << " nT, D "
              << pm(model->declination_deg, model->sigma.declination_deg, 2) << " deg, I "
              << pm(model->inclination_deg, model->sigma.inclination_deg, 2) << " deg (1-sigma "
              << "of the model's error model)\n";
    if (measured) {
      std::cout << "    the file's measured F_nT is the reference (--model-f to use the model's "
                   "instead); the model only checks it\n";
    } else {
      std::cout << "    "
                << (has_f_column ? "the model's F replaces the file's F_nT (--model-f)"
                                 : "no F_nT column: the model's F is the reference")
                << ", so the absolute scale is known to +- " << fixed(model->sigma.total_nT, 0)
                << " nT (" << fixed(1e6 * model->sigma.total_nT / model->total_nT, 0) << " ppm)\n";
    }
    if (cal->h_n_nT) {
      const core::Vec3<double> d = *cal->h_n_nT - model->enu_nT;
      const core::Vec3<double> z = d.cwiseQuotient(model->sigma.enu_nT);
      const double dec = std::atan2((*cal->h_n_nT)(0), (*cal->h_n_nT)(1)) * kDeg;
      double d_dec = dec - model->declination_deg;
      d_dec -= 360.0 * std::round(d_dec / 360.0);
      std::cout << "    fitted h_n minus model: E/N/U " << vec3(d, 1) << " nT (" << vec3(z, 2)
                << " sigma), declination " << fixed(d_dec, 3) << " deg ("
                << fixed(d_dec / model->sigma.declination_deg, 2) << " sigma)\n";
      cal->quality.extra["h_n_minus_model_E_nT"] = d(0);
      cal->quality.extra["h_n_minus_model_N_nT"] = d(1);
      cal->quality.extra["h_n_minus_model_U_nT"] = d(2);
      cal->quality.extra["h_n_minus_model_declination_deg"] = d_dec;
      if (z.cwiseAbs().maxCoeff() > 3.0 || std::abs(d_dec) > 3.0 * model->sigma.declination_deg) {
        std::cout << "    warning: the fitted field departs from the model by more than 3 sigma: "
                     "check --site/--date, the INS heading, or a local magnetic anomaly\n";
      }
    }
  }
  cal->reference = ref;
}

void run(const CalibrateOptions& o_in) {
  CalibrateOptions o = o_in;
  if (o.method == "sine" && o.sweep_xz.empty())
    throw CommandExit(2, "--method sine needs --sweep-xz (the XZ sweep; --in is the XY sweep)");
  if (o.method == "sine" && o.fixture.empty())
    throw CommandExit(
        2, "--method sine needs --fixture plane-normal|housing-y (docs/equations.md E-Sine-4)");
  if (o.method != "sine" && (!o.sweep_xz.empty() || !o.fixture.empty()))
    throw CommandExit(2, "--sweep-xz and --fixture apply only to --method sine");
  if (o.method != "ekf" && (o.paper_settings || o.passes != 1))
    throw CommandExit(2, "--paper-settings and --passes apply only to --method ekf");
  if (o.method != "ekf" && o.method != "vector-ekf" && (o.float32 || !o.trace.empty()))
    throw CommandExit(2, "--float32 and --trace apply only to --method ekf and vector-ekf");
  geomag::Site site;
  const std::optional<geomag::ReferenceField> model = model_reference(o, &site);
  bool has_f_column = false;
  CalibrationFile cal;
  try {
    {
      io::CsvReaderOptions popt;
      popt.require_time = false;
      has_f_column = io::CsvReader(o.in_path, popt).has_f();
    }
    if (model && (!has_f_column || o.model_f)) o.field_nT = model->total_nT;
    if (o.method == "sine") {
      cal = run_sine_method(o);
    } else if (o.method == "ekf") {
      cal = run_ekf_method(o);
    } else if (o.method == "vector-ekf") {
      if (!o.prior_path.empty() || std::isfinite(o.fix_heading_deg))
        throw CommandExit(2,
                          "--prior and --fix-heading-misalignment-deg apply to the batch "
                          "methods, not --method vector-ekf");
      cal = run_vector_ekf_method(o);
    } else {
      std::string method = o.method;
      if (method == "auto") {
        // li-ml needs the attitude; a compass capture without it gets the ellipsoid fit.
        io::CsvReaderOptions popt;
        popt.require_time = false;
        const io::CsvReader probe(o.in_path, popt);
        method = probe.attitude_columns() == io::AttitudeColumns::kNone ? "ellipsoid" : "li-ml";
      }
      if (!o.prior_path.empty() && method != "li-ml")
        throw CommandExit(2, "--prior applies only to --method li-ml (a recording with attitude)");
      const core::BatchMethod m = method == "li"          ? core::BatchMethod::kPlaneCompression
                                  : method == "li-joint"  ? core::BatchMethod::kJoint
                                  : method == "ellipsoid" ? core::BatchMethod::kEllipsoidOnly
                                                          : core::BatchMethod::kOneStep;
      cal = run_batch_method(o, m);
    }
  } catch (const io::CsvError& e) {
    throw CommandExit(2, e.what());
  }
  report_reference(&cal, has_f_column, o.model_f, o_in.field_nT, model, site, o.date);
  cal.provenance.magvec_version = kVersion;
  cal.provenance.created_utc = utc_now_iso8601();
  print_verdict(cal.quality);
  const bool ok = cal.quality.verdict == "ok";
  if (ok || (o.force_write && cal.has_solution)) {
    write_calibration_file(o.out_path, cal);
    std::cout << "  wrote " << o.out_path
              << (ok ? "\n" : " (verdict not ok, written because of --force-write)\n");
  } else if (o.force_write) {
    std::cout << "  nothing written to " << o.out_path
              << " (--force-write: the method refused before it had any solution to write)\n";
  } else {
    std::cout << "  nothing written to " << o.out_path
              << " (verdict not ok; --force-write writes the refused solution if one exists)\n";
  }
  if (!ok) throw CommandExit(3, "calibration refused: " + cal.quality.verdict);
}

}  // namespace

void register_calibrate(CLI::App& app) {
  auto opts = std::make_shared<CalibrateOptions>();
  CLI::App* cmd = app.add_subcommand(
      "calibrate",
      "Calibrate a recording and write cal.json (exit 0 ok, 2 bad input, 3 refused). Noise, the "
      "magnetometer-INS time offset and (without F_nT) the field come from the data unless "
      "given.");
  cmd->add_option("--method", opts->method,
                  "auto (li-ml with attitude, else ellipsoid) | li-ml (one-step) | li (plane "
                  "compression) | li-joint | ellipsoid (no attitude) | sine | ekf | vector-ekf "
                  "(online vector filter)")
      ->check(CLI::IsMember(
          {"auto", "li-ml", "li", "li-joint", "ellipsoid", "sine", "ekf", "vector-ekf"}))
      ->capture_default_str();
  cmd->add_option("--in", opts->in_path, "Input CSV (for sine: the XY sweep)")->required();
  cmd->add_option("--sweep-xz", opts->sweep_xz, "sine: the XZ-sweep CSV (theta_deg column)");
  cmd->add_option("--fixture", opts->fixture, "sine: XZ-sweep fixture (docs/equations.md E-Sine-4)")
      ->check(CLI::IsMember({"plane-normal", "housing-y"}));
  cmd->add_option("--out", opts->out_path, "Output cal.json (written atomically)")->required();
  cmd->add_option("--field-nT", opts->field_nT,
                  "Total field for rows without F_nT (sine: |B|, default the mean F_nT)")
      ->check(CLI::PositiveNumber);
  cmd->add_option(
         "--noise-nT", opts->noise_nT,
         "Magnetometer noise per axis, 1-sigma (default: estimated from the data; sine: 5)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--ins-noise-deg", opts->ins_noise_deg,
                  "INS noise per angle, 1-sigma (default: estimated from the data)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--time-offset-s", opts->time_offset_s,
                  "Fix the magnetometer-minus-INS time offset [s] instead of estimating it "
                  "(positive: the magnetometer lags)")
      ->check(CLI::Range(-10.0, 10.0));
  cmd->add_option("--max-time-offset-s", opts->max_time_offset_s,
                  "Search range of the time-offset estimate, +- [s]")
      ->check(CLI::Range(0.001, 2.0))
      ->capture_default_str();
  cmd->add_option("--prior", opts->prior_path,
                  "A previous cal.json (li-ml, with its sigmas): solve the regularised problem "
                  "that updates only what these data determine");
  cmd->add_option("--fix-heading-misalignment-deg", opts->fix_heading_deg,
                  "Hold the misalignment about the vertical (alpha_m) at this value instead of "
                  "refusing level-only data (docs/equations.md E-Li-4)");
  cmd->add_flag("--paper-settings", opts->paper_settings,
                "ekf: the printed x0/P0/Q/R of Ge 2017 (EkfConfig::paper(); they fail)");
  cmd->add_option("--passes", opts->passes, "ekf: run the data this many times through the filter")
      ->check(CLI::Range(1, 1000));
  cmd->add_flag("--float32", opts->float32,
                "ekf, vector-ekf: run the filter in float32 (as on the MCU)");
  cmd->add_option(
      "--trace", opts->trace,
      "ekf: write the state, 1-sigma, NIS and intensity 1-sigma per sample to this CSV; "
      "vector-ekf: the 19 states, their 1-sigmas, NIS and innovations (at most 2000 rows)");
  cmd->add_option("--site", opts->site,
                  "Survey site LAT,LON,ALT (deg, deg, m above the WGS84 ellipsoid): with --date, "
                  "the reference field of a recording without F_nT comes from the WMM2025 model "
                  "(F +- 138 nT, 1-sigma)");
  cmd->add_option("--date", opts->date, "Survey date YYYY-MM-DD (with --site; 2025-2029)");
  cmd->add_flag("--model-f", opts->model_f,
                "Use the model's F (--site/--date) even where the file has a measured F_nT "
                "column (default: the measured F wins, the model only checks it)");
  cmd->add_flag("--force-write", opts->force_write,
                "Write cal.json even when the verdict is not ok, if the method has a solution "
                "(the verdict is recorded in it); never writes without one");
  cmd->callback([opts] { run(*opts); });
}

}  // namespace magvec::host::cli
