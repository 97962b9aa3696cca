// VectorCalibrator: the online vector calibration filter (docs/equations.md E-VF;
// vector_calibration_filter.hpp) behind the SensorLoop Calibrator contract (sensor_loop.hpp), the
// calibrator mode `vector-ekf`.
//
// Per sample the filter needs more than {m, F, R_bn}: the n-frame rotation rate (time offset,
// E-VF-5), the interval since the previous sample (process noise) and the temperature (E-VF-6).
// The adapter therefore takes the loop's whole MagSample (add(const MagSample&, const Mat3*), the
// extended contract): the interval from successive time stamps, the temperature from
// MagSample::temperature_degC (NaN: the filter holds the last one seen), and the rate from the
// attitudes of the samples before and after (rate_n_from_attitudes over that span; zero when the
// span exceeds max_rate_span_s, an attitude gap across which a rate means nothing, or a neighbour
// is missing). DECISION: a sample is therefore processed one sample late (add() returns the
// previous sample's outcome; the first add() after begin() returns kUsed). A rate from the
// sample's own attitude and its predecessor carries the sample's own attitude noise, which its
// residual carries too: the time offset regressed on it is biased by about sa^2 / (dt |Omega|^2)
// (measured 0.4 ms at 0.05 deg and 100 Hz, 12 sigma, and 4 ms after a start from data). The
// neighbours' rate is independent of the sample's attitude noise.
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
// before). The envelope costs ~60 000 flops: it is refreshed every refresh_every samples.
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
// The time offset and the temperature coefficients the filter estimates are not part of the
// SensorModel a candidate carries (the pipeline's time offset is configured; the records apply no
// temperature term): they are diagnostics here (filter()).
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
// float), smaller on a small MCU.
template <typename Scalar, int InitCapacity = 64, int ReplayCapacity = 512>
class VectorCalibrator {
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
    have_prev_ = false;
    have_pending_ = false;
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
    filter_.configure(fc);
    // The same samples start the filter (E-VF-1): it keeps them all (they are a step apart).
    for (int i = 0; i < n_kept_; ++i) {
      const VfStatus st = filter_.update(kept_[static_cast<std::size_t>(i)]);
      if (st == VfStatus::kGated) ++counts_.gated;
    }
    n_kept_ = 0;
    noise_batch_.reset();
    refresh_output_report();
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
  // The attitude before the held sample, and the held sample (see the top).
  bool have_prev_{false};
  std::uint64_t prev_t_us_{0};
  Mat3<Scalar> prev_r_ = Mat3<Scalar>::Identity();
  bool have_pending_{false};
  std::uint64_t pending_t_us_{0};
  VfSample<Scalar> pending_{};
};

template <typename Scalar, int InitCapacity, int ReplayCapacity>
CalibratorAdd VectorCalibrator<Scalar, InitCapacity, ReplayCapacity>::add(
    const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn) noexcept {
  ++counts_.seen;
  const bool bad_f = std::isinf(s.f_ref_nT);
  const bool bad_t = std::isinf(s.temperature_degC);
  if (!s.m_nT.allFinite() || bad_f || bad_t || (r_bn != nullptr && !r_bn->allFinite())) {
    ++counts_.nonfinite;
    return CalibratorAdd::kRejected;
  }
  if (r_bn == nullptr) {
    ++counts_.no_attitude;
    // No rate across a missing attitude: the held sample goes on without one.
    if (have_pending_) (void)process(pending_);
    have_pending_ = false;
    have_prev_ = false;
    return CalibratorAdd::kRejected;
  }
  // Collecting for the noise estimate needs a reference now (the held sample would say so late).
  if (!noise_known_ && !(std::isfinite(s.f_ref_nT) && s.f_ref_nT > Scalar(0)) &&
      !(cfg_.filter.reference_field_nT > Scalar(0))) {
    ++counts_.no_reference;
    return CalibratorAdd::kRejected;
  }
  VfSample<Scalar> v;
  v.m_nT = s.m_nT;
  v.r_bn = *r_bn;
  v.f_nT = s.f_ref_nT;
  v.temperature_degC = s.temperature_degC;
  CalibratorAdd out = CalibratorAdd::kUsed;
  if (have_pending_) {
    if (s.t_us > pending_t_us_)
      v.interval_s = static_cast<Scalar>(s.t_us - pending_t_us_) * Scalar(1e-6);
    // The held sample's rate from its neighbours (see the top).
    if (have_prev_ && s.t_us > prev_t_us_) {
      const Scalar span = static_cast<Scalar>(s.t_us - prev_t_us_) * Scalar(1e-6);
      if (span <= cfg_.max_rate_span_s)
        pending_.omega_n_rad_s = rate_n_from_attitudes(prev_r_, v.r_bn, span);
    }
    out = process(pending_);
    have_prev_ = true;
    prev_t_us_ = pending_t_us_;
    prev_r_ = pending_.r_bn;
  }
  pending_ = v;
  pending_t_us_ = s.t_us;
  have_pending_ = true;
  return out;
}

template <typename Scalar, int InitCapacity, int ReplayCapacity>
CalibratorAdd VectorCalibrator<Scalar, InitCapacity, ReplayCapacity>::process(
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
