// VectorCalibrator: the online vector calibration filter (docs/equations.md E-VF;
// vector_calibration_filter.hpp) behind the SensorLoop Calibrator contract (sensor_loop.hpp), the
// calibrator mode `vector-ekf`.
//
// Per sample the filter needs more than {m, F, R_bn}: the n-frame rotation rate (time offset,
// E-VF-5), the interval since the previous sample (process noise) and the temperature (E-VF-6).
// The adapter therefore takes the loop's whole MagSample (add(const MagSample&, const Mat3*), the
// extended contract): the interval from successive time stamps, the temperature from
// MagSample::temperature_degC (NaN: the filter holds the last one seen).
//
// Attitude at t - tau (DECISION, E-VF-5). The samples wait in a ring of HoldCapacity (the recent
// ones stay as history) until the ring reaches rate_half_span_s past t - tau, tau the filter's
// current time offset; the filter is then given the attitude at t - tau interpolated (slerp)
// between the ring's attitudes, with VfSample::attitude_offset_s = tau, and the rate at t - tau
// from the attitudes rate_half_span_s either side. Rotating the sample's own attitude by tau times
// a differenced rate instead multiplies the rate's noise by tau: with an unknown 10 ms INS latency
// on a 200 Hz survey the noise estimate grew from 9.7 to 112 nT per E/N/U component, the offset
// came out at -9.2 +- 0.3 ms and validation refused the candidate. The half span keeps the rate's
// attitudes clear of the INS samples interpolated at t - tau (independent noise; a rate from the
// neighbours biased the offset by sa^2 / (dt |Omega|^2), 4 ms after a start from data) and makes
// it 4x less noisy than the neighbours'. Where the ring does not reach (its start, a gap, an
// offset beyond it) the sample's own attitude is used with the rate from its neighbours, as
// before. add() returns the outcome of the sample it processed (kUsed when it processed none); a
// sample is processed rate_half_span_s - tau late, or when the ring is full.
//
// Noise (DECISION). The filter is configured with the magnetometer and attitude noise and has no
// estimator of its own; a figure far too small makes it refuse the data (its NIS divergence test),
// one far too large slows it. Unless both figures are given (estimate_noise off), the adapter
// first keeps a motion-decimated set of samples (the filter's start-up size, attitude step
// init_min_rotation_deg) and runs the batch one-step fit with noise estimation on it
// (batch_calibrator.hpp, docs/equations.md E-TO-2); the filter is then configured with the
// estimated figures and the same samples are replayed into it, so they also form its start from
// data (E-VF-1) and nothing is collected twice. A set whose fit gives no noise estimate (too little
// variety) keeps every other sample and doubles the attitude step, as the filter's own start does.
//
// add(): non-finite reading, attitude, reference (+-inf; NaN means none) or temperature (+-inf) ->
// kRejected (counted: counts().nonfinite); no attitude -> kRejected (counts().no_attitude; the
// vector model needs one); no scalar reference while the noise or the filter's start needs one ->
// kRejected (counts().no_reference); the filter's gate -> kGated; everything else kUsed.
//
// ready(): the filter runs (initialised), the heading misalignment is no longer held (the tilt
// spread reached the batch methods' limit, E-VF-7), and the calibration's remaining uncertainty
// adds little to the outputs over the survey envelope (E-VF-10: every heading, at the tilts seen
// since the start): its 1-sigma of each E/N/U component and of |h| is at most k = max_output_ratio
// (0.5: at most 12 % in quadrature) of those outputs' per-sample noise. The ratios are the
// filter's own covariance against its own noise figures, so the rule is the same at any noise
// level and any field; it trusts the covariance, which is consistent since each sample's rate
// comes from its neighbours (measured: offsets' errors within 2.3 of their 1-sigmas). The first
// rule, every parameter's 1-sigma at most k of the noise it is seen through
// (F sigma(W_ij) <= k sm, sigma(o_i) <= k sm, F sigma(phi_i) <= k sqrt(sm^2 + (F sa)^2)), is too
// strict where the manoeuvre determines parameters only in combination (an axis's offset and
// scale through a near-constant vertical field): a 90-s survey manoeuvre stayed at 1.6x its limit
// while the output error on the survey lines was at the floor. parameter_ratio() reports it.
// progress() is the fulfilment of the readiness and noise ratios (and the start-up collection
// before). The envelope costs ~46 000 instructions on the M4F: it is refreshed every refresh_every
// samples.
//
// Noise refinement (E-VF-10): once the filter runs, its live innovations estimate both noise
// figures again (covariance matching), from thousands of samples instead of the start-up set's
// few dozen. noise() and the candidate report that estimate once it is valid; the filter keeps
// running with the figures it started with (changing its weights would leave its covariance
// inconsistent with what it already absorbed). With estimated noise, ready() also needs each
// figure's relative 1-sigma at most max_noise_rel_sigma (5 %): the candidate's noise is what the
// held-out validation and the records' 1-sigma use, and the start-up set's 48 samples give about
// 10 % (a 3 nT magnetometer was estimated at 3.8 nT, 2 sigma off); a few hundred live samples
// reach 5 %.
//
// solve(): the filter's current model (W, the offset at the last temperature seen, Rm) as the
// candidate, aligned = true, with the noise figures of noise() (estimated, or given).
// The time offset the filter estimates goes with the candidate as
// CalibratorSolve::time_offset_correction_s (relative to the attitudes the loop gave it): the
// pipeline pairs the held-out samples and, once applied, the records at its offset plus that. The
// temperature coefficients are not part of the SensorModel a candidate carries (the records apply
// no temperature term): a diagnostic here (filter()).
//
// After a solve (DECISION). solve() only reads the filter, so a copy solved on another thread
// (magvecd's worker) gives the same candidate. The loop stops feeding the calibrator once it
// solves (the held-out validation needs samples the calibrator has not seen, and an applied
// calibration must not move under the records), so after a candidate is applied or refused the
// filter pauses with its state intact; add() may continue it. begin() (a new calibration) restarts
// it from nothing, noise figures included, like the other calibrators: a refused candidate must
// not carry its model into the next attempt.
//
// Heap-free, noexcept, float and double.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"
#include "magvec/core/vector_calibration_filter.hpp"

namespace magvec::core {

// CalibratorSolve::code of VectorCalibrator refusals.
enum class VecCalCode : std::uint8_t {
  kOk = 0,
  kNotInitialised = 1,       // the filter has not started (no noise estimate or start from data)
  kHeadingUnobservable = 2,  // the heading misalignment is still held: too little pitch/roll
  kNotDetermined = 3,        // parameter 1-sigmas above the readiness limit (a solve before ready)
  kSingularModel = 4,        // W not finite or not a proper (det > 0) matrix
  kNoiseNotDetermined = 5,   // the noise estimate's relative 1-sigma above its readiness limit
};

inline const char* vec_cal_code_name(std::uint8_t code) noexcept {
  switch (static_cast<VecCalCode>(code)) {
    case VecCalCode::kOk:
      return "ok";
    case VecCalCode::kNotInitialised:
      return "filter_not_initialised";
    case VecCalCode::kHeadingUnobservable:
      return "unobservable_heading_misalignment";
    case VecCalCode::kNotDetermined:
      return "parameters_not_determined";
    case VecCalCode::kSingularModel:
      return "singular_model";
    case VecCalCode::kNoiseNotDetermined:
      return "noise_not_determined";
  }
  return "unknown";
}

template <typename Scalar>
struct VectorCalibratorConfig {
  VfConfig<Scalar> filter{};
  // Estimate the noise figures from the data first (see the top); off: filter.mag_noise_nT and
  // filter.attitude_noise_rad are the known figures.
  bool estimate_noise = true;
  // Readiness: the RMS output error from the calibration's uncertainty over the survey envelope
  // at most this fraction of the outputs' per-sample noise (see the top).
  Scalar max_output_ratio{Scalar(0.5)};
  // Readiness with estimated noise: each figure's relative 1-sigma at most this (see the top).
  Scalar max_noise_rel_sigma{Scalar(0.05)};
  // Samples between two evaluations of the output uncertainty (>= 1; see the top).
  int refresh_every{64};
  // Longest interval over which a rate is taken from two attitudes.
  Scalar max_rate_span_s{Scalar(0.5)};
  // Half the span of the rate at t - tau (see the top): at least two INS periods.
  Scalar rate_half_span_s{Scalar(0.02)};
};

struct VectorCalibratorCounts {
  std::uint64_t seen{0};         // add() calls
  std::uint64_t nonfinite{0};    // rejected: NaN/inf reading or attitude, inf reference/temperature
  std::uint64_t no_attitude{0};  // rejected: no attitude
  std::uint64_t no_reference{0};    // rejected: no reference while the start needs one
  std::uint64_t gated{0};           // gated by the filter
  std::uint64_t noise_kept{0};      // kept for the noise estimate
  std::uint32_t noise_attempts{0};  // noise fits tried
  std::uint32_t noise_failures{0};  // ... that gave no estimate
};

// ReplayCapacity: the filter's replay store (E-VF-1; its largest buffer: 52 bytes per sample in
// float), smaller on a small MCU. HoldCapacity: the ring of recent samples (see the top; 84 bytes
// per sample in float): it must span 2 (rate_half_span_s + |tau|) at the sample rate.
template <typename Scalar, int InitCapacity = 64, int ReplayCapacity = 512, int HoldCapacity = 128>
class VectorCalibrator {
  static_assert(HoldCapacity >= 4);
  static_assert(CoreScalar<Scalar>);

 public:
  using Config = VectorCalibratorConfig<Scalar>;
  using Filter = VectorCalibrationFilter<Scalar, InitCapacity, ReplayCapacity>;

  explicit VectorCalibrator(const Config& config = Config{}) noexcept : cfg_(config) { begin(); }

  void configure(const Config& config) noexcept {
    cfg_ = config;
    begin();
  }
  const Config& config() const noexcept { return cfg_; }

  // --- SensorLoop Calibrator contract (extended form) --------------------------------------------
  void begin() noexcept {
    counts_ = VectorCalibratorCounts{};
    hold_n_ = 0;
    hold_done_ = 0;
    att_.reset(hold_buffer_config(cfg_.max_rate_span_s));
    half_span_us_ = static_cast<std::int64_t>(std::lround(cfg_.rate_half_span_s * Scalar(1e6)));
    n_kept_ = 0;
    noise_batch_.reset();
    noise_step_deg_ = cfg_.filter.init_min_rotation_deg;
    noise_known_ = !cfg_.estimate_noise;
    noise_ = BatchNoise<Scalar>{};
    if (noise_known_) {
      noise_.mag_nT = cfg_.filter.mag_noise_nT;
      noise_.has_attitude = true;
      noise_.attitude_deg = rad_to_deg(cfg_.filter.attitude_noise_rad);
    }
    filter_.configure(cfg_.filter);
    out_ = VfOutputUncertainty<Scalar>{};
    since_refresh_ = 0;
  }

  CalibratorAdd add(const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn) noexcept;

  Scalar progress() const noexcept {
    // The start-up set is the first tenth (as the guidance shows the scalar EKF's).
    constexpr Scalar kStartupShare = Scalar(0.1);
    if (!filter_.initialised()) {
      const Scalar need = static_cast<Scalar>(std::max(filter_.config().init_samples, 1));
      const Scalar have = static_cast<Scalar>(noise_known_ ? filter_.startup_samples() : n_kept_);
      return kStartupShare * std::clamp(have / need, Scalar(0), Scalar(1));
    }
    Scalar p =
        std::clamp(Scalar(1) / std::max(std::max(readiness_ratio(), noise_ratio()), Scalar(1e-30)),
                   Scalar(0), Scalar(1));
    // Squared: the ratio falls as 1/sqrt(samples), progress then grows about linearly in time.
    p = p * p;
    if (filter_.heading_held()) p = std::min(p, Scalar(0.99));
    return kStartupShare + (Scalar(1) - kStartupShare) * p;
  }

  bool ready() const noexcept {
    return filter_.initialised() && !filter_.heading_held() && readiness_ratio() <= Scalar(1) &&
           noise_ratio() <= Scalar(1);
  }

  CalibratorSolve solve(SensorModel<Scalar>* out) const noexcept {
    if (!filter_.initialised()) return fail(VecCalCode::kNotInitialised);
    if (filter_.heading_held()) return fail(VecCalCode::kHeadingUnobservable);
    if (!(readiness_ratio() <= Scalar(1))) return fail(VecCalCode::kNotDetermined);
    if (!(noise_ratio() <= Scalar(1))) return fail(VecCalCode::kNoiseNotDetermined);
    const SensorModel<Scalar> m = filter_.model();
    if (!m.w.allFinite() || !m.o.allFinite() || !(m.w.determinant() > Scalar(0)))
      return fail(VecCalCode::kSingularModel);
    *out = m;
    CalibratorSolve r{true, 0, true};
    const BatchNoise<Scalar> nz = noise();
    r.mag_noise_nT = static_cast<float>(nz.mag_nT);
    r.attitude_noise_deg = static_cast<float>(nz.attitude_deg);
    // The candidate's own output 1-sigma over the survey envelope (E-VF-10).
    r.calibration_sigma_f_nT = static_cast<float>(out_.intensity_nT);
    r.calibration_sigma_enu_nT = static_cast<float>(out_.vector_nT);
    // The time offset the filter found, relative to the attitudes the loop gave it: the loop's
    // pipeline pairs the held-out samples and the records that way (E-VF-5).
    if (filter_.config().estimate_time_offset)
      r.time_offset_correction_s = static_cast<float>(filter_.time_offset_s());
    return r;
  }

  // --- diagnostics ------------------------------------------------------------------------------
  const Filter& filter() const noexcept { return filter_; }
  const VectorCalibratorCounts& counts() const noexcept { return counts_; }
  // The noise figures (valid once noise_known()): given; or estimated, from the filter's live
  // innovations once that estimate is valid (E-VF-10), before from the start-up set's batch fit.
  bool noise_known() const noexcept { return noise_known_; }
  BatchNoise<Scalar> noise() const noexcept {
    if (!cfg_.estimate_noise || !noise_known_) return noise_;
    const VfNoiseEstimate<Scalar> e = filter_.innovation_noise();
    if (!e.valid) return noise_;
    BatchNoise<Scalar> n;
    n.estimated = true;
    n.mag_nT = e.mag_nT;
    n.mag_sigma_nT = e.mag_sigma_nT;
    if (e.has_attitude) {
      n.has_attitude = true;
      n.attitude_deg = rad_to_deg(e.attitude_rad);
      n.attitude_sigma_deg = rad_to_deg(e.attitude_sigma_rad);
    } else {
      n.has_attitude = noise_.has_attitude;
      n.attitude_deg = noise_.attitude_deg;
      n.attitude_sigma_deg = noise_.attitude_sigma_deg;
    }
    return n;
  }
  // The start-up set's batch estimate (or the given figures): what the filter runs with.
  const BatchNoise<Scalar>& startup_noise() const noexcept { return noise_; }
  // Samples kept for the noise estimate (before it) and the number it needs.
  int noise_samples() const noexcept { return n_kept_; }
  int samples_needed() const noexcept { return filter_.config().init_samples; }
  // The output uncertainty over the survey envelope as last refreshed (E-VF-10).
  const VfOutputUncertainty<Scalar>& output_uncertainty() const noexcept { return out_; }
  // The readiness ratio (<= 1: determined; inf before the start and the first report): the
  // output rule's (E-VF-10), the larger of the E/N/U and |h| ratios over max_output_ratio.
  Scalar readiness_ratio() const noexcept {
    const Scalar k = cfg_.max_output_ratio;
    const Scalar inf = std::numeric_limits<Scalar>::infinity();
    if (!filter_.initialised() || !(k > Scalar(0)) || !(out_.vector_noise_nT > Scalar(0)) ||
        !(out_.intensity_noise_nT > Scalar(0)))
      return inf;
    const Scalar r = std::max(out_.vector_nT / out_.vector_noise_nT,
                              out_.intensity_nT / out_.intensity_noise_nT) /
                     k;
    return std::isfinite(r) ? r : inf;
  }
  // The largest parameter 1-sigma over k sm (k sqrt(sm^2 + (F sa)^2) for Rm): a report.
  Scalar parameter_ratio() const noexcept {
    if (!filter_.initialised()) return std::numeric_limits<Scalar>::infinity();
    const VfConfig<Scalar>& fc = filter_.config();
    const Scalar f = filter_.h_n_nT().norm();
    const Scalar sm = fc.mag_noise_nT;
    const Scalar vec =
        std::sqrt(sm * sm + (f * fc.attitude_noise_rad) * (f * fc.attitude_noise_rad));
    const Scalar k = cfg_.max_output_ratio;
    if (!(f > Scalar(0)) || !(k > Scalar(0)) || !(sm > Scalar(0)))
      return std::numeric_limits<Scalar>::infinity();
    const VfSigmas<Scalar> sg = filter_.sigmas();
    Scalar worst{0};
    worst = std::max(worst, f * sg.w.maxCoeff() / (k * sm));
    worst = std::max(worst, sg.o_nT.maxCoeff() / (k * sm));
    worst = std::max(worst, f * sg.rm_rad.maxCoeff() / (k * vec));
    return std::isfinite(worst) ? worst : std::numeric_limits<Scalar>::infinity();
  }
  // The noise figures' relative 1-sigma over max_noise_rel_sigma (<= 1: determined); 0 when the
  // figures are given.
  Scalar noise_ratio() const noexcept {
    if (!cfg_.estimate_noise) return Scalar(0);
    if (!noise_known_) return std::numeric_limits<Scalar>::infinity();
    const BatchNoise<Scalar> n = noise();
    const Scalar k = cfg_.max_noise_rel_sigma;
    if (!(k > Scalar(0)) || !(n.mag_nT > Scalar(0))) return std::numeric_limits<Scalar>::infinity();
    Scalar r = n.mag_sigma_nT / (k * n.mag_nT);
    if (n.has_attitude && n.attitude_deg > Scalar(0))
      r = std::max(r, n.attitude_sigma_deg / (k * n.attitude_deg));
    return std::isfinite(r) ? r : std::numeric_limits<Scalar>::infinity();
  }

 private:
  static CalibratorSolve fail(VecCalCode code) noexcept {
    return CalibratorSolve{false, static_cast<std::uint8_t>(code)};
  }

  CalibratorAdd to_loop(VfStatus st) noexcept {
    switch (st) {
      case VfStatus::kGated:
        ++counts_.gated;
        return CalibratorAdd::kGated;
      case VfStatus::kRejectedNonFinite:
        ++counts_.nonfinite;
        return CalibratorAdd::kRejected;
      case VfStatus::kRejectedNoReference:
        ++counts_.no_reference;
        return CalibratorAdd::kRejected;
      case VfStatus::kAccepted:
      case VfStatus::kCollecting:
      case VfStatus::kInitialised:
      case VfStatus::kInitFailed:
      case VfStatus::kFieldReopened:
      case VfStatus::kReset:
        break;
    }
    return CalibratorAdd::kUsed;
  }

  // Motion-decimated set for the noise estimate; at the filter's start-up size the batch fit.
  CalibratorAdd collect_for_noise(const VfSample<Scalar>& v) noexcept {
    Scalar f = v.f_nT;
    if (!(std::isfinite(f) && f > Scalar(0))) f = cfg_.filter.reference_field_nT;
    if (!(std::isfinite(f) && f > Scalar(0))) {
      ++counts_.no_reference;
      return CalibratorAdd::kRejected;
    }
    if (n_kept_ > 0 && rotation_angle_between(kept_[static_cast<std::size_t>(n_kept_ - 1)].r_bn,
                                              v.r_bn) < deg_to_rad(noise_step_deg_)) {
      return CalibratorAdd::kUsed;
    }
    if (noise_batch_.add_sample(v.m_nT, f, v.r_bn) != AddStatus::kAccepted)
      return CalibratorAdd::kUsed;
    kept_[static_cast<std::size_t>(n_kept_)] = v;
    ++n_kept_;
    ++counts_.noise_kept;
    if (n_kept_ < std::clamp(filter_.config().init_samples, 16, InitCapacity))
      return CalibratorAdd::kUsed;
    estimate_noise();
    return CalibratorAdd::kUsed;
  }

  void estimate_noise() noexcept {
    ++counts_.noise_attempts;
    BatchConfig<Scalar> bc;
    bc.estimate_noise = true;
    bc.mag_noise_nT = cfg_.filter.mag_noise_nT;  // start values
    bc.attitude_noise_deg = rad_to_deg(cfg_.filter.attitude_noise_rad);
    bc.attitude_model = cfg_.filter.attitude_model;
    bc.field_nT = cfg_.filter.reference_field_nT > Scalar(0)
                      ? cfg_.filter.reference_field_nT
                      : std::numeric_limits<Scalar>::quiet_NaN();
    noise_batch_.set_config(bc);
    BatchResult<Scalar> res = noise_batch_.solve(BatchMethod::kOneStep);
    if (res.verdict == Verdict::kUnobservableHeadingMisalignment) {
      // Level data: the heading misalignment is held (as the filter will hold it) for the noise.
      bc.fix_heading_misalignment = true;
      noise_batch_.set_config(bc);
      res = noise_batch_.solve(BatchMethod::kOneStep);
    }
    const Scalar lag_s = startup_time_offset(&res);
    const BatchNoise<Scalar>& nz = res.noise;
    const bool ok = res.has_model && nz.estimated && std::isfinite(nz.mag_nT) &&
                    nz.mag_nT > Scalar(0) && nz.has_attitude && std::isfinite(nz.attitude_deg) &&
                    nz.attitude_deg >= Scalar(0);
    if (!ok) {
      ++counts_.noise_failures;
      thin();
      return;
    }
    noise_ = nz;
    noise_known_ = true;
    VfConfig<Scalar> fc = cfg_.filter;
    fc.mag_noise_nT = nz.mag_nT;
    fc.attitude_noise_rad = deg_to_rad(nz.attitude_deg);
    // The kept attitudes were taken at the filter's offset then (0: it was not running).
    if (fc.estimate_time_offset) fc.time_offset0_s = lag_s;
    filter_.configure(fc);
    // The same samples start the filter (E-VF-1): it keeps them all (they are a step apart), with
    // their attitudes moved by the start's time offset as the fit saw them.
    for (int i = 0; i < n_kept_; ++i) {
      const VfStatus st = filter_.update(shifted(kept_[static_cast<std::size_t>(i)], lag_s));
      if (st == VfStatus::kGated) ++counts_.gated;
    }
    n_kept_ = 0;
    noise_batch_.reset();
    refresh_output_report();
  }

  // The kept sample with its attitude moved by a further move_s along its rate (R Exp(move
  // [Omega x]), E-VF-5), as fit_time_offset() moved the fit's copy.
  static VfSample<Scalar> shifted(const VfSample<Scalar>& v, Scalar move_s) noexcept {
    VfSample<Scalar> o = v;
    const Vec3<Scalar> rot = v.omega_n_rad_s * move_s;
    const Scalar ang = rot.norm();
    if (ang > Scalar(0)) {
      o.r_bn = v.r_bn * Eigen::AngleAxis<Scalar>(ang, rot / ang).toRotationMatrix();
      o.attitude_offset_s = v.attitude_offset_s + move_s;
    }
    return o;
  }

  // The start-up set's time offset (DECISION, E-VF-5): the one-step fit has none, so an INS
  // latency unknown to the loop would be taken for attitude noise (a 10 ms latency on a turning
  // survey: 0.12 deg instead of 0.015, and the filter runs with that figure); fit_time_offset()
  // (batch_calibrator.hpp, E-TO-4) regresses it out of the fit's residuals first. The filter then
  // starts from that offset.
  Scalar startup_time_offset(BatchResult<Scalar>* res) noexcept {
    if (!cfg_.filter.estimate_time_offset) return Scalar(0);  // configured: the filter holds it
    // The kept samples are stored as they came (offset as given); the rates are theirs.
    return fit_time_offset(
        &noise_batch_, BatchMethod::kOneStep, cfg_.max_rate_span_s,
        [this](std::size_t i) noexcept { return kept_[i].omega_n_rad_s; }, res);
  }

  // No estimate: every other kept sample, twice the attitude step (the set spans more motion).
  void thin() noexcept {
    const int half = n_kept_ / 2;
    noise_batch_.reset();
    for (int j = 0; j < half; ++j) {
      kept_[static_cast<std::size_t>(j)] = kept_[2 * static_cast<std::size_t>(j) + 1];
      const VfSample<Scalar>& v = kept_[static_cast<std::size_t>(j)];
      Scalar f = v.f_nT;
      if (!(std::isfinite(f) && f > Scalar(0))) f = cfg_.filter.reference_field_nT;
      noise_batch_.add_sample(v.m_nT, f, v.r_bn);
    }
    n_kept_ = half;
    noise_step_deg_ = std::min(Scalar(2) * noise_step_deg_, Scalar(45));
  }

  // Recomputes the output uncertainty.
  void refresh_output_report() noexcept {
    since_refresh_ = 0;
    out_ = filter_.initialised() ? filter_.output_uncertainty() : VfOutputUncertainty<Scalar>{};
  }

  Config cfg_;
  Filter filter_{};
  VfOutputUncertainty<Scalar> out_{};
  int since_refresh_{0};
  VectorCalibratorCounts counts_{};
  bool noise_known_{false};
  BatchNoise<Scalar> noise_{};
  BatchCalibrator<Scalar, static_cast<std::size_t>(InitCapacity)> noise_batch_{};
  std::array<VfSample<Scalar>, static_cast<std::size_t>(InitCapacity)> kept_{};
  int n_kept_{0};
  Scalar noise_step_deg_{2};
  CalibratorAdd process(const VfSample<Scalar>& v) noexcept;

  // ---- the hold ring (see the top) ----
  struct Held {
    VfSample<Scalar> v{};
    std::uint64_t t_us{0};
  };
  // Logical index 0 is the oldest entry (0 <= i < HoldCapacity: an unsigned remainder, which is
  // a mask for a power of two).
  Held& held(int i) noexcept {
    return hold_[static_cast<std::size_t>(hold_head_ + i) % static_cast<std::size_t>(HoldCapacity)];
  }
  const Held& held(int i) const noexcept {
    return hold_[static_cast<std::size_t>(hold_head_ + i) % static_cast<std::size_t>(HoldCapacity)];
  }
  // The offset the next sample is aligned to: the filter's, within what the ring can reach.
  Scalar offset_now() const noexcept {
    const Scalar a = filter_.time_offset_s();
    return std::isfinite(a) ? a : Scalar(0);
  }
  // Signed microseconds t - a (a in seconds), as a double-free integer step for the M4F.
  static std::int64_t shifted_us(std::uint64_t t_us, Scalar a_s) noexcept {
    return static_cast<std::int64_t>(t_us) -
           static_cast<std::int64_t>(std::lround(a_s * Scalar(1e6)));
  }
  // R_bn at t_us interpolated between the held attitudes (the pipeline's AttitudeBuffer, kept
  // alongside the ring: bracketing attitudes at most max_rate_span_s apart); false outside them.
  bool attitude_at(std::int64_t t_us, Mat3<Scalar>* r) const noexcept {
    Quat<Scalar> q_nb;
    if (!quat_at(t_us, &q_nb)) return false;
    *r = r_bn_from_quat(q_nb);
    return true;
  }
  // The same as the INS quaternion q_nb.
  bool quat_at(std::int64_t t_us, Quat<Scalar>* q_nb) const noexcept {
    if (t_us < 0) return false;
    const AttitudeQuery<Scalar> q = att_.at(static_cast<std::uint64_t>(t_us));
    if (q.status != AttitudeQueryStatus::kInterpolated) return false;
    *q_nb = q.q_nb;
    return true;
  }
  static AttitudeBufferConfig hold_buffer_config(Scalar max_span_s) noexcept {
    AttitudeBufferConfig c;
    c.max_gap_us = static_cast<std::uint64_t>(std::lround(max_span_s * Scalar(1e6)));
    c.max_extrapolation_us = 0;  // nothing past the newest held sample
    return c;
  }
  bool ready_to_process(int i) const noexcept;
  CalibratorAdd process_held(int i) noexcept;
  CalibratorAdd flush_held() noexcept;
  std::array<Held, static_cast<std::size_t>(HoldCapacity)> hold_{};
  int hold_head_{0};
  int hold_n_{0};                 // entries in the ring
  int hold_done_{0};              // the oldest hold_done_ entries are processed (history)
  std::int64_t half_span_us_{0};  // rate_half_span_s in microseconds
  AttitudeBuffer<Scalar, static_cast<std::size_t>(HoldCapacity)> att_{
      hold_buffer_config(Scalar(0.5))};
};

template <typename Scalar, int InitCapacity, int ReplayCapacity, int HoldCapacity>
CalibratorAdd VectorCalibrator<Scalar, InitCapacity, ReplayCapacity, HoldCapacity>::add(
    const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn) noexcept {
  ++counts_.seen;
  const bool bad_f = std::isinf(s.f_ref_nT);
  const bool bad_t = std::isinf(s.temperature_degC);
  if (!all_finite(s.m_nT) || bad_f || bad_t || (r_bn != nullptr && !all_finite(*r_bn))) {
    ++counts_.nonfinite;
    return CalibratorAdd::kRejected;
  }
  if (r_bn == nullptr) {
    ++counts_.no_attitude;
    // No attitude to interpolate across: the held samples go on with what the ring has.
    (void)flush_held();
    hold_n_ = 0;
    hold_done_ = 0;
    att_.clear();
    return CalibratorAdd::kRejected;
  }
  // Collecting for the noise estimate needs a reference now (the held sample would say so late).
  if (!noise_known_ && !(std::isfinite(s.f_ref_nT) && s.f_ref_nT > Scalar(0)) &&
      !(cfg_.filter.reference_field_nT > Scalar(0))) {
    ++counts_.no_reference;
    return CalibratorAdd::kRejected;
  }
  CalibratorAdd out = CalibratorAdd::kUsed;
  if (hold_n_ > 0 && !(s.t_us > held(hold_n_ - 1).t_us)) {
    // Time went back or stood still: the ring must not mix time bases.
    out = flush_held();
    hold_n_ = 0;
    hold_done_ = 0;
    att_.clear();
  }
  if (hold_n_ == HoldCapacity) {
    // Full: the oldest unprocessed sample goes now; the oldest entry makes room.
    if (hold_done_ == 0) out = process_held(0);
    hold_head_ = (hold_head_ + 1) % HoldCapacity;
    --hold_n_;
    --hold_done_;
  }
  // Written in place, every field (the ring's slot holds an old entry).
  Held& h = held(hold_n_);
  h.v.interval_s = hold_n_ > 0 ? static_cast<Scalar>(s.t_us - held(hold_n_ - 1).t_us) * Scalar(1e-6)
                               : std::numeric_limits<Scalar>::quiet_NaN();
  h.t_us = s.t_us;
  h.v.m_nT = s.m_nT;
  h.v.r_bn = *r_bn;
  h.v.omega_n_rad_s.setZero();
  h.v.attitude_offset_s = Scalar(0);
  h.v.f_nT = s.f_ref_nT;
  h.v.temperature_degC = s.temperature_degC;
  static_assert(sizeof(VfSample<Scalar>) == (3 + 9 + 3 + 4) * sizeof(Scalar),
                "every field of VfSample is written above");
  ++hold_n_;
  (void)att_.insert(s.t_us, quat_from_r_bn(*r_bn));
  if (hold_done_ < hold_n_ && ready_to_process(hold_done_)) out = process_held(hold_done_);
  return out;
}

// The ring reaches rate_half_span_s past the attitude time the sample needs.
template <typename Scalar, int InitCapacity, int ReplayCapacity, int HoldCapacity>
bool VectorCalibrator<Scalar, InitCapacity, ReplayCapacity, HoldCapacity>::ready_to_process(
    int i) const noexcept {
  const std::int64_t need = shifted_us(held(i).t_us, offset_now() - cfg_.rate_half_span_s);
  return static_cast<std::int64_t>(held(hold_n_ - 1).t_us) >= need;
}

template <typename Scalar, int InitCapacity, int ReplayCapacity, int HoldCapacity>
CalibratorAdd VectorCalibrator<Scalar, InitCapacity, ReplayCapacity, HoldCapacity>::process_held(
    int i) noexcept {
  VfSample<Scalar> v = held(i).v;
  const std::uint64_t t_us = held(i).t_us;
  const Scalar a = offset_now();
  const Scalar w = cfg_.rate_half_span_s;
  Mat3<Scalar> r_a;
  const std::int64_t t_a_us = shifted_us(t_us, a);
  std::int64_t t_q_us = static_cast<std::int64_t>(t_us);  // the time of v.r_bn
  if (attitude_at(t_a_us, &r_a)) {
    v.r_bn = r_a;
    v.attitude_offset_s = a;
    t_q_us = t_a_us;
  }
  Quat<Scalar> q_lo, q_hi;
  if (w > Scalar(0) && quat_at(t_q_us - half_span_us_, &q_lo) &&
      quat_at(t_q_us + half_span_us_, &q_hi)) {
    v.omega_n_rad_s = rate_n_from_quats(q_lo, q_hi, Scalar(2) * w);
  } else {
    // The neighbours' rate (independent of the sample's own attitude noise).
    const bool lo_ok = i > 0;
    const bool hi_ok = i + 1 < hold_n_;
    const Held& lo = held(lo_ok ? i - 1 : i);
    const Held& hi = held(hi_ok ? i + 1 : i);
    const Scalar span = static_cast<Scalar>(hi.t_us - lo.t_us) * Scalar(1e-6);
    if (span > Scalar(0) && span <= cfg_.max_rate_span_s)
      v.omega_n_rad_s = rate_n_from_attitudes(lo.v.r_bn, hi.v.r_bn, span);
  }
  hold_done_ = std::max(hold_done_, i + 1);
  return process(v);
}

// Processes every held sample with what the ring has; the outcome of the last one.
template <typename Scalar, int InitCapacity, int ReplayCapacity, int HoldCapacity>
CalibratorAdd
VectorCalibrator<Scalar, InitCapacity, ReplayCapacity, HoldCapacity>::flush_held() noexcept {
  CalibratorAdd out = CalibratorAdd::kUsed;
  while (hold_done_ < hold_n_)
    out = process_held(hold_done_);
  return out;
}

template <typename Scalar, int InitCapacity, int ReplayCapacity, int HoldCapacity>
CalibratorAdd VectorCalibrator<Scalar, InitCapacity, ReplayCapacity, HoldCapacity>::process(
    const VfSample<Scalar>& v) noexcept {
  if (!noise_known_) return collect_for_noise(v);
  const bool was_running = filter_.initialised();
  const CalibratorAdd r = to_loop(filter_.update(v));
  if (filter_.initialised() != was_running || ++since_refresh_ >= cfg_.refresh_every)
    refresh_output_report();
  return r;
}

// Compiled once per scalar with the filter (see the end of vector_calibration_filter.hpp).
#ifdef MAGVEC_CORE_VECTOR_FLOAT_COMPILED
extern template class VectorCalibrator<float>;
#endif
#ifdef MAGVEC_CORE_VECTOR_DOUBLE_COMPILED
extern template class VectorCalibrator<double>;
#endif

}  // namespace magvec::core
