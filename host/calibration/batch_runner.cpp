// Batch calibration over a recording (see batch_runner.hpp).
#include "calibration/batch_runner.hpp"

#include <cmath>
#include <memory>
#include <string>

namespace magvec::host {
namespace {

std::string f2(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}

std::vector<double> deg3(const core::Vec3<double>& rad) {
  const core::Vec3<double> d = rad * (180.0 / core::kPi<double>);
  return {d(0), d(1), d(2)};
}
std::vector<double> v3(const core::Vec3<double>& v) {
  return {v(0), v(1), v(2)};
}

}  // namespace

const char* batch_method_name(core::BatchMethod m) noexcept {
  switch (m) {
    case core::BatchMethod::kOneStep:
      return "li-ml";
    case core::BatchMethod::kPlaneCompression:
      return "li";
    case core::BatchMethod::kJoint:
      return "li-joint";
    case core::BatchMethod::kEllipsoidOnly:
      return "ellipsoid";
  }
  return "unknown";
}

std::string batch_verdict_reason(const core::BatchResult<double>& r,
                                 const core::BatchConfig<double>& cfg) {
  const core::BatchQuality<double>& q = r.quality;
  switch (r.verdict) {
    case core::Verdict::kOk:
      return "all acceptance checks passed";
    case core::Verdict::kTooFewSamples:
      return std::to_string(r.counts.used) + " usable samples, at least " +
             std::to_string(cfg.min_samples) + " needed";
    case core::Verdict::kNotAnEllipsoid:
      return "the algebraic fit is not an ellipsoid (G not positive definite): data do not lie "
             "on a distorted sphere";
    case core::Verdict::kIllConditioned:
      return "normal equations ill-conditioned (rcond " + f2(q.rcond, 12) + ", ellipsoid rcond " +
             f2(q.ellipsoid_rcond, 12) + "): the attitudes do not determine all parameters";
    case core::Verdict::kInsufficientCoverage:
      return "field directions cover " + f2(100.0 * q.coverage, 1) + " % of the sphere, at least " +
             f2(100.0 * cfg.min_coverage, 1) + " % needed";
    case core::Verdict::kFieldMismatch:
      return "calibrated intensity disagrees with the reference F (residual RMS " +
             f2(q.intensity_rms_nT, 3) + " nT, limit " + f2(cfg.max_intensity_rms_nT, 1) +
             " nT) or a scale factor is outside [" + f2(cfg.min_scale, 2) + ", " +
             f2(cfg.max_scale, 2) + "]";
    case core::Verdict::kUnobservableHeadingMisalignment:
      return "pitch/roll spread " + f2(q.tilt_spread_deg, 3) + " deg (minimum " +
             f2(cfg.min_tilt_spread_deg, 1) +
             " deg): the misalignment about the vertical is unobservable without pitch/roll "
             "variety (ERRATA 000-4); record tilted attitudes or hold it with "
             "--fix-heading-misalignment-deg";
    case core::Verdict::kResidualTooLarge:
      return "chi2/dof " + f2(q.chi2_per_dof, 2) + " above " + f2(cfg.max_chi2_per_dof, 1) +
             ": residuals far above the stated noise (" + f2(cfg.mag_noise_nT, 3) + " nT, " +
             f2(cfg.attitude_noise_deg, 4) + " deg); check --noise-nT/--ins-noise-deg";
    case core::Verdict::kNotConverged:
      return "the iterative fit did not converge in " + std::to_string(cfg.max_iterations) +
             " iterations";
  }
  return "unknown verdict";
}

BatchRun run_batch(io::CsvReader& reader, const BatchRunOptions& opt) {
  return run_batch_with_capacity<kHostBatchCapacity>(reader, opt);
}

namespace detail {

void fill_batch_file(const io::CsvReader& reader, const BatchRunOptions& opt, BatchRun* run_ptr) {
  BatchRun& run = *run_ptr;
  const core::BatchResult<double>& r = run.result;
  CalibrationFile& c = run.cal;
  c.model = r.model;
  if (r.has_h_n) c.h_n_nT = r.h_n_nT;
  const bool one_step = opt.method == core::BatchMethod::kOneStep;
  if (one_step) {
    c.sigma["ks"] = v3(r.sigma.ks);
    c.sigma["O_deg"] = deg3(r.sigma.o_rad);
    c.sigma["Kof_nT"] = v3(r.sigma.kof);
  }
  if (run.needs_attitude) c.sigma["Rm_deg"] = deg3(r.sigma.rm_rad);
  if (r.has_h_n) c.sigma["h_n_nT"] = v3(r.h_n_sigma_nT);
  c.quality.verdict = core::verdict_name(r.verdict);
  c.quality.reason = run.reason;
  c.quality.coverage = r.quality.coverage;
  c.quality.condition = r.quality.rcond > 0 ? 1.0 / r.quality.rcond : 0.0;
  c.quality.residual_rms_before_nT = run.eval.intensity_rms_before_nT;
  c.quality.residual_rms_after_nT = run.eval.intensity_rms_after_nT;
  c.quality.extra["tilt_spread_deg"] = r.quality.tilt_spread_deg;
  c.quality.extra["chi2_per_dof"] = r.quality.chi2_per_dof;
  c.quality.extra["iterations"] = r.quality.iterations;
  c.quality.extra["rows_without_attitude"] = static_cast<double>(run.rows_without_attitude);
  if (run.eval.has_enu) {
    const char* names[3] = {"E", "N", "U"};
    for (int k = 0; k < 3; ++k) {
      c.quality.extra[std::string("spread_") + names[k] + "_before_nT"] =
          run.eval.enu_sd_before_nT(k);
      c.quality.extra[std::string("spread_") + names[k] + "_after_nT"] =
          run.eval.enu_sd_after_nT(k);
    }
  }
  if (r.heading_fixed)
    c.quality.extra["heading_misalignment_fixed_deg"] = opt.config.fixed_heading_misalignment_deg;
  c.counts.samples = run.rows;
  c.counts.used = r.counts.used;
  c.counts.skipped_nonfinite = r.counts.skipped_nonfinite;
  c.counts.rejected_outliers = r.counts.outliers;
  c.provenance.input = reader.path();
  c.provenance.method = opt.method_name;
}

}  // namespace detail

}  // namespace magvec::host
