// EkfCalibrator: the online scalar EKF of Ge et al. 2017 (docs/equations.md E-Ge; scalar_ekf.hpp)
// behind the SensorLoop Calibrator contract (sensor_loop.hpp), plus the misalignment step it needs
// to give vector output.
//
// Why a misalignment step (DECISION): a scalar (|h|) method observes only G = W^T W and o
// (docs/equations.md E-Ge-2): the EKF's W is known up to an arbitrary rotation and its Rm is the
// identity, so h_n computed from an EKF-only model is rotated away from the INS frame by that
// unknown rotation (degrees to tens of degrees: the EKF pins W upper-triangular). Vector output
// therefore needs attitude. With `align` on (default) the adapter keeps a small motion-decimated
// store of {raw m, F, R_bn} while the filter runs and, at solve(), fits the rotation and the local
// field with the joint fit of docs/equations.md E-Li-5 (misalignment.hpp joint_rm_hn, closed-form
// start, so a large rotation is fine) for the EKF's (W, o); the result is re-expressed in Li form
// (canonicalize_li). If the attitudes do not determine the rotation the solve is refused
// (kAlignUnobservable etc.): never a silently misaligned calibration. With `align` off the model
// is the filter's (Rm = I) and aligned() is false: only |h| and h_s are meaningful; the
// caller must not publish h_n (documented, and reported by `magvec run`).
//
// add(): every finite sample updates the filter (attitude not needed); EkfStatus::kGated ->
// CalibratorAdd::kGated, non-finite sample or unusable reference -> kRejected, else kUsed.
// ready(): the filter is initialised, has made >= min_updates accepted updates since begin(), the
// predicted 1-sigma of the calibrated intensity at the last sample is <= max_sigma_f_nT, and (with
// align) the alignment store holds >= min_align_samples samples.
// The calibration's own 1-sigmas over the survey envelope (CalibratorSolve::calibration_sigma_*,
// docs/equations.md E-Acc-3) come from the filter's covariance once its start-up term has been
// relinearised (scalar_ekf.hpp relinearise_start); E/N/U also through the alignment fit's
// response and its own noise. Over 60 survey runs the |h| scatter is 0.95-1.11x that figure from
// 3 000 updates on, 1.5x at the default readiness (2 000, a heavy tail); E/N/U 1.00-1.14x.
// Heap-free, noexcept, Scalar-templated (float and double).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/output_envelope.hpp"
#include "magvec/core/sample_store.hpp"
#include "magvec/core/scalar_ekf.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

// CalibratorSolve::code of EkfCalibrator refusals.
enum class EkfCalCode : std::uint8_t {
  kOk = 0,
  kNotInitialised = 1,      // the filter has no initial fit yet
  kAlignTooFewSamples = 2,  // not enough attitude samples for the misalignment fit
  kAlignUnobservable = 3,   // no pitch/roll variety: rotation about the vertical undetermined
  kAlignIllConditioned = 4,
  kAlignNotConverged = 5,
  kNotLiRepresentable = 6,  // W singular or a reflection
};

inline const char* ekf_cal_code_name(std::uint8_t code) noexcept {
  switch (static_cast<EkfCalCode>(code)) {
    case EkfCalCode::kOk:
      return "ok";
    case EkfCalCode::kNotInitialised:
      return "ekf_not_initialised";
    case EkfCalCode::kAlignTooFewSamples:
      return "alignment_too_few_samples";
    case EkfCalCode::kAlignUnobservable:
      return "alignment_unobservable_heading";
    case EkfCalCode::kAlignIllConditioned:
      return "alignment_ill_conditioned";
    case EkfCalCode::kAlignNotConverged:
      return "alignment_not_converged";
    case EkfCalCode::kNotLiRepresentable:
      return "model_not_li_representable";
  }
  return "unknown";
}

template <typename Scalar>
struct EkfCalibratorConfig {
  EkfConfig<Scalar> ekf{};
  std::uint32_t min_updates = 2000;  // accepted filter updates after the initial fit
  Scalar max_sigma_f_nT{Scalar(0.1)};
  bool align = true;
  Scalar align_min_step_deg{2};  // decimation of the alignment store (attitude change)
  std::size_t min_align_samples = 100;
  MisalignmentOptions<Scalar> misalignment{};
};

template <typename Scalar, std::size_t AlignCapacity = 256, int InitCapacity = 64>
class EkfCalibrator {
  static_assert(CoreScalar<Scalar>);
  static_assert(AlignCapacity >= 16, "the misalignment fit needs well over 9 samples");

 public:
  using Config = EkfCalibratorConfig<Scalar>;
  using Filter = ScalarEkf<Scalar, InitCapacity>;

  explicit EkfCalibrator(const Config& config = Config{}) noexcept
      : cfg_(config), ekf_(config.ekf) {
    begin();
  }

  void configure(const Config& config) noexcept {
    cfg_ = config;
    begin();
  }
  const Config& config() const noexcept { return cfg_; }

  // --- SensorLoop Calibrator contract ---------------------------------------------------------
  void begin() noexcept {
    ekf_.configure(cfg_.ekf);
    store_.clear();
    tilts_.reset();
    updates_at_begin_ = 0;
    have_last_ = false;
    have_m_ = false;
    aligned_ = false;
    align_ = MisalignmentSolution<Scalar>{};
  }

  CalibratorAdd add(const Vec3<Scalar>& m, Scalar f_ref_nT, const Mat3<Scalar>* r_bn) noexcept;

  Scalar progress() const noexcept {
    if (!ekf_.initialised()) return Scalar(0);
    const Scalar pu = static_cast<Scalar>(updates()) /
                      static_cast<Scalar>(std::max<std::uint32_t>(cfg_.min_updates, 1U));
    const Scalar sig = sigma_f_nT();
    const Scalar ps = sig > 0 ? cfg_.max_sigma_f_nT / sig : Scalar(1);
    Scalar p = std::min(pu, ps);
    if (cfg_.align) {
      p = std::min(p, static_cast<Scalar>(store_.size()) /
                          static_cast<Scalar>(std::max<std::size_t>(min_align(), 1)));
    }
    return std::clamp(p, Scalar(0), Scalar(1));
  }

  bool ready() const noexcept {
    if (!ekf_.initialised() || updates() < cfg_.min_updates) return false;
    if (cfg_.align && store_.size() < min_align()) return false;
    return sigma_f_nT() <= cfg_.max_sigma_f_nT;
  }

  CalibratorSolve solve(SensorModel<Scalar>* out) noexcept;

  // --- diagnostics ------------------------------------------------------------------------------
  // True when the last solved model is aligned to the INS (Rm fitted): h_n is meaningful.
  bool aligned() const noexcept { return aligned_; }
  const MisalignmentSolution<Scalar>& alignment() const noexcept { return align_; }
  const Filter& filter() const noexcept { return ekf_; }
  std::uint32_t updates() const noexcept { return ekf_.counters().updates - updates_at_begin_; }
  std::size_t align_samples() const noexcept { return store_.size(); }
  std::size_t align_samples_needed() const noexcept { return min_align(); }
  // The motion-decimated {m, F, R_bn} samples kept for the misalignment fit.
  const SampleStore<Scalar, AlignCapacity>& alignment_store() const noexcept { return store_; }
  // The tilts of the samples the filter used (the survey envelope's, E-Acc-3).
  const TiltMoments<Scalar>& tilt_moments() const noexcept { return tilts_; }
  // The calibration's own 1-sigmas over the survey envelope (E-Acc-3, output_envelope.hpp's
  // EnvelopeGram): per-axis E/N/U and |h|, for `model` (any form with the filter's map Rm^T W and
  // offset, e.g. the solved one) and the fitted field h_n [nT]. The filter's covariance of
  // x = (C^-1, b) goes through g = R_bn^T Rm^T W (m - o) with the alignment fit's first-order
  // response (its refitted rotation absorbs part of the error: the phi rows of -N_tt^-1 N_tx of its
  // normal equations over the store), and the fit's own noise enters as three more parameters
  // with the sandwich covariance N_tt^-1 (sum B^T S B) N_tt^-1, S the residuals' covariance along
  // and across the field. (|h| sees neither rotation term.) NaN without a start, tilts or enough
  // attitudes. Cold: runs once per solve (on the M4F image, inlined, it had pushed per-sample
  // helpers out of line; see MAGVEC_APP_CORE_INLINE in firmware/app/CMakeLists.txt).
  struct OutputSigmas {
    Scalar f_nT{std::numeric_limits<Scalar>::quiet_NaN()};
    Scalar enu_nT{std::numeric_limits<Scalar>::quiet_NaN()};
  };
  [[gnu::cold]] OutputSigmas output_sigmas(const SensorModel<Scalar>& model,
                                           const Vec3<Scalar>& h_n) const noexcept {
    constexpr int kN = kEkfStateDim;
    using Mat6 = Mat<Scalar, 6, 6>;
    using Jx = Mat<Scalar, 3, kN>;
    OutputSigmas out;
    const Scalar hn = h_n.norm();
    if (!ekf_.initialised() || !(hn > Scalar(0))) return out;
    const Mat3<Scalar> w = ekf_.c_inv();
    const Vec3<Scalar> o = ekf_.offset_nT();
    // The fitted misalignment in the filter's frame: Rm^T = (Rm^T W of the model) W_filter^-1.
    const Mat3<Scalar> rmt = model.rm_matrix().transpose() * model.w * w.inverse();
    // du/dx for u = W (m - o): W row-major (ekf_w_index), then o.
    const auto du_dx = [&](const Vec3<Scalar>& m) noexcept {
      Jx j = Jx::Zero();
      const Vec3<Scalar> v = m - o;
      for (int r = 0; r < 3; ++r)
        for (int c = 0; c < 3; ++c)
          j(r, ekf_w_index(r, c)) = v(c);
      j.template rightCols<3>() = -w;
      return j;
    };
    // The alignment fit's normal equations in theta = (phi, h_n) and across to x, and the residuals
    // along the field d and across it; B_i = [R_i^T [h_b]x, -I].
    const Vec3<Scalar> d = h_n / hn;
    Mat6 n_tt = Mat6::Zero();
    Mat6 n_dd = Mat6::Zero();  // sum (B^T d)(B^T d)^T
    Mat<Scalar, 6, kN> n_tx = Mat<Scalar, 6, kN>::Zero();
    Scalar ss_par{0}, ss_perp{0};
    int n = 0;
    for (std::size_t i = 0; i < store_.size(); ++i) {
      const StoredSample<Scalar>& st = store_[i];
      if (!st.has_attitude() || st.outlier()) continue;
      const Mat3<Scalar> rt = st.r_bn().transpose();
      const Vec3<Scalar> hb = rmt * (w * (st.raw() - o));
      Mat<Scalar, 3, 6> b;
      b.template leftCols<3>() = rt * skew(hb);
      b.template rightCols<3>() = -Mat3<Scalar>::Identity();
      const Vec<Scalar, 6> bd = b.transpose() * d;
      n_tt.noalias() += b.transpose() * b;
      n_dd.noalias() += bd * bd.transpose();
      n_tx.noalias() += b.transpose() * (rt * rmt * du_dx(st.raw()));
      const Vec3<Scalar> e = rt * hb - h_n;
      const Scalar ep = e.dot(d);
      ss_par += ep * ep;
      ss_perp += e.squaredNorm() - ep * ep;
      ++n;
    }
    if (n < 3) return out;
    const Eigen::LDLT<Mat6> ldlt(n_tt);
    if (ldlt.info() != Eigen::Success || !ldlt.isPositive()) return out;
    Mat<Scalar, 6, 3> ninv_phi;  // the phi columns of N_tt^-1
    for (int c = 0; c < 3; ++c) {
      Vec<Scalar, 6> e = Vec<Scalar, 6>::Zero();
      e(c) = Scalar(1);
      ninv_phi.col(c) = ldlt.solve(e);
    }
    const Mat<Scalar, 3, kN> s_phi = -(ninv_phi.transpose() * n_tx);  // d(phi)/dx
    // S = v_perp I + (v_par - v_perp) d d^T (the attitude noise moves the field only across
    // itself; degrees of freedom 3 n - 6 shared in proportion), so sum B^T S B from the two sums.
    const Scalar dof = static_cast<Scalar>(3 * n) / static_cast<Scalar>(3 * n - 6);
    const Scalar v_par = dof * ss_par / static_cast<Scalar>(n);
    const Scalar v_perp = dof * ss_perp / static_cast<Scalar>(2 * n);
    const Mat6 meat = v_perp * n_tt + (v_par - v_perp) * n_dd;
    // Parameters (x, phi noise), block-diagonal covariance.
    Mat<Scalar, kN + 3, kN + 3> p = Mat<Scalar, kN + 3, kN + 3>::Zero();
    p.template topLeftCorner<kN, kN>() = ekf_.covariance();
    p.template bottomRightCorner<3, 3>() = ninv_phi.transpose() * meat * ninv_phi;
    EnvelopeGram<Scalar, kN + 3> gram;
    const bool ok = for_each_envelope_attitude(tilts_, [&](const Mat3<Scalar>& r_bn) {
      const Vec3<Scalar> m = model.predict_raw(r_bn, h_n);
      const Mat3<Scalar> rt = r_bn.transpose();
      const Vec3<Scalar> hb = rmt * (w * (m - o));
      const Vec3<Scalar> g = rt * hb;
      const Scalar gn = g.norm();
      if (!(gn > Scalar(0))) return;
      const Mat3<Scalar> j_phi = rt * skew(hb);
      Mat<Scalar, 3, kN + 3> j;
      j.template leftCols<kN>() = rt * rmt * du_dx(m) + j_phi * s_phi;
      j.template rightCols<3>() = j_phi;
      gram.add(j, Vec3<Scalar>(g / gn));
    });
    if (!ok || gram.n == 0) return out;
    gram.finish();
    out.enu_nT = gram.vector_rms(p.cwiseProduct(gram.gv).sum());
    out.f_nT = gram.intensity_rms(p.cwiseProduct(gram.gi).sum());
    return out;
  }
  // Predicted 1-sigma of the calibrated intensity at the last used sample (inf before the fit).
  Scalar sigma_f_nT() const noexcept {
    if (!ekf_.initialised() || !have_m_) return std::numeric_limits<Scalar>::infinity();
    return ekf_.intensity_sigma_nT(last_m_);
  }

 private:
  std::size_t min_align() const noexcept {
    return std::clamp<std::size_t>(cfg_.min_align_samples, 9, AlignCapacity);
  }

  void keep_for_alignment(const Vec3<Scalar>& m, Scalar f, const Mat3<Scalar>& r_bn) noexcept {
    if (store_.full() || !(std::isfinite(f) && f > 0)) return;
    if (have_last_ &&
        rotation_angle_between(r_bn, last_r_bn_) < deg_to_rad(cfg_.align_min_step_deg)) {
      return;
    }
    if (store_.push(m, f, &r_bn)) {
      last_r_bn_ = r_bn;
      have_last_ = true;
    }
  }

  CalibratorSolve fail(EkfCalCode code) noexcept {
    return CalibratorSolve{false, static_cast<std::uint8_t>(code)};
  }

  Config cfg_;
  Filter ekf_;
  SampleStore<Scalar, AlignCapacity> store_{};
  TiltMoments<Scalar> tilts_{};
  MisalignmentSolution<Scalar> align_{};
  std::uint32_t updates_at_begin_{0};
  bool have_last_{false};
  bool have_m_{false};
  bool aligned_{false};
  Vec3<Scalar> last_m_ = Vec3<Scalar>::Zero();
  Mat3<Scalar> last_r_bn_ = Mat3<Scalar>::Identity();
};

template <typename Scalar, std::size_t AlignCapacity, int InitCapacity>
CalibratorAdd EkfCalibrator<Scalar, AlignCapacity, InitCapacity>::add(
    const Vec3<Scalar>& m, Scalar f_ref_nT, const Mat3<Scalar>* r_bn) noexcept {
  const EkfStatus st = ekf_.update(m, f_ref_nT);
  if (st == EkfStatus::kRejectedNonFinite || st == EkfStatus::kRejectedBadReference)
    return CalibratorAdd::kRejected;
  if (st == EkfStatus::kGated) return CalibratorAdd::kGated;
  last_m_ = m;
  have_m_ = true;
  if (r_bn != nullptr && all_finite(*r_bn)) {
    tilts_.add(*r_bn);
    if (cfg_.align) keep_for_alignment(m, f_ref_nT, *r_bn);
  }
  return CalibratorAdd::kUsed;
}

template <typename Scalar, std::size_t AlignCapacity, int InitCapacity>
CalibratorSolve EkfCalibrator<Scalar, AlignCapacity, InitCapacity>::solve(
    SensorModel<Scalar>* out) noexcept {
  aligned_ = false;
  if (!ekf_.initialised()) return fail(EkfCalCode::kNotInitialised);
  SensorModel<Scalar> model = ekf_.model();
  if (cfg_.align) {
    align_ = joint_rm_hn(store_, model.w, model.o, cfg_.misalignment);
    switch (align_.status) {
      case MisalignmentStatus::kOk:
        break;
      case MisalignmentStatus::kTooFewSamples:
        return fail(EkfCalCode::kAlignTooFewSamples);
      case MisalignmentStatus::kUnobservableHeading:
        return fail(EkfCalCode::kAlignUnobservable);
      case MisalignmentStatus::kIllConditioned:
        return fail(EkfCalCode::kAlignIllConditioned);
      case MisalignmentStatus::kNotConverged:
        return fail(EkfCalCode::kAlignNotConverged);
    }
    model.rm = Quat<Scalar>(li_rm(align_.rm_rad));
    model.rm.normalize();
    SensorModel<Scalar> li;
    if (canonicalize_li(model, &li) != ConversionStatus::kOk)
      return fail(EkfCalCode::kNotLiRepresentable);
    model = li;
    aligned_ = true;
  }
  *out = model;
  // Without the alignment step W is known only up to a rotation and Rm = I: not aligned.
  CalibratorSolve r{true, 0, aligned_};
  r.mag_noise_nT = static_cast<float>(ekf_.noise_nT());
  // The alignment fit's residual (relative to F) as the attitude noise: it also holds the
  // magnetometer noise over F, so the vector check's floor is conservative, never too tight.
  if (aligned_) {
    r.attitude_noise_deg = static_cast<float>(rad_to_deg(align_.residual_rms));
    // From the filter's covariance once its start-up term is relinearised (E-Acc-3).
    if (ekf_.start_relinearised()) {
      const OutputSigmas sig = output_sigmas(model, align_.h_n);
      r.calibration_sigma_f_nT = static_cast<float>(sig.f_nT);
      r.calibration_sigma_enu_nT = static_cast<float>(sig.enu_nT);
    }
  }
  return r;
}

// Compiled once for the host with the scalar EKF (see the end of scalar_ekf.hpp).
#ifdef MAGVEC_CORE_EKF_DOUBLE_COMPILED
extern template class EkfCalibrator<double>;
#endif

}  // namespace magvec::core
