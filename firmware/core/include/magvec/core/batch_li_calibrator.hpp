// BatchLiCalibrator: the batch calibration of Li et al. 2023 as corrected by docs/equations.md E-Li
// (one-step 14-parameter fit, 000-6, by default; see batch_calibrator.hpp) behind the SensorLoop
// Calibrator contract (sensor_loop.hpp: begin/add/progress/ready/solve).
//
// Collection: the store has a fixed Capacity, while the loop delivers hundreds of samples per
// second, so add() keeps a sample only if the attitude (or, without attitude, the raw field
// direction) has turned by at least min_step_deg since the last kept sample. Consecutive samples
// of a slow manoeuvre carry almost the same information (docs/equations.md E-Li-7: the floors are
// set by the variety of attitudes); decimating by motion spreads the store over the whole manoeuvre
// instead of its first seconds. A sample that is merely skipped by the decimation is "used" from
// the loop's point of view (kUsed; it is not a fault) and counted in counts().decimated. Samples
// without attitude are rejected (kRejected) when the method needs attitude.
//
// Readiness: count >= min_samples and coverage >= min_coverage, where coverage is the fraction of
// the 32 equal-area cells (BatchCalibrator's grid) hit by the kept raw field directions (raw, not
// calibrated: before a solve no model exists; fine while the offset is small against |h|). A full
// store is also "ready": solve() then decides and reports the verdict (e.g.
// insufficient_coverage), so a poor manoeuvre fails loudly instead of collecting forever.
// progress() = min(count / min_samples, coverage / min_coverage).
//
// solve(): the BatchCalibrator verdict is returned as CalibratorSolve{false, Verdict} on refusal;
// last_result() keeps the whole BatchResult (parameters, 1-sigmas, h_n, quality figures).
//
// Time offset (DECISION, E-TO-4). Fed through the extended contract (add(MagSample, Mat3*): the
// loop's time stamps), each kept sample also gets its rotation rate, from the attitudes of the
// samples before and after it (independent of its own attitude noise); solve() then regresses the
// one-step fit's residuals on the rate (fit_time_offset, batch_calibrator.hpp), refits with the
// attitudes moved, and hands the offset found to the loop (CalibratorSolve::
// time_offset_correction_s), whose pipeline pairs the held-out samples and the records that way.
// Without it an INS latency nobody configured went into Rm and h_n (9.5 ms on the survey: h_n
// 100 nT off, the heading misalignment 0.07 deg). estimate_time_offset = false keeps the pairing.
// Heap-free, noexcept, Scalar-templated; memory = BatchCalibrator<Scalar, Capacity>.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/coverage.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

template <typename Scalar>
struct BatchLiCalibratorConfig {
  BatchConfig<Scalar> batch{};
  BatchMethod method = BatchMethod::kOneStep;
  Scalar min_step_deg{2};  // decimation: attitude (or field direction) change since last kept
  std::size_t min_samples = 300;
  Scalar min_coverage{Scalar(0.3)};
  // Estimate the magnetometer-INS time offset at solve (see the top); needs time stamps.
  bool estimate_time_offset = true;
  // Largest offset it may find, and the longest span a rate is taken over.
  Scalar max_time_offset_s{Scalar(0.25)};
};

struct BatchLiCounts {
  std::uint64_t seen{0};       // add() calls
  std::uint64_t kept{0};       // stored
  std::uint64_t decimated{0};  // skipped: not enough motion since the last kept sample
  std::uint64_t rejected{0};   // non-finite, no reference, no attitude (when needed)
  std::uint64_t full{0};       // store full
};

template <typename Scalar, std::size_t Capacity>
class BatchLiCalibrator {
  static_assert(CoreScalar<Scalar>);
  static_assert(Capacity >= 16, "the batch fit needs well over 12 samples");

 public:
  using Config = BatchLiCalibratorConfig<Scalar>;

  explicit BatchLiCalibrator(const Config& config = Config{}) noexcept
      : cfg_(config), batch_(config.batch) {
    begin();
  }

  void configure(const Config& config) noexcept {
    cfg_ = config;
    batch_.set_config(config.batch);
    begin();
  }
  const Config& config() const noexcept { return cfg_; }

  // --- SensorLoop Calibrator contract ---------------------------------------------------------
  void begin() noexcept {
    batch_.reset();
    counts_ = BatchLiCounts{};
    cells_.clear();
    have_last_ = false;
    result_ = BatchResult<Scalar>{};
    solved_ = false;
    hist_n_ = 0;
    awaiting_rate_ = false;
    time_offset_s_ = 0;
  }

  // The extended contract: as add(m, f, r_bn), and the kept samples' rotation rates from the
  // time stamps (see the top): from the attitude rate_half_span_us before a kept sample to the
  // first one as far after it (a span clear of the INS samples its own attitude came from, and a
  // 4x quieter rate than the neighbours' at 200 Hz; the neighbours' noise attenuated a 9.5 ms
  // offset by 2 %).
  CalibratorAdd add(const MagSample<Scalar>& s, const Mat3<Scalar>* r_bn) noexcept {
    const bool att = r_bn != nullptr && r_bn->allFinite();
    if (!att || (hist_n_ > 0 && !(s.t_us > hist_t_[(hist_head_ + hist_n_ - 1) % kHist]))) {
      // No attitude, or time went back: the history and a waiting rate end here.
      finish_rate(nullptr, 0);
      hist_n_ = 0;
    }
    if (awaiting_rate_ && att && s.t_us >= awaiting_t_us_ + kRateHalfSpanUs)
      finish_rate(r_bn, s.t_us);
    const std::size_t before = batch_.store().size();
    const CalibratorAdd out = add(s.m_nT, s.f_ref_nT, r_bn);
    if (batch_.store().size() > before) {
      // A newer kept sample: the waiting one takes the rate up to here.
      if (awaiting_rate_) finish_rate(r_bn, s.t_us);
      omega_[before] = Vec3<Scalar>::Zero();
      // The attitude at least the half span before (else the oldest kept).
      std::size_t k = hist_n_ > 0 ? hist_n_ - 1 : 0;
      while (k > 0 && hist_t_[(hist_head_ + k) % kHist] + kRateHalfSpanUs > s.t_us)
        --k;
      if (hist_n_ > 0) {
        const std::size_t j = (hist_head_ + k) % kHist;
        awaiting_rate_ = true;
        awaiting_index_ = before;
        awaiting_t_us_ = s.t_us;
        rate_from_r_ = hist_r_[j];
        rate_from_t_us_ = hist_t_[j];
      }
    }
    if (att) {
      const std::size_t j = (hist_head_ + hist_n_) % kHist;
      hist_r_[j] = *r_bn;
      hist_t_[j] = s.t_us;
      if (hist_n_ < kHist)
        ++hist_n_;
      else
        hist_head_ = (hist_head_ + 1) % kHist;
    }
    return out;
  }

  CalibratorAdd add(const Vec3<Scalar>& m, Scalar f_ref_nT, const Mat3<Scalar>* r_bn) noexcept {
    ++counts_.seen;
    const bool need_att = cfg_.method != BatchMethod::kEllipsoidOnly;
    const Scalar f = std::isfinite(f_ref_nT) ? f_ref_nT : cfg_.batch.field_nT;
    const Scalar len = m.norm();
    if (!m.allFinite() || !(std::isfinite(f) && f > 0) || !(len > 0) ||
        (need_att && r_bn == nullptr) || (r_bn != nullptr && !r_bn->allFinite())) {
      ++counts_.rejected;
      return CalibratorAdd::kRejected;
    }
    const Vec3<Scalar> dir = m / len;
    if (have_last_) {
      const Scalar step =
          r_bn != nullptr && last_has_att_
              ? rotation_angle_between(*r_bn, last_r_bn_)
              : std::acos(std::clamp(Scalar(dir.dot(last_dir_)), Scalar(-1), Scalar(1)));
      if (step < deg_to_rad(cfg_.min_step_deg)) {
        ++counts_.decimated;
        return CalibratorAdd::kUsed;
      }
    }
    const AddStatus st = r_bn != nullptr ? batch_.add_sample(m, f, *r_bn) : batch_.add_sample(m, f);
    if (st == AddStatus::kStoreFull) {
      ++counts_.full;
      return CalibratorAdd::kUsed;
    }
    if (st != AddStatus::kAccepted) {
      ++counts_.rejected;
      return CalibratorAdd::kRejected;
    }
    ++counts_.kept;
    have_last_ = true;
    last_dir_ = dir;
    last_has_att_ = r_bn != nullptr;
    if (last_has_att_) last_r_bn_ = *r_bn;
    cells_.add(dir);
    return CalibratorAdd::kUsed;
  }

  Scalar progress() const noexcept {
    const Scalar n = static_cast<Scalar>(batch_.store().size()) /
                     static_cast<Scalar>(std::max<std::size_t>(min_samples(), 1));
    const Scalar c = cfg_.min_coverage > 0 ? coverage() / cfg_.min_coverage : Scalar(1);
    return std::clamp(std::min(n, c), Scalar(0), Scalar(1));
  }

  bool ready() const noexcept {
    const std::size_t n = batch_.store().size();
    if (n >= Capacity) return true;
    return n >= min_samples() && coverage() >= cfg_.min_coverage;
  }

  CalibratorSolve solve(SensorModel<Scalar>* out) noexcept {
    result_ = batch_.solve(cfg_.method);
    solved_ = true;
    if (cfg_.estimate_time_offset && cfg_.method == BatchMethod::kOneStep) {
      // The store keeps the moved attitudes: a second solve adds to the first's move.
      time_offset_s_ += fit_time_offset(
          &batch_, cfg_.method,
          std::max(cfg_.max_time_offset_s - std::abs(time_offset_s_), Scalar(0)),
          [this](std::size_t i) noexcept { return omega_[i]; }, &result_);
    }
    if (!result_.ok()) return CalibratorSolve{false, static_cast<std::uint8_t>(result_.verdict)};
    *out = result_.model;
    CalibratorSolve r{true, 0, true};
    r.attitude_noise_deg = static_cast<float>(result_.noise.estimated && result_.noise.has_attitude
                                                  ? result_.noise.attitude_deg
                                                  : cfg_.batch.attitude_noise_deg);
    r.mag_noise_nT = static_cast<float>(result_.noise.estimated ? result_.noise.mag_nT
                                                                : cfg_.batch.mag_noise_nT);
    if (time_offset_s_ != 0) r.time_offset_correction_s = static_cast<float>(time_offset_s_);
    // The one-step fit's own 1-sigma of the outputs (E-Acc-3): the loop combines it with the noise
    // in the records' floors (NaN for the two-step method: none).
    r.calibration_sigma_f_nT = static_cast<float>(result_.calibration_sigma_f_nT);
    r.calibration_sigma_enu_nT = static_cast<float>(result_.calibration_sigma_enu_nT);
    return r;
  }
  // The time offset the solves found relative to the pairing the calibrator was fed (0: none or
  // not seen); the store's attitudes are moved by it.
  Scalar time_offset_s() const noexcept { return time_offset_s_; }

  // --- diagnostics ------------------------------------------------------------------------------
  // Fraction of the 32 direction cells hit by the kept raw field directions.
  Scalar coverage() const noexcept { return cells_.fraction<Scalar>(); }
  // The cells themselves (bit i: cell i of coverage.hpp's grid) and the samples ready() waits for.
  std::uint32_t coverage_cells() const noexcept { return cells_.cells(); }
  std::size_t samples_needed() const noexcept { return min_samples(); }
  std::size_t stored() const noexcept { return batch_.store().size(); }
  const BatchLiCounts& counts() const noexcept { return counts_; }
  bool solved() const noexcept { return solved_; }
  const BatchResult<Scalar>& last_result() const noexcept { return result_; }
  const BatchCalibrator<Scalar, Capacity>& batch() const noexcept { return batch_; }

 private:
  // The waiting kept sample's rate, from its "before" attitude to r_bn at t_us (none: zero).
  void finish_rate(const Mat3<Scalar>* r_bn, std::uint64_t t_us) noexcept {
    if (awaiting_rate_ && r_bn != nullptr && t_us > rate_from_t_us_) {
      const Scalar span = static_cast<Scalar>(t_us - rate_from_t_us_) * Scalar(1e-6);
      if (span <= cfg_.max_time_offset_s)
        omega_[awaiting_index_] = rate_n_from_attitudes(rate_from_r_, *r_bn, span);
    }
    awaiting_rate_ = false;
  }

  std::size_t min_samples() const noexcept {
    return std::clamp<std::size_t>(cfg_.min_samples, cfg_.batch.limits.min_samples, Capacity);
  }

  Config cfg_;
  BatchCalibrator<Scalar, Capacity> batch_;
  BatchLiCounts counts_{};
  BatchResult<Scalar> result_{};
  CoverageGrid cells_{};
  bool have_last_{false};
  bool last_has_att_{false};
  bool solved_{false};
  Vec3<Scalar> last_dir_ = Vec3<Scalar>::UnitX();
  Mat3<Scalar> last_r_bn_ = Mat3<Scalar>::Identity();
  // The kept samples' rates (zero: unknown); the recent attitudes; the kept sample waiting for
  // the attitude a half span after it.
  static constexpr std::uint64_t kRateHalfSpanUs = 20'000;
  static constexpr std::size_t kHist = 64;  // the half span at up to 3 kHz
  std::array<Vec3<Scalar>, Capacity> omega_{};
  std::array<Mat3<Scalar>, kHist> hist_r_{};
  std::array<std::uint64_t, kHist> hist_t_{};
  std::size_t hist_head_{0};
  std::size_t hist_n_{0};
  bool awaiting_rate_{false};
  std::size_t awaiting_index_{0};
  std::uint64_t awaiting_t_us_{0};
  std::uint64_t rate_from_t_us_{0};
  Mat3<Scalar> rate_from_r_ = Mat3<Scalar>::Identity();
  Scalar time_offset_s_{0};
};

}  // namespace magvec::core
