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
// Heap-free, noexcept, Scalar-templated; memory = BatchCalibrator<Scalar, Capacity>.
#pragma once

#include <algorithm>
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
    if (!result_.ok()) return CalibratorSolve{false, static_cast<std::uint8_t>(result_.verdict)};
    *out = result_.model;
    CalibratorSolve r{true, 0, true};
    r.attitude_noise_deg = static_cast<float>(result_.noise.estimated && result_.noise.has_attitude
                                                  ? result_.noise.attitude_deg
                                                  : cfg_.batch.attitude_noise_deg);
    r.mag_noise_nT = static_cast<float>(result_.noise.estimated ? result_.noise.mag_nT
                                                                : cfg_.batch.mag_noise_nT);
    return r;
  }

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
};

}  // namespace magvec::core
