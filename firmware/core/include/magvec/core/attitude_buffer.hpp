// AttitudeBuffer (docs/architecture.md#sample-pipeline): a fixed-capacity ring of timestamped INS
// attitudes and their interpolation to magnetometer sample times.
// - Attitudes are unit quaternions q_nb (body RFU -> ENU, R_bn = R(q_nb)^T, frames.hpp).
// - Interpolation: slerp between the two samples that bracket t (constant angular rate between
//   INS epochs), exact for a rotation about a fixed axis at constant rate.
// - Staleness: a query whose bracketing samples are more than max_gap_us apart is refused
//   (kGap): an INS dropout must not be bridged by interpolation.
// - Extrapolation: a query past the newest sample is answered up to max_extrapolation_us beyond
//   it (kExtrapolated), either holding the newest attitude or continuing the last angular rate
//   (ExtrapolationMode); farther is kTooNew. A query before the oldest retained sample is kTooOld.
// - Insertion policy (decided here): samples are kept sorted by time. A sample older than the
//   newest but newer than the oldest retained one is INSERTED in order (CAN arbitration and
//   driver queues can reorder frames; dropping would create gaps) and counted as reordered. A
//   sample with exactly the time of a retained one is a duplicate: rejected and counted (the first
//   one wins). A sample older than the oldest retained one (when full) is rejected as too old.
//   Non-finite times/quaternions or |q| away from 1 by more than 1e-3 are rejected as invalid.
//   A backwards clock jump larger than max_backjump_us is treated as a clock reset: the buffer is
//   cleared and restarts with the new sample (counted).
// Header-only, Scalar-templated, fixed memory (Capacity entries), noexcept, no heap.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>

#include "magvec/core/frames.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

enum class AttitudeInsert : std::uint8_t {
  kAppended,    // newest so far
  kReordered,   // inserted before the newest
  kDuplicate,   // same t_us as a retained sample: rejected
  kTooOld,      // older than everything retained while full: rejected
  kInvalid,     // non-finite or non-unit quaternion: rejected
  kClockReset,  // large backwards jump: buffer cleared, sample kept
};

enum class AttitudeQueryStatus : std::uint8_t {
  kInterpolated,  // bracketed by two samples within max_gap_us (or exactly on one)
  kExtrapolated,  // past the newest by at most max_extrapolation_us
  kEmpty,         // no samples
  kTooOld,        // before the oldest retained sample
  kTooNew,        // past the newest by more than max_extrapolation_us
  kGap,           // bracketing samples too far apart (INS dropout)
};

constexpr bool attitude_usable(AttitudeQueryStatus s) noexcept {
  return s == AttitudeQueryStatus::kInterpolated || s == AttitudeQueryStatus::kExtrapolated;
}

enum class ExtrapolationMode : std::uint8_t { kHold, kConstantRate };

struct AttitudeBufferConfig {
  std::uint64_t max_gap_us{50'000};  // e.g. 5 INS periods at 100 Hz
  std::uint64_t max_extrapolation_us{20'000};
  std::uint64_t max_backjump_us{1'000'000};
  ExtrapolationMode extrapolation{ExtrapolationMode::kHold};
};

struct AttitudeBufferCounters {
  std::uint32_t appended{0};
  std::uint32_t reordered{0};
  std::uint32_t duplicates{0};
  std::uint32_t too_old{0};
  std::uint32_t invalid{0};
  std::uint32_t clock_resets{0};
  std::uint32_t overwritten{0};  // oldest dropped to make room
};

template <typename Scalar>
struct AttitudeQuery {
  AttitudeQueryStatus status{AttitudeQueryStatus::kEmpty};
  Quat<Scalar> q_nb{Quat<Scalar>::Identity()};
  std::uint64_t gap_us{0};  // bracketing interval (interpolated) or distance past newest
};

// q0 * exp(f * log(q0^-1 q1)) along the shorter arc; valid for f outside [0, 1] (extrapolation).
// d = q0^-1 q1 = (w, v) turns by 2 theta, theta = atan(|v| / w); the step is
// (cos(f theta), sin(f theta) v / |v|). Between INS epochs theta is a few milliradians: atan's and
// the sine's and cosine's polynomials (frames.hpp) instead of atan2, sin and cos.
template <typename Scalar>
Quat<Scalar> slerp_unit(const Quat<Scalar>& q0, const Quat<Scalar>& q1, Scalar f) noexcept {
  Quat<Scalar> d = q0.conjugate() * q1;
  if (d.w() < Scalar(0)) d.coeffs() = -d.coeffs();
  const Scalar w = d.w();
  const Scalar v2 = d.vec().squaredNorm();
  Quat<Scalar> step;
  bool small = false;
  if (v2 < Scalar(kSmallAtanSq) * w * w) {
    const Scalar theta_per_v = atan_over_t(v2 / (w * w)) / w;  // theta / |v|
    const Scalar ft = f * theta_per_v;
    const Scalar a2 = ft * ft * v2;  // (f theta)^2
    if (a2 < Scalar(kSmallRotationSq)) {
      const RotationCoefficients<Scalar> c = rotation_coefficients(a2);
      const Scalar k = c.sinc * ft;  // sin(f theta) / |v|
      step = Quat<Scalar>(c.cos, k * d.x(), k * d.y(), k * d.z());
      small = true;
    }
  }
  if (!small) {
    const Scalar vnorm = std::sqrt(v2);
    const Scalar half = f * std::atan2(vnorm, w);
    const Scalar s = std::sin(half) / vnorm;
    step = Quat<Scalar>(std::cos(half), s * d.x(), s * d.y(), s * d.z());
  }
  Quat<Scalar> q = q0 * step;
  q.normalize();
  return q;
}

template <typename Scalar, std::size_t Capacity>
class AttitudeBuffer {
  static_assert(CoreScalar<Scalar>, "AttitudeBuffer is instantiated for float and double only");
  static_assert(Capacity >= 2, "interpolation needs at least two samples");

 public:
  explicit AttitudeBuffer(const AttitudeBufferConfig& config = {}) noexcept : config_(config) {}

  AttitudeInsert insert(std::uint64_t t_us, const Quat<Scalar>& q_nb) noexcept {
    if (!all_finite(q_nb.coeffs()) ||
        std::fabs(q_nb.norm() - Scalar(1)) > static_cast<Scalar>(1e-3)) {
      ++counters_.invalid;
      return AttitudeInsert::kInvalid;
    }
    Quat<Scalar> q = q_nb.normalized();
    if (size_ == 0) {
      push_back(t_us, q);
      ++counters_.appended;
      return AttitudeInsert::kAppended;
    }
    const std::uint64_t newest = time_at(size_ - 1);
    if (t_us > newest) {
      // Keep the hemisphere continuous so that stored neighbours are on the same side.
      if (q.dot(quat_at(size_ - 1)) < Scalar(0)) q.coeffs() = -q.coeffs();
      push_back(t_us, q);
      ++counters_.appended;
      return AttitudeInsert::kAppended;
    }
    if (newest - t_us > config_.max_backjump_us) {
      clear();
      push_back(t_us, q);
      ++counters_.clock_resets;
      return AttitudeInsert::kClockReset;
    }
    // Find the first index with time >= t_us.
    const std::size_t idx = lower_bound(t_us);
    if (idx < size_ && time_at(idx) == t_us) {
      ++counters_.duplicates;
      return AttitudeInsert::kDuplicate;
    }
    if (idx == 0 && size_ == Capacity) {
      ++counters_.too_old;
      return AttitudeInsert::kTooOld;
    }
    std::size_t pos = idx;
    if (size_ == Capacity) {  // drop the oldest to make room; the insert point moves down by one
      head_ = (head_ + 1) % Capacity;
      --size_;
      --pos;
      ++counters_.overwritten;
    }
    // Shift [pos, size_) up by one.
    for (std::size_t i = size_; i > pos; --i)
      entries_[phys(i)] = entries_[phys(i - 1)];
    if (q.dot(entries_[phys(pos + 1)].q) < Scalar(0)) q.coeffs() = -q.coeffs();
    entries_[phys(pos)] = Entry{t_us, q};
    ++size_;
    ++counters_.reordered;
    return AttitudeInsert::kReordered;
  }

  AttitudeQuery<Scalar> at(std::uint64_t t_us) const noexcept {
    AttitudeQuery<Scalar> r;
    if (size_ == 0) return r;
    const std::uint64_t oldest = time_at(0);
    const std::uint64_t newest = time_at(size_ - 1);
    if (t_us < oldest) {
      r.status = AttitudeQueryStatus::kTooOld;
      return r;
    }
    if (t_us >= newest) {
      r.gap_us = t_us - newest;
      if (r.gap_us == 0) {
        r.status = AttitudeQueryStatus::kInterpolated;
        r.q_nb = quat_at(size_ - 1);
        return r;
      }
      if (r.gap_us > config_.max_extrapolation_us) {
        r.status = AttitudeQueryStatus::kTooNew;
        return r;
      }
      r.status = AttitudeQueryStatus::kExtrapolated;
      r.q_nb = quat_at(size_ - 1);
      if (config_.extrapolation == ExtrapolationMode::kConstantRate && size_ >= 2) {
        const std::uint64_t t0 = time_at(size_ - 2);
        if (newest - t0 <= config_.max_gap_us) {
          const Scalar f = fraction(t_us - t0, newest - t0);
          r.q_nb = slerp_unit(quat_at(size_ - 2), quat_at(size_ - 1), f);
        }
      }
      return r;
    }
    const std::size_t hi = lower_bound(t_us);  // time_at(hi) >= t_us, hi >= 1 here
    const Entry& e1 = entries_[phys(hi)];
    if (e1.t_us == t_us) {
      r.status = AttitudeQueryStatus::kInterpolated;
      r.q_nb = e1.q;
      return r;
    }
    const Entry& e0 = entries_[phys(hi - 1)];
    r.gap_us = e1.t_us - e0.t_us;
    if (r.gap_us > config_.max_gap_us) {
      r.status = AttitudeQueryStatus::kGap;
      return r;
    }
    const Scalar f = fraction(t_us - e0.t_us, r.gap_us);
    r.status = AttitudeQueryStatus::kInterpolated;
    r.q_nb = slerp_unit(e0.q, e1.q, f);
    return r;
  }

  void clear() noexcept {
    head_ = 0;
    size_ = 0;
  }
  // Empty, with a new configuration and zero counters.
  void reset(const AttitudeBufferConfig& config) noexcept {
    config_ = config;
    counters_ = AttitudeBufferCounters{};
    clear();
  }
  std::size_t size() const noexcept { return size_; }
  static constexpr std::size_t capacity() noexcept { return Capacity; }
  std::uint64_t oldest_us() const noexcept { return size_ ? time_at(0) : 0; }
  std::uint64_t newest_us() const noexcept { return size_ ? time_at(size_ - 1) : 0; }
  const AttitudeBufferCounters& counters() const noexcept { return counters_; }
  const AttitudeBufferConfig& config() const noexcept { return config_; }

 private:
  struct Entry {
    std::uint64_t t_us{0};
    Quat<Scalar> q{Quat<Scalar>::Identity()};
  };
  // d / span (0 < span; d > span when extrapolating) for the slerp. Times within 32 bits (71
  // minutes) go through 32-bit integers, which the M4F converts in one instruction; a 64-bit
  // conversion or a double division is a soft-float call there (~430 instructions per interpolated
  // query, measured). In double the result is the same either way (the integers convert exactly).
  static Scalar fraction(std::uint64_t d, std::uint64_t span) noexcept {
    if (d <= 0xFFFFFFFFu && span <= 0xFFFFFFFFu) {
      return static_cast<Scalar>(static_cast<std::uint32_t>(d)) /
             static_cast<Scalar>(static_cast<std::uint32_t>(span));
    }
    return static_cast<Scalar>(static_cast<double>(d) / static_cast<double>(span));
  }
  std::size_t phys(std::size_t logical) const noexcept { return (head_ + logical) % Capacity; }
  std::uint64_t time_at(std::size_t logical) const noexcept { return entries_[phys(logical)].t_us; }
  const Quat<Scalar>& quat_at(std::size_t logical) const noexcept {
    return entries_[phys(logical)].q;
  }
  // The first index with time >= t_us (size_ if none). Queries and late inserts land within the
  // newest few entries (a sample waits only for the INS epochs after it): those are tried first,
  // then a binary search of the rest (every entry from hi on is at or after t_us).
  std::size_t lower_bound(std::uint64_t t_us) const noexcept {
    std::size_t hi = size_;
    std::size_t p = phys(size_);  // the slot after the newest; stepped back with hi
    for (int k = 0; k < 4 && hi > 0; ++k) {
      p = (p + Capacity - 1) % Capacity;
      if (entries_[p].t_us < t_us) return hi;
      --hi;
    }
    std::size_t lo = 0;
    while (lo < hi) {
      const std::size_t mid = lo + (hi - lo) / 2;
      if (time_at(mid) < t_us) {
        lo = mid + 1;
      } else {
        hi = mid;
      }
    }
    return lo;
  }
  void push_back(std::uint64_t t_us, const Quat<Scalar>& q) noexcept {
    if (size_ == Capacity) {
      head_ = (head_ + 1) % Capacity;
      --size_;
      ++counters_.overwritten;
    }
    entries_[phys(size_)] = Entry{t_us, q};
    ++size_;
  }

  AttitudeBufferConfig config_;
  AttitudeBufferCounters counters_{};
  Entry entries_[Capacity];
  std::size_t head_{0};
  std::size_t size_{0};
};

}  // namespace magvec::core
