// Scalar EKF over a recording (see ekf_runner.hpp).
#include "calibration/ekf_runner.hpp"

#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <limits>
#include <memory>
#include <stdexcept>
#include <vector>

namespace magvec::host {
namespace {

constexpr double kDeg = 180.0 / core::kPi<double>;
// Start-up set capacity on the host: the set starts at init_samples (64, as on the MCU) and grows
// up to this when noisy data leave the fit undetermined.
constexpr int kStartupCapacity = 512;

template <typename Scalar>
core::EkfConfig<Scalar> make_config(const EkfRunOptions& opt) {
  core::EkfConfig<Scalar> c =
      opt.paper_settings ? core::EkfConfig<Scalar>::paper() : core::EkfConfig<Scalar>{};
  if (!opt.paper_settings) {
    c.noise_sigma_nT = static_cast<Scalar>(opt.noise_nT ? *opt.noise_nT : opt.noise_guess_nT);
    c.estimate_noise = !opt.noise_nT.has_value();
    c.init_max_sigma = static_cast<Scalar>(opt.limits.max_relative_sigma);
  }
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
  auto ekf = std::make_unique<core::ScalarEkf<Scalar, kStartupCapacity>>(make_config<Scalar>(opt));
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
      if (st == core::EkfStatus::kReinitialised) run->last_reinit_row = rows;
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
    // A recording shorter than the start-up set (or ending while it was being refilled): fit what
    // was collected.
    if (!ekf->initialised()) ekf->try_start();
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
  run->noise_nT = static_cast<double>(ekf->noise_nT());
  run->noise_estimated = ekf->config().estimate_noise;
  run->noise_estimate_nT = static_cast<double>(ekf->noise_estimate_nT());
  run->noise_estimate_sigma_nT = static_cast<double>(ekf->noise_estimate_sigma_nT());
  const core::EkfInitReport<Scalar>& ir = ekf->init_report();
  run->init_report.failure = ir.failure;
  run->init_report.undetermined = ir.undetermined;
  run->init_report.relative_sigma = ir.relative_sigma.template cast<double>();
  run->init_report.samples = ir.samples;
  run->init_report.limit = static_cast<double>(ir.limit);
  run->startup_samples = ekf->startup_samples();
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

// Median of positive values from a histogram in log10 (0.002 decades: 0.5 %), O(1) memory: only
// the unit check uses it, and a factor of 10^3 is what it looks for.
class LogMedian {
 public:
  void add(double v) {
    if (!(v > 0) || !std::isfinite(v)) return;
    const double b = (std::log10(v) - kLo) / kStep;
    const auto k = static_cast<std::size_t>(std::clamp(b, 0.0, static_cast<double>(kBins - 1)));
    ++bins_[k];
    ++n_;
  }
  double median() const {
    if (n_ == 0) return std::numeric_limits<double>::quiet_NaN();
    std::uint64_t acc = 0;
    for (std::size_t k = 0; k < kBins; ++k) {
      acc += bins_[k];
      if (2 * acc >= n_) return std::pow(10.0, kLo + (static_cast<double>(k) + 0.5) * kStep);
    }
    return std::numeric_limits<double>::quiet_NaN();
  }

 private:
  static constexpr double kLo = -4, kStep = 0.002;
  static constexpr std::size_t kBins = 7000;  // 1e-4 .. 1e10
  std::vector<std::uint64_t> bins_ = std::vector<std::uint64_t>(kBins, 0);
  std::uint64_t n_{0};
};

// Normalised intensity residuals r = (|y| - F) / (sigma |W^T y^|) of the final model: their RMS
// within the filter's 5-sigma gate over their robust scale (1.4826 median |r|, from a histogram of
// |r| at 0.005 resolution), the tail ratio of the acceptance policy.
class TailRatio {
 public:
  void add(double r) {
    if (!std::isfinite(r)) return;
    const double a = std::abs(r);
    ++n_;
    if (a < kGate) {
      sum2_ += r * r;
      ++inside_;
      ++bins_[static_cast<std::size_t>(a / kStep)];
    }
  }
  double ratio() const {
    if (inside_ < 2) return std::numeric_limits<double>::quiet_NaN();
    std::uint64_t acc = 0;
    double med = kGate;
    for (std::size_t k = 0; k < bins_.size(); ++k) {
      acc += bins_[k];
      if (2 * acc >= n_) {
        med = (static_cast<double>(k) + 0.5) * kStep;
        break;
      }
    }
    return std::sqrt(sum2_ / static_cast<double>(inside_)) / (1.4826 * med);
  }

 private:
  static constexpr double kGate = 5, kStep = 0.005;
  std::vector<std::uint64_t> bins_ = std::vector<std::uint64_t>(1000, 0);
  std::uint64_t n_{0}, inside_{0};
  double sum2_{0};
};

std::string g3(double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.3g", v);
  return buf;
}

// "b_z (1-sigma 0.31 of F), Cinv_zz (0.12)" for the set bits.
std::string undetermined_list(std::uint32_t bits, const core::Vec<double, 12>& rel) {
  std::string s;
  for (int k = 0; k < 12; ++k) {
    if ((bits & (1U << static_cast<unsigned>(k))) == 0) continue;
    if (!s.empty()) s += ", ";
    s += ekf_state_name(k);
    s += " (1-sigma " + g3(rel(k)) + (k >= 9 ? " of F)" : ")");
  }
  return s;
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

const char* ekf_init_failure_name(core::EkfInitFailure f) noexcept {
  switch (f) {
    case core::EkfInitFailure::kNone:
      return "none";
    case core::EkfInitFailure::kTooFewSamples:
      return "too_few_samples";
    case core::EkfInitFailure::kUndetermined:
      return "undetermined";
    case core::EkfInitFailure::kNotAnEllipsoid:
      return "not_an_ellipsoid";
    case core::EkfInitFailure::kNotConverged:
      return "not_converged";
  }
  return "unknown";
}

const char* ekf_state_name(int k) noexcept {
  static constexpr const char* kNames[12] = {"Cinv_xx", "Cinv_xy", "Cinv_xz", "Cinv_yx",
                                             "Cinv_yy", "Cinv_yz", "Cinv_zx", "Cinv_zy",
                                             "Cinv_zz", "b_x",     "b_y",     "b_z"};
  return k >= 0 && k < 12 ? kNames[k] : "?";
}

EkfRun run_ekf(const std::string& path, const io::CsvReaderOptions& reader_options,
               const EkfRunOptions& opt) {
  if (opt.passes < 1) throw std::invalid_argument("--passes must be at least 1");
  if (opt.noise_nT && !(*opt.noise_nT > 0))
    throw std::invalid_argument("--noise-nT must be positive");
  if (!(opt.noise_guess_nT > 0)) throw std::invalid_argument("the noise guess must be positive");
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

  // Evaluation pass: intensity before/after and coverage (no E/N/U: W is known only up to a
  // rotation), medians of |m| and F for the unit check, normalised residuals for the tail ratio.
  Evaluator ev(run.model, false);
  LogMedian med_m, med_f, med_e;
  TailRatio tail;
  std::uint64_t usable = 0;
  const core::Mat3<double> w = run.model.w;
  const bool model_finite = w.allFinite() && run.model.o.allFinite();
  {
    io::CsvReader reader(path, reader_options);
    io::CsvRecord rec;
    while (reader.next(&rec)) {
      const double f =
          rec.f_nT ? *rec.f_nT
                   : (opt.field_nT ? *opt.field_nT : std::numeric_limits<double>::quiet_NaN());
      ev.add(rec.m_nT, f, nullptr);
      if (!rec.m_nT.allFinite() || !(std::isfinite(f) && f > 0)) continue;
      ++usable;
      med_m.add(rec.m_nT.norm());
      med_f.add(f);
      // The last state is kept when the filter restarts: its residuals still measure the noise.
      if (model_finite && (run.initialised || run.counters.updates > 0)) {
        const core::Vec3<double> y = w * (rec.m_nT - run.model.o);
        const double ny = y.norm();
        const double gain = ny > 0 ? (w.transpose() * y).norm() / ny : 0.0;
        if (gain > 0) {
          if (run.initialised) tail.add((ny - f) / (run.noise_nT * gain));
          med_e.add(std::abs(ny - f) / gain);
        }
      }
    }
  }
  run.eval = ev.result();
  // With a given noise the filter's own estimate leans on it (gating, an overconfident P): the
  // data's figure is then the robust scale of the final residuals per axis (1.4826 MAD, 9 fitted
  // parameters; its 1-sigma 1.167 / sqrt(n) relative).
  if (!run.noise_estimated && std::isfinite(med_e.median()) && usable > 9) {
    const double n = static_cast<double>(usable);
    run.noise_estimate_nT = 1.4826 * med_e.median() * std::sqrt(n / (n - 9));
    run.noise_estimate_sigma_nT = 1.167 * run.noise_estimate_nT / std::sqrt(n);
  }

  // Evidence for the one acceptance policy.
  core::AcceptanceEvidence<double>& e = run.evidence;
  core::AcceptanceLimits<double> limits = opt.limits;
  const int min_fit = core::EkfConfig<double>{}.init_min_samples;
  limits.min_samples = std::max<std::size_t>(limits.min_samples, static_cast<std::size_t>(min_fit));
  e.rows = run.rows;
  e.usable = usable;
  e.median_norm_nT = med_m.median();
  e.median_f_nT = med_f.median();
  e.coverage = run.eval.coverage;
  const double f_ref = std::isfinite(e.median_f_nT) ? e.median_f_nT : run.field_scale_nT;
  core::Vec<double, 12> rel =
      core::Vec<double, 12>::Constant(std::numeric_limits<double>::quiet_NaN());
  std::uint32_t undetermined = 0;
  if (run.initialised) {
    for (int k = 0; k < 12; ++k) {
      rel(k) = k < 9 ? run.sigma(k) : run.sigma(k) / f_ref;
      if (!(rel(k) <= limits.max_relative_sigma)) undetermined |= 1U << static_cast<unsigned>(k);
    }
  } else if (run.init_report.failure == core::EkfInitFailure::kUndetermined) {
    rel = run.init_report.relative_sigma;
    undetermined = run.init_report.undetermined;
    if (std::isfinite(run.init_report.limit)) limits.max_relative_sigma = run.init_report.limit;
  }
  e.undetermined = undetermined;
  e.not_an_ellipsoid =
      !run.initialised && run.init_report.failure == core::EkfInitFailure::kNotAnEllipsoid;
  const bool reflected = li_status == core::ConversionStatus::kReflection;
  e.converged = run.initialised && model_finite && run.sigma.allFinite() && !reflected;
  e.noise_given = opt.noise_nT.has_value() && !opt.paper_settings;
  e.noise_nT = run.noise_nT;
  if (e.noise_given && std::isfinite(run.noise_estimate_nT)) {
    const double ratio = run.noise_estimate_nT / *opt.noise_nT;
    e.chi2_per_dof = ratio * ratio;
  }
  if (!e.noise_given && run.initialised) e.tail_ratio = tail.ratio();
  if (run.initialised && model_finite && std::abs(w.determinant()) > 0) {
    const Eigen::JacobiSVD<core::Mat3<double>> svd(w);
    // Scale factors of the sensor: singular values of C = W^-1.
    e.min_scale = 1.0 / svd.singularValues()(0);
    e.max_scale = 1.0 / svd.singularValues()(2);
  }
  run.verdict_code = core::judge(e, limits);
  run.verdict = core::verdict_name(run.verdict_code);

  // A given noise the data disagree with.
  if (opt.noise_nT && std::isfinite(run.noise_estimate_nT) && run.noise_estimate_nT > 0) {
    const double ratio = *opt.noise_nT / run.noise_estimate_nT;
    if (ratio > 2 || ratio < 0.5) {
      run.warnings.push_back("--noise-nT " + f2(*opt.noise_nT, 3) +
                             " nT disagrees with the data's own estimate of the magnetometer "
                             "noise (" +
                             f2(run.noise_estimate_nT, 3) + " nT) by a factor of " +
                             f2(ratio > 1 ? ratio : 1 / ratio, 1));
    }
  }

  // The reason, naming the cause with the figures behind it.
  const core::EkfCounters& k = run.counters;
  const std::string tries = std::to_string(k.init_attempts) + " initial fit" +
                            (k.init_attempts == 1 ? "" : "s") + " tried";
  auto never_started = [&]() {
    return "the filter never started (" + tries + " on a start-up set of " +
           std::to_string(run.init_report.samples) + " best-spread of " + std::to_string(usable) +
           " usable samples; the last failed: " + ekf_init_failure_name(run.init_report.failure) +
           ")";
  };
  switch (run.verdict_code) {
    case core::Verdict::kOk:
      run.reason = "all acceptance checks passed";
      break;
    case core::Verdict::kNoData:
      run.reason = "no data rows: the file has a header but no samples";
      break;
    case core::Verdict::kUnitMismatch: {
      const double ratio = e.median_norm_nT / e.median_f_nT;
      run.reason = ratio < 1 ? "values look like uT under an nT header (median |m| " +
                                   f2(e.median_norm_nT, 3) + " vs F " + f2(e.median_f_nT, 1) + ")"
                             : "the reference F looks like uT under an nT header (median |m| " +
                                   f2(e.median_norm_nT, 1) + " vs F " + f2(e.median_f_nT, 3) + ")";
      break;
    }
    case core::Verdict::kTooFewSamples:
      run.reason = std::to_string(usable) +
                   " usable samples (a finite reading and a positive F), " + "at least " +
                   std::to_string(limits.min_samples) + " needed for the filter's initial fit";
      break;
    case core::Verdict::kInsufficientCoverage: {
      const bool narrow = e.coverage < limits.min_coverage;
      std::string s = "field directions cover " + f2(100.0 * e.coverage, 1) + " % of the sphere" +
                      (narrow ? " (at least " + f2(100.0 * limits.min_coverage, 1) + " % needed)"
                              : std::string());
      if (undetermined != 0) {
        s += std::string(narrow ? "; " : ", but ") + "the data do not determine " +
             undetermined_list(undetermined, rel) + " (limit " + g3(limits.max_relative_sigma) +
             ")";
      }
      if (!run.initialised) s += "; " + never_started();
      run.reason = s + "; rotate through more headings and tilts";
      break;
    }
    case core::Verdict::kNotAnEllipsoid:
      run.reason = never_started() +
                   ": the start-up set determines every parameter but the readings do not lie "
                   "on a distorted sphere (the field changed, or these are not magnetometer "
                   "readings)";
      break;
    case core::Verdict::kNotConverged:
      if (reflected) {
        run.reason =
            "C^-1 ended with a negative determinant (a reflection, docs/equations.md E-Ge-3): G "
            "may fit but "
            "no rotation maps the compensated vector to the body frame";
      } else if (!run.initialised && k.updates > 0) {
        run.reason = "the filter made " + std::to_string(k.updates) + " updates, then restarted (" +
                     run.last_reset + ", " + std::to_string(k.reinitialisations) +
                     " restarts in all, the last at row " + std::to_string(run.last_reinit_row) +
                     ") and had not started again by the end of the data (start-up set " +
                     std::to_string(run.startup_samples) + " samples, " + tries + ")";
      } else if (!run.initialised) {
        run.reason = never_started();
      } else {
        run.reason = "the state or its covariance is not finite";
      }
      break;
    case core::Verdict::kResidualTooLarge:
      if (e.noise_given && std::isfinite(e.chi2_per_dof) &&
          e.chi2_per_dof > limits.max_chi2_per_dof) {
        run.reason = "the data's noise (" + f2(run.noise_estimate_nT, 2) + " nT) is " +
                     f2(std::sqrt(e.chi2_per_dof), 1) + "x the given --noise-nT " +
                     f2(*opt.noise_nT, 2) + " nT: check it, or leave it out to estimate it";
      } else if (!(e.noise_nT <= limits.max_noise_fraction * e.median_norm_nT)) {
        run.reason = "the magnetometer noise (" + f2(e.noise_nT, 1) + " nT) exceeds " +
                     f2(100 * limits.max_noise_fraction, 0) +
                     " % of the field: nothing left to calibrate";
      } else {
        run.reason = "residuals have heavy tails (RMS " + f2(e.tail_ratio, 2) +
                     "x their robust scale, limit " + f2(limits.max_tail_ratio, 1) +
                     "): part of the data does not fit the sensor model";
      }
      break;
    case core::Verdict::kFieldMismatch:
      run.reason = "scale factors " + f2(e.min_scale, 4) + ".." + f2(e.max_scale, 4) +
                   " outside [" + f2(limits.min_scale, 2) + ", " + f2(limits.max_scale, 2) +
                   "]: the reference field does not match the readings (wrong F, or a wrong unit)";
      break;
    default:
      run.reason = "see the verdict";
      break;
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
  c.noise.mag_nT = run.noise_nT;
  c.noise.mag_estimated = run.noise_estimated;
  if (run.noise_estimated) {
    c.noise.mag_nT = run.noise_estimate_nT;
    c.noise.mag_sigma_nT = run.noise_estimate_sigma_nT;
  }
  c.quality.verdict = run.verdict;
  c.quality.reason = run.reason;
  c.quality.coverage = run.eval.coverage;
  c.quality.condition = run.condition;
  c.quality.residual_rms_before_nT = run.eval.intensity_rms_before_nT;
  c.quality.residual_rms_after_nT = run.eval.intensity_rms_after_nT;
  c.quality.extra["passes"] = opt.passes;
  c.quality.extra["updates"] = k.updates;
  c.quality.extra["gated"] = k.gated;
  c.quality.extra["reinitialisations"] = k.reinitialisations;
  c.quality.extra["init_outliers"] = k.init_outliers;
  c.quality.extra["init_attempts"] = k.init_attempts;
  c.quality.extra["init_exchanges"] = k.init_exchanges;
  if (std::isfinite(e.tail_ratio)) c.quality.extra["tail_ratio"] = e.tail_ratio;
  if (!run.noise_estimated && std::isfinite(run.noise_estimate_nT)) {
    c.quality.extra["mag_noise_data_nT"] = run.noise_estimate_nT;
    c.quality.extra["mag_noise_data_sigma_nT"] = run.noise_estimate_sigma_nT;
  }
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
