// Online full-vector calibration filter (docs/equations.md E-VF-A .. E-VF-8): an error-state
// extended Kalman filter that estimates, from every magnetometer sample with its INS attitude,
//   W (6: Li structure, the rotation belongs to Rm), offset o (3), misalignment Rm (3, body-frame
//   small-angle error folded into a quaternion), local field h_n (3, ENU), magnetometer-INS time
//   offset dt (1) and offset temperature coefficients c (3): o(T) = o + c (T - T0).
// Measurement (E-VF-2): the geographic residual of the one-step fit (E-OS-1) with the attitude
// moved back by the time offset (E-TO-1),
//   r = Exp(-dt [Omega x]) R_bn^T Rm^T W (m - o - c (T - T0)) - h_n,
// weighted by its covariance from the magnetometer and INS angle noise (E-OS-3), whitened and
// applied as three scalar updates; a scalar reference F adds the scalar update |h_n| = F (E-VF-4).
// Jacobians: E-VF-3. Time offset: E-VF-5. Temperature: E-VF-6. Heading rule: E-VF-7 (the rotation
// about the body z axis is held, its gain exactly zero, until the tilt spread reaches the batch
// methods' limit). Gating, divergence and resets: E-VF-8.
// Live updates per sample (three sequential scalar updates) or in information folds of
// fold_samples samples (E-VF-B: summed at the last fold's state, then the block's mean and trend
// as pseudo-measurements).
// Numerics: P = U D U^T (Bierman scalar update, Agee-Turner for process noise, as scalar_ekf.hpp),
// fields normalised by a reference magnitude, states held as nominal + error so float32 does not
// lose updates below the resolution of values of order one (E-VF-A).
// Start: from a stored calibration with its 1-sigmas, or from the first well-spread samples: the
// batch calibrator (one-step fit, batch_calibrator.hpp) gives the linearisation point and the
// filter then replays those samples from a diffuse prior (E-VF-1). Replays are Gauss-Newton steps
// (every sample linearised at the pass's start) and take every sample seen while collecting, kept
// in a replay store of kReplayCapacity samples; after a stored start the first kReplayCapacity
// samples are replayed the same way from the stored prior.
// Fixed-size, heap-free, noexcept, float and double.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <type_traits>

#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/output_envelope.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"
#include "magvec/core/ud_factor.hpp"

namespace magvec::core {

// One magnetometer sample with what the filter needs from the INS and the environment.
template <typename Scalar>
struct VfSample {
  Vec3<Scalar> m_nT = Vec3<Scalar>::Zero();           // raw reading
  Mat3<Scalar> r_bn = Mat3<Scalar>::Identity();       // INS attitude at stamp - attitude_offset_s
  Vec3<Scalar> omega_n_rad_s = Vec3<Scalar>::Zero();  // rotation rate of R_bn^T, n-frame axes
  // The time offset the caller already applied to r_bn: the INS attitude at the sample's stamp
  // minus this (interpolated; 0: at the stamp). The model rotates only by the rest, state - this,
  // so the rate's noise is not multiplied by the whole offset (E-VF-5).
  Scalar attitude_offset_s{0};
  Scalar f_nT = std::numeric_limits<Scalar>::quiet_NaN();  // scalar reference (NaN: none)
  Scalar temperature_degC = std::numeric_limits<Scalar>::quiet_NaN();  // NaN: none
  Scalar interval_s = std::numeric_limits<Scalar>::quiet_NaN();        // since the previous sample
};

enum class VfStatus : std::uint8_t {
  kAccepted,             // measurement updates applied
  kCollecting,           // kept (or skipped) for the start from data
  kInitialised,          // this sample completed the start; the filter runs
  kInitFailed,           // a start from data was tried and refused; collecting anew
  kGated,                // innovation outside the gate: sample rejected, state untouched
  kFieldReopened,        // consecutive reference rejections: h_n re-opened, then updated
  kRejectedNonFinite,    // NaN/inf reading or attitude
  kRejectedNoReference,  // collecting without a scalar reference (the start needs one)
  kReset,                // divergence detected (last_reset_reason()); collecting for a restart
};

enum class VfResetReason : std::uint8_t {
  kNone,
  kNonFiniteState,         // state or innovation variance became NaN/inf
  kCovarianceNotPositive,  // a D factor became <= 0
  kNisTooHigh,             // window mean NIS of the accepted scalar updates above the limit
  kTooManyGated,           // window fraction of gated samples above the limit
  kConsecutiveRejections,  // too many vector samples gated in a row
  kSingularModel,          // det W numerically zero
  kFieldChange,            // (partial) reference gated in a row: h_n re-opened, rest kept
};

inline const char* vf_reset_reason_name(VfResetReason r) noexcept {
  switch (r) {
    case VfResetReason::kNone:
      return "none";
    case VfResetReason::kNonFiniteState:
      return "non_finite_state";
    case VfResetReason::kCovarianceNotPositive:
      return "covariance_not_positive";
    case VfResetReason::kNisTooHigh:
      return "nis_too_high";
    case VfResetReason::kTooManyGated:
      return "too_many_gated";
    case VfResetReason::kConsecutiveRejections:
      return "consecutive_rejections";
    case VfResetReason::kSingularModel:
      return "singular_model";
    case VfResetReason::kFieldChange:
      return "field_change";
  }
  return "unknown";
}

struct VfCounters {
  std::uint32_t samples = 0;             // update() calls
  std::uint32_t updates = 0;             // vector samples applied (live)
  std::uint32_t reference_updates = 0;   // scalar reference updates applied (live)
  std::uint32_t gated = 0;               // vector samples rejected by the gate
  std::uint32_t gated_reference = 0;     // reference updates rejected by the gate
  std::uint32_t rejected_nonfinite = 0;  // NaN/inf inputs
  std::uint32_t heading_held = 0;        // vector updates made with the heading state held
  std::uint32_t resets = 0;              // full restarts after a detected divergence
  std::uint32_t field_reopens = 0;       // partial resets of h_n (kFieldChange)
  std::uint32_t fold_rm = 0;             // misalignment error folded into the quaternion
  std::uint32_t init_attempts = 0;       // starts from data tried
  std::uint32_t init_failures = 0;       // ... and refused
};

template <typename Scalar>
struct VfConfig {
  // Normalisation magnitude; 0: the first reference field (or the stored h_n).
  Scalar field_scale_nT{0};
  // Constant reference for the start from data when samples carry none (0: none).
  Scalar reference_field_nT{0};
  Scalar mag_noise_nT = Scalar(0.3);                      // per axis, 1-sigma
  Scalar attitude_noise_rad = deg_to_rad(Scalar(0.015));  // per INS angle, 1-sigma
  AttitudeNoiseModel attitude_model = AttitudeNoiseModel::kLiEuler;
  Scalar reference_sigma_nT = Scalar(0.01);  // noise of the scalar reference
  // Random-walk process noise (E-VF-1); 0: constant.
  Scalar offset_q_nT2_per_s{0};             // offset drift
  Scalar field_q_nT2_per_s{0};              // diurnal variation / site change
  Scalar sample_interval_s = Scalar(0.01);  // when a sample carries no interval
  // Live samples per information fold (E-VF-B). 1: every sample is three sequential scalar
  // updates (O(n^2) each). K > 1: each sample's whitened rows are only summed, linearised at the
  // last fold, and every K samples the block's mean and linear trend enter U-D as seven scalar
  // pseudo-measurements: a microcontroller's per-sample cost drops by the Bierman updates. What
  // the rows do faster than linearly within a block is not used (smooth motion: nothing). The
  // state and covariance the outputs read are those of the last fold.
  int fold_samples = 1;
  bool estimate_time_offset = true;
  Scalar time_offset0_s{0};
  Scalar time_offset_sigma0_s = Scalar(0.05);
  bool estimate_temperature = true;
  Scalar temperature_ref_degC = std::numeric_limits<Scalar>::quiet_NaN();  // NaN: first seen
  Scalar tc_sigma0_nT_per_degC = Scalar(5);
  // Heading rule (E-VF-7): RMS spread of the body-frame vertical before the rotation about body z
  // is updated (the acceptance limit of the batch methods).
  Scalar min_tilt_spread_deg = Scalar(2);
  // Start from data (E-VF-1).
  int init_samples = 48;                     // kept samples before the batch fit
  Scalar init_min_rotation_deg = Scalar(2);  // attitude change between kept samples
  int init_replay_passes = 12;               // most relinearised replays of the kept samples
  // Gauss-Newton passes over every sample seen while collecting (the replay store), after the
  // kept samples' passes have settled (E-VF-1); 0: the kept samples only.
  int init_full_passes = 2;
  Scalar prior_w_sigma = Scalar(0.01);  // diffuse prior of the replay (and fallbacks)
  Scalar prior_o_sigma_nT = Scalar(50);
  Scalar prior_rm_sigma_rad = deg_to_rad(Scalar(2));
  Scalar prior_h_n_sigma_nT = Scalar(200);
  // Misalignment error folded into the quaternion when its norm exceeds this (0: after every
  // update, in both precisions). A deferred fold leaves the Jacobian about Rm_nom Exp(-phi) off by
  // O(|phi|): with 2e-4 rad, float32 moved the time offset by 0.13 sigma from double (E-VF-A).
  Scalar rm_fold_rad{0};
  // Gating and divergence (E-VF-8).
  Scalar gate_nis = Scalar(25);  // per scalar update, chi-square 1 dof; <= 0: off
  bool divergence_detection = true;
  int nis_window = 100;  // vector samples per window
  Scalar nis_mean_limit = Scalar(4);
  Scalar gated_fraction_limit = Scalar(0.5);
  int max_consecutive_rejections = 50;
  int field_change_after = 3;  // consecutive gated references before h_n is re-opened
  Scalar field_reopen_sigma_nT = Scalar(200);
};

// A stored calibration to start from (E-VF-1). Sigmas that are 0 or NaN take the config's prior.
template <typename Scalar>
struct VfStart {
  static constexpr Scalar kNaN = std::numeric_limits<Scalar>::quiet_NaN();
  SensorModel<Scalar> model{};
  LiSigmas<Scalar> sigma{};
  Vec3<Scalar> h_n_nT = Vec3<Scalar>::Constant(kNaN);  // NaN: from the first sample
  Vec3<Scalar> h_n_sigma_nT = Vec3<Scalar>::Constant(kNaN);
  Scalar time_offset_s{0};
  Scalar time_offset_sigma_s = kNaN;
  Vec3<Scalar> tc_nT_per_degC = Vec3<Scalar>::Zero();
  Vec3<Scalar> tc_sigma_nT_per_degC = Vec3<Scalar>::Constant(kNaN);
  Scalar temperature_ref_degC = kNaN;
};

// 1-sigmas of the outputs, from the covariance.
template <typename Scalar>
struct VfSigmas {
  Mat3<Scalar> w = Mat3<Scalar>::Zero();         // structural zeros of W stay 0
  Vec3<Scalar> o_nT = Vec3<Scalar>::Zero();      // offset at the current temperature
  Vec3<Scalar> o_ref_nT = Vec3<Scalar>::Zero();  // offset at T0
  Vec3<Scalar> rm_rad = Vec3<Scalar>::Zero();    // small rotations about the body axes
  Vec3<Scalar> h_n_nT = Vec3<Scalar>::Zero();
  Scalar dt_s{0};
  Vec3<Scalar> tc_nT_per_degC = Vec3<Scalar>::Zero();
};

// What the calibration's remaining uncertainty does to the outputs over the survey envelope
// (E-VF-10: every heading, at the tilts seen since the start): per-axis RMS of the E/N/U error and
// RMS of the |h| error it adds, next to the per-sample noise of those outputs at the filter's noise
// figures. NaN while the filter is not running.
template <typename Scalar>
struct VfOutputUncertainty {
  static constexpr Scalar kNaN = std::numeric_limits<Scalar>::quiet_NaN();
  std::uint32_t attitudes{0};        // envelope attitudes evaluated (0: not running)
  Scalar vector_nT = kNaN;           // calibration error, per E/N/U axis (RMS over the envelope)
  Scalar intensity_nT = kNaN;        // calibration error of |h|
  Scalar vector_noise_nT = kNaN;     // per-sample noise per axis (magnetometer and attitude)
  Scalar intensity_noise_nT = kNaN;  // per-sample noise of |h| (magnetometer)
};

// Noise figures from the live innovations (E-VF-10): covariance matching of the whitened
// innovations against the filter's magnetometer and attitude parts. Valid after enough samples.
template <typename Scalar>
struct VfNoiseEstimate {
  static constexpr Scalar kNaN = std::numeric_limits<Scalar>::quiet_NaN();
  std::uint32_t samples{0};
  bool valid{false};
  Scalar mag_nT = kNaN, mag_sigma_nT = kNaN;
  bool has_attitude{false};  // the attitude figure is separable (attitude noise configured)
  Scalar attitude_rad = kNaN, attitude_sigma_rad = kNaN;
};

template <typename Scalar, int kInitCapacity = 64, int kReplayCapacity = 512>
class VectorCalibrationFilter {
  static_assert(CoreScalar<Scalar>);
  static_assert(kInitCapacity >= 16, "the start from data needs well over 14 samples");
  static_assert(kReplayCapacity >= 0);

 public:
  // State layout (E-VF-A). W entries in Li structure: W = (Ks Ko)^-1 is lower triangular in the
  // axis order (x, z, y), so W(0,1) = W(0,2) = W(2,1) = 0 and six entries are free.
  static constexpr int kW0 = 0;   // W(0,0)
  static constexpr int kW1 = 1;   // W(1,0)
  static constexpr int kW2 = 2;   // W(1,1)
  static constexpr int kW3 = 3;   // W(1,2)
  static constexpr int kW4 = 4;   // W(2,0)
  static constexpr int kW5 = 5;   // W(2,2)
  static constexpr int kO0 = 6;   // offset at T0 (normalised), x y z
  static constexpr int kRm0 = 9;  // misalignment error about body x, y, z (rad)
  static constexpr int kRmHeading = kRm0 + 2;
  static constexpr int kHn0 = 12;  // h_n (normalised), E N U
  static constexpr int kDt = 15;   // time offset (s)
  static constexpr int kTc0 = 16;  // temperature coefficients (normalised per degC)
  static constexpr int kStates = 19;
  static constexpr int kWEntries = 6;
  static constexpr std::array<int, kWEntries> kWRow = {0, 1, 1, 1, 2, 2};
  static constexpr std::array<int, kWEntries> kWCol = {0, 0, 1, 2, 0, 2};
  static_assert(kTc0 + 3 == kStates);

  using StateVec = Vec<Scalar, kStates>;
  using StateMat = Mat<Scalar, kStates, kStates>;
  using Config = VfConfig<Scalar>;
  using Batch = BatchCalibrator<Scalar, static_cast<std::size_t>(kInitCapacity)>;

  explicit VectorCalibrationFilter(const Config& cfg = Config{}) noexcept { configure(cfg); }

  // Replaces the configuration; clears everything (counters included) and collects for a start.
  void configure(const Config& cfg) noexcept;

  // Starts from a stored calibration (E-VF-1); the filter runs from the next sample.
  void start(const VfStart<Scalar>& s) noexcept;

  VfStatus update(const VfSample<Scalar>& in) noexcept;

  // Folds the samples accumulated since the last fold (E-VF-B; nothing to do with fold_samples 1):
  // the outputs then include every sample given. kReset when the fold found a divergence
  // (last_reset_reason()), else kAccepted.
  VfStatus flush() noexcept;

  bool initialised() const noexcept { return running_; }
  const VfCounters& counters() const noexcept { return counters_; }
  VfResetReason last_reset_reason() const noexcept { return last_reset_; }
  const Config& config() const noexcept { return cfg_; }
  Scalar field_scale_nT() const noexcept { return scale_; }
  bool heading_held() const noexcept { return held_[kRmHeading]; }
  Scalar tilt_spread_deg() const noexcept { return rad_to_deg(tilt_spread_rad()); }
  // The last vector sample's largest NIS at the prior (in folds: at R alone, an upper bound, unless
  // the gate or the noise estimate needed the exact figure; E-VF-B).
  Scalar last_nis() const noexcept { return last_nis_; }
  Scalar temperature_ref_degC() const noexcept { return t0_; }
  int startup_samples() const noexcept { return static_cast<int>(batch_.store().size()); }
  // Verdict of the last batch fit of a start from data (acceptance.hpp).
  Verdict last_init_verdict() const noexcept { return init_verdict_; }

  // ---- outputs (interface units) ---------------------------------------------------------------
  Mat3<Scalar> w() const noexcept {
    const StateVec v = full();
    Mat3<Scalar> m = Mat3<Scalar>::Zero();
    for (int k = 0; k < kWEntries; ++k)
      m(kWRow[static_cast<std::size_t>(k)], kWCol[static_cast<std::size_t>(k)]) = v(kW0 + k);
    return m;
  }
  Quat<Scalar> rm() const noexcept { return rm_current(); }
  Vec3<Scalar> offset_ref_nT() const noexcept {
    return full().template segment<3>(kO0) * scale_or_one();
  }
  Vec3<Scalar> temperature_coefficients_nT_per_degC() const noexcept {
    return full().template segment<3>(kTc0) * scale_or_one();
  }
  // Offset at a temperature (NaN: the last one seen).
  Vec3<Scalar> offset_nT(Scalar t_degC = std::numeric_limits<Scalar>::quiet_NaN()) const noexcept {
    return offset_ref_nT() + temperature_coefficients_nT_per_degC() * delta_t(t_degC);
  }
  Vec3<Scalar> h_n_nT() const noexcept { return full().template segment<3>(kHn0) * scale_or_one(); }
  Scalar time_offset_s() const noexcept { return full()(kDt); }
  // The calibration at a temperature (NaN: the last one seen), canonical form.
  SensorModel<Scalar> model(
      Scalar t_degC = std::numeric_limits<Scalar>::quiet_NaN()) const noexcept;

  // Covariance in interface units (W 1, o nT, Rm rad about body axes, h_n nT, dt s, c nT/degC).
  StateMat covariance() const noexcept;
  VfSigmas<Scalar> sigmas(Scalar t_degC = std::numeric_limits<Scalar>::quiet_NaN()) const noexcept;
  // E-VF-10. output_uncertainty() sums over 48 envelope attitudes in closed form and takes a trace
  // over the U-D factors (about 46 000 instructions on the M4F): poll it, not per sample.
  VfOutputUncertainty<Scalar> output_uncertainty() const noexcept;
  VfNoiseEstimate<Scalar> innovation_noise() const noexcept;
  // Live samples before innovation_noise() is valid.
  static constexpr std::uint32_t kMinNoiseSamples = 100;

 private:
  static constexpr Scalar kNaN = std::numeric_limits<Scalar>::quiet_NaN();
  // Replay of the kept samples: residuals at this mean chi^2 per observation count as settled.
  static constexpr Scalar kReplaySettled = Scalar(2);
  // Calibration states (W, o, Rm, c: what a candidate's output depends on), for E-VF-10.
  static constexpr int kCalStates = 15;
  static constexpr std::array<int, kCalStates> kCalIndex = {0, 1, 2,  3,  4,  5,  6, 7,
                                                            8, 9, 10, 11, 16, 17, 18};
  static_assert(kRm0 + 3 == 12 && kTc0 == 16);
  using CalMat = Mat<Scalar, kCalStates, kCalStates>;
  // Running means of E-VF-10 stop growing their count here: past it they are moving averages
  // (float32 sums of 2^24 terms would stop moving).
  static constexpr std::uint32_t kStatsCountCap = 1u << 20;
  // Parts of a linearisation beyond the whitened residual and Jacobian: the noise terms of a live
  // sample (E-VF-10).
  struct LinExtras {
    Mat3<Scalar> cov_mag;  // the residual covariance's magnetometer part
    Mat3<Scalar> l;        // Cholesky factor of the residual covariance
    Vec3<Scalar> h_n;      // the field state it is compared with
  };

  // A sample in the filter's units.
  struct Prepared {
    Vec3<Scalar> m;          // normalised reading
    Mat3<Scalar> r;          // R_bn
    Vec3<Scalar> omega;      // rad/s, n frame
    Scalar att_offset_s{0};  // offset already applied to r (VfSample::attitude_offset_s)
    Scalar f{0};             // normalised reference (NaN: none)
    Scalar dtemp{0};         // T - T0 (0 without temperatures)
  };

  Scalar scale_or_one() const noexcept { return scale_ > Scalar(0) ? scale_ : Scalar(1); }
  Scalar delta_t(Scalar t_degC) const noexcept {
    const Scalar t = std::isfinite(t_degC) ? t_degC : last_t_;
    return std::isfinite(t) && std::isfinite(t0_) ? t - t0_ : Scalar(0);
  }
  StateVec unit_scale() const noexcept {
    StateVec t = StateVec::Ones();
    t.template segment<3>(kO0).setConstant(scale_or_one());
    t.template segment<3>(kHn0).setConstant(scale_or_one());
    t.template segment<3>(kTc0).setConstant(scale_or_one());
    return t;
  }
  // Nominal + error for the additive states; the misalignment block is the error itself.
  StateVec full() const noexcept { return nom_ + x_; }
  Quat<Scalar> rm_current() const noexcept {
    // Rm = Rm_nom Exp(-[phi x]) (E-VF-A): a body-frame small rotation of the frame.
    Quat<Scalar> q = rm_nom_ * quat_exp(Vec3<Scalar>(-x_.template segment<3>(kRm0)));
    q.normalize();
    return q;
  }

  // Rm^T at the nominal misalignment or the current one, for linearise: the same for every sample
  // between two folds, so kept with the misalignment it was formed from and formed again only
  // when that differs (compared exactly; a NaN never matches).
  const Mat3<Scalar>& rm_transposed(bool nominal) const noexcept {
    const Vec3<Scalar> phi =
        nominal ? Vec3<Scalar>::Zero() : Vec3<Scalar>(x_.template segment<3>(kRm0));
    if (!(rmt_nominal_ == nominal && rmt_phi_ == phi && rmt_nom_.coeffs() == rm_nom_.coeffs())) {
      rmt_ = (nominal ? rm_nom_ : rm_current()).toRotationMatrix().transpose();
      rmt_nominal_ = nominal;
      rmt_phi_ = phi;
      rmt_nom_ = rm_nom_;
    }
    return rmt_;
  }

  Prepared prepare(const Vec3<Scalar>& m_nT, const Mat3<Scalar>& r, const Vec3<Scalar>& omega,
                   Scalar att_offset_s, Scalar f_nT, Scalar t_degC) const noexcept {
    Prepared p;
    p.m = m_nT / scale_;
    p.r = r;
    p.omega = omega;
    p.att_offset_s = att_offset_s;
    p.f = f_nT / scale_;
    p.dtemp = std::isfinite(t_degC) && std::isfinite(t0_) ? t_degC - t0_ : Scalar(0);
    return p;
  }

  // ---- restart and the two starts
  // ----------------------------------------------------------------
  void restart() noexcept {
    running_ = false;
    settling_ = false;
    batch_.reset();
    replay_n_ = 0;
    replay_head_ = 0;
    BatchConfig<Scalar> bc;
    bc.mag_noise_nT = cfg_.mag_noise_nT;
    bc.attitude_noise_deg = rad_to_deg(cfg_.attitude_noise_rad);
    bc.attitude_model = cfg_.attitude_model;
    batch_.set_config(bc);
    n_kept_ = 0;
    min_rotation_deg_ = cfg_.init_min_rotation_deg;
    nom_.setZero();
    x_.setZero();
    rm_nom_ = Quat<Scalar>::Identity();
    ref_dir_.setZero();
    u_.setIdentity();
    d_.setOnes();
    ref_hph_ = Scalar(-1);
    held_.fill(false);
    tilts_.reset();
    tilt_released_ = false;
    reset_windows();
    nz_n_ = 0;
    nz_mean_.setZero();
    blk_.clear();
  }
  void reset_windows() noexcept {
    window_n_ = 0;
    window_gated_ = 0;
    window_nis_sum_ = 0;
    window_nis_n_ = 0;
    consecutive_rejections_ = 0;
    consecutive_ref_gated_ = 0;
  }

  // Nominal state from a model (Li structure), h_n, dt, c (all interface units).
  void set_nominal(const SensorModel<Scalar>& li_model, const Vec3<Scalar>& h_n_nT, Scalar dt_s,
                   const Vec3<Scalar>& tc) noexcept {
    const Scalar s = scale_or_one();
    nom_.setZero();
    for (int k = 0; k < kWEntries; ++k)
      nom_(kW0 + k) =
          li_model.w(kWRow[static_cast<std::size_t>(k)], kWCol[static_cast<std::size_t>(k)]);
    nom_.template segment<3>(kO0) = li_model.o / s;
    nom_.template segment<3>(kHn0) = h_n_nT / s;
    nom_(kDt) = dt_s;
    nom_.template segment<3>(kTc0) = tc / s;
    rm_nom_ = li_model.rm.normalized();
    x_.setZero();
  }

  // d W entries / d (ks, O): dW = -W dA W with A = Ks Ko (E-OS-2).
  static Mat<Scalar, kWEntries, 6> w_jacobian_li(const LiParams<Scalar>& li) noexcept {
    using std::cos;
    using std::sin;
    const Mat3<Scalar> ko = li_ko(li.o_rad);
    const Mat3<Scalar> w = (li.ks.asDiagonal() * ko).inverse();
    const Vec3<Scalar>& o = li.o_rad;
    std::array<Mat3<Scalar>, 6> da;
    for (int k = 0; k < 3; ++k) {
      da[static_cast<std::size_t>(k)].setZero();
      da[static_cast<std::size_t>(k)].row(k) = ko.row(k);
    }
    for (std::size_t k = 3; k < 6; ++k)
      da[k].setZero();
    da[3].row(2) = li.ks(2) * Vec3<Scalar>(cos(o(0)), 0, -sin(o(0))).transpose();
    da[4].row(1) =
        li.ks(1) *
        Vec3<Scalar>(-sin(o(1)) * sin(o(2)), -sin(o(1)) * cos(o(2)), cos(o(1))).transpose();
    da[5].row(1) =
        li.ks(1) * Vec3<Scalar>(cos(o(1)) * cos(o(2)), -cos(o(1)) * sin(o(2)), 0).transpose();
    Mat<Scalar, kWEntries, 6> j;
    for (std::size_t c = 0; c < 6; ++c) {
      const Mat3<Scalar> dw = -w * da[c] * w;
      for (int k = 0; k < kWEntries; ++k)
        j(k, static_cast<int>(c)) =
            dw(kWRow[static_cast<std::size_t>(k)], kWCol[static_cast<std::size_t>(k)]);
    }
    return j;
  }

  static Scalar pick(Scalar given, Scalar fallback) noexcept {
    return std::isfinite(given) && given > Scalar(0) ? given : fallback;
  }

  // Prior covariance (normalised) from Li sigmas and the other states' sigmas (interface units).
  StateMat prior_covariance(const LiParams<Scalar>& li, const LiSigmas<Scalar>& sg,
                            const Vec3<Scalar>& h_n_sigma_nT, Scalar dt_sigma_s,
                            const Vec3<Scalar>& tc_sigma) const noexcept {
    const Scalar s = scale_or_one();
    StateMat p = StateMat::Zero();
    Vec<Scalar, 6> v;
    bool w_given = true;
    for (int k = 0; k < 3; ++k) {
      v(k) = sg.ks(k);
      v(3 + k) = sg.o_rad(k);
    }
    for (int k = 0; k < 6; ++k)
      w_given = w_given && std::isfinite(v(k)) && v(k) > Scalar(0);
    if (w_given) {
      const Mat<Scalar, kWEntries, 6> j = w_jacobian_li(li);
      const Mat<Scalar, kWEntries, 6> jv = j * v.asDiagonal();
      p.template block<kWEntries, kWEntries>(kW0, kW0) = jv * jv.transpose();
    } else {
      for (int k = 0; k < kWEntries; ++k)
        p(kW0 + k, kW0 + k) = cfg_.prior_w_sigma * cfg_.prior_w_sigma;
    }
    // Li angle errors map to body-frame rotations along li_rm_axes_body (E-VF-1).
    const Mat3<Scalar> axes = li_rm_axes_body(li.rm_rad);
    Vec3<Scalar> sr;
    for (int k = 0; k < 3; ++k)
      sr(k) = pick(sg.rm_rad(k), cfg_.prior_rm_sigma_rad);
    const Mat3<Scalar> ar = axes * sr.asDiagonal();
    p.template block<3, 3>(kRm0, kRm0) = ar * ar.transpose();
    for (int k = 0; k < 3; ++k) {
      const Scalar so = pick(sg.kof(k), cfg_.prior_o_sigma_nT) / s;
      p(kO0 + k, kO0 + k) = so * so;
      const Scalar sh = pick(h_n_sigma_nT(k), cfg_.prior_h_n_sigma_nT) / s;
      p(kHn0 + k, kHn0 + k) = sh * sh;
      const Scalar sc = pick(tc_sigma(k), cfg_.tc_sigma0_nT_per_degC) / s;
      p(kTc0 + k, kTc0 + k) = sc * sc;
    }
    const Scalar st = pick(dt_sigma_s, cfg_.time_offset_sigma0_s);
    p(kDt, kDt) = st * st;
    return p;
  }

  // Holds: states not estimated (config) and the heading until the tilt spread suffices.
  void apply_holds(StateMat* p) noexcept {
    held_.fill(false);
    if (!cfg_.estimate_time_offset) held_[kDt] = true;
    if (!cfg_.estimate_temperature)
      for (int k = 0; k < 3; ++k)
        held_[static_cast<std::size_t>(kTc0) + static_cast<std::size_t>(k)] = true;
    if (!tilt_released_) held_[kRmHeading] = true;
    // A held state must be uncorrelated so that a zero Jacobian column gives it exactly zero gain
    // (E-VF-7); removing a state's cross-covariances keeps P positive semi-definite.
    for (int k = 0; k < kStates; ++k) {
      if (!held_[static_cast<std::size_t>(k)]) continue;
      for (int j = 0; j < kStates; ++j) {
        if (j == k) continue;
        (*p)(k, j) = Scalar(0);
        (*p)(j, k) = Scalar(0);
      }
    }
  }

  void start_stored(const VfSample<Scalar>& in, Scalar f_nT) noexcept {
    pending_start_ = false;
    SensorModel<Scalar> li_model;
    LiParams<Scalar> li;
    if (to_li(stored_.model, &li) != ConversionStatus::kOk) return;  // collect from data instead
    li_model = from_li(li);
    Vec3<Scalar> h_n = stored_.h_n_nT;
    if (!h_n.allFinite()) {
      // The stored calibration applied to this sample (E-VF-1), magnitude from the reference.
      const Mat3<Scalar> rmt = li_model.rm_matrix().transpose();
      h_n = in.r_bn.transpose() * (rmt * (li_model.w * (in.m_nT - li_model.o)));
      if (std::isfinite(f_nT) && h_n.norm() > Scalar(0)) h_n *= f_nT / h_n.norm();
    }
    set_nominal(li_model, h_n, stored_.time_offset_s, stored_.tc_nT_per_degC);
    StateMat p = prior_covariance(li, stored_.sigma, stored_.h_n_sigma_nT,
                                  stored_.time_offset_sigma_s, stored_.tc_sigma_nT_per_degC);
    update_tilt_release();
    apply_holds(&p);
    if (!ud_factorise(p)) return;
    running_ = true;
    reset_windows();
    // The prior, for the Gauss-Newton passes over the first samples (E-VF-1).
    settling_ = kReplayCapacity > 0 && cfg_.init_full_passes > 0;
    settle_nom_ = nom_;
    settle_rm_ = rm_nom_;
    settle_p_ = p;
    replay_n_ = 0;
    replay_head_ = 0;
  }

  // After a start from a stored calibration, once the replay store is full: Gauss-Newton passes
  // over its samples from the stored prior, each linearised at the previous pass's result, so the
  // first samples' information is taken at a good linearisation point (E-VF-1).
  VfStatus settle(VfStatus status) noexcept {
    settling_ = false;
    blk_.clear();  // the passes take every stored sample again, the pending ones included
    for (int pass = 0; pass < cfg_.init_full_passes; ++pass) {
      fold_all();
      StateMat p = settle_p_;
      apply_holds(&p);
      if (!ud_factorise(p)) return reset(VfResetReason::kCovarianceNotPositive);
      // The prior mean as an error about the new nominal: Rm_prior = Rm_nom Exp(-[phi x]).
      x_ = settle_nom_ - nom_;
      const Eigen::AngleAxis<Scalar> aa(rm_nom_.conjugate() * settle_rm_);
      x_.template segment<3>(kRm0) = -aa.angle() * aa.axis();
      for (int k = 0; k < kStates; ++k)
        if (held_[static_cast<std::size_t>(k)]) x_(k) = Scalar(0);
      if (!replay_samples(true)) return reset(VfResetReason::kNonFiniteState);
    }
    replay_n_ = 0;
    replay_head_ = 0;
    reset_windows();
    return status;
  }

  // Motion-decimated collection (E-VF-1); the batch fit when enough samples are kept.
  VfStatus collect(const VfSample<Scalar>& in, Scalar f_nT) noexcept {
    Scalar f = f_nT;
    if (!std::isfinite(f) && cfg_.reference_field_nT > Scalar(0)) f = cfg_.reference_field_nT;
    if (!std::isfinite(f)) return VfStatus::kRejectedNoReference;
    const std::uint32_t seq = counters_.samples;
    remember(in, f_nT, seq);
    if (n_kept_ > 0) {
      const Mat3<Scalar> last = batch_.store()[static_cast<std::size_t>(n_kept_ - 1)].r_bn();
      if (rotation_angle_between(last, in.r_bn) < deg_to_rad(min_rotation_deg_))
        return VfStatus::kCollecting;
    }
    if (batch_.add_sample(in.m_nT, f, in.r_bn) != AddStatus::kAccepted)
      return VfStatus::kCollecting;
    const std::size_t i = static_cast<std::size_t>(n_kept_);
    kept_omega_.col(n_kept_) = in.omega_n_rad_s;
    kept_att_offset_(n_kept_) = in.attitude_offset_s;
    kept_t_(n_kept_) = last_t_;
    kept_has_f_[i] = std::isfinite(f_nT);
    kept_seq_[i] = seq;
    ++n_kept_;
    if (n_kept_ < cfg_.init_samples) return VfStatus::kCollecting;
    if (start_from_data()) return VfStatus::kInitialised;
    ++counters_.init_failures;
    thin_collection();
    return VfStatus::kInitFailed;
  }
  // After a refused start: keep every other kept sample and double the attitude step, so the set
  // spans twice the motion when it is full again (a slow platform still reaches enough spread).
  void thin_collection() noexcept {
    const int half = n_kept_ / 2;
    std::array<Vec3<Scalar>, static_cast<std::size_t>(kInitCapacity / 2 + 1)> m;
    std::array<Mat3<Scalar>, static_cast<std::size_t>(kInitCapacity / 2 + 1)> r;
    std::array<Scalar, static_cast<std::size_t>(kInitCapacity / 2 + 1)> f{};
    for (int j = 0; j < half; ++j) {
      const int i = 2 * j + 1;
      const StoredSample<Scalar>& s = batch_.store()[static_cast<std::size_t>(i)];
      const std::size_t ju = static_cast<std::size_t>(j);
      m[ju] = s.raw();
      r[ju] = s.r_bn();
      f[ju] = s.f;
      kept_omega_.col(j) = kept_omega_.col(i);
      kept_att_offset_(j) = kept_att_offset_(i);
      kept_t_(j) = kept_t_(i);
      kept_has_f_[ju] = kept_has_f_[static_cast<std::size_t>(i)];
      kept_seq_[ju] = kept_seq_[static_cast<std::size_t>(i)];
    }
    batch_.reset();
    for (int j = 0; j < half; ++j) {
      const std::size_t ju = static_cast<std::size_t>(j);
      batch_.add_sample(m[ju], f[ju], r[ju]);
    }
    n_kept_ = half;
    min_rotation_deg_ = std::min(Scalar(2) * min_rotation_deg_, Scalar(45));
  }
  void restart_collection() noexcept {
    min_rotation_deg_ = cfg_.init_min_rotation_deg;
    batch_.reset();
    n_kept_ = 0;
    replay_n_ = 0;
    replay_head_ = 0;
  }
  // Every sample seen while collecting, for the final replay passes (a ring: the oldest go first).
  void remember(const VfSample<Scalar>& in, Scalar f_nT, std::uint32_t seq) noexcept {
    if constexpr (kReplayCapacity > 0) {
      ReplaySample& r = replay_[static_cast<std::size_t>(replay_head_)];
      r.m_nT = in.m_nT;
      r.q = Quat<Scalar>(in.r_bn);
      r.omega = in.omega_n_rad_s;
      r.att_offset_s = in.attitude_offset_s;
      r.f_nT = f_nT;
      r.temperature_degC = last_t_;
      r.seq = seq;
      replay_head_ = (replay_head_ + 1) % kReplayCapacity;
      replay_n_ = std::min(replay_n_ + 1, kReplayCapacity);
    } else {
      (void)in;
      (void)f_nT;
      (void)seq;
    }
  }

  bool start_from_data() noexcept {
    ++counters_.init_attempts;
    update_tilt_release();
    BatchConfig<Scalar> bc = batch_.config();
    bc.fix_heading_misalignment = !tilt_released_;
    bc.fixed_heading_misalignment_deg = Scalar(0);
    batch_.set_config(bc);
    BatchResult<Scalar> res = batch_.solve(BatchMethod::kOneStep);
    if (res.verdict == Verdict::kUnobservableHeadingMisalignment && !bc.fix_heading_misalignment) {
      // The tilts suffice (E-VF-7) but the kept set does not determine the heading misalignment
      // to the batch limit (a noisy sensor and a few dozen samples): the fit with it held at 0
      // is the linearisation point, and the filter estimates it from its prior like every other
      // state (E-VF-1); readiness waits until the data determine it.
      bc.fix_heading_misalignment = true;
      batch_.set_config(bc);
      res = batch_.solve(BatchMethod::kOneStep);
    }
    init_verdict_ = res.verdict;
    // The batch fit knows neither the time offset nor the temperature term: residuals too large
    // or a fit that did not settle still give a linearisation point; the replay decides (E-VF-1).
    // Raw direction coverage below the batch methods' limit is accepted when every parameter is
    // still determined to the acceptance limit: a linearisation point is all the filter needs,
    // and waiting for coverage would discard the samples passing meanwhile.
    const bool determined = res.verdict == Verdict::kInsufficientCoverage &&
                            res.quality.undetermined == 0 && res.converged;
    const bool usable = res.verdict == Verdict::kOk || res.verdict == Verdict::kResidualTooLarge ||
                        res.verdict == Verdict::kNotConverged || determined;
    if (!usable || !res.has_model || !res.has_h_n || !res.h_n_nT.allFinite()) return false;
    const SensorModel<Scalar> li_model = from_li(res.li);
    if (!li_model.w.allFinite() || !(li_model.w.determinant() > Scalar(0))) return false;
    set_nominal(li_model, res.h_n_nT, cfg_.time_offset0_s, Vec3<Scalar>::Zero());
    // Each pass restarts from the diffuse prior at the previous pass's estimate: Gauss-Newton on
    // the kept samples with the filter's own model (time offset and temperature included). The
    // noise is scaled up to the residuals at the pass's start, so a linearisation point far off
    // (the batch fit knows no lag) takes damped steps; the last pass runs at the configured noise.
    bool final_pass = false;
    for (int pass = 0; pass < cfg_.init_replay_passes && !final_pass; ++pass) {
      fold_all();
      const Scalar chi2_per_obs = replay_chi2_per_observation();
      if (!std::isfinite(chi2_per_obs)) return false;
      final_pass = chi2_per_obs <= kReplaySettled || pass + 1 == cfg_.init_replay_passes;
      noise_factor_ =
          chi2_per_obs <= kReplaySettled ? Scalar(1) : std::sqrt(std::max(chi2_per_obs, Scalar(1)));
      if (!replay_pass(false)) {
        noise_factor_ = Scalar(1);
        return false;
      }
    }
    noise_factor_ = Scalar(1);
    if (replay_n_ > 0) {
      for (int pass = 0; pass < cfg_.init_full_passes; ++pass) {
        fold_all();
        if (!replay_pass(true)) return false;
      }
    }
    running_ = true;
    reset_windows();
    restart_collection();
    return true;
  }

  // One replay from the diffuse prior at the current (folded) estimate: a Gauss-Newton step, every
  // sample linearised at the pass's start (E-VF-1). `all`: every sample seen while collecting
  // (the kept ones older than the replay store, then the store), else the kept samples only.
  bool replay_pass(bool all) noexcept {
    LiParams<Scalar> li_now;
    if (to_li(model_nominal(), &li_now) != ConversionStatus::kOk) return false;
    LiSigmas<Scalar> none;
    none.ks.setConstant(kNaN);
    none.o_rad.setConstant(kNaN);
    none.kof.setConstant(kNaN);
    none.rm_rad.setConstant(kNaN);
    const Vec3<Scalar> nan3 = Vec3<Scalar>::Constant(kNaN);
    StateMat p = prior_covariance(li_now, none, nan3, kNaN, nan3);
    apply_holds(&p);
    if (!ud_factorise(p)) return false;
    return replay_samples(all);
  }
  bool replay_samples(bool all) noexcept {
    lin_at_nominal_ = true;
    const std::uint32_t oldest =
        all && replay_n_ > 0
            ? replay_[static_cast<std::size_t>((replay_head_ + kReplayCapacity - replay_n_) %
                                               std::max(kReplayCapacity, 1))]
                  .seq
            : std::numeric_limits<std::uint32_t>::max();
    for (int i = 0; i < n_kept_; ++i) {
      const StoredSample<Scalar>& s = batch_.store()[static_cast<std::size_t>(i)];
      if (s.outlier() || kept_seq_[static_cast<std::size_t>(i)] >= oldest) continue;
      const Prepared pr = kept(i);
      if (std::isfinite(pr.f)) reference_update(pr.f, false);
      vector_update(pr, false);
    }
    if (all) {
      for (int j = 0; j < replay_n_; ++j) {
        const ReplaySample& r = replay_[static_cast<std::size_t>(
            (replay_head_ + kReplayCapacity - replay_n_ + j) % std::max(kReplayCapacity, 1))];
        const Prepared pr = prepare(r.m_nT, r.q.toRotationMatrix(), r.omega, r.att_offset_s, r.f_nT,
                                    r.temperature_degC);
        if (std::isfinite(pr.f)) reference_update(pr.f, false);
        // Outliers: the kept samples have the batch fit's screen, these the gate (the pass starts
        // near the solution: after the kept samples' passes, or after the live samples).
        vector_update(pr, true);
      }
    }
    lin_at_nominal_ = false;
    return x_.allFinite() && d_.allFinite() && (d_.array() > Scalar(0)).all();
  }
  Prepared kept(int i) const noexcept {
    const StoredSample<Scalar>& s = batch_.store()[static_cast<std::size_t>(i)];
    return prepare(s.raw(), s.r_bn(), kept_omega_.col(i), kept_att_offset_(i),
                   kept_has_f_[static_cast<std::size_t>(i)] ? s.f : kNaN, kept_t_(i));
  }
  // Mean squared whitened residual per scalar observation over the kept samples at the current
  // estimate and the configured noise (1 at the optimum of consistent data).
  Scalar replay_chi2_per_observation() noexcept {
    noise_factor_ = Scalar(1);
    Scalar chi2{0};
    int n = 0;
    const Scalar sf = reference_sigma();
    const Scalar hn = full().template segment<3>(kHn0).norm();
    for (int i = 0; i < n_kept_; ++i) {
      if (batch_.store()[static_cast<std::size_t>(i)].outlier()) continue;
      const Prepared pr = kept(i);
      Vec3<Scalar> rw;
      Mat<Scalar, 3, kStates> hw;
      if (!linearise(pr, &rw, &hw)) return kNaN;
      chi2 += rw.squaredNorm();
      n += 3;
      if (std::isfinite(pr.f)) {
        const Scalar e = (pr.f - hn) / sf;
        chi2 += e * e;
        ++n;
      }
    }
    return n > 0 ? chi2 / static_cast<Scalar>(n) : kNaN;
  }

  // Nominal + error folded into the nominal (x = 0 afterwards, covariance unchanged).
  void fold_all() noexcept {
    ref_dir_.setZero();  // the next reference update takes the current direction
    rm_nom_ = rm_current();
    const StateVec f = full();
    nom_ = f;
    nom_.template segment<3>(kRm0).setZero();
    x_.setZero();
  }
  SensorModel<Scalar> model_nominal() const noexcept {
    SensorModel<Scalar> m;
    m.w = w();
    m.o = offset_ref_nT();
    m.rm = rm_current();
    return m;
  }
  void maybe_fold_rm() noexcept {
    const Vec3<Scalar> phi = x_.template segment<3>(kRm0);
    if (phi.squaredNorm() > Scalar(0) && phi.norm() > cfg_.rm_fold_rad) {
      // The covariance stays that of phi: the reset Jacobian I - [phi/2 x] differs from I by the
      // fold threshold's size (E-VF-A).
      rm_nom_ = rm_current();
      x_.template segment<3>(kRm0).setZero();
      ++counters_.fold_rm;
    }
  }

  // ---- tilt spread and the heading rule
  // ----------------------------------------------------------
  void note_tilt(const Mat3<Scalar>& r) noexcept {
    tilts_.add(r);
    if (running_ && !tilt_released_) {
      update_tilt_release();
      if (tilt_released_) held_[kRmHeading] = false;
    }
  }
  Scalar tilt_spread_rad() const noexcept { return tilts_.spread_rad(); }
  void update_tilt_release() noexcept {
    if (tilt_spread_rad() >= deg_to_rad(cfg_.min_tilt_spread_deg)) tilt_released_ = true;
  }

  // ---- measurement model ---------------------------------------------------------------------
  // Whitened residual and Jacobian of a vector sample at the current estimate (E-VF-2, E-VF-3).
  bool linearise(const Prepared& p, Vec3<Scalar>* rw, Mat<Scalar, 3, kStates>* hw,
                 LinExtras* ex = nullptr) const noexcept {
    StateVec xf;
    if (lin_at_nominal_)
      xf = nom_;
    else
      xf = nom_ + x_;
    Mat3<Scalar> wm = Mat3<Scalar>::Zero();
    for (int k = 0; k < kWEntries; ++k)
      wm(kWRow[static_cast<std::size_t>(k)], kWCol[static_cast<std::size_t>(k)]) = xf(kW0 + k);
    const Mat3<Scalar>& rmt = rm_transposed(lin_at_nominal_);
    // Only the part of the offset the caller did not apply to r (E-VF-5).
    const Scalar tau = xf(kDt) - p.att_offset_s;
    const Mat3<Scalar> e = exp_so3(Vec3<Scalar>(-tau * p.omega));
    const Mat3<Scalar> et_r = e * p.r.transpose();  // E R^T
    const Mat3<Scalar> mm = et_r * rmt;             // M = E R^T Rm^T
    const Vec3<Scalar> v =
        p.m - xf.template segment<3>(kO0) - xf.template segment<3>(kTc0) * p.dtemp;
    const Vec3<Scalar> hs = wm * v;
    const Vec3<Scalar> hb = rmt * hs;
    const Vec3<Scalar> g = mm * hs;
    const Vec3<Scalar> hn = xf.template segment<3>(kHn0);
    const Vec3<Scalar> r = g - hn;
    const Mat3<Scalar> pm = mm * wm;  // P = M W
    if (ex != nullptr) ex->h_n = hn;
    // Residual covariance (E-OS-3): magnetometer noise through P, attitude noise across h_n.
    const Scalar sm = mag_sigma();
    const Scalar sa = attitude_sigma();
    const Mat3<Scalar> c = attitude_noise_columns(p.r, hn);
    const Mat3<Scalar> cov_mag = sm * sm * (pm * pm.transpose());
    const Mat3<Scalar> cov = cov_mag + sa * sa * (c * c.transpose());
    if (ex != nullptr) ex->cov_mag = cov_mag;
    // Cholesky L L^T of the 3x3 covariance, written out (no level-3 solver), and forward
    // substitution.
    Mat3<Scalar> l;
    const Scalar d0 = cov(0, 0);
    if (!(d0 > Scalar(0))) return false;
    const Scalar l00 = std::sqrt(d0);
    const Scalar l10 = cov(1, 0) / l00;
    const Scalar l20 = cov(2, 0) / l00;
    const Scalar d1 = cov(1, 1) - l10 * l10;
    if (!(d1 > Scalar(0))) return false;
    const Scalar l11 = std::sqrt(d1);
    const Scalar l21 = (cov(2, 1) - l20 * l10) / l11;
    const Scalar d2 = cov(2, 2) - l20 * l20 - l21 * l21;
    if (!(d2 > Scalar(0))) return false;
    l << l00, Scalar(0), Scalar(0),  //
        l10, l11, Scalar(0),         //
        l20, l21, std::sqrt(d2);
    // The whitened Jacobian L^-1 H (E-VF-3) block by block: W's columns are M's scaled by v, o's
    // are -M W and c_T's dT times o's, so L^-1 M is solved once and they follow from it; the
    // misalignment's, h_n's (-L^-1) and dt's are solved. Every column is written (kStates).
    static_assert(kWEntries + 3 + 3 + 3 + 1 + 3 == kStates);
    const Mat3<Scalar> lm = lower_solve(l, mm);  // L^-1 M
    for (int k = 0; k < kWEntries; ++k)
      hw->col(kW0 + k) =
          lm.col(kWRow[static_cast<std::size_t>(k)]) * v(kWCol[static_cast<std::size_t>(k)]);
    const Mat3<Scalar> lpm = lm * wm;  // L^-1 M W
    hw->template block<3, 3>(0, kO0) = -lpm;
    hw->template block<3, 3>(0, kRm0) = lower_solve(l, Mat3<Scalar>(-et_r * skew(hb)));
    hw->template block<3, 3>(0, kHn0) = lower_solve(l, Mat3<Scalar>(-Mat3<Scalar>::Identity()));
    hw->col(kDt) = lower_solve(l, Vec3<Scalar>(-p.omega.cross(g)));
    hw->template block<3, 3>(0, kTc0) = -lpm * p.dtemp;
    for (int k = 0; k < kStates; ++k)
      if (held_[static_cast<std::size_t>(k)]) hw->col(k).setZero();
    *rw = lower_solve(l, r);
    if (ex != nullptr) ex->l = l;
    // False when the residual is not finite. The rows' finiteness is the caller's to check:
    // vector_update checks them before they touch the state; a block checks its sums at the fold
    // (fold_and_check), ~190 instructions per sample less on the M4F.
    return all_finite(*rw);
  }

  // The residual's noise figures in normalised units (E-OS-3).
  Scalar mag_sigma() const noexcept {
    return noise_factor_ * std::max(cfg_.mag_noise_nT / scale_or_one(),
                                    Scalar(16) * std::numeric_limits<Scalar>::epsilon());
  }
  Scalar attitude_sigma() const noexcept { return noise_factor_ * cfg_.attitude_noise_rad; }
  // C with the attitude part of the residual covariance sa^2 C C^T at R_bn = r (E-OS-3): the
  // attitude's small rotations turn h_n about the model's axes.
  Mat3<Scalar> attitude_noise_columns(const Mat3<Scalar>& r,
                                      const Vec3<Scalar>& hn) const noexcept {
    Mat3<Scalar> c;
    if (cfg_.attitude_model == AttitudeNoiseModel::kLiEuler) {
      const Scalar ax = r(1, 1), ay = -r(1, 0);
      const Scalar al = std::sqrt(ax * ax + ay * ay);
      const Vec3<Scalar> a1 =
          al > Scalar(0) ? Vec3<Scalar>(ax / al, ay / al, Scalar(0)) : Vec3<Scalar>::UnitX();
      c.col(0) = Vec3<Scalar>::UnitZ().cross(hn);
      c.col(1) = a1.cross(hn);
      c.col(2) = Vec3<Scalar>(r.row(1).transpose()).cross(hn);
    } else {
      c = skew(hn).transpose();
    }
    return c;
  }

  Scalar reference_sigma() const noexcept {
    // Floor at the resolution of a normalised field of order one. (A floor of 16 eps made float32
    // weight the reference at 0.1 nT instead of the configured 0.01 nT: another model, E-VF-8.)
    return std::max(cfg_.reference_sigma_nT / scale_or_one(),
                    std::numeric_limits<Scalar>::epsilon());
  }

  // Scalar reference |h_n| = F (E-VF-4). Returns false when gated.
  bool reference_update(Scalar f, bool gate) noexcept {
    // In a replay pass the reference is linearised at the pass's start like the vector samples.
    const Vec3<Scalar> hn = (lin_at_nominal_ ? nom_ : full()).template segment<3>(kHn0);
    const Scalar n = hn.norm();
    if (!(n > Scalar(0))) return false;
    // First-estimate Jacobian: the direction is fixed at the start (and at a field re-open). A
    // precise constraint relinearised along a wandering direction would remove variance across
    // h_n that no measurement removed (an overconfident declination, heading and time offset).
    // The measurement is then the linear d0^T h_n = F, whose innovation the update can remove: with
    // F - |h_n| the second-order term |h_n| (1 - cos theta) of a direction that turned by theta
    // stays in the innovation, and a field whose direction is still being determined (a heading
    // misalignment estimated from its prior) gated every precise reference and re-opened h_n
    // again and again (2706 times on a real recording). The cost is |h_n| = F / cos theta (E-VF-4).
    // Taking the direction anew when that exceeded F by the magnetometer noise made the h_n and
    // heading 1-sigmas overconfident (0.3-0.4 of the scatter) and a stored start diverge.
    const Scalar sf = noise_factor_ * reference_sigma();
    if (!(ref_dir_.squaredNorm() > Scalar(0))) ref_dir_ = hn / n;
    const Vec3<Scalar> hn_now =
        lin_at_nominal_ ? Vec3<Scalar>(hn + x_.template segment<3>(kHn0)) : hn;
    StateVec h = StateVec::Zero();
    h.template segment<3>(kHn0) = ref_dir_;
    const Scalar r = sf * sf;
    const Scalar nu = f - ref_dir_.dot(hn_now);
    // The row is h_n only: U^T h from kHn0 on, as reference_check takes it in folds.
    const StateVec fv = ud_ut_times<Scalar, kStates, true>(u_, h, kHn0);
    const Scalar s_pred = fv.dot(d_.cwiseProduct(fv)) + r;
    const Scalar nis = nu * nu / s_pred;
    if (gate && cfg_.gate_nis > Scalar(0) && !(nis <= cfg_.gate_nis)) return false;
    StateVec k;
    Scalar s;
    bierman(fv, r, &k, &s);
    x_ += k * (nu / s);
    return true;
  }

  // Three whitened scalar updates of a vector sample (E-VF-2). With `gate`, the sample is rejected
  // as a whole when any component's NIS (at the prior covariance) exceeds the gate.
  enum class VecResult : std::uint8_t { kApplied, kGated, kFailed };
  // `live`: a live sample (not a replay), whose prior innovation and Jacobian feed E-VF-10.
  VecResult vector_update(const Prepared& p, bool gate, bool live = false) noexcept {
    Vec3<Scalar> rw;
    Mat<Scalar, 3, kStates> hw;
    LinExtras ex;
    if (!linearise(p, &rw, &hw, live ? &ex : nullptr) || !all_finite(hw)) return VecResult::kFailed;
    std::array<StateVec, 3> f;
    Vec3<Scalar> nu_prior;
    Scalar nis_max{0};
    const StateVec x_lin = lin_at_nominal_ ? StateVec::Zero() : x_;
    Mat3<Scalar> hph;
    ud_ut_times_rows<Scalar, kStates>(u_, d_, hw, &f, &hph);
    for (int j = 0; j < 3; ++j) {
      const Scalar sj = hph(j, j) + Scalar(1);
      const Scalar nuj = rw(j) + hw.row(j).dot(x_ - x_lin);
      nu_prior(j) = nuj;
      nis_max = std::max(nis_max, nuj * nuj / sj);
    }
    last_nis_ = nis_max;
    if (gate && cfg_.gate_nis > Scalar(0) && !(nis_max <= cfg_.gate_nis)) return VecResult::kGated;
    if (live) note_innovation(ex, hph, nu_prior);
    for (int j = 0; j < 3; ++j) {
      const StateVec hj = hw.row(j).transpose();
      const StateVec fj = j == 0 ? f[0] : ut_times(hj);
      // Linearised once per sample: the later components see the earlier components' step.
      const Scalar nu = -rw(j) - hj.dot(x_ - x_lin);
      StateVec k;
      Scalar s;
      bierman(fj, Scalar(1), &k, &s);
      x_ += k * (nu / s);
      window_nis_sum_ += nu * nu / s;
      ++window_nis_n_;
    }
    return VecResult::kApplied;
  }

  // E-VF-10, per live sample at the prior: covariance matching of the whitened innovation y,
  // E[y y^T] = lm Aw + la Bw + lh C, with Aw, Bw = I - Aw the whitened magnetometer and attitude
  // parts, C = Hw P Hw^T the state part, lm, la the ratios of the true to the configured noise
  // variances and lh that of the state part (the filter's P scales with the noise it was
  // configured with). Attitude noise turns the field, so along u = L^T h_n (normalised) Bw
  // vanishes: p = (u^T y)^2 has E[p] = lm + lh c_p (c_p = u^T C u), and the rest of the energy,
  // q = |y|^2 - p, E[q] = lm (tr Aw - 1) + la tr Bw + lh (tr C - c_p). Separating the two this
  // way keeps the attitude part (often a hundred times the magnetometer's) out of lm: a fit of
  // all nine products, equally weighted, was 20 % low on a 0.3 nT sensor with 13 nT of attitude
  // noise. Running means of the terms are kept; the state part is told apart by its decay.
  // (A replay's innovations start from a diffuse prior, where C dwarfs the noise: live samples
  // only.)
  // hph: C = Hw P Hw^T (ud_ut_times_rows), whose diagonal the gate used too.
  void note_innovation(const LinExtras& ex, const Mat3<Scalar>& hph,
                       const Vec3<Scalar>& y) noexcept {
    // A sample whose predicted innovation is mostly the state's uncertainty (just after a start,
    // or a state released with its prior) says little about the noise and much about how well
    // that uncertainty is known: skipped while the state part exceeds the noise part (tr 3).
    if (!(hph.trace() <= Scalar(3))) return;
    Vec3<Scalar> u = ex.l.transpose() * ex.h_n;
    const Scalar un = u.norm();
    if (!(un > Scalar(0))) return;
    u /= un;
    const Mat3<Scalar> lc = lower_solve(ex.l, ex.cov_mag);  // L^-1 Sigma_m
    const Mat3<Scalar> aw = lower_solve(ex.l, Mat3<Scalar>(lc.transpose()));
    const Scalar py = u.dot(y);
    const Scalar p = py * py;
    const Scalar q = y.squaredNorm() - p;
    const Scalar cp = u.dot(hph * u);
    const Scalar ta = aw.trace() - Scalar(1);
    const Scalar tb = Scalar(3) - aw.trace();
    const Scalar tc = hph.trace() - cp;
    NoiseTerms t;
    t << cp, cp * cp, p, p * cp, q * tb, ta * tb, tc * tb, tb * tb;
    if (!all_finite(t)) return;
    if (nz_n_ < kStatsCountCap) ++nz_n_;
    nz_mean_ += (t - nz_mean_) / static_cast<Scalar>(nz_n_);
  }
  // Running means of c_p, c_p^2, p, p c_p, q tb, ta tb, tc tb, tb^2 (see note_innovation;
  // ta = tr Aw - 1, tb = tr Bw, tc = tr C - c_p).
  using NoiseTerms = Vec<Scalar, 8>;
  // lm, la and their relative variances per sample (E-VF-10). lm and lh from the p equations
  // (lh only when the state part varied enough to be told apart; else lm from p - c_p), la from
  // the q equations given them. False when not solvable.
  struct NoiseSolution {
    Scalar lm{0}, la{0};
    bool has_attitude{false};
    // n Var(lm), n Var(la): p is (lm + lh c_p) times a chi-square of one degree of freedom, and
    // separating lh from lm costs the factor <c^2> / var(c) of the regression; q carries about two
    // degrees of freedom (the state part's share inflating it likewise).
    Scalar n_var_lm{0}, n_var_la{0};
  };
  static bool solve_noise_ratios(const NoiseTerms& t, NoiseSolution* out) noexcept {
    const Scalar m_c = t(0), m_cc = t(1), m_p = t(2), m_pc = t(3);
    const Scalar var_c = m_cc - m_c * m_c;
    Scalar lm{0}, lh{1}, design{1};
    if (var_c > Scalar(1e-3) * std::max(m_cc, std::numeric_limits<Scalar>::min())) {
      lh = (m_pc - m_p * m_c) / var_c;
      lm = m_p - lh * m_c;
      design = m_cc / var_c;
    } else {
      lm = m_p - m_c;
    }
    const Scalar sp = std::abs(lm) + std::abs(lh) * m_c;
    out->lm = lm;
    out->n_var_lm = Scalar(2) * sp * sp * design;
    out->has_attitude = t(7) > Scalar(1e-6);
    out->la = out->has_attitude ? (t(4) - lm * t(5) - lh * t(6)) / t(7) : Scalar(0);
    const Scalar sq = std::abs(out->la) + std::abs(lh) * t(6) / std::max(t(7), Scalar(1e-6));
    out->n_var_la = sq * sq * design;
    return std::isfinite(out->lm) && std::isfinite(out->la);
  }

  static constexpr int kFoldNoiseEvery = 2;
  // Samples accumulated since the last fold (E-VF-B): sums of the rows and residuals and of their
  // products with the sample time, centred on the block's first accepted sample.
  struct Block {
    int live = 0;                                                  // live samples (gated too)
    int n = 0;                                                     // vector samples accumulated
    int n_ref = 0;                                                 // references accumulated
    Scalar ref_sum{0};                                             // sum of their innovations
    Scalar dt_s{0};                                                // time since the last fold
    Scalar t0_s{0};                                                // first sample's time
    Mat<Scalar, 3, kStates> h0 = Mat<Scalar, 3, kStates>::Zero();  // first sample's rows
    Vec3<Scalar> y0 = Vec3<Scalar>::Zero();
    Mat<Scalar, 3, kStates> sh = Mat<Scalar, 3, kStates>::Zero();   // sums of d = h - h0
    Vec3<Scalar> sy = Vec3<Scalar>::Zero();                         // sums of e = y - y0
    Vec3<Scalar> see = Vec3<Scalar>::Zero();                        // sums of e^2
    Scalar st{0}, stt{0};                                           // sums of t, t^2 (t - t0_s)
    Mat<Scalar, 3, kStates> sth = Mat<Scalar, 3, kStates>::Zero();  // sums of t d
    Vec3<Scalar> sty = Vec3<Scalar>::Zero();                        // sums of t e
    void clear() noexcept {
      live = 0;
      n = 0;
      n_ref = 0;
      ref_sum = Scalar(0);
      dt_s = Scalar(0);
    }
  };

  void add_process_noise(Scalar interval_s) noexcept {
    const Scalar s2 = scale_or_one() * scale_or_one();
    const Scalar qo = cfg_.offset_q_nT2_per_s * interval_s / s2;
    const Scalar qh = cfg_.field_q_nT2_per_s * interval_s / s2;
    for (int k = 0; k < 3; ++k) {
      if (qo > Scalar(0)) add_diagonal_noise(kO0 + k, qo);
      if (qh > Scalar(0)) add_diagonal_noise(kHn0 + k, qh);
    }
  }

  VfStatus live_step(const Prepared& p) noexcept {
    VfStatus status = VfStatus::kAccepted;
    if (std::isfinite(p.f)) {
      if (reference_update(p.f, true)) {
        ++counters_.reference_updates;
        consecutive_ref_gated_ = 0;
      } else {
        ++counters_.gated_reference;
        if (++consecutive_ref_gated_ < cfg_.field_change_after)
          return window_check(VfStatus::kGated, true);
        // The reference says the field changed (E-VF-8): re-open h_n and take this sample.
        reopen_field();
        if (!reference_update(p.f, true)) return window_check(VfStatus::kGated, true);
        status = VfStatus::kFieldReopened;
      }
    }
    if (held_[kRmHeading]) ++counters_.heading_held;
    const VecResult vr = vector_update(p, true, true);
    if (vr == VecResult::kFailed) return reset(VfResetReason::kNonFiniteState);
    if (vr == VecResult::kGated) {
      ++counters_.gated;
      if (++consecutive_rejections_ >= cfg_.max_consecutive_rejections && cfg_.divergence_detection)
        return reset(VfResetReason::kConsecutiveRejections);
      return window_check(VfStatus::kGated, true);
    }
    consecutive_rejections_ = 0;
    maybe_fold_rm();
    if (state_check() == VfStatus::kReset) return VfStatus::kReset;
    ++counters_.updates;
    return window_check(status, false);
  }

  // Divergence of the state itself (E-VF-8): kReset (restarted) or kAccepted.
  VfStatus state_check() noexcept {
    if (!all_finite(x_) || !all_finite(d_) || !u_upper_finite())
      return reset(VfResetReason::kNonFiniteState);
    if (!(d_.array() > Scalar(0)).all()) return reset(VfResetReason::kCovarianceNotPositive);
    if (!(std::abs(w().determinant()) > std::numeric_limits<Scalar>::epsilon()))
      return reset(VfResetReason::kSingularModel);
    return VfStatus::kAccepted;
  }

  // ---- information folds (E-VF-B) ---------------------------------------------------------------
  bool block_mode() const noexcept { return cfg_.fold_samples > 1; }

  // A live sample with fold_samples > 1: the same gates as live_step, at the last fold's state
  // and covariance, and the accepted rows accumulated instead of applied.
  VfStatus live_step_block(const Prepared& p) noexcept {
    VfStatus status = VfStatus::kAccepted;
    if (std::isfinite(p.f)) {
      Scalar nu{0};
      if (reference_check(p.f, &nu)) {
        ++counters_.reference_updates;
        consecutive_ref_gated_ = 0;
      } else {
        ++counters_.gated_reference;
        if (++consecutive_ref_gated_ < cfg_.field_change_after)
          return block_step_end(VfStatus::kGated, true);
        // The pending samples were taken with the old field: folded first, then h_n re-opened.
        if (fold_and_check() == VfStatus::kReset) return VfStatus::kReset;
        reopen_field();
        if (!reference_check(p.f, &nu)) return block_step_end(VfStatus::kGated, true);
        status = VfStatus::kFieldReopened;
      }
      ++blk_.n_ref;
      blk_.ref_sum += nu;
    }
    if (held_[kRmHeading]) ++counters_.heading_held;
    // E-VF-10 takes every kFoldNoiseEvery-th sample (its U^T products and statistics cost about
    // a third of the rest of the sample): half the information for the noise figures.
    const bool noise_sample = blk_.live % kFoldNoiseEvery == 0;
    Vec3<Scalar> rw;
    Mat<Scalar, 3, kStates> hw;
    LinExtras ex;
    if (!linearise(p, &rw, &hw, noise_sample ? &ex : nullptr))
      return reset(VfResetReason::kNonFiniteState);
    // The state has not moved since the fold, so the prior innovation is rw itself. Its NIS at R
    // alone bounds the true one (S_j = f^T D f + 1 >= 1): the U^T products are needed only when
    // the bound fails the gate, and for the samples E-VF-10 takes.
    Scalar nis = rw.cwiseAbs2().maxCoeff();
    Mat3<Scalar> hph = Mat3<Scalar>::Zero();
    if (noise_sample || (cfg_.gate_nis > Scalar(0) && !(nis <= cfg_.gate_nis))) {
      std::array<StateVec, 3> f;
      ud_ut_times_rows<Scalar, kStates>(u_, d_, hw, &f, &hph);
      nis = Scalar(0);
      for (int j = 0; j < 3; ++j)
        nis = std::max(nis, rw(j) * rw(j) / (hph(j, j) + Scalar(1)));
    }
    last_nis_ = nis;
    if (cfg_.gate_nis > Scalar(0) && !(nis <= cfg_.gate_nis)) {
      ++counters_.gated;
      if (++consecutive_rejections_ >= cfg_.max_consecutive_rejections && cfg_.divergence_detection)
        return reset(VfResetReason::kConsecutiveRejections);
      return block_step_end(VfStatus::kGated, true);
    }
    if (noise_sample) note_innovation(ex, hph, rw);
    consecutive_rejections_ = 0;
    accumulate(hw, Vec3<Scalar>(-rw));
    ++counters_.updates;
    return block_step_end(status, false);
  }

  VfStatus block_step_end(VfStatus status, bool gated) noexcept {
    if (++blk_.live >= cfg_.fold_samples && fold_and_check() == VfStatus::kReset)
      return VfStatus::kReset;
    return window_check(status, gated);
  }

  // The reference's gate at the fold's state (E-VF-4): innovation into *nu; false when gated.
  // Its row's h P h^T is the same for every sample between two folds: computed once (ref_hph_).
  bool reference_check(Scalar f, Scalar* nu) noexcept {
    const Vec3<Scalar> hn = full().template segment<3>(kHn0);
    const Scalar n = hn.norm();
    if (!(n > Scalar(0))) return false;
    if (!(ref_dir_.squaredNorm() > Scalar(0))) {
      ref_dir_ = hn / n;
      ref_hph_ = Scalar(-1);
    }
    if (!(ref_hph_ >= Scalar(0))) {
      StateVec h = StateVec::Zero();
      h.template segment<3>(kHn0) = ref_dir_;
      const StateVec fv = ud_ut_times<Scalar, kStates, true>(u_, h, kHn0);
      ref_hph_ = fv.dot(d_.cwiseProduct(fv));
    }
    const Scalar sf = reference_sigma();
    *nu = f - ref_dir_.dot(hn);
    const Scalar nis = *nu * *nu / (ref_hph_ + sf * sf);
    return !(cfg_.gate_nis > Scalar(0)) || nis <= cfg_.gate_nis;
  }

  // Accumulates a sample's whitened rows hw and residuals y (y = hw dx + noise) at the block time
  // blk_.dt_s: centred on the block's first sample, so that the differences that carry the block's
  // variation keep their digits in float32 (E-VF-B).
  void accumulate(const Mat<Scalar, 3, kStates>& hw, const Vec3<Scalar>& y) noexcept {
    if (blk_.n == 0) {
      blk_.t0_s = blk_.dt_s;
      blk_.h0 = hw;
      blk_.y0 = y;
      blk_.sh.setZero();
      blk_.sy.setZero();
      blk_.see.setZero();
      blk_.st = Scalar(0);
      blk_.stt = Scalar(0);
      blk_.sth.setZero();
      blk_.sty.setZero();
    } else {
      const Scalar t = blk_.dt_s - blk_.t0_s;
      const Vec3<Scalar> e = y - blk_.y0;
      // Column-major: the three rows of a column are contiguous; a column per step (the loop's
      // count and branch once per three elements on the M4F).
      const Scalar* hp = hw.data();
      const Scalar* h0 = blk_.h0.data();
      Scalar* sh = blk_.sh.data();
      Scalar* sth = blk_.sth.data();
      for (int i = 0; i < 3 * kStates; i += 3) {
        const Scalar d0 = hp[i] - h0[i];
        const Scalar d1 = hp[i + 1] - h0[i + 1];
        const Scalar d2 = hp[i + 2] - h0[i + 2];
        sh[i] += d0;
        sh[i + 1] += d1;
        sh[i + 2] += d2;
        sth[i] += t * d0;
        sth[i + 1] += t * d1;
        sth[i + 2] += t * d2;
      }
      blk_.sy += e;
      blk_.see += e.cwiseProduct(e);
      blk_.sty += t * e;
      blk_.st += t;
      blk_.stt += t * t;
    }
    ++blk_.n;
  }

  // One scalar pseudo-measurement h^T dx = z (variance r) of a fold, dx = x - x_lin: its NIS.
  Scalar pseudo_update(const StateVec& h, Scalar z, Scalar r, int first,
                       const StateVec& x_lin) noexcept {
    const Scalar nu = z - h.dot(x_ - x_lin);
    const StateVec fv = ud_ut_times<Scalar, kStates, true>(u_, h, first);
    StateVec k;
    Scalar s;
    ud_bierman_update<Scalar, kStates, true>(u_, d_, fv, r, &k, &s, first);
    ref_hph_ = Scalar(-1);
    x_ += k * (nu / s);
    return nu * nu / s;
  }

  // E-VF-B: the block's process noise, then its information as pseudo-measurements: the
  // reference's mean innovation along its fixed direction; the three mean rows (variance 1/n); the
  // three trend rows, the rows' and residuals' regressions on the sample time (variance 1/T).
  // Mean and trend are two orthogonal projections of the block's rows, each linearised at the
  // fold's state: exactly the information of rows that vary linearly over the block, what varies
  // faster is left out (never counted twice). The block's NIS (the pseudo-measurements' plus the
  // residuals about mean and trend, 3 n degrees of freedom) feeds the divergence window.
  void fold_block() noexcept {
    if (blk_.dt_s > Scalar(0)) add_process_noise(blk_.dt_s);
    const StateVec x_lin = x_;
    if (blk_.n_ref > 0) {
      StateVec h = StateVec::Zero();
      h.template segment<3>(kHn0) = ref_dir_;
      const Scalar nr = static_cast<Scalar>(blk_.n_ref);
      const Scalar sf = reference_sigma();
      pseudo_update(h, blk_.ref_sum / nr, sf * sf / nr, kHn0, x_lin);
    }
    if (blk_.n > 0) {
      const Scalar inv = Scalar(1) / static_cast<Scalar>(blk_.n);
      Scalar chi2{0};
      Scalar energy{0};
      for (int j = 0; j < 3; ++j) {
        const StateVec hbar = (blk_.h0.row(j) + blk_.sh.row(j) * inv).transpose();
        chi2 += pseudo_update(hbar, blk_.y0(j) + blk_.sy(j) * inv, inv, 0, x_lin);
        energy += blk_.see(j) - blk_.sy(j) * blk_.sy(j) * inv;
      }
      // Trend: sum (t - tbar) h / T with T = sum (t - tbar)^2; the centring on h0 cancels.
      const Scalar tbar = blk_.st * inv;
      const Scalar tt = blk_.stt - blk_.st * tbar;
      if (blk_.n > 1 && tt > Scalar(0)) {
        const Scalar inv_t = Scalar(1) / tt;
        for (int j = 0; j < 3; ++j) {
          const StateVec a = ((blk_.sth.row(j) - blk_.sh.row(j) * tbar) * inv_t).transpose();
          const Scalar z = (blk_.sty(j) - blk_.sy(j) * tbar) * inv_t;
          chi2 += pseudo_update(a, z, inv_t, 0, x_lin);
          energy -= z * z * tt;
        }
      }
      window_nis_sum_ += chi2 + std::max(energy, Scalar(0));
      window_nis_n_ += 3 * blk_.n;
    }
    blk_.clear();
  }

  VfStatus fold_and_check() noexcept {
    // The block's rows are checked here, in their sums, not per sample (linearise): a non-finite
    // row (an overflow) makes them non-finite, and the filter restarts before they are folded.
    if (blk_.n > 0 && !(all_finite(blk_.h0) && all_finite(blk_.sh) && all_finite(blk_.sth))) {
      blk_.clear();
      return reset(VfResetReason::kNonFiniteState);
    }
    fold_block();
    maybe_fold_rm();
    return state_check();
  }

  VfStatus window_check(VfStatus status, bool gated) noexcept {
    ++window_n_;
    if (gated) ++window_gated_;
    if (window_n_ < cfg_.nis_window) return status;
    const Scalar frac = static_cast<Scalar>(window_gated_) / static_cast<Scalar>(window_n_);
    const Scalar mean_nis =
        window_nis_n_ > 0 ? window_nis_sum_ / static_cast<Scalar>(window_nis_n_) : Scalar(0);
    window_n_ = 0;
    window_gated_ = 0;
    window_nis_sum_ = 0;
    window_nis_n_ = 0;
    if (cfg_.divergence_detection) {
      if (frac > cfg_.gated_fraction_limit) return reset(VfResetReason::kTooManyGated);
      if (mean_nis > cfg_.nis_mean_limit) return reset(VfResetReason::kNisTooHigh);
    }
    return status;
  }

  VfStatus reset(VfResetReason reason) noexcept {
    last_reset_ = reason;
    ++counters_.resets;
    restart();
    return VfStatus::kReset;
  }

  // Partial reset: h_n's covariance re-opened and decorrelated, everything else kept.
  void reopen_field() noexcept {
    StateMat p = covariance_normalised();
    const Scalar sh = cfg_.field_reopen_sigma_nT / scale_or_one();
    for (int k = kHn0; k < kHn0 + 3; ++k) {
      for (int j = 0; j < kStates; ++j) {
        p(k, j) = Scalar(0);
        p(j, k) = Scalar(0);
      }
      p(k, k) = sh * sh;
    }
    if (ud_factorise(p)) {
      ref_dir_.setZero();
      last_reset_ = VfResetReason::kFieldChange;
      ++counters_.field_reopens;
      consecutive_ref_gated_ = 0;
      consecutive_rejections_ = 0;
    }
  }

  // ---- U-D factor updates (ud_factor.hpp, E-Ge-C) ----------------------------------------------
  StateMat covariance_normalised() const noexcept {
    StateMat p = StateMat::Zero();
    for (int i = 0; i < kStates; ++i)
      for (int j = i; j < kStates; ++j) {
        Scalar acc{0};
        for (int k = j; k < kStates; ++k)
          acc += u_(i, k) * d_(k) * u_(j, k);
        p(i, j) = acc;
        p(j, i) = acc;
      }
    return p;
  }
  StateVec ut_times(const StateVec& h) const noexcept {
    return ud_ut_times<Scalar, kStates>(u_, h);
  }
  bool u_upper_finite() const noexcept { return ud_upper_finite<Scalar, kStates>(u_); }
  // Agee-Turner: U D U^T + c e_k e_k^T, c > 0.
  // Every change of U or D goes through these four functions and restart(): each drops ref_hph_.
  void add_diagonal_noise(int k, Scalar c) noexcept {
    ud_add_diagonal_noise<Scalar, kStates>(u_, d_, k, c);
    ref_hph_ = Scalar(-1);
  }
  // Bierman's scalar update for f = U^T h and variance r: unnormalised gain k into *k_out (the
  // caller's local, not f) and s = h P h^T + r into *s_out.
  void bierman(const StateVec& f, Scalar r, StateVec* k_out, Scalar* s_out) noexcept {
    ud_bierman_update<Scalar, kStates, true>(u_, d_, f, r, k_out, s_out);
    ref_hph_ = Scalar(-1);
  }
  bool ud_factorise(const StateMat& p) noexcept {
    ref_hph_ = Scalar(-1);
    return core::ud_factorise<Scalar, kStates>(p, &u_, &d_);
  }

  Config cfg_{};
  VfCounters counters_{};
  VfResetReason last_reset_ = VfResetReason::kNone;
  Verdict init_verdict_ = Verdict::kNoData;
  Scalar scale_{0};
  Scalar t0_ = kNaN;      // reference temperature
  Scalar last_t_ = kNaN;  // last temperature seen (held for samples without one)
  bool running_ = false;
  bool pending_start_ = false;
  VfStart<Scalar> stored_{};
  StateVec nom_ = StateVec::Zero();
  StateVec x_ = StateVec::Zero();
  Quat<Scalar> rm_nom_ = Quat<Scalar>::Identity();
  // rm_transposed()'s cache: Rm^T and the Rm_nom and misalignment error it was formed from (NaN
  // at first: no match).
  mutable Mat3<Scalar> rmt_ = Mat3<Scalar>::Identity();
  mutable Vec3<Scalar> rmt_phi_ = Vec3<Scalar>::Constant(std::numeric_limits<Scalar>::quiet_NaN());
  mutable Quat<Scalar> rmt_nom_ = Quat<Scalar>::Identity();
  mutable bool rmt_nominal_{false};
  StateMat u_ = StateMat::Identity();
  StateVec d_ = StateVec::Ones();
  std::array<bool, kStates> held_{};
  // Start from data: kept samples (m, F, R_bn in the batch store) with their rate and temperature.
  Batch batch_{};
  int n_kept_ = 0;
  Scalar min_rotation_deg_{2};  // attitude step between kept samples (grows after refusals)
  Mat<Scalar, 3, kInitCapacity> kept_omega_ = Mat<Scalar, 3, kInitCapacity>::Zero();
  Vec<Scalar, kInitCapacity> kept_att_offset_ = Vec<Scalar, kInitCapacity>::Zero();
  Vec<Scalar, kInitCapacity> kept_t_ = Vec<Scalar, kInitCapacity>::Zero();
  std::array<bool, static_cast<std::size_t>(kInitCapacity)> kept_has_f_{};
  std::array<std::uint32_t, static_cast<std::size_t>(kInitCapacity)> kept_seq_{};
  struct ReplaySample {
    Vec3<Scalar> m_nT = Vec3<Scalar>::Zero();
    Quat<Scalar> q = Quat<Scalar>::Identity();  // R_bn (4 numbers instead of 9)
    Vec3<Scalar> omega = Vec3<Scalar>::Zero();
    Scalar att_offset_s{0};      // VfSample::attitude_offset_s
    Scalar f_nT{0};              // NaN: none
    Scalar temperature_degC{0};  // the last one seen at the time
    std::uint32_t seq = 0;       // counters_.samples at the time
  };
  std::array<ReplaySample, static_cast<std::size_t>(std::max(kReplayCapacity, 1))> replay_{};
  int replay_n_ = 0;
  int replay_head_ = 0;
  bool lin_at_nominal_ = false;  // replay: every sample linearised at the pass's start
  // Start from a stored calibration: its prior, kept for the passes over the first samples.
  bool settling_ = false;
  StateVec settle_nom_ = StateVec::Zero();
  Quat<Scalar> settle_rm_ = Quat<Scalar>::Identity();
  StateMat settle_p_ = StateMat::Zero();
  // Tilt statistics of the body-frame vertical (Welford).
  TiltMoments<Scalar> tilts_{};
  bool tilt_released_ = false;
  // Divergence windows.
  int window_n_ = 0;
  int window_gated_ = 0;
  Scalar window_nis_sum_{0};
  int window_nis_n_ = 0;
  int consecutive_rejections_ = 0;
  int consecutive_ref_gated_ = 0;
  Scalar last_nis_{0};
  Scalar noise_factor_{1};                       // replay damping (1 when running live)
  Vec3<Scalar> ref_dir_ = Vec3<Scalar>::Zero();  // reference update's direction (E-VF-4)
  Scalar ref_hph_{-1};  // its row's h P h^T at the current U-D (reference_check); < 0: not known
  Block blk_{};         // E-VF-B (fold_samples > 1)
  // E-VF-10: running means over the live samples since the last (re)start.
  // E-VF-10: running means of the covariance matching over the live samples since the (re)start.
  std::uint32_t nz_n_ = 0;
  NoiseTerms nz_mean_ = NoiseTerms::Zero();
};

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
void VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::configure(
    const Config& cfg) noexcept {
  cfg_ = cfg;
  cfg_.init_samples = std::clamp(cfg_.init_samples, 16, kInitCapacity);
  cfg_.init_replay_passes = std::max(cfg_.init_replay_passes, 1);
  cfg_.init_full_passes = std::max(cfg_.init_full_passes, 0);
  cfg_.nis_window = std::max(cfg_.nis_window, 10);
  cfg_.field_change_after = std::max(cfg_.field_change_after, 1);
  cfg_.fold_samples = std::max(cfg_.fold_samples, 1);
  counters_ = VfCounters{};
  last_reset_ = VfResetReason::kNone;
  scale_ = cfg_.field_scale_nT > Scalar(0) ? cfg_.field_scale_nT : Scalar(0);
  t0_ = cfg_.temperature_ref_degC;
  last_t_ = t0_;
  pending_start_ = false;
  restart();
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
void VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::start(
    const VfStart<Scalar>& s) noexcept {
  restart();
  stored_ = s;
  pending_start_ = true;
  if (std::isfinite(s.temperature_ref_degC)) {
    t0_ = s.temperature_ref_degC;
    last_t_ = t0_;
  }
  if (!(scale_ > Scalar(0)) && s.h_n_nT.allFinite() && s.h_n_nT.norm() > Scalar(0))
    scale_ = s.h_n_nT.norm();
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
VfStatus VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::update(
    const VfSample<Scalar>& in) noexcept {
  ++counters_.samples;
  if (!all_finite(in.m_nT) || !all_finite(in.r_bn) || !all_finite(in.omega_n_rad_s) ||
      !std::isfinite(in.attitude_offset_s)) {
    ++counters_.rejected_nonfinite;
    return VfStatus::kRejectedNonFinite;
  }
  Scalar f = in.f_nT;
  if (!(std::isfinite(f) && f > Scalar(0))) f = std::numeric_limits<Scalar>::quiet_NaN();
  if (!(scale_ > Scalar(0))) {
    if (std::isfinite(f)) {
      scale_ = f;
    } else if (cfg_.reference_field_nT > Scalar(0)) {
      scale_ = cfg_.reference_field_nT;
    } else if (pending_start_) {
      scale_ = (stored_.model.w * (in.m_nT - stored_.model.o)).norm();
    }
    if (!(scale_ > Scalar(0))) return VfStatus::kRejectedNoReference;
  }
  if (std::isfinite(in.temperature_degC)) {
    if (!std::isfinite(t0_)) t0_ = in.temperature_degC;
    last_t_ = in.temperature_degC;
  }
  note_tilt(in.r_bn);
  if (pending_start_) start_stored(in, f);
  if (!running_) return collect(in, f);
  Prepared p = prepare(in.m_nT, in.r_bn, in.omega_n_rad_s, in.attitude_offset_s, f, last_t_);
  const Scalar dt = std::isfinite(in.interval_s) && in.interval_s >= Scalar(0)
                        ? in.interval_s
                        : cfg_.sample_interval_s;
  if (block_mode())
    blk_.dt_s += dt;
  else
    add_process_noise(dt);
  if (settling_) remember(in, f, counters_.samples);
  const VfStatus st = block_mode() ? live_step_block(p) : live_step(p);
  if (settling_ && running_ && replay_n_ >= kReplayCapacity) return settle(st);
  return st;
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
VfStatus VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::flush() noexcept {
  if (!running_ || blk_.live == 0) return VfStatus::kAccepted;
  return fold_and_check();
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
SensorModel<Scalar> VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::model(
    Scalar t_degC) const noexcept {
  SensorModel<Scalar> m;
  m.w = w();
  m.o = offset_nT(t_degC);
  m.rm = rm_current();
  return m;
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
typename VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::StateMat
VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::covariance() const noexcept {
  const StateMat p = covariance_normalised();
  const StateVec t = unit_scale();
  return t.asDiagonal() * p * t.asDiagonal();
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
VfSigmas<Scalar> VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::sigmas(
    Scalar t_degC) const noexcept {
  const StateMat p = covariance();
  VfSigmas<Scalar> s;
  auto sd = [&](int k) { return std::sqrt(std::max(p(k, k), Scalar(0))); };
  for (int k = 0; k < kWEntries; ++k)
    s.w(kWRow[static_cast<std::size_t>(k)], kWCol[static_cast<std::size_t>(k)]) = sd(kW0 + k);
  const Scalar dtc = delta_t(t_degC);
  for (int i = 0; i < 3; ++i) {
    s.o_ref_nT(i) = sd(kO0 + i);
    const Scalar v = p(kO0 + i, kO0 + i) + Scalar(2) * dtc * p(kO0 + i, kTc0 + i) +
                     dtc * dtc * p(kTc0 + i, kTc0 + i);
    s.o_nT(i) = std::sqrt(std::max(v, Scalar(0)));
    s.rm_rad(i) = sd(kRm0 + i);
    s.h_n_nT(i) = sd(kHn0 + i);
    s.tc_nT_per_degC(i) = sd(kTc0 + i);
  }
  s.dt_s = sd(kDt);
  return s;
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
VfOutputUncertainty<Scalar> VectorCalibrationFilter<
    Scalar, kInitCapacity, kReplayCapacity>::output_uncertainty() const noexcept {
  VfOutputUncertainty<Scalar> o;
  if (!running_ || tilts_.count() < 1) return o;
  const StateVec xf = full();
  Mat3<Scalar> wm = Mat3<Scalar>::Zero();
  for (int k = 0; k < kWEntries; ++k)
    wm(kWRow[static_cast<std::size_t>(k)], kWCol[static_cast<std::size_t>(k)]) = xf(kW0 + k);
  if (!(std::abs(wm.determinant()) > Scalar(0))) return o;
  const Mat3<Scalar> w_inv = wm.inverse();
  const Mat3<Scalar> rm = rm_current().toRotationMatrix();
  const Vec3<Scalar> h_n = xf.template segment<3>(kHn0);
  const Scalar dtemp = delta_t(kNaN);
  const Scalar hn2 = h_n.squaredNorm();
  if (!(hn2 > Scalar(0))) return o;
  const Vec3<Scalar> g_dir = h_n / std::sqrt(hn2);
  // The envelope (output_envelope.hpp, E-VF-10) of the tilts seen since the start, in closed form
  // (docs/equations.md E-VF-10): at an envelope attitude R, with no rate and the reading the
  // current model predicts there, E-VF-3's Jacobian is H_c = M B(b), M = R^T Rm^T orthogonal and
  // b = R h_n, the field in INS axes; the predicted field is g = h_n. B's columns are constant
  // (o: -W; c_T: -dT W) or linear in b (W_k: e_r a_c^T b, a_c^T row c of A = W^-1 Rm; phi_m:
  // Rm [e_m x] b), so G_v = sum H_c^T H_c = sum B^T B needs only n, sum b and sum b b^T, and
  // H_c^T g / |g| = B^T Rm b / |h_n|.
  const Mat3<Scalar> a = w_inv * rm;
  std::array<Mat3<Scalar>, kCalStates> lin{};  // column p = lin[p] b (linear columns)
  std::array<Vec3<Scalar>, kCalStates> cst{};  // column p = cst[p] (constant columns)
  std::array<bool, kCalStates> is_lin{};
  for (int k = 0; k < kWEntries; ++k) {
    const auto kk = static_cast<std::size_t>(k);
    lin[kk].setZero();
    lin[kk].row(kWRow[kk]) = a.row(kWCol[kk]);
    is_lin[kk] = true;
  }
  for (int m = 0; m < 3; ++m) {
    const auto mm = static_cast<std::size_t>(m);
    cst[static_cast<std::size_t>(kWEntries) + mm] = -wm.col(m);  // o
    lin[static_cast<std::size_t>(kWEntries) + 3 + mm] =
        rm * skew(Vec3<Scalar>(Vec3<Scalar>::Unit(m)));  // phi
    is_lin[static_cast<std::size_t>(kWEntries) + 3 + mm] = true;
    cst[static_cast<std::size_t>(kWEntries) + 6 + mm] = -dtemp * wm.col(m);  // c_T
  }
  static_assert(kWEntries + 9 == kCalStates);
  // Noise at the envelope (E-OS-3): tr(Sigma_m) = sm^2 |W|_F^2 (M orthogonal) at every attitude;
  // along g the attitude part vanishes (it turns h_n) and the magnetometer's is sm^2 |W^T Rm b|^2
  // / |h_n|^2.
  const Scalar sm = mag_sigma();
  const Scalar sa = attitude_sigma();
  const Scalar tr_mag = sm * sm * wm.squaredNorm();
  // The |h| row at an attitude, h_i(p) = rb^T B_p with rb = M^T g / |g| = Rm b / |h_n|: Rm's
  // entries are zero (rb^T Rm (e_m x b) = b . (e_m x b) / |h_n|: a misalignment leaves |h|
  // alone), W_k's is rb(row k) (A b)(column k), o's are -(W^T rb) and c_T's dT times o's. The sum
  // runs over the nine W and o entries; the rest of G_i follows after it.
  constexpr int kHi = kWEntries + 3;
  Mat<Scalar, kHi, kHi> gi_wo = Mat<Scalar, kHi, kHi>::Zero();  // upper triangle
  EnvelopeGram<Scalar, kCalStates> gram;
  Vec3<Scalar> s1 = Vec3<Scalar>::Zero();
  Mat3<Scalar> m2 = Mat3<Scalar>::Zero();
  Scalar nv{0}, ni{0};
  for_each_envelope_attitude(tilts_, [&](const Mat3<Scalar>& r) {
    const Vec3<Scalar> b = r * h_n;
    const Vec3<Scalar> rb = rm * (r * g_dir);  // M^T g / |g|
    s1 += b;
    m2 += b * b.transpose();
    const Vec3<Scalar> ab = a * b;
    const Vec3<Scalar> wt_rb = wm.transpose() * rb;
    Vec<Scalar, kHi> hi;
    for (std::size_t k = 0; k < static_cast<std::size_t>(kWEntries); ++k)
      hi(static_cast<Eigen::Index>(k)) = rb(kWRow[k]) * ab(kWCol[k]);
    hi.template tail<3>() = -wt_rb;
    Scalar* w = gi_wo.data();
    for (int c = 0; c < kHi; ++c)
      for (int q = 0; q <= c; ++q)
        w[kHi * c + q] += hi(q) * hi(c);
    ++gram.n;
    nv += tr_mag + sa * sa * attitude_noise_columns(r, h_n).squaredNorm();
    ni += sm * sm * wt_rb.squaredNorm();
  });
  // G_i's upper triangle: W and o from the sum, c_T as dT times o, zero for Rm.
  for (int c = 0; c < kCalStates; ++c) {
    for (int q = 0; q <= c; ++q) {
      const int sq = q < kHi ? q : q - 6;  // c_T's entries follow o's (6 places on)
      const int sc = c < kHi ? c : c - 6;
      const bool zero = (q >= kHi && q < kHi + 3) || (c >= kHi && c < kHi + 3);
      const Scalar f = (q >= kHi ? dtemp : Scalar(1)) * (c >= kHi ? dtemp : Scalar(1));
      gram.gi(q, c) = zero ? Scalar(0) : f * gi_wo(std::min(sq, sc), std::max(sq, sc));
    }
  }
  const int na = gram.n;
  if (na == 0) return o;
  // G_v from the moments: constant-constant n c_p.c_q, constant-linear c_p.(L_q sum b),
  // linear-linear tr(L_p^T L_q sum b b^T).
  std::array<Vec3<Scalar>, kCalStates> ls1{};
  std::array<Mat3<Scalar>, kCalStates> lm2{};
  for (std::size_t p = 0; p < static_cast<std::size_t>(kCalStates); ++p) {
    if (!is_lin[p]) continue;
    ls1[p] = lin[p] * s1;
    lm2[p] = lin[p] * m2;
  }
  for (std::size_t c = 0; c < static_cast<std::size_t>(kCalStates); ++c) {
    for (std::size_t q = 0; q <= c; ++q) {
      Scalar v;
      if (is_lin[q] && is_lin[c])
        v = lin[q].cwiseProduct(lm2[c]).sum();
      else if (is_lin[q])
        v = cst[c].dot(ls1[q]);
      else if (is_lin[c])
        v = cst[q].dot(ls1[c]);
      else
        v = static_cast<Scalar>(na) * cst[q].dot(cst[c]);
      gram.gv(static_cast<Eigen::Index>(q), static_cast<Eigen::Index>(c)) = v;
    }
  }
  const int n = gram.n;
  const CalMat& gv = gram.gv;
  const CalMat& gi = gram.gi;
  o.attitudes = static_cast<std::uint32_t>(n);
  // tr(P_cc G) = sum_ij P_cc(i, j) G(i, j) over the upper triangles (the only parts filled),
  // P_cc = U_c D U_c^T from the calibration rows of U (upper triangular: U(c, k) = 0 for k < c).
  Scalar tv{0}, ti{0};
  for (int j = 0; j < kCalStates; ++j) {
    const int cj = kCalIndex[static_cast<std::size_t>(j)];
    for (int i = 0; i <= j; ++i) {
      const int ci = kCalIndex[static_cast<std::size_t>(i)];
      Scalar pij{0};
      for (int k = std::max(ci, cj); k < kStates; ++k)
        pij += u_(ci, k) * d_(k) * u_(cj, k);
      const Scalar wgt = i == j ? Scalar(1) : Scalar(2);
      tv += wgt * pij * gv(i, j);
      ti += wgt * pij * gi(i, j);
    }
  }
  const Scalar sc = scale_or_one();
  const Scalar inv_n = Scalar(1) / static_cast<Scalar>(n);
  o.vector_nT = sc * gram.vector_rms(tv);
  o.intensity_nT = sc * gram.intensity_rms(ti);
  o.vector_noise_nT = sc * std::sqrt(std::max(nv * inv_n, Scalar(0)) / Scalar(3));
  o.intensity_noise_nT = sc * std::sqrt(std::max(ni * inv_n, Scalar(0)));
  return o;
}

template <typename Scalar, int kInitCapacity, int kReplayCapacity>
VfNoiseEstimate<Scalar>
VectorCalibrationFilter<Scalar, kInitCapacity, kReplayCapacity>::innovation_noise() const noexcept {
  VfNoiseEstimate<Scalar> e;
  e.samples = nz_n_;
  if (nz_n_ < kMinNoiseSamples) return e;
  const Scalar n = static_cast<Scalar>(nz_n_);
  const Scalar sm = cfg_.mag_noise_nT;
  const Scalar sa = cfg_.attitude_noise_rad;
  NoiseSolution ns;
  if (!solve_noise_ratios(nz_mean_, &ns)) return e;
  const Scalar lm = ns.lm, la = ns.la;
  e.has_attitude = sa > Scalar(0) && ns.has_attitude;
  if (!(lm > Scalar(0)) || !std::isfinite(lm)) return e;
  // Relative sigma of a figure: half that of its variance ratio (NoiseSolution, E-VF-10).
  e.valid = true;
  e.mag_nT = sm * std::sqrt(lm);
  e.mag_sigma_nT = e.mag_nT * std::sqrt(ns.n_var_lm / n) / (Scalar(2) * lm);
  if (e.has_attitude) {
    e.attitude_rad = sa * std::sqrt(std::max(la, Scalar(0)));
    e.attitude_sigma_rad =
        la > Scalar(0) ? e.attitude_rad * std::sqrt(ns.n_var_la / n) / (Scalar(2) * la) : kNaN;
  }
  return e;
}

// Compiled once per scalar (firmware/core/src/inst_vector_<scalar>.cpp, the
// magvec::core_vector_<scalar> library): an instantiation of the filter costs minutes of compile
// time, so the units that use it only call it. Its entry points are defined outside the class
// because GCC instantiates in-class (implicitly inline) members for inlining even under `extern
// template`. A unit sees the declaration when it links that library (the library's compile
// definition); any other unit instantiates the filter itself.
#ifdef MAGVEC_CORE_VECTOR_FLOAT_COMPILED
extern template class VectorCalibrationFilter<float>;
#endif
#ifdef MAGVEC_CORE_VECTOR_DOUBLE_COMPILED
extern template class VectorCalibrationFilter<double>;
#endif

}  // namespace magvec::core
