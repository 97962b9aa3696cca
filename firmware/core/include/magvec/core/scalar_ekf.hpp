// Online scalar-observation calibration filter after Ge et al. 2017 (seed 002), corrected per
// shared/seeds/ERRATA.md section 002.
//   State (eq. 15): x = [C^-1 row-major (9), b (3)], constant parameters (eq. 16) plus process
//   noise. Measurement (eq. 17-21, ERRATA 002-1): h(x) = |C^-1 (m - b)|^2 against z = F_ref^2, with
//   the exact Jacobian dh/d(C^-1)_rc = 2 y_r v_c, dh/db = -2 C^-T y (v = m - b, y = C^-1 v); the
//   printed eq. (25) is wrong and not used.
// Numerics: the covariance is held as P = U D U^T (U unit upper triangular, D > 0) and updated with
// Bierman's scalar measurement update and the Agee-Turner rank-one update for diagonal process
// noise, both O(n^2) and symmetric positive definite by construction, which keeps float32 usable.
// Fields are divided by a reference magnitude s (the first reference total field unless configured)
// so that every state is O(1) in float32 (ERRATA 002-5); the interface is in nT.
// One-pass convergence (ERRATA 002-3): by default the filter starts from a fit of the first N
// samples (an algebraic quadric least-squares fit, outlier screening, then Gauss-Newton on the
// exact model over those samples); P0 is the inverse information of those samples, so no data is
// wasted and the filter continues as a recursive Gauss-Newton from there. `EkfConfig::paper()`
// reproduces the printed x0/P0/Q/R (with gate and divergence detection off) so the paper's setup
// can be rerun. Note for later deduplication: the algebraic quadric fit in scalar_ekf_detail
// overlaps with the batch EllipsoidFit module; it is kept here small and self-contained on purpose.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/LU>
#include <algorithm>
#include <cmath>
#include <cstdint>
#include <limits>

#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

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
  kQuadricFit,  // default: fit the first init_samples samples, then filter (one-pass)
  kGiven,       // start from w0/b0_nT/p0 as configured (paper, or "identity + mean" start)
};

// Result of one update() call.
enum class EkfStatus : std::uint8_t {
  kAccepted,     // measurement update applied
  kCollecting,   // buffered for the initial fit
  kInitialised,  // this sample completed the initial fit; the filter is now running
  kInitFailed,   // the initial fit failed (poor coverage or not an ellipsoid); collecting again
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

struct EkfCounters {
  std::uint32_t updates = 0;             // accepted measurement updates
  std::uint32_t gated = 0;               // rejected by the innovation gate
  std::uint32_t rejected_nonfinite = 0;  // NaN/inf magnetometer samples
  std::uint32_t rejected_reference = 0;  // unusable reference field values
  std::uint32_t reinitialisations = 0;   // automatic restarts after detected divergence
  std::uint32_t init_outliers = 0;       // samples dropped by the initial fit's screening
  std::uint32_t init_failures = 0;       // initial fits that failed and restarted collection
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
  Scalar noise_sigma_nT{10};
  Scalar reference_sigma_nT{0};
  Scalar r_fixed_nT4{0};
  // Predict E[h] = |y|^2 + sigma^2 tr(C^-T C^-1) (removes the noise-power bias of |m - b|^2).
  bool debias = true;
  // kGiven start: x0 and P0 in interface units (C^-1 dimensionless, b in nT, P0_b in nT^2).
  Mat3<Scalar> w0 = Mat3<Scalar>::Identity();
  Vec3<Scalar> b0_nT = Vec3<Scalar>::Zero();
  Vec<Scalar, kN> p0 = Vec<Scalar, kN>::Zero();
  // Process noise per update (diagonal, interface units). q(9..11) on b tracks slow offset drift.
  Vec<Scalar, kN> q = Vec<Scalar, kN>::Zero();
  int iterations = 1;  // > 1: iterated EKF (relinearise the measurement about the updated state)
  // Initial quadric fit (kQuadricFit).
  int init_samples = 64;  // <= the filter's init capacity
  int init_gauss_newton_iterations = 4;
  // A sample enters the initial fit only if it differs from the last one taken by this fraction of
  // the reference field, so a slowly turning platform still gets a spread set (others are skipped).
  Scalar init_min_step{Scalar(0.2)};
  // The initial fit is refused (poor coverage) if any predicted 1-sigma exceeds this fraction of
  // the field scale (C^-1 elements are dimensionless, b relative to the scale).
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
  // divergence detection, no debiasing. They do not work (ERRATA 002-3); kept to show it.
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

  // ERRATA 002-3 "sound filter": start at C^-1 = identity (or w0), b = a given offset (e.g. the
  // mean of the measurements), broad P0, Q = 0, R from the noise. Used to compare against the
  // default.
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

namespace scalar_ekf_detail {

// Quadric monomials of p (centred, normalised): phi^T theta = (p - b)^T G (p - b) for
// theta = [G00, G11, G22, G01, G02, G12, (G b)_0..2, b^T G b].
template <typename Scalar>
Vec<Scalar, 10> quadric_monomials(const Vec3<Scalar>& p) noexcept {
  Vec<Scalar, 10> phi;
  phi << p(0) * p(0), p(1) * p(1), p(2) * p(2), Scalar(2) * p(0) * p(1), Scalar(2) * p(0) * p(2),
      Scalar(2) * p(1) * p(2), Scalar(-2) * p(0), Scalar(-2) * p(1), Scalar(-2) * p(2), Scalar(1);
  return phi;
}

// Small streaming algebraic ellipsoid fit: accumulates S = sum phi phi^T (10x10, O(1) memory) and
// solves min theta^T S theta subject to tr(G) = 1 (a linear constraint: substitute
// G22 = 1 - G00 - G11, a 9x9 linear least-squares problem). The quadric (p - b)^T G (p - b) = k is
// then scaled to the mean reference z = F^2. With a constant reference the problem is homogeneous,
// so an unconstrained fit of phi^T theta = z would be singular. Returns W as the upper-triangular
// Cholesky factor (W^T W = G) and b.
template <typename Scalar>
class QuadricAccumulator {
 public:
  void clear() noexcept {
    s_.setZero();
    z_sum_ = 0;
    n_ = 0;
  }
  void add(const Vec3<Scalar>& p, Scalar z) noexcept {
    s_.template selfadjointView<Eigen::Lower>().rankUpdate(quadric_monomials<Scalar>(p));
    z_sum_ += z;
    ++n_;
  }
  int count() const noexcept { return n_; }

  // W, b in the accumulated (centred) coordinates. False if the quadric is not an ellipsoid.
  bool solve(Mat3<Scalar>* w, Vec3<Scalar>* b) const noexcept {
    if (n_ < 10) return false;
    const Mat<Scalar, 10, 10> full = s_.template selfadjointView<Eigen::Lower>();
    // theta = t0 + T^T theta' with t0 = e_2 (G22 = 1 - G00 - G11).
    Mat<Scalar, 9, 10> t = Mat<Scalar, 9, 10>::Zero();
    t(0, 0) = 1;
    t(0, 2) = -1;
    t(1, 1) = 1;
    t(1, 2) = -1;
    for (int i = 2; i < 9; ++i)
      t(i, i + 1) = 1;
    const Mat<Scalar, 9, 9> a = t * full * t.transpose();
    const Vec<Scalar, 9> rhs = -(t * full.col(2));
    const Eigen::LDLT<Mat<Scalar, 9, 9>> ldlt(a);
    if (ldlt.info() != Eigen::Success) return false;
    const Vec<Scalar, 9> tp = ldlt.solve(rhs);
    if (!tp.allFinite()) return false;
    Vec<Scalar, 10> theta = t.transpose() * tp;
    theta(2) += 1;
    Mat3<Scalar> g;
    g << theta(0), theta(3), theta(4), theta(3), theta(1), theta(5), theta(4), theta(5), theta(2);
    const Eigen::LLT<Mat3<Scalar>> llt_g(g);
    if (llt_g.info() != Eigen::Success) return false;
    const Vec3<Scalar> center = llt_g.solve(theta.template segment<3>(6));
    // phi^T theta = (p - b)^T G (p - b) - k with k = b^T G b - theta_9.
    const Scalar k = center.dot(g * center) - theta(9);
    const Scalar z_mean = z_sum_ / static_cast<Scalar>(n_);
    if (!(k > 0 && z_mean > 0)) return false;
    const Eigen::LLT<Mat3<Scalar>> llt(g * (z_mean / k));
    if (llt.info() != Eigen::Success) return false;
    *w = llt.matrixU();
    *b = center;
    return w->allFinite() && b->allFinite();
  }

 private:
  Mat<Scalar, 10, 10> s_ = Mat<Scalar, 10, 10>::Zero();
  Scalar z_sum_{0};
  int n_ = 0;
};

}  // namespace scalar_ekf_detail

template <typename Scalar, int kInitCapacity = 64>
class ScalarEkf {
  static_assert(CoreScalar<Scalar>);
  static_assert(kInitCapacity >= 16, "the initial fit needs well over 10 samples");

 public:
  static constexpr int kN = kEkfStateDim;
  using StateVec = Vec<Scalar, kN>;
  using StateMat = Mat<Scalar, kN, kN>;
  using Config = EkfConfig<Scalar>;

  explicit ScalarEkf(const Config& config = Config{}) noexcept { configure(config); }

  // Replaces the configuration and restarts the filter; counters are cleared.
  void configure(const Config& config) noexcept {
    cfg_ = config;
    cfg_.init_samples = std::clamp(cfg_.init_samples, 16, kInitCapacity);
    cfg_.iterations = std::max(cfg_.iterations, 1);
    cfg_.nis_window = std::max(cfg_.nis_window, 10);
    counters_ = EkfCounters{};
    last_reset_ = EkfResetReason::kNone;
    scale_ = 0;
    use_fit_ = cfg_.init_mode == EkfInitMode::kQuadricFit;
    x_.setZero();
    x_.template head<9>() = flatten(cfg_.w0);
    restart();
  }

  // Restarts estimation (new initial fit or the configured start); keeps counters and scale.
  void restart() noexcept {
    initialised_ = false;
    n_buf_ = 0;
    window_n_ = 0;
    window_gated_ = 0;
    window_nis_sum_ = 0;
    last_nis_ = 0;
    // Until a start exists the covariance is "unknown" (unit variance in normalised units); the
    // last state estimate is kept so model() still returns the best known calibration.
    u_.setIdentity();
    d_.setOnes();
    if (!use_fit_ && scale_ > 0) start_given();
  }

  EkfStatus update(const Vec3<Scalar>& m_nT) noexcept {
    return update(m_nT, cfg_.reference_field_nT);
  }

  // One sample: raw magnetometer reading m [nT] and the reference total field F [nT] at that time.
  EkfStatus update(const Vec3<Scalar>& m_nT, Scalar f_ref_nT) noexcept {
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
      restart();
    }
    const Vec3<Scalar> m = m_nT / scale_;
    const Scalar fn = f_ref_nT / scale_;
    if (!m.allFinite()) {
      ++counters_.rejected_nonfinite;
      return EkfStatus::kRejectedNonFinite;
    }
    const Scalar z = fn * fn;
    if (!initialised_) {
      if (n_buf_ > 0 && (m - buf_m_.col(n_buf_ - 1)).norm() < cfg_.init_min_step * fn) {
        return EkfStatus::kCollecting;
      }
      buf_m_.col(n_buf_) = m;
      buf_f_(n_buf_) = fn;
      ++n_buf_;
      if (n_buf_ < cfg_.init_samples) return EkfStatus::kCollecting;
      if (solve_initial_fit()) {
        initialised_ = true;
        return EkfStatus::kInitialised;
      }
      ++counters_.init_failures;
      n_buf_ = 0;
      return EkfStatus::kInitFailed;
    }
    return filter_step(m, fn, z);
  }

  bool initialised() const noexcept { return initialised_; }
  const EkfCounters& counters() const noexcept { return counters_; }
  EkfResetReason last_reset_reason() const noexcept { return last_reset_; }
  const Config& config() const noexcept { return cfg_; }
  Scalar field_scale_nT() const noexcept { return scale_; }
  // Normalised innovation squared of the last processed (accepted or gated) sample.
  Scalar last_nis() const noexcept { return last_nis_; }

  Mat3<Scalar> c_inv() const noexcept { return unflatten(x_.template head<9>()); }
  Vec3<Scalar> offset_nT() const noexcept { return x_.template tail<3>() * scale_or_one(); }
  // Canonical form (DESIGN.md): W = C^-1, o = b, Rm = identity. Only G = W^T W and o are
  // observable.
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
    // diag(U D U^T)_i = sum_j U_ij^2 D_j (j >= i)
    StateVec s;
    for (int i = 0; i < kN; ++i) {
      Scalar acc{0};
      for (int j = i; j < kN; ++j)
        acc += u_(i, j) * u_(i, j) * d_(j);
      s(i) = std::sqrt(std::max(acc, Scalar(0)));
    }
    return s.cwiseProduct(unit_scale());
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

 private:
  static StateVec flatten_state(const Mat3<Scalar>& w, const Vec3<Scalar>& b) noexcept {
    StateVec x;
    x.template head<9>() = flatten(w);
    x.template tail<3>() = b;
    return x;
  }
  static Vec<Scalar, 9> flatten(const Mat3<Scalar>& w) noexcept {
    Vec<Scalar, 9> v;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        v(ekf_w_index(r, c)) = w(r, c);
    return v;
  }
  static Mat3<Scalar> unflatten(const Vec<Scalar, 9>& v) noexcept {
    Mat3<Scalar> w;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        w(r, c) = v(ekf_w_index(r, c));
    return w;
  }
  Scalar scale_or_one() const noexcept { return scale_ > 0 ? scale_ : Scalar(1); }
  StateVec unit_scale() const noexcept {
    StateVec t = StateVec::Ones();
    t.template tail<3>().setConstant(scale_or_one());
    return t;
  }

  // dh/dx with v = m - b, y = W v; debias adds d(sigma^2 tr(W^T W))/dW = 2 sigma^2 W.
  StateVec jacobian(const Vec3<Scalar>& y, const Vec3<Scalar>& v,
                    Scalar sigma2_debias) const noexcept {
    StateVec h;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        h(ekf_w_index(r, c)) =
            Scalar(2) * y(r) * v(c) + Scalar(2) * sigma2_debias * x_(ekf_w_index(r, c));
    h.template tail<3>() = Scalar(-2) * (c_inv().transpose() * y);
    return h;
  }

  struct Linearisation {
    StateVec h_row = StateVec::Zero();
    Scalar h{0};  // predicted measurement
    Scalar r{0};  // measurement variance
  };
  // Measurement model at the current state for normalised m and F (fn).
  Linearisation linearise(const Vec3<Scalar>& m, Scalar fn) const noexcept {
    const Scalar s = scale_or_one();
    const Mat3<Scalar> w = c_inv();
    const Vec3<Scalar> v = m - x_.template tail<3>();
    const Vec3<Scalar> y = w * v;
    const Scalar sig = cfg_.noise_sigma_nT / s;
    const Scalar sig2 = sig * sig;
    const Scalar deb = cfg_.debias ? sig2 : Scalar(0);
    Linearisation l;
    l.h_row = jacobian(y, v, deb);
    l.h = y.squaredNorm() + deb * w.squaredNorm();
    if (cfg_.r_fixed_nT4 > 0) {
      l.r = cfg_.r_fixed_nT4 / (s * s * s * s);
    } else {
      const Mat3<Scalar> g = w.transpose() * w;
      const Scalar sf = cfg_.reference_sigma_nT / s;
      l.r = Scalar(4) * sig2 * (w.transpose() * y).squaredNorm() +
            Scalar(2) * sig2 * sig2 * g.squaredNorm() + Scalar(4) * fn * fn * sf * sf;
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

  // All of U finite. Only the strict upper triangle can change (the diagonal stays 1, the lower
  // triangle 0: Bierman, Agee-Turner and ud_factorise write i < j only), and v * 0 is 0 for a
  // finite v but NaN for inf/NaN: an exact test at one multiply-add per element, a third of the
  // cost of allFinite() over all 144 elements on the per-sample path (issue 8 budget).
  bool u_upper_finite() const noexcept {
    Scalar probe{0};
    for (int j = 1; j < kN; ++j)
      for (int i = 0; i < j; ++i)
        probe += u_(i, j) * Scalar(0);
    return probe == Scalar(0);
  }

  // U^T h for the unit upper triangular U: 66 multiply-adds instead of the 144 of a full product
  // (per sample, twice: the update and the loop's intensity sigma). Same terms, summed in order.
  StateVec ut_times(const StateVec& h) const noexcept {
    StateVec f;
    for (int j = 0; j < kN; ++j) {
      Scalar acc = h(j);
      for (int i = 0; i < j; ++i)
        acc += u_(i, j) * h(i);
      f(j) = acc;
    }
    return f;
  }

  // ---- covariance factor updates ----------------------------------------------------------------
  // Agee-Turner: U D U^T + c e_k e_k^T for c > 0, O(k^2).
  void add_diagonal_noise(int k, Scalar c) noexcept {
    StateVec a = StateVec::Zero();
    a(k) = Scalar(1);
    for (int j = k; j > 0; --j) {
      const Scalar s = a(j);
      const Scalar dj = d_(j) + c * s * s;
      const Scalar beta = c * s / dj;
      c = c * d_(j) / dj;
      d_(j) = dj;
      for (int i = 0; i < j; ++i) {
        a(i) -= s * u_(i, j);
        u_(i, j) += beta * a(i);
      }
    }
    d_(0) += c * a(0) * a(0);
  }

  // Bierman's scalar update of U, D for a measurement with f = U^T h^T and variance r. Returns the
  // unnormalised gain k (K = k / s) and the innovation variance s = h P h^T + r.
  void bierman(const StateVec& f, Scalar r, StateVec* k_out, Scalar* s_out) noexcept {
    const StateVec v = d_.cwiseProduct(f);
    StateVec k = StateVec::Zero();
    Scalar alpha = r + f(0) * v(0);
    d_(0) *= r / alpha;
    k(0) = v(0);
    for (int j = 1; j < kN; ++j) {
      const Scalar beta = alpha;
      alpha += f(j) * v(j);
      const Scalar lambda = -f(j) / beta;
      d_(j) *= beta / alpha;
      for (int i = 0; i < j; ++i) {
        const Scalar uij = u_(i, j);
        u_(i, j) = uij + lambda * k(i);
        k(i) += v(j) * uij;
      }
      k(j) = v(j);
    }
    *k_out = k;
    *s_out = alpha;
  }

  // ---- the filter step ---------------------------------------------------------------------
  EkfStatus filter_step(const Vec3<Scalar>& m, Scalar fn, Scalar z) noexcept {
    const Linearisation l0 = linearise(m, fn);
    // A finite but absurd sample can overflow the prediction: reject it before touching anything.
    if (!(std::isfinite(l0.h) && std::isfinite(l0.r) && l0.h_row.allFinite())) {
      ++counters_.rejected_nonfinite;
      return EkfStatus::kRejectedNonFinite;
    }
    const Scalar s2 = scale_or_one() * scale_or_one();
    for (int k = 0; k < kN; ++k) {
      const Scalar qk = k >= kEkfBx ? cfg_.q(k) / s2 : cfg_.q(k);
      if (qk > 0) add_diagonal_noise(k, qk);
    }
    const StateVec f0 = ut_times(l0.h_row);
    const Scalar s0 = l0.r + f0.dot(d_.cwiseProduct(f0));
    const Scalar nu0 = z - l0.h;
    if (!(std::isfinite(s0) && s0 > 0 && std::isfinite(nu0)))
      return reinitialise(EkfResetReason::kNonFiniteState);
    last_nis_ = nu0 * nu0 / s0;
    if (cfg_.gate_nis > 0 && last_nis_ > cfg_.gate_nis) {
      ++counters_.gated;
      ++window_gated_;
      return end_of_window_check(EkfStatus::kGated);
    }
    StateVec k;
    Scalar s;
    if (cfg_.iterations == 1) {
      bierman(f0, l0.r, &k, &s);
      x_ += k * (nu0 / s);
    } else {
      const StateVec x_prior = x_;
      const StateMat u_prior = u_;
      const StateVec d_prior = d_;
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
    if (!x_.allFinite() || !d_.allFinite() || !u_upper_finite())
      return reinitialise(EkfResetReason::kNonFiniteState);
    if (!(d_.array() > 0).all()) return reinitialise(EkfResetReason::kCovarianceNotPositive);
    if (!(std::abs(c_inv().determinant()) > std::numeric_limits<Scalar>::epsilon())) {
      return reinitialise(EkfResetReason::kSingularModel);
    }
    ++counters_.updates;
    window_nis_sum_ += last_nis_;
    return end_of_window_check(EkfStatus::kAccepted);
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
    if (!cfg_.divergence_detection) return status;
    if (gated_fraction > cfg_.gated_fraction_limit)
      return reinitialise(EkfResetReason::kTooManyGated);
    if (mean_nis > cfg_.nis_mean_limit) return reinitialise(EkfResetReason::kNisTooHigh);
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

  // ---- initial fit over the buffered samples -----------------------------------------------
  bool algebraic_fit(const Vec3<Scalar>& center) noexcept {
    scalar_ekf_detail::QuadricAccumulator<Scalar> acc;
    acc.clear();
    for (int i = 0; i < n_buf_; ++i) {
      if (used_(i) > 0) acc.add(buf_m_.col(i) - center, buf_f_(i) * buf_f_(i));
    }
    Mat3<Scalar> w;
    Vec3<Scalar> b;
    if (!acc.solve(&w, &b)) return false;
    x_ = flatten_state(w, b + center);
    return true;
  }

  // Normal equations of the exact model over the used buffered samples at x_.
  // Returns the number of samples used; info = sum H^T H / R (+ gauge prior), grad = sum H^T r / R.
  int normal_equations(StateMat* info, StateVec* grad) const noexcept {
    info->setZero();
    grad->setZero();
    int n = 0;
    for (int i = 0; i < n_buf_; ++i) {
      if (!(used_(i) > 0)) continue;
      const Linearisation l = linearise(buf_m_.col(i), buf_f_(i));
      const Scalar res = buf_f_(i) * buf_f_(i) - l.h;
      info->template selfadjointView<Eigen::Lower>().rankUpdate(l.h_row, Scalar(1) / l.r);
      *grad += l.h_row * (res / l.r);
      ++n;
    }
    *info = info->template selfadjointView<Eigen::Lower>();
    // The rotation gauge (ERRATA 002-2) is unobservable: pin it by a prior on the lower triangle of
    // W, which the Cholesky start sets to zero, at the scale of the data's information.
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
      if (!(used_(i) > 0)) continue;
      const Linearisation l = linearise(buf_m_.col(i), buf_f_(i));
      const Scalar res = buf_f_(i) * buf_f_(i) - l.h;
      if (!(res * res <= threshold * l.r)) {
        used_(i) = 0;
        ++dropped;
      }
    }
    return dropped;
  }

  Scalar median_abs_normalised_residual() const noexcept {
    Vec<Scalar, kInitCapacity> e;
    int n = 0;
    for (int i = 0; i < n_buf_; ++i) {
      if (!(used_(i) > 0)) continue;
      const Linearisation l = linearise(buf_m_.col(i), buf_f_(i));
      e(n++) = std::abs(buf_f_(i) * buf_f_(i) - l.h) / std::sqrt(l.r);
    }
    if (n == 0) return Scalar(0);
    Scalar* first = e.data();
    std::nth_element(first, first + n / 2, first + n);
    return e(n / 2);
  }

  bool gauss_newton(int iterations) noexcept {
    for (int it = 0; it < iterations; ++it) {
      StateMat info;
      StateVec grad;
      if (normal_equations(&info, &grad) < 16) return false;
      const Eigen::LDLT<StateMat> ldlt(info);
      if (ldlt.info() != Eigen::Success) return false;
      const StateVec step = ldlt.solve(grad);
      if (!step.allFinite()) return false;
      x_ += step;
    }
    return x_.allFinite();
  }

  bool solve_initial_fit() noexcept {
    const StateVec x_before = x_;
    used_.setZero();
    used_.head(n_buf_).setOnes();
    Vec3<Scalar> center = Vec3<Scalar>::Zero();
    for (int i = 0; i < n_buf_; ++i)
      center += buf_m_.col(i);
    center /= static_cast<Scalar>(n_buf_);
    bool ok = algebraic_fit(center);
    // Robust screening: spikes bias the algebraic fit, so use a threshold that adapts to its
    // residual spread, refit without the outliers, then Gauss-Newton with the gate proper.
    const Scalar gate = cfg_.gate_nis > 0 ? cfg_.gate_nis : std::numeric_limits<Scalar>::infinity();
    int dropped = 0;
    if (ok) {
      const Scalar robust = Scalar(5) * Scalar(1.4826) * median_abs_normalised_residual();
      dropped = screen(std::max(gate, robust * robust));
      if (dropped > 0) ok = algebraic_fit(center);
    }
    ok = ok && gauss_newton(cfg_.init_gauss_newton_iterations);
    if (ok) {
      const int late = screen(gate);
      dropped += late;
      if (late > 0) ok = gauss_newton(2);
    }
    StateMat info;
    StateVec grad;
    ok = ok && normal_equations(&info, &grad) >= 16;
    if (ok) {
      // P0 = info^-1: the filter has absorbed these samples and continues from here.
      const Eigen::LDLT<StateMat> ldlt(info);
      // Column by column: a matrix right-hand side would go through Eigen's blocked level-3
      // triangular solver, whose (unused) heap fallback the firmware image must not link.
      StateMat p0;
      for (int c = 0; c < kN; ++c) {
        StateVec e = StateVec::Zero();
        e(c) = 1;
        const StateVec col = ldlt.solve(e);
        p0.col(c) = col;
      }
      ok = ldlt.info() == Eigen::Success && ldlt.isPositive() && p0.allFinite() &&
           sigma_acceptable(p0) && c_inv().determinant() > 0 && ud_factorise(p0);
    }
    if (!ok) {
      x_ = x_before;
      u_.setIdentity();
      d_.setOnes();
      return false;
    }
    counters_.init_outliers += static_cast<std::uint32_t>(dropped);
    return true;
  }

  // Predicted 1-sigma of every state below init_max_sigma (C^-1 elements; b relative to the field).
  bool sigma_acceptable(const StateMat& p0) const noexcept {
    Scalar f_mean{0};
    for (int i = 0; i < n_buf_; ++i)
      f_mean += buf_f_(i);
    f_mean /= static_cast<Scalar>(n_buf_);
    const Scalar lim_w = cfg_.init_max_sigma * cfg_.init_max_sigma;
    const Scalar lim_b = lim_w * f_mean * f_mean;
    return p0.diagonal().template head<9>().maxCoeff() < lim_w &&
           p0.diagonal().template tail<3>().maxCoeff() < lim_b;
  }

  // P = U D U^T with U unit upper triangular. False unless P is positive definite.
  bool ud_factorise(const StateMat& p) noexcept {
    StateMat u = StateMat::Identity();
    StateVec d = StateVec::Zero();
    for (int j = kN - 1; j >= 0; --j) {
      Scalar dj = p(j, j);
      for (int k = j + 1; k < kN; ++k)
        dj -= d(k) * u(j, k) * u(j, k);
      if (!(dj > 0)) return false;
      d(j) = dj;
      for (int i = 0; i < j; ++i) {
        Scalar a = p(i, j);
        for (int k = j + 1; k < kN; ++k)
          a -= d(k) * u(i, k) * u(j, k);
        u(i, j) = a / dj;
      }
    }
    u_ = u;
    d_ = d;
    return true;
  }

  Config cfg_{};
  EkfCounters counters_{};
  EkfResetReason last_reset_ = EkfResetReason::kNone;
  Scalar scale_{0};
  bool initialised_ = false;
  bool use_fit_ = true;  // start from the initial fit (else from the configured start)
  StateVec x_ = StateVec::Zero();
  StateMat u_ = StateMat::Identity();
  StateVec d_ = StateVec::Ones();
  // Initial-fit buffer (normalised samples and reference field).
  Mat<Scalar, 3, kInitCapacity> buf_m_ = Mat<Scalar, 3, kInitCapacity>::Zero();
  Vec<Scalar, kInitCapacity> buf_f_ = Vec<Scalar, kInitCapacity>::Zero();
  Vec<Scalar, kInitCapacity> used_ = Vec<Scalar, kInitCapacity>::Zero();
  int n_buf_ = 0;
  // Divergence-detection window.
  int window_n_ = 0;
  int window_gated_ = 0;
  Scalar window_nis_sum_{0};
  Scalar last_nis_{0};
};

}  // namespace magvec::core
