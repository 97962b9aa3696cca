// Online scalar-observation calibration filter after Ge et al. 2017, corrected per
// docs/equations.md E-Ge.
//   State (eq. 15): x = [C^-1 row-major (9), b (3)], constant parameters (eq. 16) plus process
//   noise. Measurement (eq. 17-21, docs/equations.md E-Ge-1): h(x) = |C^-1 (m - b)|^2 against z =
//   F_ref^2, with the exact Jacobian dh/d(C^-1)_rc = 2 y_r v_c, dh/db = -2 C^-T y (v = m - b, y =
//   C^-1 v); the printed eq. (25) is wrong and not used.
// Noise bias: the reading m carries the noise, F_ref does not. For m = m_true + n, n ~ N(0, s^2 I),
// E|W (m - b)|^2 = F^2 + s^2 tr(W^T W), so the prediction of z = F^2 from the noisy m is
// h = |y|^2 - s^2 tr(W^T W) (debias). Adding the term instead doubles the bias it should remove.
// Numerics: the covariance is held as P = U D U^T (U unit upper triangular, D > 0) and updated with
// Bierman's scalar measurement update and the Agee-Turner rank-one update for diagonal process
// noise, both O(n^2) and symmetric positive definite by construction, which keeps float32 usable.
// Fields are divided by a reference magnitude s (the first reference total field unless configured)
// so that every state is O(1) in float32 (docs/equations.md E-Ge-5); the interface is in nT.
// One-pass convergence (docs/equations.md E-Ge-3): by default the filter starts from a fit of a
// start-up set of samples (an algebraic quadric least-squares fit, outlier screening, then
// Gauss-Newton on the exact model over those samples); P0 is the inverse information of those
// samples, so no data is wasted and the filter continues as a recursive Gauss-Newton from there.
// The start-up set is kept, and its term in the filter's cost is relinearised at the running
// estimate after relinearise_start_after updates and each time that count doubles (E-Acc-3): as a
// Gaussian fixed at the fit it left the covariance 1.4-2.5x optimistic and the estimate worse.
// Start-up by information: the start-up set is a bounded, well-spread subset of the samples seen so
// far, kept by a D-optimal exchange on the quadric features of the field directions (a sample
// enters if it adds information, and replaces the member whose exchange raises the determinant of
// the set's information most). The fit is tried when the set is full, then again whenever its
// information has grown by init_retry_gain per dimension; a failed try keeps the set and records
// why (init_report(): which parameters the set does not determine, or not an ellipsoid). After an
// undetermined try the set may grow, doubling up to its capacity (noisy data need more samples).
// The filter is ScalarEkfBase<Scalar>; ScalarEkf<Scalar, kInitCapacity> only adds the start-up
// set's storage, so every capacity shares one compiled filter per scalar type.
// Noise from the data: the magnetometer noise is estimated from the start-up fit's residuals
// (robust scale) and then from the innovations (winsorised, with the parameter part of the
// innovation variance removed), per window of nis_window samples, discarding windows that ended in
// a detected divergence. With estimate_noise the estimate is used for weighting, debias and
// gating; otherwise noise_sigma_nT is used and the estimate is only reported.
// `EkfConfig::paper()` reproduces the printed x0/P0/Q/R (with gate and divergence detection off) so
// the paper's setup can be rerun. The start-up set's algebraic quadric fit is the batch
// EllipsoidFit's (docs/equations.md E-Ell-2, E-Ell-3), centred on the set's mean reading.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/LU>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"
#include "magvec/core/ud_factor.hpp"

namespace magvec::core {

// State indices: C^-1 row-major, then the offset b.
inline constexpr int kEkfW00 = 0;
inline constexpr int kEkfW01 = 1;
inline constexpr int kEkfW02 = 2;
inline constexpr int kEkfW10 = 3;
inline constexpr int kEkfW11 = 4;
inline constexpr int kEkfW12 = 5;
inline constexpr int kEkfW20 = 6;
inline constexpr int kEkfW21 = 7;
inline constexpr int kEkfW22 = 8;
inline constexpr int kEkfBx = 9;
inline constexpr int kEkfBy = 10;
inline constexpr int kEkfBz = 11;
inline constexpr int kEkfStateDim = 12;
constexpr int ekf_w_index(int r, int c) noexcept {
  return 3 * r + c;
}
static_assert(ekf_w_index(2, 2) == kEkfW22 && kEkfBx == 9 && kEkfBz + 1 == kEkfStateDim);

enum class EkfInitMode : std::uint8_t {
  kQuadricFit,  // default: fit a well-spread start-up set, then filter (one-pass)
  kGiven,       // start from w0/b0_nT/p0 as configured (paper, or "identity + mean" start)
};

// Result of one update() call.
enum class EkfStatus : std::uint8_t {
  kAccepted,     // measurement update applied
  kCollecting,   // buffered for the initial fit
  kInitialised,  // this sample completed the initial fit; the filter is now running
  kInitFailed,   // an initial fit was tried and failed (init_report() says why); collecting on
  kGated,        // innovation outside the gate: rejected and counted
  kRejectedNonFinite,     // NaN/inf in the magnetometer sample: rejected, state untouched
  kRejectedBadReference,  // reference field not finite or not positive: rejected, state untouched
  kReinitialised,         // divergence detected (see last_reset_reason()); filter restarted
};

enum class EkfResetReason : std::uint8_t {
  kNone,
  kNonFiniteState,         // state, gain or innovation variance became NaN/inf
  kCovarianceNotPositive,  // a D factor (variance) became <= 0
  kNisTooHigh,             // mean normalised innovation squared over a window above the limit
  kTooManyGated,           // fraction of gated samples over a window above the limit
  kSingularModel,          // C^-1 became (numerically) singular
};

// Why the last initial fit failed (EkfInitReport::failure).
enum class EkfInitFailure : std::uint8_t {
  kNone,
  kTooFewSamples,   // fewer than init_min_samples in the start-up set
  kUndetermined,    // the set does not determine some parameters (EkfInitReport::undetermined)
  kNotAnEllipsoid,  // the parameters are determined but the readings are not on an ellipsoid
  kNotConverged,    // the Gauss-Newton refinement did not settle
};

struct EkfCounters {
  std::uint32_t updates = 0;             // accepted measurement updates
  std::uint32_t gated = 0;               // rejected by the innovation gate
  std::uint32_t rejected_nonfinite = 0;  // NaN/inf magnetometer samples
  std::uint32_t rejected_reference = 0;  // unusable reference field values
  std::uint32_t reinitialisations = 0;   // automatic restarts after detected divergence
  std::uint32_t init_outliers = 0;       // samples dropped by the initial fit's screening
  std::uint32_t init_attempts = 0;       // initial fits tried
  std::uint32_t init_failures = 0;       // initial fits that failed (collection goes on)
  std::uint32_t init_exchanges = 0;      // start-up set members replaced by better-spread samples
  std::uint32_t start_relinearisations = 0;  // the start-up set's term relinearised (E-Acc-3)
};

template <typename Scalar>
struct EkfConfig {
  static constexpr int kN = kEkfStateDim;
  EkfInitMode init_mode = EkfInitMode::kQuadricFit;
  // Constant reference total field for update(m); 0 = the caller passes F per sample.
  Scalar reference_field_nT{0};
  // Normalisation magnitude s; 0 = the first valid reference field. 1 = raw nT (for comparison
  // only).
  Scalar field_scale_nT{0};
  // Measurement noise: z = F^2 has variance 4 sigma^2 |C^-T y|^2 (+ reference noise (2 F
  // sigma_F)^2) evaluated per sample, unless r_fixed_nT4 > 0 (the paper's constant R).
  // noise_sigma_nT is the magnetometer noise per axis (1-sigma); with estimate_noise it is only the
  // guess used until the data give an estimate (the start-up fit's residuals, then innovations).
  Scalar noise_sigma_nT{10};
  bool estimate_noise = false;
  Scalar reference_sigma_nT{0};
  Scalar r_fixed_nT4{0};
  // Predict E[z] = |y|^2 - sigma^2 tr(C^-T C^-1): the noise power of the reading m inflates |y|^2.
  bool debias = true;
  // kGiven start: x0 and P0 in interface units (C^-1 dimensionless, b in nT, P0_b in nT^2).
  Mat3<Scalar> w0 = Mat3<Scalar>::Identity();
  Vec3<Scalar> b0_nT = Vec3<Scalar>::Zero();
  Vec<Scalar, kN> p0 = Vec<Scalar, kN>::Zero();
  // Process noise per update (diagonal, interface units). q(9..11) on b tracks slow offset drift.
  Vec<Scalar, kN> q = Vec<Scalar, kN>::Zero();
  int iterations = 1;  // > 1: iterated EKF (relinearise the measurement about the updated state)
  // Initial quadric fit (kQuadricFit) over the start-up set (see the header comment).
  int init_samples = 64;      // size of the start-up set (<= the filter's init capacity)
  int init_min_samples = 20;  // fewest samples try_start() fits (>= 16)
  int init_gauss_newton_iterations = 4;
  // The start-up set's information is relinearised at the running estimate after this many
  // updates from the fitted start, then each time the count has doubled (docs/equations.md
  // E-Acc-3: the start as a Gaussian made the covariance 1.4-2.5x optimistic). 0: never, and
  // never with process noise (q not zero).
  std::uint32_t relinearise_start_after = 250;
  // After a failed fit, try again once the set's information (det^(1/9) of its direction
  // features) has grown by this factor.
  Scalar init_retry_gain{Scalar(1.25)};
  // The initial fit is refused (parameters undetermined) if any predicted 1-sigma exceeds this
  // fraction of the field scale (C^-1 elements are dimensionless, b relative to the scale); the
  // same figure as AcceptanceLimits::max_relative_sigma.
  Scalar init_max_sigma{Scalar(0.02)};
  // Innovation gate on NIS = nu^2 / S (chi-square, 1 dof); <= 0 disables. 25 = 5 sigma.
  Scalar gate_nis{25};
  // Divergence detection over windows of nis_window updates (accepted + gated).
  bool divergence_detection = true;
  // After a detected divergence, restart from a fit of new samples even when init_mode is kGiven
  // (restarting from the same given start would usually diverge the same way).
  bool reinit_from_fit = true;
  int nis_window = 100;
  Scalar nis_mean_limit{4};  // expected 1; the window mean has SD sqrt(2/window)
  Scalar gated_fraction_limit{Scalar(0.5)};

  // The printed settings of Ge et al. 2017 (raw nT units), faithfully: x0, P0, Q, R, no gate, no
  // divergence detection, no debiasing. They do not work (docs/equations.md E-Ge-3); kept to show
  // it.
  static EkfConfig paper() noexcept {
    EkfConfig c;
    c.init_mode = EkfInitMode::kGiven;
    c.w0 << Scalar(1.5), Scalar(0.05), Scalar(0.05), Scalar(0.05), Scalar(0.5), Scalar(0.05),
        Scalar(0.05), Scalar(0.05), Scalar(1);
    c.b0_nT.setZero();
    c.p0 << Scalar(1), Scalar(1e-4), Scalar(1e-4), Scalar(1e-4), Scalar(1), Scalar(1e-4),
        Scalar(1e-4), Scalar(1e-4), Scalar(1), Scalar(1e4), Scalar(1e4), Scalar(1e4);
    c.q << Scalar(1e-4), Scalar(1e-4), Scalar(1e-4), Scalar(1e-4), Scalar(1e-4), Scalar(1e-4),
        Scalar(1e-4), Scalar(1e-4), Scalar(1e-4), Scalar(1e4), Scalar(1e4), Scalar(1e4);
    c.r_fixed_nT4 = Scalar(1e4);
    c.debias = false;
    c.gate_nis = 0;
    c.divergence_detection = false;
    return c;
  }

  // docs/equations.md E-Ge-3 "sound filter": start at C^-1 = identity (or w0), b = a given offset
  // (e.g. the mean of the measurements), broad P0, Q = 0, R from the noise. Used to compare against
  // the default.
  static EkfConfig given_start(const Vec3<Scalar>& b0_nT_in, Scalar f_nT,
                               Scalar sigma_nT) noexcept {
    EkfConfig c;
    c.init_mode = EkfInitMode::kGiven;
    c.b0_nT = b0_nT_in;
    c.noise_sigma_nT = sigma_nT;
    const Scalar pb = Scalar(0.25) * f_nT * f_nT;  // b SD F/2
    c.p0 << Scalar(0.25), Scalar(0.01), Scalar(0.01), Scalar(0.01), Scalar(0.25), Scalar(0.01),
        Scalar(0.01), Scalar(0.01), Scalar(0.25), pb, pb, pb;
    return c;
  }
};

// Outcome of the last initial-fit try (ScalarEkf::init_report()).
template <typename Scalar>
struct EkfInitReport {
  EkfInitFailure failure = EkfInitFailure::kNone;
  // Bit k set: state k (kEkfW00..kEkfBz) has a predicted 1-sigma above `limit`.
  std::uint32_t undetermined = 0;
  // Predicted 1-sigma of every state relative to its natural size (C^-1 elements: 1; b: the
  // reference field), from the fit, or from the set's information about a nominal sphere when no
  // ellipsoid could be fitted. NaN before any try.
  Vec<Scalar, kEkfStateDim> relative_sigma =
      Vec<Scalar, kEkfStateDim>::Constant(std::numeric_limits<Scalar>::quiet_NaN());
  int samples = 0;  // size of the start-up set at the try
  // The 1-sigma limit applied: init_max_sigma, or tighter where the noise is so low that a start
  // that far off would leave linearisation errors above it (sqrt(2 sigma / F)).
  Scalar limit = std::numeric_limits<Scalar>::quiet_NaN();
};

template <typename Scalar>
class ScalarEkfBase {
  static_assert(CoreScalar<Scalar>);

 public:
  static constexpr int kN = kEkfStateDim;
  using StateVec = Vec<Scalar, kN>;
  using StateMat = Mat<Scalar, kN, kN>;
  using Config = EkfConfig<Scalar>;
  using InitReport = EkfInitReport<Scalar>;

  // Replaces the configuration and restarts the filter; counters and the noise estimate are
  // cleared.
  void configure(const Config& config) noexcept;

  // Restarts estimation (new initial fit or the configured start); keeps counters, scale and the
  // noise estimate.
  void restart() noexcept;

  EkfStatus update(const Vec3<Scalar>& m_nT) noexcept;

  // One sample: raw magnetometer reading m [nT] and the reference total field F [nT] at that time.
  EkfStatus update(const Vec3<Scalar>& m_nT, Scalar f_ref_nT) noexcept;

  // Tries the initial fit now with the start-up set as it is (at least init_min_samples), e.g. at
  // the end of a recording shorter than the set. True when the filter is running.
  bool try_start() noexcept;

  bool initialised() const noexcept { return initialised_; }
  // The start-up set's term has been relinearised since the filter started (E-Acc-3): from then on
  // its covariance is a usable 1-sigma of G and o.
  bool start_relinearised() const noexcept { return start_relinearised_; }
  const EkfCounters& counters() const noexcept { return counters_; }
  EkfResetReason last_reset_reason() const noexcept { return last_reset_; }
  const Config& config() const noexcept { return cfg_; }
  Scalar field_scale_nT() const noexcept { return scale_; }
  // Normalised innovation squared of the last processed (accepted or gated) sample.
  Scalar last_nis() const noexcept { return last_nis_; }
  // The last initial-fit try and the current size of the start-up set.
  const InitReport& init_report() const noexcept { return report_; }
  int startup_samples() const noexcept { return n_buf_; }

  // Magnetometer noise per axis [nT] the filter uses (the estimate with estimate_noise).
  Scalar noise_nT() const noexcept { return sigma_ * scale_or_one(); }
  // The data's estimate of that noise and its 1-sigma [nT]; NaN until a start-up fit or innovations
  // gave one.
  Scalar noise_estimate_nT() const noexcept {
    const Scalar v = noise_var();
    return v > 0 ? std::sqrt(v) * scale_or_one() : std::numeric_limits<Scalar>::quiet_NaN();
  }
  Scalar noise_estimate_sigma_nT() const noexcept {
    const Scalar v = noise_var();
    const Scalar n = noise_prior_n_ + noise_n_;
    if (!(v > 0 && n > 0)) return std::numeric_limits<Scalar>::quiet_NaN();
    // Var of the combined mean of per-sample variance terms: the start-up fit's share at the
    // Gaussian per-term variance of the winsorised estimator, the innovations' at their own.
    const Scalar var_v = (kTermVariance * v * v * noise_prior_n_ + noise_m2_) / (n * n);
    return std::sqrt(var_v) / (Scalar(2) * std::sqrt(v)) * scale_or_one();
  }
  // Number of innovations behind the noise estimate (without the start-up fit's share).
  Scalar noise_estimate_samples() const noexcept { return noise_n_; }

  Mat3<Scalar> c_inv() const noexcept { return unflatten(x_.template head<9>()); }
  Vec3<Scalar> offset_nT() const noexcept { return x_.template tail<3>() * scale_or_one(); }
  // Canonical form (docs/conventions.md#canonical-sensor-model): W = C^-1, o = b, Rm = identity.
  // Only G = W^T W and o are observable.
  SensorModel<Scalar> model() const noexcept {
    return from_ge(GeParams<Scalar>{c_inv(), offset_nT()});
  }

  // State and covariance in interface units (C^-1 dimensionless, b in nT).
  StateVec state() const noexcept {
    StateVec s = x_;
    s.template tail<3>() *= scale_or_one();
    return s;
  }
  StateMat covariance() const noexcept {
    StateMat p = u_ * d_.asDiagonal() * u_.transpose();
    const StateVec t = unit_scale();
    return t.asDiagonal() * p * t.asDiagonal();
  }
  StateVec sigma() const noexcept {
    return ud_variances<Scalar, kN>(u_, d_).cwiseSqrt().cwiseProduct(unit_scale());
  }

  // Calibrated intensity |C^-1 (m - b)| [nT] and its predicted 1-sigma from the parameter
  // covariance.
  Scalar intensity_nT(const Vec3<Scalar>& m_nT) const noexcept {
    const Scalar s = scale_or_one();
    return (c_inv() * (m_nT / s - x_.template tail<3>())).norm() * s;
  }
  Scalar intensity_sigma_nT(const Vec3<Scalar>& m_nT) const noexcept {
    const Scalar s = scale_or_one();
    const Vec3<Scalar> v = m_nT / s - x_.template tail<3>();
    const Vec3<Scalar> y = c_inv() * v;
    const Scalar ny = y.norm();
    if (!(ny > 0)) return std::numeric_limits<Scalar>::infinity();
    const StateVec grad = jacobian(y, v, Scalar(0)) / (Scalar(2) * ny);  // d|y|/dx
    const StateVec f = ut_times(grad);
    return std::sqrt(f.dot(d_.cwiseProduct(f))) * s;
  }

 protected:
  // A start-up set of at most `capacity` samples, stored in the derived class's arrays (given by
  // bind_storage before configure()).
  explicit ScalarEkfBase(int capacity) noexcept : capacity_(capacity) {}
  // Copies state and storage pointers: the derived class copies its arrays and binds them again.
  ScalarEkfBase(const ScalarEkfBase&) noexcept = default;
  ScalarEkfBase& operator=(const ScalarEkfBase&) noexcept = default;
  ~ScalarEkfBase() = default;
  // buf_m: 3 x capacity (column-major, one column per sample); the others capacity entries each.
  void bind_storage(Scalar* buf_m, Scalar* buf_f, Scalar* used, Scalar* lev,
                    Scalar* scratch) noexcept {
    buf_m_ = buf_m;
    buf_f_ = buf_f;
    used_ = used;
    lev_ = lev;
    scratch_ = scratch;
  }

 private:
  using Features = Vec<Scalar, 9>;
  using FeatureMat = Mat<Scalar, 9, 9>;
  // Winsorising the innovations at kNoiseClip standard deviations keeps spikes from inflating the
  // noise estimate; for Gaussian innovations E[min(x^2, c^2)] = kNoiseClipMean (c = 2.5) and the
  // per-term variance of the estimator is kTermVariance sigma^4.
  static constexpr Scalar kNoiseClip2 = Scalar(6.25);
  static constexpr Scalar kNoiseClipMean = Scalar(0.97757);
  static constexpr Scalar kTermVariance = Scalar(1.76);
  // Share of a MAD-based start-up estimate from n residuals, in innovation terms (its efficiency
  // relative to the winsorised estimator: (0.663 / 1.167)^2).
  static constexpr Scalar kMadShare = Scalar(0.32);

  static StateVec flatten_state(const Mat3<Scalar>& w, const Vec3<Scalar>& b) noexcept {
    StateVec x;
    x.template head<9>() = flatten(w);
    x.template tail<3>() = b;
    return x;
  }
  // The state holds W row by row (ekf_w_index): the transpose of Eigen's column-major storage, a
  // plain copy (the index loops stayed a call of ~80 instructions on the M4F's per-sample path).
  static_assert(ekf_w_index(0, 1) == 1 && ekf_w_index(1, 0) == 3, "row-major W in the state");
  static Vec<Scalar, 9> flatten(const Mat3<Scalar>& w) noexcept {
    Vec<Scalar, 9> v;
    Eigen::Map<Mat3<Scalar>>(v.data()) = w.transpose();
    return v;
  }
  static Mat3<Scalar> unflatten(const Vec<Scalar, 9>& v) noexcept {
    return Eigen::Map<const Mat3<Scalar>>(v.data()).transpose();
  }
  Scalar scale_or_one() const noexcept { return scale_ > 0 ? scale_ : Scalar(1); }
  StateVec unit_scale() const noexcept {
    StateVec t = StateVec::Ones();
    t.template tail<3>().setConstant(scale_or_one());
    return t;
  }

  // Combined noise variance estimate (normalised units); 0 when there is none.
  Scalar noise_var() const noexcept {
    const Scalar n = noise_prior_n_ + noise_n_;
    if (!(n > 0)) return Scalar(0);
    const Scalar v = (noise_prior_n_ * noise_prior_var_ + noise_n_ * noise_mean_) / n;
    return v > 0 ? v : Scalar(0);
  }
  // Smallest usable noise: a noise-free recording must not make R zero.
  Scalar sigma_floor() const noexcept {
    return Scalar(16) * std::numeric_limits<Scalar>::epsilon();
  }
  void use_noise_estimate() noexcept {
    if (!cfg_.estimate_noise) return;
    const Scalar v = noise_var();
    if (v > 0) sigma_ = std::max(std::sqrt(v), sigma_floor());
  }

  // dh/dx with v = m - b, y = W v; debias subtracts sigma^2 tr(W^T W), whose derivative is
  // 2 sigma^2 W.
  StateVec jacobian(const Vec3<Scalar>& y, const Vec3<Scalar>& v,
                    Scalar sigma2_debias) const noexcept {
    StateVec h;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        h(ekf_w_index(r, c)) =
            Scalar(2) * y(r) * v(c) - Scalar(2) * sigma2_debias * x_(ekf_w_index(r, c));
    h.template tail<3>() = Scalar(-2) * (c_inv().transpose() * y);
    return h;
  }

  struct Linearisation {
    StateVec h_row = StateVec::Zero();
    Scalar h{0};      // predicted measurement
    Scalar r{0};      // measurement variance
    Scalar a{0};      // |C^-T y|^2: r = 4 sigma^2 a + 2 sigma^4 g2 + r_ref
    Scalar g2{0};     // |C^-T C^-1|_F^2
    Scalar r_ref{0};  // reference-field part of r
  };
  // Measurement model at the current state for normalised m and F (fn).
  Linearisation linearise(const Vec3<Scalar>& m, Scalar fn) const noexcept {
    const Scalar s = scale_or_one();
    const Mat3<Scalar> w = c_inv();
    const Vec3<Scalar> v = m - x_.template tail<3>();
    const Vec3<Scalar> y = w * v;
    const Scalar sig2 = sigma_ * sigma_;
    const Scalar deb = cfg_.debias ? sig2 : Scalar(0);
    Linearisation l;
    l.h_row = jacobian(y, v, deb);
    l.h = y.squaredNorm() - deb * w.squaredNorm();
    const Mat3<Scalar> g = w.transpose() * w;
    const Scalar sf = cfg_.reference_sigma_nT / s;
    l.a = (w.transpose() * y).squaredNorm();
    l.g2 = g.squaredNorm();
    l.r_ref = Scalar(4) * fn * fn * sf * sf;
    if (cfg_.r_fixed_nT4 > 0) {
      l.r = cfg_.r_fixed_nT4 / (s * s * s * s);
    } else {
      l.r = Scalar(4) * sig2 * l.a + Scalar(2) * sig2 * sig2 * l.g2 + l.r_ref;
    }
    return l;
  }

  void start_given() noexcept {
    const Scalar s = scale_or_one();
    x_ = flatten_state(cfg_.w0, cfg_.b0_nT / s);
    u_.setIdentity();
    d_ = cfg_.p0;
    d_.template tail<3>() /= s * s;
    initialised_ = d_.allFinite() && (d_.array() > 0).all();
  }

  // All of U finite (ud_factor.hpp: a third of the cost of allFinite() on the per-sample path).
  bool u_upper_finite() const noexcept { return ud_upper_finite<Scalar, kN>(u_); }

  // U^T h for the unit upper triangular U: 66 multiply-adds instead of the 144 of a full product
  // (per sample, twice: the update and the loop's intensity sigma).
  StateVec ut_times(const StateVec& h) const noexcept { return ud_ut_times<Scalar, kN>(u_, h); }

  // ---- covariance factor updates ----------------------------------------------------------------
  // Agee-Turner: U D U^T + c e_k e_k^T for c > 0, O(k^2).
  void add_diagonal_noise(int k, Scalar c) noexcept {
    ud_add_diagonal_noise<Scalar, kN>(u_, d_, k, c);
  }

  // Bierman's scalar update of U, D for a measurement with f = U^T h^T and variance r: the
  // unnormalised gain k (K = k / s) into *k_out (the caller's local, not f) and the innovation
  // variance s = h P h^T + r into *s_out.
  void bierman(const StateVec& f, Scalar r, StateVec* k_out, Scalar* s_out) noexcept {
    ud_bierman_update<Scalar, kN>(u_, d_, f, r, k_out, s_out);
  }

  // ---- noise estimate from the innovations -----------------------------------------------------
  // nu = z - h with variance hph + r: (nu^2 winsorised at kNoiseClip sigma of the current estimate,
  // corrected for the clipping) - hph - the non-magnetometer part, per unit 4 a, estimates sigma^2.
  void note_innovation(Scalar nu, Scalar hph, const Linearisation& l) noexcept {
    const Scalar v = noise_var() > 0 ? noise_var() : sigma_ * sigma_;
    if (!(l.a > 0 && v > 0)) return;
    const Scalar r_hat = Scalar(4) * v * l.a + Scalar(2) * v * v * l.g2 + l.r_ref;
    const Scalar nu2 = std::min(nu * nu, kNoiseClip2 * (hph + r_hat));
    const Scalar t =
        (nu2 / kNoiseClipMean - hph - l.r_ref - Scalar(2) * v * v * l.g2) / (Scalar(4) * l.a);
    if (!std::isfinite(t)) return;
    window_noise_sum_ += t;
    window_noise_sum2_ += t * t;
    ++window_noise_n_;
  }
  // Merges the window's terms (Chan et al. pairwise update of mean and M2).
  void merge_noise_window() noexcept {
    const Scalar nb = static_cast<Scalar>(window_noise_n_);
    if (window_noise_n_ > 0) {
      const Scalar mean_b = window_noise_sum_ / nb;
      const Scalar m2_b = std::max(window_noise_sum2_ - window_noise_sum_ * mean_b, Scalar(0));
      const Scalar n = noise_n_ + nb;
      const Scalar delta = mean_b - noise_mean_;
      noise_mean_ += delta * nb / n;
      noise_m2_ += m2_b + delta * delta * noise_n_ * nb / n;
      noise_n_ = n;
      use_noise_estimate();
    }
    window_noise_n_ = 0;
    window_noise_sum_ = 0;
    window_noise_sum2_ = 0;
  }

  // ---- the filter step ---------------------------------------------------------------------
  EkfStatus filter_step(const Vec3<Scalar>& m, Scalar fn, Scalar z) noexcept {
    const Linearisation l0 = linearise(m, fn);
    // A finite but absurd sample can overflow the prediction: reject it before touching anything.
    if (!(std::isfinite(l0.h) && std::isfinite(l0.r) && all_finite(l0.h_row))) {
      ++counters_.rejected_nonfinite;
      return EkfStatus::kRejectedNonFinite;
    }
    const Scalar s2 = scale_or_one() * scale_or_one();
    for (int k = 0; k < kN; ++k) {
      const Scalar qk = k >= kEkfBx ? cfg_.q(k) / s2 : cfg_.q(k);
      if (qk > 0) add_diagonal_noise(k, qk);
    }
    const StateVec f0 = ut_times(l0.h_row);
    const Scalar hph = f0.dot(d_.cwiseProduct(f0));
    const Scalar s0 = l0.r + hph;
    const Scalar nu0 = z - l0.h;
    if (!(std::isfinite(s0) && s0 > 0 && std::isfinite(nu0)))
      return reinitialise(EkfResetReason::kNonFiniteState);
    note_innovation(nu0, hph, l0);
    last_nis_ = nu0 * nu0 / s0;
    if (cfg_.gate_nis > 0 && last_nis_ > cfg_.gate_nis) {
      ++counters_.gated;
      ++window_gated_;
      return end_of_window_check(EkfStatus::kGated);
    }
    Scalar s;
    if (cfg_.iterations == 1) {
      StateVec k;
      bierman(f0, l0.r, &k, &s);
      x_ += k * (nu0 / s);
    } else {
      const StateVec x_prior = x_;
      const StateMat u_prior = u_;
      const StateVec d_prior = d_;
      StateVec k;
      bierman(f0, l0.r, &k, &s);
      x_ += k * (nu0 / s);
      for (int it = 1; it < cfg_.iterations; ++it) {
        // Iterated EKF: x = x_prior + K_i (z - h(x_i) - H_i (x_prior - x_i)), with K_i and the
        // posterior covariance from the prior covariance and H_i linearised at the iterate x_i.
        const Linearisation l = linearise(m, fn);
        u_ = u_prior;
        d_ = d_prior;
        bierman(ut_times(l.h_row), l.r, &k, &s);
        const Scalar nu = z - l.h - l.h_row.dot(x_prior - x_);
        x_ = x_prior + k * (nu / s);
      }
    }
    if (!all_finite(x_) || !all_finite(d_) || !u_upper_finite())
      return reinitialise(EkfResetReason::kNonFiniteState);
    if (!(d_.array() > 0).all()) return reinitialise(EkfResetReason::kCovarianceNotPositive);
    if (!(std::abs(c_inv().determinant()) > std::numeric_limits<Scalar>::epsilon())) {
      return reinitialise(EkfResetReason::kSingularModel);
    }
    ++counters_.updates;
    window_nis_sum_ += last_nis_;
    if (start_term_ && relin_next_ > 0 && counters_.updates - start_updates_ >= relin_next_) {
      relin_next_ = relin_next_ > 0x7fffffffU ? 0U : 2U * relin_next_;
      relinearise_start();
    }
    return end_of_window_check(EkfStatus::kAccepted);
  }

  // E-Acc-3: the start-up set enters the filter as a Gaussian, the quadratic of its likelihood at
  // the fit, which is too narrow for an ellipsoid seen over a cap of directions; it stays
  // influential for thousands of updates in the directions a survey adds little to. Here that
  // quadratic is replaced by the set's quadratic at the current estimate x_T (its samples are
  // kept), in information form: N' = P^-1 - N_old + N_T, and one Newton step from x_T on the
  // changed cost, whose gradient at x_T (where the old cost had its minimum) is
  // N_old (x_T - x_old) - g_old + g_T. Skipped (state untouched) when N' is not positive definite.
  void relinearise_start() noexcept {
    StateMat info = ud_information<Scalar, kN>(u_, d_);  // P^-1 from the factors
    StateMat n_t;
    StateVec g_t;
    if (normal_equations(&n_t, &g_t) < 16) return;
    info += n_t - start_info_;
    const StateVec rhs = start_info_ * (x_ - start_x_lin_) - start_grad_ + g_t;
    StateMat p;
    if (!invert_information(info, &p)) return;
    const StateVec dx = p * rhs;
    if (!dx.allFinite() || !ud_factorise(p)) return;  // ud_factorise: u_, d_ untouched on failure
    start_x_lin_ = x_;
    start_info_ = n_t;
    start_grad_ = g_t;
    x_ += dx;
    start_relinearised_ = true;
    ++counters_.start_relinearisations;
  }

  EkfStatus end_of_window_check(EkfStatus status) noexcept {
    ++window_n_;
    if (window_n_ < cfg_.nis_window) return status;
    const int accepted = window_n_ - window_gated_;
    const Scalar gated_fraction =
        static_cast<Scalar>(window_gated_) / static_cast<Scalar>(window_n_);
    const Scalar mean_nis =
        accepted > 0 ? window_nis_sum_ / static_cast<Scalar>(accepted) : Scalar(0);
    window_n_ = 0;
    window_gated_ = 0;
    window_nis_sum_ = 0;
    if (cfg_.divergence_detection) {
      if (gated_fraction > cfg_.gated_fraction_limit)
        return reinitialise(EkfResetReason::kTooManyGated);
      if (mean_nis > cfg_.nis_mean_limit) return reinitialise(EkfResetReason::kNisTooHigh);
    }
    // A window that did not end in a divergence contributes to the noise estimate.
    merge_noise_window();
    return status;
  }

  EkfStatus reinitialise(EkfResetReason reason) noexcept {
    last_reset_ = reason;
    ++counters_.reinitialisations;
    if (cfg_.reinit_from_fit) use_fit_ = true;
    if (!x_.allFinite()) x_ = flatten_state(cfg_.w0, cfg_.b0_nT / scale_or_one());
    restart();
    return EkfStatus::kReinitialised;
  }

  Eigen::Map<Vec3<Scalar>> buf_m(int j) noexcept {
    return Eigen::Map<Vec3<Scalar>>(buf_m_ + 3 * j);
  }
  Eigen::Map<const Vec3<Scalar>> buf_m(int j) const noexcept {
    return Eigen::Map<const Vec3<Scalar>>(buf_m_ + 3 * j);
  }

  // ---- start-up set: D-optimal exchange on direction features --------------------------------
  // Quadric features of the unit direction u of a reading: the parameters of the exact model at a
  // sphere (W ~ I) see a sample through u u^T and u, so these 9 carry its information about the
  // shape and centre; a radial outlier adds nothing (directions only).
  static Features features(const Vec3<Scalar>& u) noexcept;
  Features buffered_features(int j) const noexcept { return features(buf_m(j) / buf_m(j).norm()); }
  // Factorises the set's information (ridge for sets of fewer than 9 directions) and updates the
  // log-determinant.
  void refactor_features() noexcept {
    if (!feat_dirty_) return;
    // Directions closer than ~0.5 deg to the set's span add nothing (the ridge is the information
    // of a feature resolution of 1e-2), so a slow platform does not fill the set with near-copies.
    const Scalar ridge = Scalar(1e-4);
    FeatureMat a = feat_info_;
    a.diagonal().array() += ridge;
    // The inverse is kept rather than the factorisation: an Eigen::LDLT member would give the
    // filter a non-trivial destructor (a static instance then needs __dso_handle on bare metal).
    const Eigen::LDLT<FeatureMat> ldlt(a);
    Scalar logdet{0};
    const auto dvec = ldlt.vectorD();
    for (int i = 0; i < 9; ++i)
      logdet += std::log(std::max(dvec(i), ridge));
    feat_logdet_ = logdet;
    for (int c = 0; c < 9; ++c) {  // column by column: no level-3 solver (heap fallback)
      Features e = Features::Zero();
      e(c) = 1;
      const Features col = ldlt.solve(e);
      feat_inv_.col(c) = col;
    }
    feat_dirty_ = false;
    lev_dirty_ = true;
  }
  void refresh_leverages() noexcept {
    refactor_features();
    if (!lev_dirty_) return;
    for (int j = 0; j < n_buf_; ++j) {
      const Features f = buffered_features(j);
      const Features g = feat_inv_ * f;
      lev_[j] = f.dot(g);
    }
    lev_dirty_ = false;
  }
  void store(int j, const Vec3<Scalar>& m, Scalar fn) noexcept {
    buf_m(j) = m;
    buf_f_[j] = fn;
  }

  EkfStatus collect(const Vec3<Scalar>& m, Scalar fn) noexcept {
    const Scalar norm = m.norm();
    if (!(norm > 0)) return EkfStatus::kCollecting;
    const Features f = features(m / norm);
    refactor_features();
    const Features g = feat_inv_ * f;
    const Scalar dx = f.dot(g);  // leverage: det grows by (1 + dx) if the sample is added
    if (n_buf_ < target_) {
      // An average member of a set of n in 9 dimensions has leverage 9 / n: take samples that add
      // at least half that, so a still platform does not fill the set with copies.
      if (!(dx > Scalar(4.5) / static_cast<Scalar>(target_))) return EkfStatus::kCollecting;
      store(n_buf_, m, fn);
      ++n_buf_;
      feat_info_.template selfadjointView<Eigen::Lower>().rankUpdate(f);
      feat_dirty_ = true;
      changed_since_try_ = true;
    } else {
      // Fedorov exchange: replacing member j by the sample multiplies det by
      // (1 + dx)(1 - d_j) + (g . f_j)^2.
      refresh_leverages();
      int best = -1;
      Scalar best_gain = Scalar(0.02);  // ignore marginal exchanges (churn)
      for (int j = 0; j < n_buf_; ++j) {
        const Features fj = buffered_features(j);
        const Scalar dxj = g.dot(fj);
        const Scalar gain = (Scalar(1) + dx) * (Scalar(1) - lev_[j]) + dxj * dxj - Scalar(1);
        if (gain > best_gain) {
          best_gain = gain;
          best = j;
        }
      }
      if (best < 0) return EkfStatus::kCollecting;
      const Features old = buffered_features(best);
      feat_info_.template selfadjointView<Eigen::Lower>().rankUpdate(old, Scalar(-1));
      feat_info_.template selfadjointView<Eigen::Lower>().rankUpdate(f);
      store(best, m, fn);
      feat_dirty_ = true;
      changed_since_try_ = true;
      ++counters_.init_exchanges;
    }
    if (n_buf_ < cfg_.init_samples) return EkfStatus::kCollecting;
    refactor_features();
    const Scalar retry = Scalar(9) * std::log(std::max(cfg_.init_retry_gain, Scalar(1)));
    if (tried_ && !(feat_logdet_ >= logdet_at_try_ + retry)) return EkfStatus::kCollecting;
    if (attempt_fit()) return EkfStatus::kInitialised;
    return EkfStatus::kInitFailed;
  }

  bool attempt_fit() noexcept {
    refactor_features();
    tried_ = true;
    changed_since_try_ = false;
    logdet_at_try_ = feat_logdet_;
    ++counters_.init_attempts;
    if (solve_initial_fit()) {
      initialised_ = true;
      use_noise_estimate();
      return true;
    }
    ++counters_.init_failures;
    // Undetermined: more samples (up to the capacity) may determine it; noise shrinks as 1/sqrt(n).
    if (report_.failure == EkfInitFailure::kUndetermined && target_ < capacity_)
      target_ = std::min(2 * target_, capacity_);
    return false;
  }

  // ---- initial fit over the start-up set ---------------------------------------------------
  bool algebraic_fit(const Vec3<Scalar>& center) noexcept {
    // Centred on the set's mean and scaled by its mean reference, so that the quadric's
    // monomials stay well conditioned in float32 however far the offset is from zero.
    Scalar f_mean{0};
    int n = 0;
    for (int i = 0; i < n_buf_; ++i) {
      if (!(used_[i] > 0)) continue;
      f_mean += buf_f_[i];
      ++n;
    }
    if (n == 0) return false;
    EllipsoidFit<Scalar> fit;
    fit.set_normalization(Normalization<Scalar>{center, f_mean / static_cast<Scalar>(n)});
    for (int i = 0; i < n_buf_; ++i) {
      if (used_[i] > 0) fit.add(buf_m(i), buf_f_[i]);
    }
    // Its algebraic start only: the exact-model Gauss-Newton follows. G = W^T W is scale-free, so
    // the normalised fit's G is the one in nT.
    Mat3<Scalar> g;
    Vec3<Scalar> u;
    if (fit.algebraic_start(&g, &u) != EllipsoidStatus::kOk) return false;
    const Eigen::LLT<Mat3<Scalar>> llt(g);
    if (llt.info() != Eigen::Success) return false;
    const Mat3<Scalar> w = llt.matrixU();
    const Vec3<Scalar> b = fit.normalization().to_nt(u);
    if (!w.allFinite() || !b.allFinite()) return false;
    x_ = flatten_state(w, b);
    return true;
  }

  // Normal equations of the exact model over the used buffered samples at x_.
  // Returns the number of samples used; info = sum H^T H / R (+ gauge prior), grad = sum H^T r / R.
  int normal_equations(StateMat* info, StateVec* grad) const noexcept {
    info->setZero();
    grad->setZero();
    int n = 0;
    for (int i = 0; i < n_buf_; ++i) {
      if (!(used_[i] > 0)) continue;
      const Linearisation l = linearise(buf_m(i), buf_f_[i]);
      const Scalar res = buf_f_[i] * buf_f_[i] - l.h;
      info->template selfadjointView<Eigen::Lower>().rankUpdate(l.h_row, Scalar(1) / l.r);
      *grad += l.h_row * (res / l.r);
      ++n;
    }
    *info = info->template selfadjointView<Eigen::Lower>();
    // The rotation gauge (docs/equations.md E-Ge-2) is unobservable: pin it by a prior on the lower
    // triangle of W, which the Cholesky start sets to zero, at the scale of the data's information.
    const Scalar lambda = info->diagonal().maxCoeff();
    for (const int k : {kEkfW10, kEkfW20, kEkfW21}) {
      (*info)(k, k) += lambda;
      (*grad)(k) -= lambda * x_(k);
    }
    return n;
  }

  // Marks samples whose normalised residual exceeds the threshold as unused; returns how many.
  int screen(Scalar threshold) noexcept {
    int dropped = 0;
    for (int i = 0; i < n_buf_; ++i) {
      if (!(used_[i] > 0)) continue;
      const Linearisation l = linearise(buf_m(i), buf_f_[i]);
      const Scalar res = buf_f_[i] * buf_f_[i] - l.h;
      if (!(res * res <= threshold * l.r)) {
        used_[i] = 0;
        ++dropped;
      }
    }
    return dropped;
  }

  // Median over the used samples of |residual| / sqrt(R) (normalised = true) or of the residual in
  // per-axis reading units, |residual| / (2 |C^-T y|), whose scale is the noise (false).
  Scalar median_abs_residual(bool normalised, int* count = nullptr) const noexcept {
    Scalar* e = scratch_;  // working space of the storage, not state
    int n = 0;
    for (int i = 0; i < n_buf_; ++i) {
      if (!(used_[i] > 0)) continue;
      const Linearisation l = linearise(buf_m(i), buf_f_[i]);
      const Scalar res = std::abs(buf_f_[i] * buf_f_[i] - l.h);
      e[n++] = normalised ? res / std::sqrt(l.r) : res / (Scalar(2) * std::sqrt(l.a));
    }
    if (count != nullptr) *count = n;
    if (n == 0) return Scalar(0);
    std::nth_element(e, e + n / 2, e + n);
    return e[n / 2];
  }

  // Robust noise variance from the fit's residuals (1.4826 MAD, corrected for the 9 fitted
  // parameters), less the reference's share; 0 when there are too few residuals.
  Scalar noise_var_from_fit(int* n_out) const noexcept {
    int n = 0;
    const Scalar med = median_abs_residual(false, &n);
    *n_out = n;
    if (n <= 9 || !(med > 0)) return Scalar(0);
    const Scalar sig =
        Scalar(1.4826) * med * std::sqrt(static_cast<Scalar>(n) / static_cast<Scalar>(n - 9));
    const Scalar sf = cfg_.reference_sigma_nT / scale_or_one();
    const Scalar v = std::max(sig * sig - sf * sf, sigma_floor() * sigma_floor());
    return std::isfinite(v) ? v : Scalar(0);
  }
  // A converged fit's residual scale becomes the prior of the running estimate (unless the
  // innovations already gave one: a restart).
  void commit_fit_noise() noexcept {
    int n = 0;
    const Scalar v = noise_var_from_fit(&n);
    if (!(v > 0) || noise_n_ > 0) return;
    noise_prior_var_ = v;
    noise_prior_n_ = kMadShare * static_cast<Scalar>(n - 9);
  }

  // Gauss-Newton; *converged: the last step was below a tenth of a standard deviation (in the
  // metric of the information).
  bool gauss_newton(int iterations, bool* converged = nullptr) noexcept {
    bool settled = false;
    for (int it = 0; it < iterations; ++it) {
      StateMat info;
      StateVec grad;
      if (normal_equations(&info, &grad) < 16) return false;
      const Eigen::LDLT<StateMat> ldlt(info);
      if (ldlt.info() != Eigen::Success) return false;
      const StateVec step = ldlt.solve(grad);
      if (!step.allFinite()) return false;
      x_ += step;
      settled = step.dot(grad) < Scalar(0.01);
    }
    if (converged != nullptr) *converged = settled;
    return x_.allFinite();
  }

  // P = info^-1, column by column: a matrix right-hand side would go through Eigen's blocked
  // level-3 triangular solver, whose (unused) heap fallback the firmware image must not link.
  static bool invert_information(const StateMat& info, StateMat* p) noexcept {
    const Eigen::LDLT<StateMat> ldlt(info);
    if (ldlt.info() != Eigen::Success || !ldlt.isPositive()) return false;
    for (int c = 0; c < kN; ++c) {
      StateVec e = StateVec::Zero();
      e(c) = 1;
      const StateVec col = ldlt.solve(e);
      p->col(c) = col;
    }
    return p->allFinite();
  }

  // Relative 1-sigmas (C^-1 elements; b over the mean reference field) and the undetermined bits.
  void judge_sigmas(const StateMat& p0) noexcept {
    Scalar f_mean{0};
    for (int i = 0; i < n_buf_; ++i)
      f_mean += buf_f_[i];
    f_mean /= static_cast<Scalar>(n_buf_);
    // The filter linearises about the start: a relative error d leaves a second-order term d^2 F^2
    // in z = F^2, against the noise 2 F sigma of z. A start is good enough when d^2 F^2 <= 2 F
    // sigma, i.e. d <= sqrt(2 sigma / F): at 0.3 nT in 50 uT that is 0.35 %, far tighter than
    // init_max_sigma.
    report_.limit = std::min(cfg_.init_max_sigma, std::sqrt(Scalar(2) * sigma_ / f_mean));
    report_.undetermined = 0;
    for (int k = 0; k < kN; ++k) {
      Scalar sd = std::sqrt(std::max(p0(k, k), Scalar(0)));
      if (k >= kEkfBx) sd /= f_mean;
      if (!std::isfinite(sd)) sd = std::numeric_limits<Scalar>::infinity();
      report_.relative_sigma(k) = sd;
      if (!(sd <= report_.limit)) report_.undetermined |= 1U << k;
    }
  }

  // What the set can determine when no ellipsoid could be fitted: its information about a
  // nominal sphere (W = I / mean |m| times the mean F, b = 0) at the noise in use (when estimating
  // and no estimate exists yet, the algebraic fit's residual scale, else the configured guess). A
  // tiny ridge keeps a rank-deficient set (a plane of directions) invertible; its directions come
  // out with huge sigmas.
  void diagnose_without_fit(const StateVec& x_keep) noexcept {
    Scalar r_mean{0}, f_mean{0};
    for (int i = 0; i < n_buf_; ++i) {
      r_mean += buf_m(i).norm();
      f_mean += buf_f_[i];
    }
    x_ = flatten_state(Mat3<Scalar>::Identity() * (f_mean / r_mean), Vec3<Scalar>::Zero());
    std::fill_n(used_, n_buf_, Scalar(1));
    StateMat info;
    StateVec grad;
    normal_equations(&info, &grad);
    const Scalar ridge =
        info.diagonal().maxCoeff() * Scalar(64) * std::numeric_limits<Scalar>::epsilon();
    info.diagonal().array() += ridge;
    StateMat p0;
    if (invert_information(info, &p0)) {
      judge_sigmas(p0);
    } else {
      report_.relative_sigma.setConstant(std::numeric_limits<Scalar>::infinity());
      report_.undetermined = (1U << kN) - 1U;
    }
    x_ = x_keep;
  }

  bool solve_initial_fit() noexcept {
    const StateVec x_before = x_;
    const Scalar sigma_before = sigma_;
    report_ = InitReport{};
    report_.samples = n_buf_;
    std::fill_n(used_, capacity_, Scalar(0));
    std::fill_n(used_, n_buf_, Scalar(1));
    Vec3<Scalar> center = Vec3<Scalar>::Zero();
    for (int i = 0; i < n_buf_; ++i)
      center += buf_m(i);
    center /= static_cast<Scalar>(n_buf_);
    bool ok = algebraic_fit(center);
    const bool ellipsoid = ok;
    // Robust screening: spikes bias the algebraic fit, so use a threshold that adapts to its
    // residual spread, refit without the outliers, then Gauss-Newton with the gate proper.
    const Scalar gate = cfg_.gate_nis > 0 ? cfg_.gate_nis : std::numeric_limits<Scalar>::infinity();
    int dropped = 0;
    if (ok) {
      const Scalar robust = Scalar(5) * Scalar(1.4826) * median_abs_residual(true);
      dropped = screen(std::max(gate, robust * robust));
      if (dropped > 0) ok = algebraic_fit(center);
    }
    // The algebraic fit's residual scale: the noise the diagnosis assumes if nothing better comes.
    int n_alg = 0;
    const Scalar v_alg = ok ? noise_var_from_fit(&n_alg) : Scalar(0);
    bool converged = false;
    ok = ok && gauss_newton(cfg_.init_gauss_newton_iterations, &converged);
    if (ok && converged) {
      // The noise from these residuals (debias and gating depend on it), then settle again.
      int n = 0;
      const Scalar v = noise_var_from_fit(&n);
      if (cfg_.estimate_noise && v > 0 && !(noise_n_ > 0))
        sigma_ = std::max(std::sqrt(v), sigma_floor());
      // A given noise far below the residuals would gate every sample: screen no tighter than the
      // residuals' own robust spread.
      const Scalar robust = Scalar(5) * Scalar(1.4826) * median_abs_residual(true);
      const int late = screen(std::max(gate, robust * robust));
      dropped += late;
      ok = gauss_newton(2, &converged);
      if (ok && !converged) ok = gauss_newton(cfg_.init_gauss_newton_iterations, &converged);
    }
    StateMat info;
    StateVec grad;
    StateMat p0;
    const bool fitted =
        ok && converged && normal_equations(&info, &grad) >= 16 && invert_information(info, &p0);
    if (fitted) {
      judge_sigmas(p0);
      commit_fit_noise();
    } else {
      // No fit to judge (no ellipsoid, or Gauss-Newton wandered off): what could the set tell?
      if (cfg_.estimate_noise && v_alg > 0 && !(noise_var() > 0))
        sigma_ = std::max(std::sqrt(v_alg), sigma_floor());
      diagnose_without_fit(x_before);
    }
    if (fitted && report_.undetermined == 0 && c_inv().determinant() > 0 && ud_factorise(p0)) {
      counters_.init_outliers += static_cast<std::uint32_t>(dropped);
      // The filter's prior is this fit as a Gaussian: its quadratic, kept to be replaced later.
      start_x_lin_ = x_;
      start_info_ = info;
      start_grad_.setZero();
      start_term_ = true;
      start_updates_ = counters_.updates;
      // With process noise the filter forgets part of that term, and replacing the whole of it
      // would remove information it no longer holds: no relinearisation (and no 1-sigma from it).
      relin_next_ = cfg_.q.isZero() ? cfg_.relinearise_start_after : 0U;
      return true;
    }
    // Failed: say why, in the order the acceptance policy checks causes.
    if (report_.undetermined != 0) {
      report_.failure = EkfInitFailure::kUndetermined;
    } else if (!ellipsoid) {
      report_.failure = EkfInitFailure::kNotAnEllipsoid;
    } else {
      report_.failure = EkfInitFailure::kNotConverged;  // or a reflection / non-PD covariance
    }
    x_ = x_before;
    sigma_ = sigma_before;
    use_noise_estimate();
    u_.setIdentity();
    d_.setOnes();
    return false;
  }

  // P = U D U^T with U unit upper triangular. False unless P is positive definite.
  bool ud_factorise(const StateMat& p) noexcept {
    return core::ud_factorise<Scalar, kN>(p, &u_, &d_);
  }

  Config cfg_{};
  EkfCounters counters_{};
  EkfResetReason last_reset_ = EkfResetReason::kNone;
  InitReport report_{};
  Scalar scale_{0};
  Scalar sigma_{0};  // noise in use (normalised)
  bool initialised_ = false;
  bool use_fit_ = true;  // start from the initial fit (else from the configured start)
  StateVec x_ = StateVec::Zero();
  StateMat u_ = StateMat::Identity();
  StateVec d_ = StateVec::Ones();
  // The start-up set's term in the filter's cost (E-Acc-3): linearised at start_x_lin_, its
  // information and its gradient there; relinearised at updates start_updates_ + relin_next_.
  bool start_term_ = false;
  bool start_relinearised_ = false;  // since the current start
  StateVec start_x_lin_ = StateVec::Zero();
  StateMat start_info_ = StateMat::Zero();
  StateVec start_grad_ = StateVec::Zero();
  std::uint32_t start_updates_ = 0;
  std::uint32_t relin_next_ = 0;
  // Start-up set (normalised samples and reference field) and its direction information. The
  // arrays (capacity_ entries each; buf_m_ 3 per sample) are the derived class's storage.
  Scalar* buf_m_ = nullptr;
  Scalar* buf_f_ = nullptr;
  Scalar* used_ = nullptr;
  Scalar* lev_ = nullptr;
  Scalar* scratch_ = nullptr;  // for the median of residuals
  int capacity_ = 0;
  int n_buf_ = 0;
  int target_ = 0;  // size the set grows to (init_samples, doubled after undetermined tries)
  FeatureMat feat_info_ = FeatureMat::Zero();
  FeatureMat feat_inv_ = FeatureMat::Identity();  // (info + ridge I)^-1
  Scalar feat_logdet_{0};
  Scalar logdet_at_try_{0};
  bool feat_dirty_ = true;
  bool lev_dirty_ = true;
  bool tried_ = false;
  bool changed_since_try_ = false;
  // Noise estimate: the start-up fit's (prior_var with weight prior_n) and the innovations' terms
  // (count, mean, M2), merged per clean window.
  Scalar noise_prior_var_{0};
  Scalar noise_prior_n_{0};
  Scalar noise_n_{0};
  Scalar noise_mean_{0};
  Scalar noise_m2_{0};
  int window_noise_n_ = 0;
  Scalar window_noise_sum_{0};
  Scalar window_noise_sum2_{0};
  // Divergence-detection window.
  int window_n_ = 0;
  int window_gated_ = 0;
  Scalar window_nis_sum_{0};
  Scalar last_nis_{0};
};

template <typename Scalar>
void ScalarEkfBase<Scalar>::configure(const Config& config) noexcept {
  cfg_ = config;
  cfg_.init_samples = std::clamp(cfg_.init_samples, 16, capacity_);
  cfg_.init_min_samples = std::clamp(cfg_.init_min_samples, 16, cfg_.init_samples);
  cfg_.iterations = std::max(cfg_.iterations, 1);
  cfg_.nis_window = std::max(cfg_.nis_window, 10);
  counters_ = EkfCounters{};
  last_reset_ = EkfResetReason::kNone;
  report_ = InitReport{};
  scale_ = 0;
  sigma_ = 0;
  noise_prior_var_ = 0;
  noise_prior_n_ = 0;
  noise_n_ = 0;
  noise_mean_ = 0;
  noise_m2_ = 0;
  use_fit_ = cfg_.init_mode == EkfInitMode::kQuadricFit;
  x_.setZero();
  x_.template head<9>() = flatten(cfg_.w0);
  restart();
}

template <typename Scalar>
void ScalarEkfBase<Scalar>::restart() noexcept {
  initialised_ = false;
  start_term_ = false;
  start_relinearised_ = false;
  n_buf_ = 0;
  target_ = cfg_.init_samples;
  feat_info_.setZero();
  feat_dirty_ = true;
  lev_dirty_ = true;
  tried_ = false;
  changed_since_try_ = false;
  logdet_at_try_ = 0;
  window_n_ = 0;
  window_gated_ = 0;
  window_nis_sum_ = 0;
  window_noise_n_ = 0;
  window_noise_sum_ = 0;
  window_noise_sum2_ = 0;
  last_nis_ = 0;
  // Until a start exists the covariance is "unknown" (unit variance in normalised units); the
  // last state estimate is kept so model() still returns the best known calibration.
  u_.setIdentity();
  d_.setOnes();
  if (!use_fit_ && scale_ > 0) start_given();
}

template <typename Scalar>
EkfStatus ScalarEkfBase<Scalar>::update(const Vec3<Scalar>& m_nT) noexcept {
  return update(m_nT, cfg_.reference_field_nT);
}

template <typename Scalar>
EkfStatus ScalarEkfBase<Scalar>::update(const Vec3<Scalar>& m_nT, Scalar f_ref_nT) noexcept {
  using std::isfinite;
  if (!m_nT.allFinite()) {
    ++counters_.rejected_nonfinite;
    return EkfStatus::kRejectedNonFinite;
  }
  if (!(isfinite(f_ref_nT) && f_ref_nT > 0)) {
    ++counters_.rejected_reference;
    return EkfStatus::kRejectedBadReference;
  }
  if (!(scale_ > 0)) {
    scale_ = cfg_.field_scale_nT > 0 ? cfg_.field_scale_nT : f_ref_nT;
    sigma_ = cfg_.noise_sigma_nT / scale_;
    restart();
  }
  const Vec3<Scalar> m = m_nT / scale_;
  const Scalar fn = f_ref_nT / scale_;
  if (!m.allFinite()) {
    ++counters_.rejected_nonfinite;
    return EkfStatus::kRejectedNonFinite;
  }
  if (!initialised_) return collect(m, fn);
  return filter_step(m, fn, fn * fn);
}

template <typename Scalar>
bool ScalarEkfBase<Scalar>::try_start() noexcept {
  if (initialised_ || !use_fit_) return initialised_;
  if (n_buf_ < cfg_.init_min_samples) {
    report_ = InitReport{};
    report_.failure = EkfInitFailure::kTooFewSamples;
    report_.samples = n_buf_;
    return false;
  }
  if (tried_ && !changed_since_try_) return false;
  return attempt_fit();
}

template <typename Scalar>
typename ScalarEkfBase<Scalar>::Features ScalarEkfBase<Scalar>::features(
    const Vec3<Scalar>& u) noexcept {
  Features f;
  f << u(0) * u(0), u(1) * u(1), u(2) * u(2), u(0) * u(1), u(0) * u(2), u(1) * u(2), u(0), u(1),
      u(2);
  return f;
}

// The filter with the storage of a start-up set of up to kInitCapacity samples (64 on the MCU;
// the host's recording runner lets noisy sets grow to 512).
template <typename Scalar, int kInitCapacity = 64>
class ScalarEkf : public ScalarEkfBase<Scalar> {
  static_assert(kInitCapacity >= 16, "the initial fit needs well over 10 samples");
  using Base = ScalarEkfBase<Scalar>;

 public:
  using typename Base::Config;

  explicit ScalarEkf(const Config& config = Config{}) noexcept : Base(kInitCapacity) {
    bind();
    this->configure(config);
  }
  ScalarEkf(const ScalarEkf& other) noexcept : Base(other), store_(other.store_) { bind(); }
  ScalarEkf& operator=(const ScalarEkf& other) noexcept {
    Base::operator=(other);
    store_ = other.store_;
    bind();
    return *this;
  }
  ~ScalarEkf() = default;

 private:
  void bind() noexcept {
    this->bind_storage(store_.m.data(), store_.f.data(), store_.used.data(), store_.lev.data(),
                       store_.scratch.data());
  }
  static constexpr auto kCap = static_cast<std::size_t>(kInitCapacity);
  struct Store {
    std::array<Scalar, 3 * kCap> m{};
    std::array<Scalar, kCap> f{};
    std::array<Scalar, kCap> used{};
    std::array<Scalar, kCap> lev{};
    std::array<Scalar, kCap> scratch{};
  };
  Store store_{};
};

// The filter compiled once per scalar for the host (firmware/core/src/inst_ekf_<scalar>.cpp, the
// magvec::core_ekf_<scalar> libraries), as the batch calibrator is (see the end of
// batch_calibrator.hpp): the units that use it, at any capacity, only call it (when they link the
// library: its compile definition).
#ifdef MAGVEC_CORE_EKF_DOUBLE_COMPILED
extern template class ScalarEkfBase<double>;
extern template class ScalarEkf<double>;
#endif
#ifdef MAGVEC_CORE_EKF_FLOAT_COMPILED
extern template class ScalarEkfBase<float>;
extern template class ScalarEkf<float>;
#endif

}  // namespace magvec::core
