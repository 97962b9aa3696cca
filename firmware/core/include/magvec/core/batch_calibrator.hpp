// Batch calibration entry point (issue 3): collects samples {raw m, scalar reference F, R_bn} in a
// fixed-capacity store and solves Li et al. 2023 as corrected by ERRATA 000:
//   kEllipsoidOnly    ellipsoid fit (algebraic + geometric refinement), no attitude needed
//   kPlaneCompression ellipsoid + plane compression (Li's two-step method, 000-2/3)
//   kJoint            ellipsoid + joint fit of Rm and h_n (000-5)
//   kOneStep          the above as a start, then the 14-parameter weighted fit (000-6; default)
// Robustness: non-finite rows are skipped and counted; outliers are rejected by an iterated
// median/MAD screen on the intensity residual |W(m - o)| - F and counted. Quality: coverage of the
// sphere of field directions (fraction of 32 equal-area cells hit), conditioning, residuals; a
// specific Verdict for every refusal, never a silent bad calibration.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/sample_store.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

enum class BatchMethod : std::uint8_t { kEllipsoidOnly, kPlaneCompression, kJoint, kOneStep };

enum class Verdict : std::uint8_t {
  kOk,
  kTooFewSamples,
  kNotAnEllipsoid,
  kIllConditioned,
  kInsufficientCoverage,
  kFieldMismatch,                    // data and scalar reference disagree (residual or scale)
  kUnobservableHeadingMisalignment,  // no pitch/roll variety (ERRATA 000-4)
  kResidualTooLarge,                 // vector residuals far above the stated noise
  kNotConverged,
};

inline const char* verdict_name(Verdict v) noexcept {
  switch (v) {
    case Verdict::kOk:
      return "ok";
    case Verdict::kTooFewSamples:
      return "too_few_samples";
    case Verdict::kNotAnEllipsoid:
      return "not_an_ellipsoid";
    case Verdict::kIllConditioned:
      return "ill_conditioned";
    case Verdict::kInsufficientCoverage:
      return "insufficient_coverage";
    case Verdict::kFieldMismatch:
      return "field_mismatch";
    case Verdict::kUnobservableHeadingMisalignment:
      return "unobservable_heading_misalignment";
    case Verdict::kResidualTooLarge:
      return "residual_too_large";
    case Verdict::kNotConverged:
      return "not_converged";
  }
  return "unknown";
}

enum class AddStatus : std::uint8_t { kAccepted, kSkippedNonFinite, kStoreFull };

template <typename Scalar>
struct BatchConfig {
  Scalar field_nT = std::numeric_limits<Scalar>::quiet_NaN();  // used when a sample's F is NaN
  Scalar mag_noise_nT = Scalar(0.3);                           // per axis, 1-sigma
  Scalar attitude_noise_deg = Scalar(0.015);                   // per INS angle, 1-sigma
  AttitudeNoiseModel attitude_model = AttitudeNoiseModel::kLiEuler;
  bool fix_heading_misalignment = false;  // hold am (ERRATA 000-4) instead of refusing
  Scalar fixed_heading_misalignment_deg{0};
  std::size_t min_samples = 12;
  Scalar min_coverage = Scalar(0.2);
  Scalar min_tilt_spread_deg = Scalar(2);  // RMS spread of the body-frame vertical
  Scalar max_misalignment_sigma_deg = Scalar(0.5);
  Scalar max_intensity_rms_nT = Scalar(50);
  Scalar min_scale = Scalar(0.5), max_scale = Scalar(2);
  Scalar max_chi2_per_dof = Scalar(25);
  Scalar outlier_k = Scalar(5);         // threshold in robust SDs (1.4826 MAD)
  Scalar outlier_floor_nT = Scalar(1);  // never reject below this intensity residual
  int outlier_max_passes = 8;
  int max_iterations = 30;
};

template <typename Scalar>
struct BatchQuality {
  Scalar coverage{0};  // fraction of 32 equal-area direction cells containing data
  Scalar rcond{0};     // of the final solver's scaled normal matrix
  Scalar ellipsoid_rcond{0};
  Scalar tilt_spread_deg{0};                       // RMS spread of the vertical in body axes
  Scalar intensity_rms_raw_nT{0};                  // |m| - F before calibration
  Scalar intensity_rms_nT{0};                      // |W(m - o)| - F after
  Vec3<Scalar> enu_rms_nT = Vec3<Scalar>::Zero();  // spread of R^T Rm^T h_s about h_n (E, N, U)
  Scalar chi2_per_dof{0};                          // one-step only
  int iterations{0};
};

struct BatchCounts {
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
  LiParams<Scalar> li{};
  LiSigmas<Scalar> sigma{};  // one-step: full; two-step: Rm only
  bool has_h_n = false;
  Vec3<Scalar> h_n_nT = Vec3<Scalar>::Zero();
  Vec3<Scalar> h_n_sigma_nT = Vec3<Scalar>::Zero();
  bool heading_fixed = false;
  BatchQuality<Scalar> quality{};
  BatchCounts counts{};

  bool ok() const noexcept { return verdict == Verdict::kOk; }
};

template <typename Scalar, std::size_t Capacity>
class BatchCalibrator {
 public:
  static constexpr std::size_t kCapacity = Capacity;
  static constexpr int kCoverageBands = 4, kCoverageSectors = 8;  // 32 equal-area cells

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
  AddStatus add_sample(const Vec3<Scalar>& m, Scalar f_nT, const Mat3<Scalar>& r_bn) noexcept {
    return add(m, f_nT, &r_bn);
  }
  // Scalar-only sample (kEllipsoidOnly).
  AddStatus add_sample(const Vec3<Scalar>& m, Scalar f_nT) noexcept {
    return add(m, f_nT, nullptr);
  }

  BatchResult<Scalar> solve(BatchMethod method = BatchMethod::kOneStep) noexcept {
    BatchResult<Scalar> res;
    res.method = method;
    res.heading_fixed = cfg_.fix_heading_misalignment && method != BatchMethod::kEllipsoidOnly;
    const bool need_att = method != BatchMethod::kEllipsoidOnly;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      store_[i].flags = static_cast<std::uint8_t>(store_[i].flags & ~kSampleOutlier);
    }
    res.counts = counts_;
    std::size_t n_att = 0;
    for (std::size_t i = 0; i < store_.size(); ++i)
      n_att += store_[i].has_attitude() ? 1U : 0U;
    const std::size_t n_avail = need_att ? n_att : store_.size();
    res.counts.used = n_avail;
    if (n_avail < cfg_.min_samples || n_avail < EllipsoidFit<Scalar>::kMinSamples) {
      res.verdict = Verdict::kTooFewSamples;
      return res;
    }
    const Normalization<Scalar> norm = normalization();
    res.quality.intensity_rms_raw_nT =
        intensity_rms(Mat3<Scalar>::Identity(), Vec3<Scalar>::Zero());
    // Pitch/roll variety first: without it neither the misalignment nor the ellipsoid is defined,
    // and the root cause is the attitude set (ERRATA 000-4).
    if (need_att) {
      res.quality.tilt_spread_deg = rad_to_deg(tilt_spread());
      if (res.quality.tilt_spread_deg < cfg_.min_tilt_spread_deg &&
          !cfg_.fix_heading_misalignment) {
        res.verdict = Verdict::kUnobservableHeadingMisalignment;
        return res;
      }
    }
    // Ellipsoid with the iterated median/MAD screen.
    EllipsoidSolution<Scalar> ell = robust_ellipsoid(norm, need_att, &res.counts.outliers);
    res.quality.ellipsoid_rcond = ell.rcond;
    res.counts.used = n_avail - res.counts.outliers;
    if (ell.status == EllipsoidStatus::kTooFewSamples) {
      res.verdict = Verdict::kTooFewSamples;
      return res;
    }
    if (ell.status == EllipsoidStatus::kNotAnEllipsoid) {
      res.verdict = Verdict::kNotAnEllipsoid;
      return res;
    }
    if (ell.status == EllipsoidStatus::kIllConditioned) {
      res.verdict = Verdict::kIllConditioned;
      return res;
    }
    if (method == BatchMethod::kEllipsoidOnly) {
      ell = refine_ellipsoid_geometric(store_, norm, ell, cfg_.max_iterations);
      res.model = ell.model();
      res.li = ell.li;
      res.quality.rcond = ell.rcond;
      res.quality.iterations = ell.iterations;
      finish(&res, ell.status == EllipsoidStatus::kOk ? Verdict::kOk : Verdict::kNotConverged);
      return res;
    }

    MisalignmentOptions<Scalar> mopt;
    mopt.fix_heading = cfg_.fix_heading_misalignment;
    mopt.fixed_heading_rad = deg_to_rad(cfg_.fixed_heading_misalignment_deg);
    mopt.max_sigma_rad = deg_to_rad(cfg_.max_misalignment_sigma_deg);
    mopt.noise_floor =
        std::hypot(cfg_.mag_noise_nT / norm.scale, deg_to_rad(cfg_.attitude_noise_deg));
    mopt.max_iterations = cfg_.max_iterations;
    const MisalignmentSolution<Scalar> mis = method == BatchMethod::kPlaneCompression
                                                 ? plane_compression(store_, ell.w, ell.o, mopt)
                                                 : joint_rm_hn(store_, ell.w, ell.o, mopt);
    res.li = ell.li;
    res.li.rm_rad = mis.rm_rad;
    res.sigma.rm_rad = mis.rm_sigma_rad;
    res.has_h_n = mis.has_h_n;
    res.h_n_nT = mis.h_n;
    res.h_n_sigma_nT = mis.h_n_sigma;
    res.quality.rcond = mis.rcond;
    res.quality.iterations = mis.iterations;
    Verdict v = Verdict::kOk;
    if (mis.status == MisalignmentStatus::kUnobservableHeading)
      v = Verdict::kUnobservableHeadingMisalignment;
    if (mis.status == MisalignmentStatus::kIllConditioned) v = Verdict::kIllConditioned;
    if (mis.status == MisalignmentStatus::kNotConverged) v = Verdict::kNotConverged;
    if (mis.status == MisalignmentStatus::kTooFewSamples) v = Verdict::kTooFewSamples;
    if (method == BatchMethod::kOneStep && v == Verdict::kOk) {
      OneStepOptions<Scalar> oopt;
      oopt.mag_noise_nT = cfg_.mag_noise_nT;
      oopt.attitude_noise_rad = deg_to_rad(cfg_.attitude_noise_deg);
      oopt.attitude_model = cfg_.attitude_model;
      oopt.fix_heading = cfg_.fix_heading_misalignment;
      oopt.max_rm_sigma_rad = deg_to_rad(cfg_.max_misalignment_sigma_deg);
      oopt.max_iterations = cfg_.max_iterations;
      const OneStepSolution<Scalar> os =
          OneStepFit<Scalar>::solve(store_, norm, res.li, mis.h_n, oopt);
      res.li = os.li;
      res.sigma = os.sigma;
      res.h_n_nT = os.h_n;
      res.h_n_sigma_nT = os.h_n_sigma;
      res.has_h_n = true;
      res.quality.rcond = os.rcond;
      res.quality.chi2_per_dof = os.chi2_per_dof;
      res.quality.iterations = os.iterations;
      switch (os.status) {
        case OneStepStatus::kOk:
          break;
        case OneStepStatus::kTooFewSamples:
          v = Verdict::kTooFewSamples;
          break;
        case OneStepStatus::kUnobservableHeading:
          v = Verdict::kUnobservableHeadingMisalignment;
          break;
        case OneStepStatus::kIllConditioned:
          v = Verdict::kIllConditioned;
          break;
        case OneStepStatus::kNotConverged:
          v = Verdict::kNotConverged;
          break;
      }
      if (v == Verdict::kOk && os.chi2_per_dof > cfg_.max_chi2_per_dof)
        v = Verdict::kResidualTooLarge;
    }
    res.model = from_li(res.li);
    finish(&res, v);
    return res;
  }

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

  // Fraction of 32 equal-area cells (4 bands equal in z, 8 sectors) hit by the directions of
  // h_s = W (m - o) of the samples in use.
  Scalar coverage(const SensorModel<Scalar>& model) const noexcept {
    std::uint32_t cells = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      if (store_[i].outlier()) continue;
      const Vec3<Scalar> h = model.w * (store_[i].raw() - model.o);
      const Scalar len = h.norm();
      if (!(len > Scalar(0))) continue;
      const Vec3<Scalar> d = h / len;
      int band = static_cast<int>((d(2) + Scalar(1)) * Scalar(0.5) * Scalar(kCoverageBands));
      band = std::clamp(band, 0, kCoverageBands - 1);
      const Scalar az = std::atan2(d(1), d(0)) + kPi<Scalar>;
      int sector = static_cast<int>(az / (Scalar(2) * kPi<Scalar>)*Scalar(kCoverageSectors));
      sector = std::clamp(sector, 0, kCoverageSectors - 1);
      cells |= 1U << static_cast<unsigned>(band * kCoverageSectors + sector);
    }
    int hit = 0;
    for (unsigned k = 0; k < 32U; ++k)
      hit += static_cast<int>((cells >> k) & 1U);
    return static_cast<Scalar>(hit) / Scalar(kCoverageBands * kCoverageSectors);
  }

 private:
  AddStatus add(const Vec3<Scalar>& m, Scalar f, const Mat3<Scalar>* r_bn) noexcept {
    if (!std::isfinite(f)) f = cfg_.field_nT;
    const bool bad_att = r_bn != nullptr && !r_bn->allFinite();
    if (!m.allFinite() || !std::isfinite(f) || !(f > Scalar(0)) || bad_att) {
      ++counts_.skipped_nonfinite;
      return AddStatus::kSkippedNonFinite;
    }
    if (!store_.push(m, f, r_bn)) {
      ++counts_.dropped_full;
      return AddStatus::kStoreFull;
    }
    ++counts_.added;
    return AddStatus::kAccepted;
  }

  bool in_use(const StoredSample<Scalar>& s, bool need_att) const noexcept {
    return (!need_att || s.has_attitude()) && !s.outlier();
  }

  EllipsoidSolution<Scalar> robust_ellipsoid(const Normalization<Scalar>& norm, bool need_att,
                                             std::size_t* outliers) noexcept {
    EllipsoidSolution<Scalar> ell;
    *outliers = 0;
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
        scratch_[k++] = (ell.w * (s.raw() - ell.o)).norm() - s.f;
      }
      if (k == 0) return ell;
      const Scalar med = median(k);
      for (std::size_t i = 0; i < k; ++i)
        scratch_[i] = std::abs(scratch_[i] - med);
      const Scalar mad = median(k);
      const Scalar thr = std::max(cfg_.outlier_k * Scalar(1.4826) * mad, cfg_.outlier_floor_nT);
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

  Scalar tilt_spread() const noexcept {
    Vec3<Scalar> sum = Vec3<Scalar>::Zero();
    Mat3<Scalar> sq = Mat3<Scalar>::Zero();
    std::size_t n = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      if (!store_[i].has_attitude()) continue;
      const Vec3<Scalar> u = store_[i].r_bn().col(2);
      sum += u;
      sq += u * u.transpose();
      ++n;
    }
    if (n == 0) return Scalar(0);
    const Scalar nn = static_cast<Scalar>(n);
    const Mat3<Scalar> cov = sq / nn - (sum / nn) * (sum / nn).transpose();
    return std::sqrt(std::max(cov.trace(), Scalar(0)));
  }

  Scalar intensity_rms(const Mat3<Scalar>& w, const Vec3<Scalar>& o) const noexcept {
    Scalar sse{0};
    std::size_t n = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      if (store_[i].outlier()) continue;
      const Scalar r = (w * (store_[i].raw() - o)).norm() - store_[i].f;
      sse += r * r;
      ++n;
    }
    return std::sqrt(sse / static_cast<Scalar>(n > 0 ? n : 1));
  }

  // Quality figures of the final model and the acceptance thresholds.
  void finish(BatchResult<Scalar>* res, Verdict v) const noexcept {
    res->quality.coverage = coverage(res->model);
    res->quality.intensity_rms_nT = intensity_rms(res->model.w, res->model.o);
    if (res->has_h_n) {
      const Mat3<Scalar> rmt = res->model.rm_matrix().transpose();
      const Vec3<Scalar> dir = res->h_n_nT.normalized();
      Vec3<Scalar> sse = Vec3<Scalar>::Zero();
      std::size_t n = 0;
      for (std::size_t i = 0; i < store_.size(); ++i) {
        const StoredSample<Scalar>& s = store_[i];
        if (!detail::usable(s)) continue;
        const Vec3<Scalar> e =
            s.r_bn().transpose() * (rmt * (res->model.w * (s.raw() - res->model.o))) - s.f * dir;
        sse += e.cwiseProduct(e);
        ++n;
      }
      res->quality.enu_rms_nT = (sse / static_cast<Scalar>(n > 0 ? n : 1)).cwiseSqrt();
    }
    const bool scale_ok = (res->li.ks.array() >= cfg_.min_scale).all() &&
                          (res->li.ks.array() <= cfg_.max_scale).all();
    if (v == Verdict::kOk && res->quality.coverage < cfg_.min_coverage)
      v = Verdict::kInsufficientCoverage;
    if (v == Verdict::kOk &&
        (!scale_ok || !(res->quality.intensity_rms_nT <= cfg_.max_intensity_rms_nT))) {
      v = Verdict::kFieldMismatch;
    }
    if (v == Verdict::kOk && !(res->model.w.allFinite() && res->model.o.allFinite()))
      v = Verdict::kIllConditioned;
    res->verdict = v;
  }

  BatchConfig<Scalar> cfg_;
  SampleStore<Scalar, Capacity> store_{};
  std::array<Scalar, Capacity> scratch_{};
  BatchCounts counts_{};
};

}  // namespace magvec::core
