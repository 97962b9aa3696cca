// SensorLoop: the per-sample pipeline of docs/architecture.md#sample-pipeline, free of any driver
// or OS type. Per magnetometer sample: attitude aligned by the caller-supplied attitude (see
// AttitudeBuffer), the active calibrator fed, the sample compensated with the *active* calibration,
// one OutputRecord emitted. A calibration state machine decides when new parameters replace the
// active ones:
//   idle -> collecting (progress) -> solving -> validating (held-out samples) -> applied |
//   failed(reason)
// The previous calibration stays active until a new one validates.
//
// The calibrator is a template parameter (PX4-style "control vs fusion" split: the loop owns
// gating, state and bookkeeping; the calibrator owns the estimation math). It must provide:
//   void begin() noexcept;                                   start a new calibration
//   CalibratorAdd add(const Vec3<S>& m, S f_ref_nT, const Mat3<S>* r_bn) noexcept;
//     or, for a calibrator that needs more of the sample (time stamp, temperature: the online
//     vector filter derives its rate and interval from successive samples), instead
//   CalibratorAdd add(const MagSample<S>& s, const Mat3<S>* r_bn) noexcept;
//     (the loop calls this form when the calibrator provides it, else the first);
//   S progress() const noexcept;                             0..1 (coverage / convergence)
//   bool ready() const noexcept;                             enough data to solve
//   CalibratorSolve solve(SensorModel<S>* out) noexcept;     candidate model or a failure code
//
// Where the solve runs. By default (the MCU, the simulation) the loop calls solve() itself on the
// sample after the calibrator reported ready. With LoopConfig::external_solve the owner runs it
// elsewhere (magvecd: a worker thread) so that a solve of many sample periods never delays a
// sample: the loop enters kSolving, increments solve_ticket() and keeps compensating with the
// active model without touching the calibrator (no add(), no progress()), so its data are frozen
// and the owner may copy them and solve on the copy; install_solve(ticket, result, model) then
// continues exactly as the inline path would (validation on the following samples). The loop
// stays allocation-free and thread-agnostic: the hand-over is the owner's.
#pragma once

#include <cmath>
#include <concepts>
#include <cstdint>
#include <limits>

#include "magvec/core/compensator.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

// Bits of OutputRecord::flags.
enum OutputFlag : std::uint32_t {
  kOutDropout = 1u << 0,        // raw sample not finite: no output values
  kOutDeviceError = 1u << 1,    // the device reported an error (CRC, saturation, stuck channel)
  kOutNoAttitude = 1u << 2,     // no valid attitude for this time: h_n not computed
  kOutUncalibrated = 1u << 3,   // no calibration applied yet (identity model)
  kOutCalibrating = 1u << 4,    // a calibration is in progress (output still uses the active one)
  kOutRejectedByCal = 1u << 5,  // the calibrator gated this sample (spike)
  // The attitude was extrapolated past the newest INS sample (the fusion horizon expired before
  // INS samples bracketed the sample's time; SamplePipeline).
  kOutAttExtrapolated = 1u << 6,
  // The active calibration does not align the sensor to the INS (no calibration yet, or one from
  // a calibrator that cannot see the misalignment, e.g. the scalar EKF without its alignment
  // step): h_n is the field rotated with Rm = I, not an E/N/U estimate; |h| is unaffected.
  kOutNotAligned = 1u << 7,
  // The sample stands out from both neighbours (a spike; SamplePipeline's spike screen): its
  // values are kept, flagged; the calibrator never sees it.
  kOutSpike = 1u << 8,
  // The active calibration's absolute scale comes from a model reference field (a geomagnetic
  // model at the INS position, LoopConfig::reference_sigma_nT): |h| is as accurate as the model
  // (sigma_f includes the model's 1-sigma); its scatter is the held-out one.
  kOutModelReference = 1u << 9,
};

enum class CalState : std::uint8_t { kIdle, kCollecting, kSolving, kValidating, kApplied, kFailed };

constexpr const char* cal_state_name(CalState s) noexcept {
  switch (s) {
    case CalState::kIdle:
      return "idle";
    case CalState::kCollecting:
      return "collecting";
    case CalState::kSolving:
      return "solving";
    case CalState::kValidating:
      return "validating";
    case CalState::kApplied:
      return "applied";
    case CalState::kFailed:
      return "failed";
  }
  return "unknown";
}

enum class CalFailure : std::uint8_t {
  kNone,
  kSolverRejected,    // the calibrator refused (see solver_code)
  kValidationFailed,  // held-out residuals not better than the active calibration / above bound
  kNoReference,       // validation needs a scalar reference and none arrived
  kVectorValidationFailed,  // held-out E/N/U scatter above the attitude-noise floor: Rm is wrong
  // Model reference: the held-out mean of |h| - F lies beyond the model's stated 1-sigma times
  // LoopConfig::validation_max_reference_sigmas (a wrong position or date, or a local anomaly).
  kReferenceMismatch,
};

constexpr const char* cal_failure_name(CalFailure f) noexcept {
  switch (f) {
    case CalFailure::kNone:
      return "none";
    case CalFailure::kSolverRejected:
      return "solver_rejected";
    case CalFailure::kValidationFailed:
      return "validation_failed";
    case CalFailure::kNoReference:
      return "no_reference";
    case CalFailure::kVectorValidationFailed:
      return "vector_validation_failed";
    case CalFailure::kReferenceMismatch:
      return "reference_mismatch";
  }
  return "unknown";
}

enum class CalibratorAdd : std::uint8_t { kUsed, kGated, kRejected };

struct CalibratorSolve {
  bool ok{false};
  std::uint8_t code{0};  // calibrator-specific verdict code when !ok
  bool aligned{true};    // the model's Rm estimates the misalignment to the INS
  // The INS attitude noise 1-sigma the solve used or estimated (NaN: the loop's configured one);
  // sets the floor of the held-out vector check.
  float attitude_noise_deg{std::numeric_limits<float>::quiet_NaN()};
  // The magnetometer noise 1-sigma per axis the solve used or estimated from its data (NaN: the
  // loop's configured one); sets the held-out intensity bound and the floor of sigma_f.
  float mag_noise_nT{std::numeric_limits<float>::quiet_NaN()};
  // The 1-sigma the candidate's own uncertainty adds to |h| and to each E/N/U component, from its
  // covariance (NaN: not given). The records' sigma_f and sigma_enu are never below the noise
  // combined with these.
  float calibration_sigma_f_nT{std::numeric_limits<float>::quiet_NaN()};
  float calibration_sigma_enu_nT{std::numeric_limits<float>::quiet_NaN()};
  // The magnetometer-INS time offset the solve found in its data, relative to the attitudes it was
  // given (positive: the magnetometer lags; NaN or 0: none). The candidate holds only with its
  // samples paired that way, so the pipeline moves its offset by this for the held-out samples
  // and keeps it when the candidate is applied (take_time_offset_step_us()).
  float time_offset_correction_s{std::numeric_limits<float>::quiet_NaN()};
};

template <typename Scalar>
struct MagSample {
  std::uint64_t t_us{0};
  Vec3<Scalar> m_nT = Vec3<Scalar>::Zero();
  Scalar f_ref_nT = std::numeric_limits<Scalar>::quiet_NaN();  // scalar reference, NaN when none
  // Sensor temperature (for a calibrator with a temperature model), degC; NaN when none.
  Scalar temperature_degC = std::numeric_limits<Scalar>::quiet_NaN();
  bool device_error{false};
  bool spike{false};  // set by the pipeline's spike screen
};

template <typename Scalar>
struct OutputRecord {
  std::uint64_t t_us{0};
  Vec3<Scalar> raw_nT = Vec3<Scalar>::Zero();
  Vec3<Scalar> h_s_nT = Vec3<Scalar>::Zero();
  Scalar intensity_nT{0};
  Vec3<Scalar> h_n_nT = Vec3<Scalar>::Zero();  // ENU; valid unless kOutNoAttitude
  std::uint32_t flags{0};
  std::uint32_t cal_id{0};  // 0 = uncalibrated; increments with every applied calibration
  Scalar sigma_f_nT{0};     // 1-sigma of the intensity (noise + calibration uncertainty)
  // 1-sigma per axis of h_n (noise, attitude noise and calibration error together); NaN when
  // h_n is not an E/N/U estimate (no attitude, or kOutNotAligned).
  Scalar sigma_enu_nT{std::numeric_limits<Scalar>::quiet_NaN()};
};

struct LoopHealth {
  std::uint64_t samples{0};
  std::uint64_t dropouts{0};
  std::uint64_t device_errors{0};
  std::uint64_t no_attitude{0};
  std::uint64_t cal_used{0};
  std::uint64_t cal_gated{0};
  std::uint64_t cal_rejected{0};
  std::uint64_t calibrations_applied{0};
  std::uint64_t calibrations_failed{0};
};

template <typename Scalar>
struct LoopConfig {
  // Magnetometer noise 1-sigma per axis (the held-out intensity bound and the floor of sigma_f).
  // NaN: not known; each candidate is then judged with the noise its solve estimated
  // (CalibratorSolve::mag_noise_nT), and records carry NaN sigma_f until a calibration applies.
  Scalar noise_nT{1};
  std::uint32_t validation_samples{200};
  Scalar validation_max_rms_factor{3};  // accept if held-out intensity RMS <= factor * noise ...
  Scalar validation_min_rms_nT{1};      // ... or <= this floor
  bool validate_against_active{
      true};  // and not worse than the active calibration on the same samples
  // Vector check of an aligned candidate on the held-out samples with attitude: the scatter of
  // its E/N/U field about their mean must be within factor * sqrt(noise^2 + (F sigma_att)^2)
  // (a wrong Rm turns with the platform; the true field does not). sigma_att: INS attitude
  // noise 1-sigma (the solve's figure when it gives one, CalibratorSolve); F: the mean held-out
  // intensity. NaN: not known (the solve's figure, or no vector check without one).
  Scalar attitude_noise_deg{Scalar(0.05)};
  Scalar validation_max_vector_rms_factor{3};
  // The owner runs the calibrator's solve and hands the result to install_solve() (see the top).
  bool external_solve{false};
  // The reference F is a model (a geomagnetic model at the INS position) with this stated
  // 1-sigma; NaN: a measured reference (scalar magnetometer, or a given value judged alike). A
  // model's F is biased by up to its 1-sigma but nearly noise-free, so the held-out check then
  // splits |h| - F into its scatter about the mean, judged against the noise bound as the RMS is
  // otherwise, and its mean, judged against validation_max_reference_sigmas * reference_sigma_nT;
  // an applied calibration's sigma_f is the scatter and the model's 1-sigma combined (its
  // absolute accuracy cannot be better than the model's) and its records carry kOutModelReference.
  Scalar reference_sigma_nT{std::numeric_limits<Scalar>::quiet_NaN()};
  Scalar validation_max_reference_sigmas{3};
};

template <typename Scalar, typename Calibrator>
class SensorLoop {
  static constexpr Scalar kNaN = std::numeric_limits<Scalar>::quiet_NaN();
  // The calibrator takes the whole sample (the extended add of the contract at the top).
  static constexpr bool kTakesSample =
      requires(Calibrator & c, const MagSample<Scalar>& m, const Mat3<Scalar>* r) {
    { c.add(m, r) } -> std::same_as<CalibratorAdd>;
  };

 public:
  SensorLoop(Calibrator& calibrator, const LoopConfig<Scalar>& config) noexcept
      : calibrator_(calibrator), config_(config) {}

  // Installs a calibration (e.g. loaded from the ParamStore) as the active one. The next applied
  // calibration gets an id above every id seen so far, so reverting to an older calibration never
  // lets a later, different one reuse an id that records already carry.
  // aligned: the model's Rm is an estimate (records are flagged kOutNotAligned otherwise);
  // sigma_f_nT, sigma_enu_nT: the 1-sigma of |h| and of each E/N/U component the calibration
  // achieved (NaN: not known; sigma_f then falls back to the configured noise).
  // model_reference: its scale came from a model reference (kOutModelReference; sigma_f_nT should
  // then include the model's 1-sigma).
  void set_active(const SensorModel<Scalar>& model, std::uint32_t cal_id, bool aligned = true,
                  Scalar sigma_f_nT = std::numeric_limits<Scalar>::quiet_NaN(),
                  Scalar sigma_enu_nT = std::numeric_limits<Scalar>::quiet_NaN(),
                  bool model_reference = false) noexcept {
    active_.set_model(model);
    cal_id_ = cal_id;
    active_model_reference_ = model_reference;
    if (cal_id > max_cal_id_) max_cal_id_ = cal_id;
    active_aligned_ = aligned;
    // fmax ignores a NaN operand: the known one of the two, NaN only when neither is known.
    active_sigma_f_ = std::fmax(sigma_f_nT, config_.noise_nT);
    // Without its own figure an installed calibration's E/N/U 1-sigma is not known (sigma_F alone
    // would leave out the attitude noise, F sigma_att, which usually dominates).
    active_sigma_enu_ =
        aligned && std::isfinite(sigma_enu_nT) ? std::fmax(sigma_enu_nT, active_sigma_f_) : kNaN;
  }
  bool active_aligned() const noexcept { return active_aligned_ && cal_id_ != 0; }
  // The active calibration's scale came from a model reference (kOutModelReference).
  bool active_model_reference() const noexcept { return active_model_reference_ && cal_id_ != 0; }
  // What kind of reference F the samples carry from now on (LoopConfig::reference_sigma_nT): a
  // calibration validated afterwards is judged, and flagged, accordingly.
  void set_reference_sigma_nT(Scalar sigma_nT) noexcept { config_.reference_sigma_nT = sigma_nT; }
  Scalar reference_sigma_nT() const noexcept { return config_.reference_sigma_nT; }
  // The 1-sigma of |h| in the records: the held-out intensity RMS of the applied calibration
  // against the scalar reference (noise and calibration error together), never below the noise.
  Scalar active_sigma_f_nT() const noexcept { return active_sigma_f_; }
  // The 1-sigma per E/N/U component of an applied aligned calibration: the held-out E/N/U
  // scatter, never below sqrt(sigma_f^2 + (F sigma_att)^2) (NaN when not aligned).
  Scalar active_sigma_enu_nT() const noexcept { return active_sigma_enu_; }
  const SensorModel<Scalar>& active_model() const noexcept { return active_.model(); }
  std::uint32_t cal_id() const noexcept { return cal_id_; }

  void start_calibration() noexcept {
    calibrator_.begin();
    state_ = CalState::kCollecting;
    failure_ = CalFailure::kNone;
    solver_code_ = 0;
  }
  CalState state() const noexcept { return state_; }
  // The step the loop asks of the pipeline's magnetometer-INS time offset since the last call
  // (0: none), in microseconds: + the candidate's correction when its validation starts, - it
  // again when the validation refuses the candidate (CalibratorSolve::time_offset_correction_s).
  std::int64_t take_time_offset_step_us() noexcept {
    const std::int64_t d = offset_step_us_;
    offset_step_us_ = 0;
    return d;
  }
  CalFailure failure() const noexcept { return failure_; }
  std::uint8_t solver_code() const noexcept { return solver_code_; }
  Scalar progress() const noexcept {
    return state_ == CalState::kCollecting ? calibrator_.progress()
                                           : Scalar(state_ == CalState::kApplied);
  }
  const LoopHealth& health() const noexcept { return health_; }
  // The candidate of the last solve (valid in kValidating, kApplied, and kFailed after validation).
  const SensorModel<Scalar>& candidate() const noexcept { return candidate_.model(); }
  // Held-out |h| - F of the last candidate: its RMS, or with a model reference its scatter about
  // the mean; and its mean.
  Scalar last_validation_rms_nT() const noexcept { return last_validation_rms_; }
  Scalar last_validation_mean_nT() const noexcept { return last_validation_mean_; }
  // E/N/U scatter of the last validated candidate (NaN: not checked: not aligned, or too few
  // held-out samples with attitude).
  Scalar last_validation_vector_rms_nT() const noexcept { return last_vector_rms_; }
  // The bounds the last candidate was judged by (NaN: not reached) and the magnetometer noise
  // they were computed from: what a refusal's message names.
  Scalar last_validation_bound_nT() const noexcept { return last_validation_bound_; }
  Scalar last_validation_vector_bound_nT() const noexcept { return last_vector_bound_; }
  Scalar candidate_noise_nT() const noexcept { return candidate_noise_; }
  // The active calibration's figure on the same held-out samples (validate_against_active).
  Scalar last_validation_active_rms_nT() const noexcept { return last_active_rms_; }

  // Increments each time the loop enters kSolving (with external_solve: a solve is wanted; the
  // calibrator's data stay frozen while the state is kSolving).
  std::uint32_t solve_ticket() const noexcept { return solve_ticket_; }
  // Switches LoopConfig::external_solve (magvecd: a session declares it in its event log).
  void set_external_solve(bool on) noexcept { config_.external_solve = on; }
  // The result of the external solve of `ticket`. Ignored (false) unless the loop is still
  // solving that ticket: a calibration restarted meanwhile has a new one.
  bool install_solve(std::uint32_t ticket, const CalibratorSolve& r,
                     const SensorModel<Scalar>& model) noexcept {
    if (state_ != CalState::kSolving || ticket != solve_ticket_) return false;
    finish_solve(r, model);
    return true;
  }

  // One magnetometer sample; r_bn is the attitude aligned to s.t_us, or nullptr when none is valid.
  OutputRecord<Scalar> process(const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn) noexcept {
    OutputRecord<Scalar> rec;
    rec.t_us = s.t_us;
    rec.raw_nT = s.m_nT;
    rec.cal_id = cal_id_;
    ++health_.samples;
    if (cal_id_ == 0) rec.flags |= kOutUncalibrated;
    if (cal_id_ == 0 || !active_aligned_) rec.flags |= kOutNotAligned;
    if (cal_id_ != 0 && active_model_reference_) rec.flags |= kOutModelReference;
    if (state_ == CalState::kCollecting || state_ == CalState::kSolving ||
        state_ == CalState::kValidating) {
      rec.flags |= kOutCalibrating;
    }
    if (s.device_error) {
      rec.flags |= kOutDeviceError;
      ++health_.device_errors;
    }
    Compensated<Scalar> c;
    if (s.device_error || !active_.compensate(s.m_nT, &c)) {
      if (!s.device_error) ++health_.dropouts;
      rec.flags |= kOutDropout;
      return rec;
    }
    rec.h_s_nT = c.h_s;
    rec.intensity_nT = c.intensity;
    rec.sigma_f_nT = active_sigma_f_;
    if (r_bn != nullptr) {
      rec.h_n_nT = Compensator<Scalar>::to_nav(c.h_b, *r_bn);
      if (cal_id_ != 0 && active_aligned_) rec.sigma_enu_nT = active_sigma_enu_;
    } else {
      rec.flags |= kOutNoAttitude;
      ++health_.no_attitude;
    }
    if (s.spike) {
      // Flagged, kept, and kept away from the calibration (collection and validation).
      rec.flags |= kOutSpike;
      return rec;
    }
    step_calibration(s, r_bn, &rec);
    return rec;
  }

 private:
  void step_calibration(const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn,
                        OutputRecord<Scalar>* rec) noexcept {
    switch (state_) {
      case CalState::kCollecting: {
        const CalibratorAdd a = [&]() noexcept {
          if constexpr (kTakesSample) {
            return calibrator_.add(s, r_bn);
          } else {
            return calibrator_.add(s.m_nT, s.f_ref_nT, r_bn);
          }
        }();
        if (a == CalibratorAdd::kUsed) ++health_.cal_used;
        if (a == CalibratorAdd::kGated) {
          ++health_.cal_gated;
          rec->flags |= kOutRejectedByCal;
        }
        if (a == CalibratorAdd::kRejected) ++health_.cal_rejected;
        if (calibrator_.ready()) {
          state_ = CalState::kSolving;
          ++solve_ticket_;
        }
        break;
      }
      case CalState::kSolving: {
        if (config_.external_solve) break;  // install_solve() continues
        // Solving happens on the sample after the calibrator reported ready, so a long solve
        // never delays the sample that completed the data set.
        SensorModel<Scalar> model;
        const CalibratorSolve r = calibrator_.solve(&model);
        finish_solve(r, model);
        break;
      }
      case CalState::kValidating:
        validate(s, r_bn);
        break;
      case CalState::kIdle:
      case CalState::kApplied:
      case CalState::kFailed:
        break;
    }
  }

  void finish_solve(const CalibratorSolve& r, const SensorModel<Scalar>& model) noexcept {
    if (!r.ok) {
      fail(CalFailure::kSolverRejected, r.code);
      return;
    }
    candidate_.set_model(model);
    candidate_aligned_ = r.aligned;
    candidate_att_noise_deg_ = std::isfinite(r.attitude_noise_deg)
                                   ? static_cast<Scalar>(r.attitude_noise_deg)
                                   : config_.attitude_noise_deg;
    // The configured noise overrides; without one, the noise the solve estimated from its data.
    candidate_noise_ =
        std::isfinite(config_.noise_nT) ? config_.noise_nT : static_cast<Scalar>(r.mag_noise_nT);
    candidate_cal_sigma_f_ = static_cast<Scalar>(r.calibration_sigma_f_nT);
    candidate_cal_sigma_enu_ = static_cast<Scalar>(r.calibration_sigma_enu_nT);
    // Whole microseconds (float holds them exactly to 16 s).
    const float corr_us = r.time_offset_correction_s * 1e6F;
    candidate_offset_step_us_ =
        std::isfinite(corr_us) && std::fabs(corr_us) < 1e7F ? std::lround(corr_us) : 0;
    offset_step_us_ += candidate_offset_step_us_;
    validation_count_ = 0;
    sum_sq_candidate_ = 0;
    missing_reference_ = 0;
    sum_sq_active_ = 0;
    sum_candidate_ = 0;
    sum_active_ = 0;
    sum_f_ = 0;
    vector_count_ = 0;
    vector_sum_.setZero();
    vector_sum_sq_.setZero();
    state_ = CalState::kValidating;
  }

  void validate(const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn) noexcept {
    if (!std::isfinite(s.f_ref_nT)) {
      ++missing_reference_;
      if (missing_reference_ > config_.validation_samples) fail(CalFailure::kNoReference, 0);
      return;
    }
    Compensated<Scalar> cand;
    Compensated<Scalar> act;
    if (!candidate_.compensate(s.m_nT, &cand) || !active_.compensate(s.m_nT, &act)) return;
    const Scalar rc = cand.intensity - s.f_ref_nT;
    const Scalar ra = act.intensity - s.f_ref_nT;
    sum_sq_candidate_ += rc * rc;
    sum_sq_active_ += ra * ra;
    sum_candidate_ += rc;
    sum_active_ += ra;
    sum_f_ += s.f_ref_nT;
    if (candidate_aligned_ && r_bn != nullptr) {
      // About the first vector (shifted sums: no cancellation of 50 000 nT squares in float).
      const Vec3<Scalar> h = Compensator<Scalar>::to_nav(cand.h_b, *r_bn);
      if (vector_count_ == 0) vector_ref_ = h;
      const Vec3<Scalar> d = h - vector_ref_;
      vector_sum_ += d;
      vector_sum_sq_ += d.cwiseProduct(d);
      ++vector_count_;
    }
    if (++validation_count_ < config_.validation_samples) return;
    const Scalar n = static_cast<Scalar>(validation_count_);
    const Scalar mean_c = sum_candidate_ / n;
    const Scalar mean_a = sum_active_ / n;
    const bool model_reference = std::isfinite(config_.reference_sigma_nT);
    // Measured reference: the RMS. Model reference: the scatter about the mean (the model's bias
    // is no noise of the candidate's, and an active calibration from another reference may sit
    // at another mean); the mean is judged on its own below.
    const auto spread = [n, model_reference](Scalar sum_sq, Scalar mean) {
      return model_reference ? std::sqrt(std::fmax(sum_sq / n - mean * mean, Scalar(0)))
                             : std::sqrt(sum_sq / n);
    };
    const Scalar rms_c = spread(sum_sq_candidate_, mean_c);
    const Scalar rms_a = spread(sum_sq_active_, mean_a);
    last_validation_rms_ = rms_c;
    last_validation_mean_ = mean_c;
    const Scalar bound = std::fmax(config_.validation_max_rms_factor * candidate_noise_,
                                   config_.validation_min_rms_nT);
    last_validation_bound_ = bound;
    last_active_rms_ = rms_a;
    last_vector_bound_ = std::numeric_limits<Scalar>::quiet_NaN();
    const bool better = cal_id_ == 0 || !config_.validate_against_active || rms_c <= rms_a;
    if (rms_c > bound || !better) {
      fail(CalFailure::kValidationFailed, 0);
      return;
    }
    if (model_reference &&
        std::fabs(mean_c) > config_.validation_max_reference_sigmas * config_.reference_sigma_nT) {
      fail(CalFailure::kReferenceMismatch, 0);
      return;
    }
    // sigma_f: the held-out intensity RMS (noise and calibration error), never below the noise
    // (combined with the calibration's own 1-sigma when the solve gives it: the held-out window
    // sees only its own attitudes); with a model reference combined with the model's 1-sigma,
    // which bounds the absolute scale. (fmax ignores a NaN figure.)
    const Scalar noise_cal_f = std::sqrt(candidate_noise_ * candidate_noise_ +
                                         candidate_cal_sigma_f_ * candidate_cal_sigma_f_);
    const Scalar relative_f = std::fmax(std::fmax(rms_c, candidate_noise_), noise_cal_f);
    const Scalar sigma_f = model_reference
                               ? std::sqrt(relative_f * relative_f +
                                           config_.reference_sigma_nT * config_.reference_sigma_nT)
                               : relative_f;
    // Attitude noise seen as field: F sigma_att (NaN when the attitude noise is not known).
    const Scalar att = deg_to_rad(candidate_att_noise_deg_) * (sum_f_ / n);
    last_vector_rms_ = std::numeric_limits<Scalar>::quiet_NaN();
    if (2 * vector_count_ >= validation_count_ && vector_count_ >= 2) {
      const Scalar m = static_cast<Scalar>(vector_count_);
      const Vec3<Scalar> mean = vector_sum_ / m;
      const Scalar var = ((vector_sum_sq_ / m) - mean.cwiseProduct(mean)).sum() / Scalar(3);
      last_vector_rms_ = std::sqrt(std::fmax(var, Scalar(0)));
      const Scalar floor = std::sqrt(candidate_noise_ * candidate_noise_ + att * att);
      const Scalar vector_bound = std::fmax(config_.validation_max_vector_rms_factor * floor,
                                            config_.validation_min_rms_nT);
      last_vector_bound_ = vector_bound;
      // No floor (neither a configured nor an estimated attitude noise): nothing to judge by.
      if (std::isfinite(floor) && last_vector_rms_ > vector_bound) {
        fail(CalFailure::kVectorValidationFailed, 0);
        return;
      }
    }
    active_ = candidate_;
    active_aligned_ = candidate_aligned_;
    active_model_reference_ = model_reference;
    active_sigma_f_ = sigma_f;
    // Per E/N/U axis: the held-out scatter measures noise, attitude noise and a wrong Rm
    // together; it is never taken below the intensity's sigma and the attitude noise (a short
    // held-out window with little motion understates both). Without a check (too few samples
    // with attitude) the floor alone.
    // The calibration's own E/N/U 1-sigma (when the solve gives it) adds to that floor.
    const Scalar enu_floor = std::sqrt(sigma_f * sigma_f + att * att);
    const Scalar enu_cal =
        std::sqrt(enu_floor * enu_floor + candidate_cal_sigma_enu_ * candidate_cal_sigma_enu_);
    active_sigma_enu_ =
        candidate_aligned_ ? std::fmax(std::fmax(last_vector_rms_, enu_floor), enu_cal) : kNaN;
    cal_id_ = ++max_cal_id_;
    ++health_.calibrations_applied;
    state_ = CalState::kApplied;
  }

  void fail(CalFailure why, std::uint8_t code) noexcept {
    if (state_ == CalState::kValidating) offset_step_us_ -= candidate_offset_step_us_;
    candidate_offset_step_us_ = 0;
    failure_ = why;
    solver_code_ = code;
    state_ = CalState::kFailed;
    ++health_.calibrations_failed;
  }

  Calibrator& calibrator_;
  LoopConfig<Scalar> config_;
  Compensator<Scalar> active_{};
  Compensator<Scalar> candidate_{};
  std::uint32_t cal_id_{0};
  std::uint32_t max_cal_id_{0};  // highest id installed or issued (ids are never reused)
  CalState state_{CalState::kIdle};
  CalFailure failure_{CalFailure::kNone};
  std::uint8_t solver_code_{0};
  std::uint32_t solve_ticket_{0};
  std::uint32_t validation_count_{0};
  std::uint32_t missing_reference_{0};
  Scalar sum_sq_candidate_{0};
  Scalar sum_sq_active_{0};
  Scalar last_validation_rms_{0};
  Scalar last_validation_mean_{0};
  Scalar last_validation_bound_{std::numeric_limits<Scalar>::quiet_NaN()};
  Scalar last_vector_bound_{std::numeric_limits<Scalar>::quiet_NaN()};
  Scalar last_active_rms_{std::numeric_limits<Scalar>::quiet_NaN()};
  Scalar sum_candidate_{0};
  Scalar sum_active_{0};
  bool active_model_reference_{false};
  Scalar last_vector_rms_{std::numeric_limits<Scalar>::quiet_NaN()};
  bool active_aligned_{false};
  bool candidate_aligned_{false};
  Scalar candidate_att_noise_deg_{0};
  Scalar active_sigma_f_{config_.noise_nT};
  Scalar active_sigma_enu_{kNaN};
  Scalar candidate_noise_{config_.noise_nT};
  Scalar candidate_cal_sigma_f_{kNaN};        // CalibratorSolve::calibration_sigma_f_nT
  Scalar candidate_cal_sigma_enu_{kNaN};      // CalibratorSolve::calibration_sigma_enu_nT
  std::int64_t candidate_offset_step_us_{0};  // CalibratorSolve::time_offset_correction_s
  std::int64_t offset_step_us_{0};            // not yet taken by the pipeline
  Scalar sum_f_{0};
  std::uint32_t vector_count_{0};
  Vec3<Scalar> vector_ref_ = Vec3<Scalar>::Zero();
  Vec3<Scalar> vector_sum_ = Vec3<Scalar>::Zero();
  Vec3<Scalar> vector_sum_sq_ = Vec3<Scalar>::Zero();
  LoopHealth health_{};
};

}  // namespace magvec::core
