// Batch calibration entry point: collects samples {raw m, scalar reference F, R_bn} in a store
// (fixed capacity on the MCU, growing on the host) and solves Li et al. 2023 with the corrections
// of docs/equations.md:
//   kEllipsoidOnly    ellipsoid fit (algebraic + geometric refinement), no attitude needed
//   kPlaneCompression ellipsoid + plane compression (Li's two-step method, E-Li-2/3)
//   kJoint            ellipsoid + joint fit of Rm and h_n (E-Li-5)
//   kOneStep          the above as a start, then the 14-parameter weighted fit (E-Li-6; default)
// Noise: given, or estimated from the data (BatchConfig::estimate_noise): the robust scale of the
// intensity residuals for the ellipsoid, variance components of the one-step fit for the attitude
// methods. A prior calibration (BatchConfig::prior) turns the one-step fit into the regularised
// (MAP) problem that updates only what the data determine.
// Robustness: non-finite rows are skipped and counted; outliers are rejected by an iterated
// median/MAD screen on the intensity residual |W(m - o)| - F and counted.
// Acceptance: acceptance.hpp's one policy (no data, units, what the data determine, model and
// convergence, residuals against the noise, plausibility), never a silent bad calibration.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/acceptance.hpp"
#include "magvec/core/coverage.hpp"
#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/output_envelope.hpp"
#include "magvec/core/sample_store.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

enum class BatchMethod : std::uint8_t { kEllipsoidOnly, kPlaneCompression, kJoint, kOneStep };

enum class AddStatus : std::uint8_t { kAccepted, kSkippedNonFinite, kStoreFull };

template <typename Scalar>
struct BatchConfig {
  Scalar field_nT = std::numeric_limits<Scalar>::quiet_NaN();  // used when a sample's F is NaN
  // Noise per magnetometer axis and per INS angle, 1-sigma. With estimate_noise they are only
  // start values: the fit estimates both from its residuals and reports them.
  Scalar mag_noise_nT = Scalar(0.3);
  Scalar attitude_noise_deg = Scalar(0.015);
  bool estimate_noise = false;
  AttitudeNoiseModel attitude_model = AttitudeNoiseModel::kLiEuler;
  bool fix_heading_misalignment = false;  // hold am (docs/equations.md E-Li-4) instead of refusing
  Scalar fixed_heading_misalignment_deg{0};
  AcceptanceLimits<Scalar> limits{};
  Scalar max_misalignment_sigma_deg = Scalar(0.5);
  Scalar outlier_k = Scalar(5);  // threshold in robust SDs (1.4826 MAD)
  int outlier_max_passes = 8;
  int max_iterations = 50;
  // A previous calibration with its 1-sigmas: the one-step fit solves the MAP problem.
  const OneStepPrior<Scalar>* prior = nullptr;
};

template <typename Scalar>
struct BatchQuality {
  Scalar coverage{0};  // fraction of the 32 equal-area direction cells containing data
  Scalar rcond{0};     // of the final solver's scaled normal matrix
  Scalar ellipsoid_rcond{0};
  Scalar tilt_spread_deg{0};                       // RMS spread of the vertical in body axes
  Scalar intensity_rms_raw_nT{0};                  // |m| - F before calibration
  Scalar intensity_rms_nT{0};                      // |W(m - o)| - F after
  Vec3<Scalar> enu_rms_nT = Vec3<Scalar>::Zero();  // spread of R^T Rm^T h_s about h_n (E, N, U)
  Scalar chi2_per_dof{0};  // against the noise in use (1 by construction when estimated)
  Scalar tail_ratio{0};    // RMS over robust scale of the normalised residuals
  Scalar median_norm_nT{0}, median_f_nT{0};
  int iterations{0};
  std::uint32_t undetermined{0};  // one-step parameter bits the data do not determine
  std::uint32_t updated{0};       // with a prior: parameters the data updated
  std::uint32_t moved{0};         // with a prior: parameters that moved from it
};

// Noise figures in use: estimated (with their 1-sigma) or given.
template <typename Scalar>
struct BatchNoise {
  bool estimated = false;
  Scalar mag_nT{0}, mag_sigma_nT{0};
  bool has_attitude = false;
  Scalar attitude_deg{0}, attitude_sigma_deg{0};
};

struct BatchCounts {
  std::size_t offered{0};            // add_sample calls
  std::size_t added{0};              // accepted into the store
  std::size_t skipped_nonfinite{0};  // NaN/inf reading, field or attitude
  std::size_t dropped_full{0};       // store full
  std::size_t outliers{0};           // rejected by the robust screen
  std::size_t used{0};               // used by the final fit
};

template <typename Scalar>
struct BatchResult {
  Verdict verdict = Verdict::kTooFewSamples;
  BatchMethod method = BatchMethod::kOneStep;
  SensorModel<Scalar> model{};
  bool has_model = false;  // a solution exists (possibly refused); false: nothing to write
  LiParams<Scalar> li{};
  LiSigmas<Scalar> sigma{};  // one-step: full; two-step: Rm only
  bool has_h_n = false;
  Vec3<Scalar> h_n_nT = Vec3<Scalar>::Zero();
  Vec3<Scalar> h_n_sigma_nT = Vec3<Scalar>::Zero();
  // One-step: what the parameters' covariance does to the outputs over the survey envelope of the
  // data's tilts (E-Acc-3): per-axis RMS of the E/N/U error and RMS of the |h| error; NaN for the
  // two-step method.
  Scalar calibration_sigma_enu_nT = std::numeric_limits<Scalar>::quiet_NaN();
  Scalar calibration_sigma_f_nT = std::numeric_limits<Scalar>::quiet_NaN();
  bool heading_fixed = false;
  bool converged = false;
  Scalar cost{0};  // one-step: chi^2 (+ prior term) at the solution
  BatchNoise<Scalar> noise{};
  BatchQuality<Scalar> quality{};
  AcceptanceEvidence<Scalar> evidence{};
  BatchCounts counts{};

  bool ok() const noexcept { return verdict == Verdict::kOk; }
};

template <typename Scalar, std::size_t Capacity>
class BatchCalibrator {
 public:
  static constexpr std::size_t kCapacity = Capacity;

  explicit BatchCalibrator(const BatchConfig<Scalar>& cfg = BatchConfig<Scalar>{}) noexcept
      : cfg_(cfg) {}

  void reset() noexcept {
    store_.clear();
    counts_ = BatchCounts{};
  }
  void set_config(const BatchConfig<Scalar>& cfg) noexcept { cfg_ = cfg; }
  const BatchConfig<Scalar>& config() const noexcept { return cfg_; }
  const BatchCounts& counts() const noexcept { return counts_; }
  const SampleStore<Scalar, Capacity>& store() const noexcept { return store_; }

  // m [nT]; f_nT: scalar reference for this sample (NaN: use config().field_nT); r_bn: attitude.
  // att_var: the attitude's noise variance relative to one INS record (interpolated attitudes
  // average two records: (1-u)^2 + u^2).
  AddStatus add_sample(const Vec3<Scalar>& m, Scalar f_nT, const Mat3<Scalar>& r_bn,
                       Scalar att_var = Scalar(1)) noexcept {
    return add(m, f_nT, &r_bn, att_var);
  }
  // Scalar-only sample (kEllipsoidOnly).
  AddStatus add_sample(const Vec3<Scalar>& m, Scalar f_nT) noexcept {
    return add(m, f_nT, nullptr);
  }

  // Moves the attitude of each stored sample i < n to its time minus step_s, R_bn Exp(step_s
  // [omega_of(i) x]) (omega_of(i): its rotation rate, n-frame axes): fit_time_offset() below.
  template <typename OmegaOf>
  void shift_attitudes(std::size_t n, Scalar step_s, OmegaOf&& omega_of) noexcept {
    for (std::size_t i = 0; i < std::min(n, store_.size()); ++i) {
      StoredSample<Scalar>& s = store_[i];
      const Vec3<Scalar> rot = omega_of(i) * step_s;
      const Scalar a = rot.norm();
      if (!s.has_attitude() || !(a > Scalar(0))) continue;
      Quat<Scalar> q = Quat<Scalar>(s.q[0], s.q[1], s.q[2], s.q[3]) *
                       Quat<Scalar>(Eigen::AngleAxis<Scalar>(a, rot / a));
      q.normalize();
      s.q = {q.w(), q.x(), q.y(), q.z()};
    }
  }

  BatchResult<Scalar> solve(BatchMethod method = BatchMethod::kOneStep) noexcept;

  // The one-step fit alone from a previous result, at that result's noise figures (no
  // re-estimation): the profile cost for a search over a nuisance (the time offset) after the
  // samples' attitudes changed. Status and cost of the fit.
  OneStepSolution<Scalar> refit_one_step(const BatchResult<Scalar>& from) const noexcept;

  // Normalisation of the stored samples: centre = mean reading, scale = mean reference field.
  Normalization<Scalar> normalization() const noexcept {
    Normalization<Scalar> norm;
    Vec3<Scalar> sum = Vec3<Scalar>::Zero();
    Scalar fsum{0};
    for (std::size_t i = 0; i < store_.size(); ++i) {
      sum += store_[i].raw();
      fsum += store_[i].f;
    }
    const Scalar n = static_cast<Scalar>(store_.size() > 0 ? store_.size() : 1);
    norm.centre = sum / n;
    norm.scale = fsum > Scalar(0) ? fsum / n : Scalar(1);
    return norm;
  }

  // Fraction of the direction cells (coverage.hpp) hit by h_s = W (m - o) of the samples in use.
  Scalar coverage(const SensorModel<Scalar>& model) const noexcept {
    CoverageGrid grid;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      if (store_[i].outlier()) continue;
      grid.add(Vec3<Scalar>(model.w * (store_[i].raw() - model.o)));
    }
    return grid.fraction<Scalar>();
  }

 private:
  OneStepOptions<Scalar> one_step_options(Scalar mag_noise_nT, Scalar att_deg) const noexcept {
    OneStepOptions<Scalar> oopt;
    oopt.mag_noise_nT = mag_noise_nT;
    oopt.attitude_noise_rad = deg_to_rad(att_deg);
    oopt.attitude_model = cfg_.attitude_model;
    oopt.estimate_noise = cfg_.estimate_noise;
    oopt.fix_heading = cfg_.fix_heading_misalignment;
    oopt.max_rm_sigma_rad = deg_to_rad(cfg_.max_misalignment_sigma_deg);
    oopt.max_relative_sigma = cfg_.limits.max_relative_sigma;
    oopt.max_iterations = cfg_.max_iterations;
    oopt.prior = cfg_.prior;
    return oopt;
  }

  AddStatus add(const Vec3<Scalar>& m, Scalar f, const Mat3<Scalar>* r_bn,
                Scalar att_var = Scalar(1)) noexcept {
    ++counts_.offered;
    if (!std::isfinite(f)) f = cfg_.field_nT;
    const bool bad_att = r_bn != nullptr && !r_bn->allFinite();
    if (!m.allFinite() || !std::isfinite(f) || !(f > Scalar(0)) || bad_att) {
      ++counts_.skipped_nonfinite;
      return AddStatus::kSkippedNonFinite;
    }
    if (!(att_var > Scalar(0)) || !std::isfinite(att_var)) att_var = Scalar(1);
    if (!store_.push(m, f, r_bn, att_var)) {
      ++counts_.dropped_full;
      return AddStatus::kStoreFull;
    }
    ++counts_.added;
    return AddStatus::kAccepted;
  }

  bool in_use(const StoredSample<Scalar>& s, bool need_att) const noexcept {
    return (!need_att || s.has_attitude()) && !s.outlier();
  }

  // Medians of |m| and of F over the samples the method can use (the unit check).
  void medians(bool need_att, Scalar* norm_nT, Scalar* f_nT) noexcept {
    if (!scratch_.ensure(store_.size())) return;
    std::size_t k = 0;
    for (std::size_t i = 0; i < store_.size(); ++i)
      if (in_use(store_[i], need_att)) scratch_.data()[k++] = store_[i].raw().norm();
    if (k == 0) return;
    *norm_nT = median(k);
    k = 0;
    for (std::size_t i = 0; i < store_.size(); ++i)
      if (in_use(store_[i], need_att)) scratch_.data()[k++] = store_[i].f;
    *f_nT = median(k);
  }

  // Coverage of the raw reading directions (before any fit).
  Scalar raw_coverage(bool need_att) const noexcept {
    CoverageGrid grid;
    for (std::size_t i = 0; i < store_.size(); ++i)
      if (in_use(store_[i], need_att)) grid.add(store_[i].raw());
    return grid.fraction<Scalar>();
  }

  // Direction of the mean of R^T Rm^T h_s under a model (start of h_n from a prior).
  Vec3<Scalar> mean_direction(const SensorModel<Scalar>& model) const noexcept {
    // Rm kept, its transpose taken in the product: constructing a matrix from a transpose makes
    // GCC 12 warn -Wmaybe-uninitialized inside Eigen's aliasing check at -O1 (the sanitizer build).
    const Mat3<Scalar> rm = model.rm_matrix();
    Vec3<Scalar> sum = Vec3<Scalar>::Zero();
    for (std::size_t i = 0; i < store_.size(); ++i) {
      if (!detail::usable(store_[i])) continue;
      sum +=
          store_[i].r_bn().transpose() * (rm.transpose() * (model.w * (store_[i].raw() - model.o)));
    }
    return sum.squaredNorm() > Scalar(0) ? Vec3<Scalar>(sum.normalized()) : Vec3<Scalar>::UnitY();
  }

  // 1.4826 MAD of |W(m - o)| - F over the samples in use (0 if none).
  Scalar robust_intensity_scale(const Mat3<Scalar>& w, const Vec3<Scalar>& o,
                                bool need_att) noexcept {
    if (!scratch_.ensure(store_.size())) return Scalar(0);
    std::size_t k = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      const StoredSample<Scalar>& s = store_[i];
      if (in_use(s, need_att)) scratch_.data()[k++] = (w * (s.raw() - o)).norm() - s.f;
    }
    if (k == 0) return Scalar(0);
    const Scalar med = median(k);
    for (std::size_t i = 0; i < k; ++i)
      scratch_.data()[i] = std::abs(scratch_.data()[i] - med);
    return Scalar(1.4826) * median(k);
  }

  // Magnetometer noise from the intensity residuals of a model (the intensity carries the
  // magnetometer noise only): ML scale with the parameter count removed; tails against the MAD.
  void intensity_noise(const SensorModel<Scalar>& model, bool need_att, Scalar given_nT,
                       BatchResult<Scalar>* res) noexcept {
    Scalar sse{0};
    std::size_t n = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      const StoredSample<Scalar>& s = store_[i];
      if (!in_use(s, need_att)) continue;
      const Scalar r = (model.w * (s.raw() - model.o)).norm() - s.f;
      sse += r * r;
      ++n;
    }
    const Scalar robust = robust_intensity_scale(model.w, model.o, need_att);
    const Scalar dof = static_cast<Scalar>(n > 9 ? n - 9 : 1);
    const Scalar ml = std::sqrt(sse / dof);
    const Scalar rms = std::sqrt(sse / static_cast<Scalar>(n > 0 ? n : 1));
    res->quality.tail_ratio = robust > Scalar(0) ? rms / robust : Scalar(0);
    res->evidence.tail_ratio = res->quality.tail_ratio;
    res->noise.estimated = cfg_.estimate_noise;
    res->noise.mag_nT = cfg_.estimate_noise ? ml : given_nT;
    res->noise.mag_sigma_nT = cfg_.estimate_noise
                                  ? ml / std::sqrt(Scalar(2) * static_cast<Scalar>(n > 0 ? n : 1))
                                  : Scalar(0);
    res->quality.chi2_per_dof = given_nT > Scalar(0) ? (ml * ml) / (given_nT * given_nT) : 0;
    res->evidence.chi2_per_dof = res->quality.chi2_per_dof;
    res->evidence.noise_nT = res->noise.mag_nT;
  }

  // Calls f(sample, e) with e = R^T Rm^T W (m - o) - F d, the geographic residual of every
  // sample with attitude in use, under a result's model and h_n direction d.
  template <typename F>
  void for_geographic_residuals(const BatchResult<Scalar>& res, F&& f) const noexcept {
    const Mat3<Scalar> rm = res.model.rm_matrix();  // (see mean_direction)
    const Vec3<Scalar> dir = res.h_n_nT.normalized();
    for (std::size_t i = 0; i < store_.size(); ++i) {
      const StoredSample<Scalar>& s = store_[i];
      if (!detail::usable(s)) continue;
      f(s, Vec3<Scalar>(s.r_bn().transpose() *
                            (rm.transpose() * (res.model.w * (s.raw() - res.model.o))) -
                        s.f * dir));
    }
  }

  // Attitude noise of a two-step result from the residual across h_n: E|r_perp|^2 = 2 sm^2 +
  // 2 sa^2 F^2 (isotropic attitude noise, two directions across the field).
  void attitude_noise(BatchResult<Scalar>* res) const noexcept {
    if (!res->has_h_n) return;
    const Vec3<Scalar> dir = res->h_n_nT.normalized();
    Scalar ss{0}, f2{0};
    std::size_t n = 0;
    for_geographic_residuals(*res, [&](const StoredSample<Scalar>& s, const Vec3<Scalar>& e) {
      ss += (e - dir * dir.dot(e)).squaredNorm();
      f2 += s.f * s.f;
      ++n;
    });
    if (n == 0) return;
    const Scalar nn = static_cast<Scalar>(n);
    const Scalar sm2 = res->noise.mag_nT * res->noise.mag_nT;
    const Scalar sa2 = std::max((ss / nn / Scalar(2) - sm2) / (f2 / nn), Scalar(0));
    res->noise.has_attitude = true;
    res->noise.attitude_deg =
        cfg_.estimate_noise ? rad_to_deg(std::sqrt(sa2)) : cfg_.attitude_noise_deg;
    res->noise.attitude_sigma_deg =
        cfg_.estimate_noise ? res->noise.attitude_deg / std::sqrt(Scalar(2) * nn) : Scalar(0);
  }

  EllipsoidSolution<Scalar> robust_ellipsoid(const Normalization<Scalar>& norm, bool need_att,
                                             std::size_t* outliers) noexcept {
    EllipsoidSolution<Scalar> ell;
    *outliers = 0;
    if (!scratch_.ensure(store_.size())) return ell;
    for (int pass = 0; pass < cfg_.outlier_max_passes; ++pass) {
      EllipsoidFit<Scalar> fit;
      fit.set_normalization(norm);
      for (std::size_t i = 0; i < store_.size(); ++i) {
        if (in_use(store_[i], need_att)) fit.add(store_[i].raw(), store_[i].f);
      }
      ell = fit.solve(cfg_.max_iterations);
      if (ell.status != EllipsoidStatus::kOk && ell.status != EllipsoidStatus::kNotConverged)
        return ell;
      // Intensity residuals of the samples in use -> median and MAD.
      std::size_t k = 0;
      for (std::size_t i = 0; i < store_.size(); ++i) {
        const StoredSample<Scalar>& s = store_[i];
        if (!in_use(s, need_att)) continue;
        scratch_.data()[k++] = (ell.w * (s.raw() - ell.o)).norm() - s.f;
      }
      if (k == 0) return ell;
      const Scalar med = median(k);
      for (std::size_t i = 0; i < k; ++i)
        scratch_.data()[i] = std::abs(scratch_.data()[i] - med);
      const Scalar mad = median(k);
      // A relative floor (1e-6 F): never reject residuals at the level of rounding.
      const Scalar thr = std::max(cfg_.outlier_k * Scalar(1.4826) * mad, Scalar(1e-6) * norm.scale);
      bool changed = false;
      std::size_t count = 0;
      for (std::size_t i = 0; i < store_.size(); ++i) {
        StoredSample<Scalar>& s = store_[i];
        if (need_att && !s.has_attitude()) continue;
        const bool out = std::abs((ell.w * (s.raw() - ell.o)).norm() - s.f - med) > thr;
        if (out != s.outlier()) changed = true;
        s.flags = static_cast<std::uint8_t>(out ? (s.flags | kSampleOutlier)
                                                : (s.flags & ~kSampleOutlier));
        count += out ? 1U : 0U;
      }
      *outliers = count;
      if (!changed) break;
    }
    return ell;
  }

  // Median of scratch_[0, k) (reorders it).
  Scalar median(std::size_t k) noexcept {
    auto* first = scratch_.data();
    auto* mid = first + k / 2;
    std::nth_element(first, mid, first + k);
    Scalar m = *mid;
    if (k % 2 == 0) m = Scalar(0.5) * (m + *std::max_element(first, mid));
    return m;
  }

  // RMS spread of the body-frame vertical over the samples with attitude (the moments the vector
  // filter's heading rule and the output envelope use: output_envelope.hpp).
  Scalar tilt_spread() const noexcept {
    TiltMoments<Scalar> tilts;
    for (std::size_t i = 0; i < store_.size(); ++i)
      if (store_[i].has_attitude()) tilts.add(store_[i].r_bn());
    return tilts.spread_rad();
  }

  Scalar intensity_rms(const Mat3<Scalar>& w, const Vec3<Scalar>& o, bool need_att) const noexcept {
    Scalar sse{0};
    std::size_t n = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      if (!in_use(store_[i], need_att)) continue;
      const Scalar r = (w * (store_[i].raw() - o)).norm() - store_[i].f;
      sse += r * r;
      ++n;
    }
    return std::sqrt(sse / static_cast<Scalar>(n > 0 ? n : 1));
  }

  // Quality figures of the final model and the verdict of the acceptance policy.
  void finish(BatchResult<Scalar>* res) const noexcept {
    AcceptanceEvidence<Scalar>& ev = res->evidence;
    const bool need_att = res->method != BatchMethod::kEllipsoidOnly;
    if (res->has_model) {
      res->quality.coverage = coverage(res->model);
      ev.coverage = res->quality.coverage;
    }
    res->quality.intensity_rms_nT = intensity_rms(res->model.w, res->model.o, need_att);
    if (res->has_h_n) {
      Vec3<Scalar> sse = Vec3<Scalar>::Zero();
      std::size_t n = 0;
      for_geographic_residuals(*res, [&](const StoredSample<Scalar>&, const Vec3<Scalar>& e) {
        sse += e.cwiseProduct(e);
        ++n;
      });
      res->quality.enu_rms_nT = (sse / static_cast<Scalar>(n > 0 ? n : 1)).cwiseSqrt();
    }
    ev.min_scale = res->li.ks.minCoeff();
    ev.max_scale = res->li.ks.maxCoeff();
    if (!res->has_model) ev.ill_conditioned = true;
    res->verdict = judge(ev, cfg_.limits);
  }

  BatchConfig<Scalar> cfg_;
  SampleStore<Scalar, Capacity> store_{};
  detail::StoreBuffer<Scalar, Capacity> scratch_{};
  BatchCounts counts_{};
};

template <typename Scalar, std::size_t Capacity>
BatchResult<Scalar> BatchCalibrator<Scalar, Capacity>::solve(BatchMethod method) noexcept {
  BatchResult<Scalar> res;
  res.method = method;
  res.heading_fixed = cfg_.fix_heading_misalignment && method != BatchMethod::kEllipsoidOnly;
  const bool need_att = method != BatchMethod::kEllipsoidOnly;
  const bool given = !cfg_.estimate_noise;
  AcceptanceEvidence<Scalar>& ev = res.evidence;
  for (std::size_t i = 0; i < store_.size(); ++i) {
    store_[i].flags = static_cast<std::uint8_t>(store_[i].flags & ~kSampleOutlier);
  }
  res.counts = counts_;
  std::size_t n_att = 0;
  for (std::size_t i = 0; i < store_.size(); ++i)
    n_att += store_[i].has_attitude() ? 1U : 0U;
  const std::size_t n_avail = need_att ? n_att : store_.size();
  res.counts.used = n_avail;
  ev.rows = counts_.offered;
  ev.usable = n_avail;
  ev.noise_given = given;
  ev.heading_fixed = res.heading_fixed;
  ev.has_prior = cfg_.prior != nullptr && method == BatchMethod::kOneStep;
  medians(need_att, &ev.median_norm_nT, &ev.median_f_nT);
  res.quality.median_norm_nT = ev.median_norm_nT;
  res.quality.median_f_nT = ev.median_f_nT;
  // 1-3 before any fit: rows, units, sample count, pitch/roll variety, raw direction coverage
  // (the field seen from the sensor; offsets are small against |h| for a fluxgate, and a cap
  // stays a cap whatever the offset).
  if (need_att) res.quality.tilt_spread_deg = rad_to_deg(tilt_spread());
  if (need_att) ev.tilt_spread_deg = res.quality.tilt_spread_deg;
  ev.coverage = raw_coverage(need_att);
  res.quality.coverage = ev.coverage;
  Verdict early = judge(ev, cfg_.limits);
  if (early == Verdict::kOk && n_avail < EllipsoidFit<Scalar>::kMinSamples)
    early = Verdict::kTooFewSamples;  // below what the ellipsoid fit needs, whatever the limits
  if (early != Verdict::kOk) {
    res.verdict = early;
    return res;
  }
  const Normalization<Scalar> norm = normalization();
  res.quality.intensity_rms_raw_nT =
      intensity_rms(Mat3<Scalar>::Identity(), Vec3<Scalar>::Zero(), need_att);

  // Ellipsoid with the iterated median/MAD screen.
  EllipsoidSolution<Scalar> ell = robust_ellipsoid(norm, need_att, &res.counts.outliers);
  res.quality.ellipsoid_rcond = ell.rcond;
  res.counts.used = n_avail - res.counts.outliers;
  ev.usable = res.counts.used;
  const bool ell_ok =
      ell.status == EllipsoidStatus::kOk || ell.status == EllipsoidStatus::kNotConverged;
  const bool from_prior = ev.has_prior && need_att;
  if (!ell_ok && !from_prior) {
    ev.not_an_ellipsoid = ell.status == EllipsoidStatus::kNotAnEllipsoid;
    ev.ill_conditioned = ell.status == EllipsoidStatus::kIllConditioned;
    if (ell.status == EllipsoidStatus::kTooFewSamples) ev.usable = 0;
    res.verdict = judge(ev, cfg_.limits);
    return res;
  }
  // Magnetometer noise start (or final, for the ellipsoid): robust scale of |h| - F.
  Scalar mag_noise = cfg_.mag_noise_nT;
  if (cfg_.estimate_noise && ell_ok) {
    const Scalar est = robust_intensity_scale(ell.w, ell.o, need_att);
    if (est > Scalar(0)) mag_noise = est;
  }
  if (method == BatchMethod::kEllipsoidOnly) {
    ell = refine_ellipsoid_geometric(store_, norm, ell, cfg_.max_iterations);
    res.model = ell.model();
    res.has_model = ell.w.allFinite() && ell.o.allFinite();
    res.li = ell.li;
    res.quality.rcond = ell.rcond;
    res.quality.iterations = ell.iterations;
    res.converged = ell.status == EllipsoidStatus::kOk;
    ev.converged = res.converged;
    ev.not_an_ellipsoid = ell.status == EllipsoidStatus::kNotAnEllipsoid;
    ev.ill_conditioned = ell.status == EllipsoidStatus::kIllConditioned;
    intensity_noise(res.model, need_att, mag_noise, &res);
    finish(&res);
    return res;
  }

  MisalignmentOptions<Scalar> mopt;
  mopt.fix_heading = cfg_.fix_heading_misalignment;
  mopt.fixed_heading_rad = deg_to_rad(cfg_.fixed_heading_misalignment_deg);
  mopt.max_sigma_rad = deg_to_rad(cfg_.max_misalignment_sigma_deg);
  mopt.noise_floor = std::hypot(mag_noise / norm.scale, deg_to_rad(cfg_.attitude_noise_deg));
  mopt.max_iterations = cfg_.max_iterations;
  LiParams<Scalar> start = ell.li;
  Vec3<Scalar> d_start = Vec3<Scalar>::UnitY();
  MisalignmentStatus mis_status = MisalignmentStatus::kOk;
  if (from_prior && (!ell_ok || method == BatchMethod::kOneStep)) {
    // The prior is the start: on a cap the ellipsoid is not determined, and near a good prior
    // the MAP fit needs no two-step start.
    start = cfg_.prior->mean;
    d_start = mean_direction(from_li(start));
  } else {
    const MisalignmentSolution<Scalar> mis = method == BatchMethod::kPlaneCompression
                                                 ? plane_compression(store_, ell.w, ell.o, mopt)
                                                 : joint_rm_hn(store_, ell.w, ell.o, mopt);
    start.rm_rad = mis.rm_rad;
    d_start = mis.h_n;
    mis_status = mis.status;
    res.li = start;
    res.sigma.rm_rad = mis.rm_sigma_rad;
    res.has_h_n = mis.has_h_n;
    res.h_n_nT = mis.h_n;
    res.h_n_sigma_nT = mis.h_n_sigma;
    res.quality.rcond = mis.rcond;
    res.quality.iterations = mis.iterations;
    res.converged = mis.status != MisalignmentStatus::kNotConverged;
  }
  res.li = start;
  if (mis_status == MisalignmentStatus::kUnobservableHeading) ev.tilt_spread_deg = 0;
  if (mis_status == MisalignmentStatus::kIllConditioned) ev.ill_conditioned = true;
  if (mis_status == MisalignmentStatus::kTooFewSamples) ev.usable = 0;
  if (mis_status == MisalignmentStatus::kNotConverged) ev.converged = false;
  if (method == BatchMethod::kOneStep && mis_status == MisalignmentStatus::kOk) {
    const OneStepSolution<Scalar> os = OneStepFit<Scalar>::solve(
        store_, norm, start, d_start, one_step_options(mag_noise, cfg_.attitude_noise_deg));
    res.li = os.li;
    res.sigma = os.sigma;
    res.h_n_nT = os.h_n;
    res.h_n_sigma_nT = os.h_n_sigma;
    res.calibration_sigma_enu_nT = os.calibration_sigma_enu_nT;
    res.calibration_sigma_f_nT = os.calibration_sigma_f_nT;
    res.has_h_n = true;
    res.cost = os.cost;
    res.converged = os.converged;
    res.quality.rcond = os.rcond;
    res.quality.chi2_per_dof = os.chi2_per_dof;
    res.quality.iterations = os.iterations;
    res.quality.tail_ratio = os.tail_ratio;
    res.quality.undetermined = os.undetermined;
    res.quality.updated = os.updated;
    res.quality.moved = os.moved;
    res.noise.estimated = os.noise_estimated;
    res.noise.mag_nT = os.mag_noise_nT;
    res.noise.mag_sigma_nT = os.mag_noise_sigma_nT;
    res.noise.has_attitude = true;
    res.noise.attitude_deg = rad_to_deg(os.attitude_noise_rad);
    res.noise.attitude_sigma_deg = rad_to_deg(os.attitude_noise_sigma_rad);
    ev.converged = os.converged;
    ev.undetermined = os.undetermined;
    ev.tail_ratio = os.tail_ratio;
    ev.chi2_per_dof = os.chi2_per_dof;
    ev.noise_nT = os.mag_noise_nT;
    if (os.status == OneStepStatus::kIllConditioned) ev.ill_conditioned = true;
    if (os.status == OneStepStatus::kUnobservableHeading && !ev.has_prior) ev.tilt_spread_deg = 0;
    if (os.status == OneStepStatus::kTooFewSamples) ev.usable = 0;
  }
  res.model = from_li(res.li);
  res.has_model = res.model.w.allFinite() && res.model.o.allFinite();
  if (method != BatchMethod::kOneStep) {
    intensity_noise(res.model, need_att, mag_noise, &res);
    attitude_noise(&res);
  }
  finish(&res);
  return res;
}

template <typename Scalar, std::size_t Capacity>
OneStepSolution<Scalar> BatchCalibrator<Scalar, Capacity>::refit_one_step(
    const BatchResult<Scalar>& from) const noexcept {
  OneStepOptions<Scalar> o = one_step_options(from.noise.mag_nT, from.noise.attitude_deg);
  o.estimate_noise = false;
  o.scale_sigma_by_residual = false;
  return OneStepFit<Scalar>::solve(store_, normalization(), from.li, from.h_n_nT, o);
}

// The magnetometer-INS time offset of a batch fit's set (docs/equations.md E-TO-4). The one-step
// fit has no time offset, so a latency nobody configured is taken for attitude noise and absorbed
// into Rm and h_n. The fit's n-frame residuals e_i = g_i - h_n (g_i = R_i^T Rm^T W (m_i - o)) are
// regressed on d_i = Omega_i x g_i (moving the attitude to t - lag changes e_i by -lag d_i):
// lag += (d . e) / (d . d); the stored attitudes are moved by the step and the set is fitted
// again, up to `passes` times. A step within twice its standard error (no rotation to see it by)
// ends it. On return the batch holds the moved set and *res its fit; the lag is the total move
// (0: none). omega_of(i): sample i's rotation rate (n-frame axes, rad/s; zero when unknown).
template <typename Scalar, std::size_t Capacity, typename OmegaOf>
Scalar fit_time_offset(BatchCalibrator<Scalar, Capacity>* batch, BatchMethod method,
                       Scalar max_abs_s, OmegaOf&& omega_of, BatchResult<Scalar>* res,
                       int passes = 3) noexcept {
  Scalar lag{0};
  const std::size_t n = batch->store().size();
  for (int pass = 0; pass < passes; ++pass) {
    if (!res->has_model || !res->has_h_n) break;
    const Mat3<Scalar> rmt = res->model.rm.toRotationMatrix().transpose();
    Scalar num{0}, den{0}, ee{0};
    std::size_t used = 0;
    for (std::size_t i = 0; i < n; ++i) {
      const StoredSample<Scalar>& s = batch->store()[i];
      if (!s.has_attitude() || s.outlier()) continue;
      const Vec3<Scalar> g =
          s.r_bn().transpose() * (rmt * (res->model.w * (s.raw() - res->model.o)));
      const Vec3<Scalar> d = omega_of(i).cross(g);
      const Vec3<Scalar> e = g - res->h_n_nT;
      num += d.dot(e);
      den += d.dot(d);
      ee += e.dot(e);
      ++used;
    }
    if (!(den > Scalar(0)) || used < 2) break;
    const Scalar step = num / den;
    const Scalar s2 = std::max(ee - step * num, Scalar(0)) / static_cast<Scalar>(3 * used - 1);
    if (!std::isfinite(step) || step * step <= Scalar(4) * s2 / den) break;
    const Scalar next = std::clamp(lag + step, -max_abs_s, max_abs_s);
    const Scalar move = next - lag;
    batch->shift_attitudes(n, move, omega_of);
    BatchResult<Scalar> again = batch->solve(method);
    if (!again.has_model) {
      batch->shift_attitudes(n, -move, omega_of);
      break;
    }
    *res = again;
    lag = next;
  }
  return lag;
}

// Compiled once for the host's capacities (firmware/core/src/inst_batch_calibrator_double.cpp,
// the magvec::core_batch_double library; float at the vector filter's capacity in
// magvec::core_batch_float): a unit that instantiates the batch solve costs about
// two minutes of compile time, so the units that use these only call it. solve() and
// refit_one_step() are defined outside the class because GCC instantiates in-class (implicitly
// inline) members for inlining even under `extern template`. A unit sees these declarations when
// it links that library (its compile definition); any other unit instantiates its own.
#ifdef MAGVEC_CORE_BATCH_DOUBLE_COMPILED
extern template class BatchCalibrator<double, 64>;    // the vector filter's start from data
extern template class BatchCalibrator<double, 512>;   // the host's li calibrator
extern template class BatchCalibrator<double, 1024>;  // core tests
extern template class BatchCalibrator<double, kDynamicCapacity>;  // batch over recordings
#endif
#ifdef MAGVEC_CORE_BATCH_FLOAT_COMPILED
extern template class BatchCalibrator<float, 64>;  // the float vector filter's start from data
#endif

}  // namespace magvec::core
