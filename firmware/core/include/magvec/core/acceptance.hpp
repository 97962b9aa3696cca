// One acceptance policy for every calibration: the batch methods, the scalar EKF and the sample
// pipeline's hold-out validation (docs/equations.md "Acceptance"). Each estimator gathers the
// evidence below; judge() checks the causes in a fixed order and names the first that holds:
//   1. no data rows / too few usable samples;
//   2. units: the readings and the reference field differ by ~10^3 (uT under an nT header);
//   3. what the data determine: direction coverage, pitch/roll variety, the information matrix
//      (conditioning and the parameter directions it does not determine);
//   4. the algebraic model (an ellipsoid) and convergence of the iterative fit;
//   5. residuals against the noise: against the given noise (chi^2/dof), or, when the noise was
//      estimated from the same residuals, their tails (RMS over a robust scale) and size;
//   6. physical plausibility of the scale factors.
// No threshold is in nT: every limit is relative to the estimated noise, the field or a 1-sigma.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

namespace magvec::core {

enum class Verdict : std::uint8_t {
  kOk,
  kNoData,        // no data rows at all
  kUnitMismatch,  // |m| and F off by ~10^3 from each other
  kTooFewSamples,
  kInsufficientCoverage,             // the data do not determine some parameter directions
  kUnobservableHeadingMisalignment,  // no pitch/roll variety (misalignment about the vertical)
  kIllConditioned,                   // the normal equations are numerically singular
  kNotAnEllipsoid,                   // the readings do not lie on a distorted sphere
  kNotConverged,
  kResidualTooLarge,  // residuals inconsistent with the noise (given, or estimated)
  kFieldMismatch,     // scale factors physically implausible for the reference field
};

inline const char* verdict_name(Verdict v) noexcept {
  switch (v) {
    case Verdict::kOk:
      return "ok";
    case Verdict::kNoData:
      return "no_data";
    case Verdict::kUnitMismatch:
      return "unit_mismatch";
    case Verdict::kTooFewSamples:
      return "too_few_samples";
    case Verdict::kInsufficientCoverage:
      return "insufficient_coverage";
    case Verdict::kUnobservableHeadingMisalignment:
      return "unobservable_heading_misalignment";
    case Verdict::kIllConditioned:
      return "ill_conditioned";
    case Verdict::kNotAnEllipsoid:
      return "not_an_ellipsoid";
    case Verdict::kNotConverged:
      return "not_converged";
    case Verdict::kResidualTooLarge:
      return "residual_too_large";
    case Verdict::kFieldMismatch:
      return "field_mismatch";
  }
  return "unknown";
}

template <typename Scalar>
struct AcceptanceLimits {
  std::size_t min_samples = 12;
  // Fraction of the 32 equal-area direction cells hit. Below it the data are refused unless a
  // prior supplies the directions the data do not determine.
  Scalar min_coverage = Scalar(0.2);
  Scalar min_tilt_spread_deg = Scalar(2);  // RMS spread of the body-frame vertical
  // |m| / F beyond this factor (either way) is a unit error, not a calibration (a fluxgate's scale
  // error is a few per cent; uT vs nT is 10^3).
  Scalar unit_ratio = Scalar(30);
  // A parameter is determined when its predicted 1-sigma is below this fraction of its natural
  // size (scale 1, angle 1 rad, offset F): beyond it the fit only echoes the noise.
  Scalar max_relative_sigma = Scalar(0.02);
  // Given noise: residuals up to 5x the stated noise (chi^2/dof 25) before refusing.
  Scalar max_chi2_per_dof = Scalar(25);
  // Estimated noise: RMS of the normalised residuals over their robust scale (1.4826 MAD). Gaussian
  // residuals give 1; a misfit (wrong model, unmodelled lag, disturbed field) gives heavy tails.
  Scalar max_tail_ratio = Scalar(3);
  // Estimated magnetometer noise above this fraction of the field: nothing left to calibrate.
  Scalar max_noise_fraction = Scalar(0.05);
  Scalar min_scale = Scalar(0.5), max_scale = Scalar(2);
};

template <typename Scalar>
struct AcceptanceEvidence {
  static constexpr Scalar kNaN = std::numeric_limits<Scalar>::quiet_NaN();
  std::size_t rows = 0;           // data rows read
  std::size_t usable = 0;         // rows the method can use
  Scalar median_norm_nT = kNaN;   // median |m| of the usable rows
  Scalar median_f_nT = kNaN;      // median reference F (NaN: the method had none)
  Scalar coverage = kNaN;         // NaN: not assessed
  Scalar tilt_spread_deg = kNaN;  // NaN: not an attitude method
  bool heading_fixed = false;     // the vertical misalignment is held (no tilt check)
  bool has_prior = false;         // a prior supplies what the data do not determine
  // Bit k set: parameter k of the method (the method names them) is not determined by the data.
  std::uint32_t undetermined = 0;
  bool ill_conditioned = false;
  bool not_an_ellipsoid = false;
  bool converged = true;
  bool noise_given = false;                   // true: chi2_per_dof is against the given noise
  Scalar chi2_per_dof = kNaN;                 // with the given noise
  Scalar tail_ratio = kNaN;                   // RMS / robust scale of normalised residuals
  Scalar noise_nT = kNaN;                     // magnetometer noise in use (given or estimated)
  Scalar min_scale = kNaN, max_scale = kNaN;  // of the fitted scale factors
};

// The first cause that holds, in the order of the header comment.
template <typename Scalar>
Verdict judge(const AcceptanceEvidence<Scalar>& e, const AcceptanceLimits<Scalar>& l) noexcept {
  if (e.rows == 0) return Verdict::kNoData;
  if (std::isfinite(e.median_norm_nT) && std::isfinite(e.median_f_nT) && e.median_f_nT > 0 &&
      e.median_norm_nT > 0) {
    const Scalar ratio = e.median_norm_nT / e.median_f_nT;
    if (ratio > l.unit_ratio || ratio < Scalar(1) / l.unit_ratio) return Verdict::kUnitMismatch;
  }
  if (e.usable < l.min_samples) return Verdict::kTooFewSamples;
  if (!e.has_prior) {
    if (std::isfinite(e.tilt_spread_deg) && !e.heading_fixed &&
        e.tilt_spread_deg < l.min_tilt_spread_deg) {
      return Verdict::kUnobservableHeadingMisalignment;
    }
    if ((std::isfinite(e.coverage) && e.coverage < l.min_coverage) || e.undetermined != 0)
      return Verdict::kInsufficientCoverage;
  }
  if (e.ill_conditioned) return Verdict::kIllConditioned;
  if (e.not_an_ellipsoid) return Verdict::kNotAnEllipsoid;
  if (!e.converged) return Verdict::kNotConverged;
  if (e.noise_given) {
    if (std::isfinite(e.chi2_per_dof) && e.chi2_per_dof > l.max_chi2_per_dof)
      return Verdict::kResidualTooLarge;
  } else {
    if (std::isfinite(e.tail_ratio) && e.tail_ratio > l.max_tail_ratio)
      return Verdict::kResidualTooLarge;
  }
  if (std::isfinite(e.noise_nT) && std::isfinite(e.median_norm_nT) &&
      !(e.noise_nT <= l.max_noise_fraction * e.median_norm_nT)) {
    return Verdict::kResidualTooLarge;
  }
  if (std::isfinite(e.min_scale) && std::isfinite(e.max_scale) &&
      (e.min_scale < l.min_scale || e.max_scale > l.max_scale)) {
    return Verdict::kFieldMismatch;
  }
  return Verdict::kOk;
}

}  // namespace magvec::core
