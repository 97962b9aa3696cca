// Scalar EKF over a recording (see ekf_runner.hpp).
#include "calibration/ekf_runner.hpp"

#include <Eigen/Eigenvalues>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>
#include <vector>

namespace magvec::host {
namespace {

constexpr double kDeg = 180.0 / core::kPi<double>;

template <typename Scalar>
core::EkfConfig<Scalar> make_config(const EkfRunOptions& opt) {
  core::EkfConfig<Scalar> c =
      opt.paper_settings ? core::EkfConfig<Scalar>::paper() : core::EkfConfig<Scalar>{};
  if (!opt.paper_settings) c.noise_sigma_nT = static_cast<Scalar>(opt.noise_nT);
  return c;
}

std::vector<std::string> trace_columns() {
  std::vector<std::string> c = {"update", "pass", "t_s", "status"};
  const char* states[12] = {"cinv00", "cinv01", "cinv02", "cinv10", "cinv11", "cinv12",
                            "cinv20", "cinv21", "cinv22", "b_x_nT", "b_y_nT", "b_z_nT"};
  for (const char* s : states)
    c.emplace_back(s);
  for (const char* s : states)
    c.push_back(std::string("sigma_") + s);
  c.emplace_back("nis");
  c.emplace_back("intensity_sigma_nT");
  return c;
}

double finite_or_nan(double v) {
  return std::isfinite(v) ? v : std::numeric_limits<double>::quiet_NaN();
}

// ks, O, Kof of the Li form as a function of the 12 states (C^-1 row-major, b).
bool li_of_state(const core::Vec<double, 12>& x, core::Vec<double, 9>* out) {
  core::GeParams<double> ge;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      ge.c_inv(r, c) = x(core::ekf_w_index(r, c));
  ge.b = x.tail<3>();
  core::LiParams<double> li;
  if (core::to_li(core::from_ge(ge), &li) != core::ConversionStatus::kOk) return false;
  *out << li.ks, li.o_rad, li.kof;
  return true;
}

template <typename Scalar>
void run_filter(const std::string& path, const io::CsvReaderOptions& ropt, const EkfRunOptions& opt,
                EkfRun* run) {
  auto ekf = std::make_unique<core::ScalarEkf<Scalar>>(make_config<Scalar>(opt));
  std::unique_ptr<io::CsvWriter> trace;
  if (!opt.trace_path.empty()) {
    trace = std::make_unique<io::CsvWriter>(
        opt.trace_path, trace_columns(),
        std::vector<std::string>{
            "magvec calibrate --method ekf trace of " + path +
                ": one row per sample fed to the filter",
            "status: 0 accepted, 1 collecting (initial fit), 2 initialised, 3 init_failed, "
            "4 gated, 5 rejected_nonfinite, 6 rejected_bad_reference, 7 reinitialised",
            "states C^-1 row-major (dimensionless) and b (nT) with their 1-sigma; nis of the "
            "last processed sample; intensity_sigma_nT: predicted 1-sigma of |C^-1 (m - b)|"});
  }
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::vector<double> row(trace ? trace->column_count() : 0);
  std::uint64_t update = 0;
  for (int pass = 0; pass < opt.passes; ++pass) {
    io::CsvReader reader(path, ropt);
    io::CsvRecord rec;
    std::uint64_t rows = 0, dropouts = 0;
    EkfPassCounts last;
    while (reader.next(&rec)) {
      ++rows;
      dropouts += rec.dropout ? 1U : 0U;
      const double f = rec.f_nT ? *rec.f_nT : (opt.field_nT ? *opt.field_nT : nan);
      const core::EkfStatus st =
          ekf->update(rec.m_nT.template cast<Scalar>(), static_cast<Scalar>(f));
      switch (st) {
        case core::EkfStatus::kAccepted:
        case core::EkfStatus::kInitialised:
          ++last.accepted;
          break;
        case core::EkfStatus::kGated:
          ++last.gated;
          break;
        case core::EkfStatus::kRejectedNonFinite:
        case core::EkfStatus::kRejectedBadReference:
          ++last.rejected_nonfinite;
          break;
        default:
          break;
      }
      if (trace) {
        std::size_t k = 0;
        row[k++] = static_cast<double>(update);
        row[k++] = static_cast<double>(pass + 1);
        row[k++] = rec.t_s;
        row[k++] = static_cast<double>(static_cast<int>(st));
        const auto x = ekf->state();
        const auto s = ekf->sigma();
        for (int i = 0; i < 12; ++i)
          row[k++] = finite_or_nan(static_cast<double>(x(i)));
        for (int i = 0; i < 12; ++i)
          row[k++] = finite_or_nan(static_cast<double>(s(i)));
        row[k++] = finite_or_nan(static_cast<double>(ekf->last_nis()));
        row[k++] = rec.dropout ? nan
                               : finite_or_nan(static_cast<double>(
                                     ekf->intensity_sigma_nT(rec.m_nT.template cast<Scalar>())));
        trace->write_row(row);
      }
      ++update;
    }
    run->rows = rows;
    run->dropouts = dropouts;
    run->last_pass = last;
  }
  if (trace) {
    trace->commit();
    run->trace_rows = trace->rows();
  }
  run->state = ekf->state().template cast<double>();
  run->sigma = ekf->sigma().template cast<double>();
  run->covariance = ekf->covariance().template cast<double>();
  run->model = ekf->model().template cast<double>();
  run->counters = ekf->counters();
  run->last_reset = ekf_reset_name(ekf->last_reset_reason());
  run->initialised = ekf->initialised();
  run->field_scale_nT = static_cast<double>(ekf->field_scale_nT());
  // Conditioning of the covariance in normalised units (b divided by the field scale).
  const double s = ekf->field_scale_nT() > 0 ? static_cast<double>(ekf->field_scale_nT()) : 1.0;
  core::Vec<double, 12> t = core::Vec<double, 12>::Ones();
  t.tail<3>().setConstant(1.0 / s);
  const core::Mat<double, 12, 12> pn = t.asDiagonal() * run->covariance * t.asDiagonal();
  const Eigen::SelfAdjointEigenSolver<core::Mat<double, 12, 12>> es(pn, Eigen::EigenvaluesOnly);
  const double lo = es.eigenvalues()(0), hi = es.eigenvalues()(11);
  run->condition = lo > 0 ? hi / lo : std::numeric_limits<double>::infinity();
}

std::string f2(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}

}  // namespace

const char* ekf_status_name(core::EkfStatus s) noexcept {
  switch (s) {
    case core::EkfStatus::kAccepted:
      return "accepted";
    case core::EkfStatus::kCollecting:
      return "collecting";
    case core::EkfStatus::kInitialised:
      return "initialised";
    case core::EkfStatus::kInitFailed:
      return "init_failed";
    case core::EkfStatus::kGated:
      return "gated";
    case core::EkfStatus::kRejectedNonFinite:
      return "rejected_nonfinite";
    case core::EkfStatus::kRejectedBadReference:
      return "rejected_bad_reference";
    case core::EkfStatus::kReinitialised:
      return "reinitialised";
  }
  return "unknown";
}

const char* ekf_reset_name(core::EkfResetReason r) noexcept {
  switch (r) {
    case core::EkfResetReason::kNone:
      return "none";
    case core::EkfResetReason::kNonFiniteState:
      return "non_finite_state";
    case core::EkfResetReason::kCovarianceNotPositive:
      return "covariance_not_positive";
    case core::EkfResetReason::kNisTooHigh:
      return "nis_too_high";
    case core::EkfResetReason::kTooManyGated:
      return "too_many_gated";
    case core::EkfResetReason::kSingularModel:
      return "singular_model";
  }
  return "unknown";
}

EkfRun run_ekf(const std::string& path, const io::CsvReaderOptions& reader_options,
               const EkfRunOptions& opt) {
  if (opt.passes < 1) throw std::invalid_argument("--passes must be at least 1");
  if (!(opt.noise_nT > 0)) throw std::invalid_argument("--noise-nT must be positive");
  EkfRun run;
  if (opt.float32) {
    run_filter<float>(path, reader_options, opt, &run);
  } else {
    run_filter<double>(path, reader_options, opt, &run);
  }

  // Li form of the result and its 1-sigma by linear propagation of the state covariance.
  core::LiParams<double> li;
  const core::ConversionStatus li_status = core::to_li(run.model, &li);
  run.li_ok = li_status == core::ConversionStatus::kOk;
  if (run.li_ok) {
    run.li = li;
    core::Vec<double, 9> p0;
    core::Mat<double, 9, 12> j = core::Mat<double, 9, 12>::Zero();
    bool ok = li_of_state(run.state, &p0);
    for (int i = 0; ok && i < 12; ++i) {
      const double h = i < 9 ? 1e-7 : 1e-4;
      core::Vec<double, 12> xp = run.state, xm = run.state;
      xp(i) += h;
      xm(i) -= h;
      core::Vec<double, 9> pp, pm;
      ok = li_of_state(xp, &pp) && li_of_state(xm, &pm);
      j.col(i) = (pp - pm) / (2 * h);
    }
    if (ok) {
      const core::Vec<double, 9> var = (j * run.covariance * j.transpose()).diagonal();
      const core::Vec<double, 9> sd = var.cwiseMax(0.0).cwiseSqrt();
      run.li_sigma.ks = sd.segment<3>(0);
      run.li_sigma.o_rad = sd.segment<3>(3);
      run.li_sigma.kof = sd.segment<3>(6);
    }
  }

  // Evaluation pass (intensity before/after, coverage); no E/N/U: W is known only up to a
  // rotation.
  Evaluator ev(run.model, false);
  {
    io::CsvReader reader(path, reader_options);
    io::CsvRecord rec;
    while (reader.next(&rec)) {
      const double f =
          rec.f_nT ? *rec.f_nT
                   : (opt.field_nT ? *opt.field_nT : std::numeric_limits<double>::quiet_NaN());
      ev.add(rec.m_nT, f, nullptr);
    }
  }
  run.eval = ev.result();

  // Verdict.
  const double noise = opt.noise_nT;
  const std::uint64_t usable = run.rows - run.dropouts;
  const double max_rms = 3.0 * noise + 1.0;
  double max_rel_sigma = 0;
  for (int i = 0; i < 9; ++i)
    max_rel_sigma = std::fmax(max_rel_sigma, run.sigma(i));
  const double b_sigma = run.sigma.tail<3>().maxCoeff();
  const double b_rel_sigma = b_sigma / (run.field_scale_nT > 0 ? run.field_scale_nT : 1.0);
  if (run.eval.n_intensity == 0) {
    run.verdict = "field_mismatch";
    run.reason = "no reference total field: the file has no usable F_nT and no --field-nT";
  } else if (!run.initialised && usable < 64) {
    run.verdict = "too_few_samples";
    run.reason = std::to_string(usable) +
                 " usable samples; the filter's initial fit needs 64 "
                 "well-spread samples";
  } else if (!run.initialised || run.counters.updates == 0) {
    run.verdict = "not_converged";
    run.reason = "the filter never started (" + std::to_string(run.counters.init_failures) +
                 " failed initial fits: poor direction coverage or not an ellipsoid)";
  } else if (!run.model.w.allFinite() || !run.model.o.allFinite() || !run.sigma.allFinite()) {
    run.verdict = "ill_conditioned";
    run.reason = "the state or its covariance is not finite";
  } else if (li_status == core::ConversionStatus::kReflection) {
    run.verdict = "reflected_solution";
    run.reason =
        "C^-1 ended with a negative determinant (a reflection, ERRATA 002-3): G may fit "
        "but no rotation maps the compensated vector to the body frame";
  } else if (!run.li_ok) {
    run.verdict = "not_an_ellipsoid";
    run.reason = "G = C^-T C^-1 is not positive definite";
  } else if (run.eval.coverage < opt.min_coverage) {
    run.verdict = "insufficient_coverage";
    run.reason = "field directions cover " + f2(100.0 * run.eval.coverage, 1) +
                 " % of the sphere, at least " + f2(100.0 * opt.min_coverage, 1) + " % needed";
  } else if (max_rel_sigma > opt.max_relative_sigma || b_rel_sigma > opt.max_relative_sigma) {
    run.verdict = "ill_conditioned";
    run.reason = "a parameter 1-sigma is too large (C^-1 " + f2(max_rel_sigma, 5) + ", b " +
                 f2(b_sigma, 1) + " nT): the data do not determine the calibration";
  } else if (!(run.eval.intensity_rms_after_nT <= max_rms)) {
    run.verdict = "residual_too_large";
    run.reason = "calibrated intensity residual RMS " + f2(run.eval.intensity_rms_after_nT, 2) +
                 " nT above 3x the stated noise + 1 nT (" + f2(max_rms, 2) +
                 " nT): check --noise-nT or the data";
  } else {
    run.verdict = "ok";
    run.reason = "all acceptance checks passed";
  }

  CalibrationFile& c = run.cal;
  c.model = run.model;
  std::vector<double> s_cinv(9), s_b(3);
  for (int i = 0; i < 9; ++i)
    s_cinv[static_cast<std::size_t>(i)] = run.sigma(i);
  for (int i = 0; i < 3; ++i)
    s_b[static_cast<std::size_t>(i)] = run.sigma(9 + i);
  c.sigma["Cinv"] = s_cinv;
  c.sigma["b_nT"] = s_b;
  if (run.li_ok) {
    c.sigma["ks"] = {run.li_sigma.ks(0), run.li_sigma.ks(1), run.li_sigma.ks(2)};
    c.sigma["O_deg"] = {run.li_sigma.o_rad(0) * kDeg, run.li_sigma.o_rad(1) * kDeg,
                        run.li_sigma.o_rad(2) * kDeg};
    c.sigma["Kof_nT"] = {run.li_sigma.kof(0), run.li_sigma.kof(1), run.li_sigma.kof(2)};
  }
  c.quality.verdict = run.verdict;
  c.quality.reason = run.reason;
  c.quality.coverage = run.eval.coverage;
  c.quality.condition = run.condition;
  c.quality.residual_rms_before_nT = run.eval.intensity_rms_before_nT;
  c.quality.residual_rms_after_nT = run.eval.intensity_rms_after_nT;
  c.quality.extra["passes"] = opt.passes;
  c.quality.extra["updates"] = run.counters.updates;
  c.quality.extra["gated"] = run.counters.gated;
  c.quality.extra["reinitialisations"] = run.counters.reinitialisations;
  c.quality.extra["init_outliers"] = run.counters.init_outliers;
  c.quality.extra["float32"] = opt.float32 ? 1.0 : 0.0;
  c.counts.samples = run.rows;
  // Counts of the last pass (the samples behind the final state); cumulative counters in extra.
  c.counts.used = run.last_pass.accepted;
  c.counts.skipped_nonfinite = run.last_pass.rejected_nonfinite;
  c.counts.rejected_outliers = run.last_pass.gated;
  c.provenance.input = path;
  c.provenance.method = opt.paper_settings ? "ekf-paper" : "ekf";
  return run;
}

}  // namespace magvec::host
