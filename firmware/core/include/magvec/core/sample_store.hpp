// Fixed-capacity store of calibration samples (raw magnetometer reading, scalar reference field,
// INS attitude) for the batch estimators of Li et al. 2023 (ellipsoid refinement, misalignment,
// one-step fit, docs/equations.md E-Li-2..E-Li-6). Plain arrays, no heap: a Capacity of 256 fits a
// Cortex-M4F. Also holds the normalisation (centre and scale) every batch solver works in: fields
// are divided by the reference magnitude so float32 keeps precision
// (docs/equations.md#normalisation).
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <vector>

#include "magvec/core/frames.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

// x = (m - centre) / scale: raw nT -> dimensionless, O(1) numbers.
template <typename Scalar>
struct Normalization {
  Vec3<Scalar> centre = Vec3<Scalar>::Zero();
  Scalar scale{1};

  Vec3<Scalar> to_unit(const Vec3<Scalar>& m) const noexcept { return (m - centre) / scale; }
  Vec3<Scalar> to_nt(const Vec3<Scalar>& x) const noexcept { return x * scale + centre; }
};

// Sample flags.
enum SampleFlag : std::uint8_t {
  kSampleHasAttitude = 1U << 0,  // r_bn is valid
  kSampleOutlier = 1U << 1,      // rejected by the robust (median/MAD) screen
};

template <typename Scalar>
struct StoredSample {
  std::array<Scalar, 3> m{};  // raw reading [nT]
  Scalar f{0};                // scalar reference field [nT]
  std::array<Scalar, 4> q{};  // R_bn as a unit quaternion (w, x, y, z)
  // Attitude-noise variance of this sample relative to one INS record: (1-u)^2 + u^2 for an
  // attitude interpolated at fraction u between two records with independent noise, else 1.
  Scalar att_var{1};
  std::uint8_t flags{0};

  Vec3<Scalar> raw() const noexcept { return Vec3<Scalar>(m[0], m[1], m[2]); }
  bool has_attitude() const noexcept { return (flags & kSampleHasAttitude) != 0; }
  bool outlier() const noexcept { return (flags & kSampleOutlier) != 0; }
  Mat3<Scalar> r_bn() const noexcept {
    return Quat<Scalar>(q[0], q[1], q[2], q[3]).toRotationMatrix();
  }
};

// Capacity of a store that grows on the heap (host batch calibration of recordings: memory in
// proportion to the samples kept). Never instantiated by the firmware images.
inline constexpr std::size_t kDynamicCapacity = 0;

namespace detail {
// Storage of a store: a fixed array, or (kDynamicCapacity) a growing vector.
template <typename T, std::size_t Capacity>
struct StoreBuffer {
  std::array<T, Capacity> items{};
  static constexpr std::size_t capacity() noexcept { return Capacity; }
  bool ensure(std::size_t n) noexcept { return n <= Capacity; }
  T* data() noexcept { return items.data(); }
  const T* data() const noexcept { return items.data(); }
};
template <typename T>
struct StoreBuffer<T, kDynamicCapacity> {
  std::vector<T> items;
  static constexpr std::size_t capacity() noexcept {
    return std::numeric_limits<std::size_t>::max();
  }
  // Host only: grows geometrically; false if the allocation fails.
  bool ensure(std::size_t n) noexcept {
    if (n <= items.size()) return true;
#if defined(__cpp_exceptions) || defined(__EXCEPTIONS)
    try {
      items.resize(std::max<std::size_t>(n, items.size() * 2));
    } catch (...) {
      return false;
    }
    return true;
#else
    return false;
#endif
  }
  T* data() noexcept {
    return items.data();
  }
  const T* data() const noexcept {
    return items.data();
  }
};
}  // namespace detail

// Append-only store; samples beyond Capacity are refused (and counted by the caller).
template <typename Scalar, std::size_t Capacity>
class SampleStore {
 public:
  static constexpr std::size_t kCapacity = Capacity;

  void clear() noexcept { size_ = 0; }
  std::size_t size() const noexcept { return size_; }
  bool full() const noexcept { return size_ == samples_.capacity(); }

  // Stores a finite sample; returns false when full. r_bn may be null (no attitude).
  bool push(const Vec3<Scalar>& m, Scalar f, const Mat3<Scalar>* r_bn,
            Scalar att_var = Scalar(1)) noexcept {
    if (!samples_.ensure(size_ + 1)) return false;
    StoredSample<Scalar>& s = samples_.data()[size_];
    s.m = {m(0), m(1), m(2)};
    s.f = f;
    s.att_var = att_var;
    s.flags = 0;
    if (r_bn != nullptr) {
      Quat<Scalar> q(*r_bn);
      q.normalize();
      s.q = {q.w(), q.x(), q.y(), q.z()};
      s.flags = kSampleHasAttitude;
    } else {
      s.q = {Scalar(1), Scalar(0), Scalar(0), Scalar(0)};
    }
    ++size_;
    return true;
  }

  const StoredSample<Scalar>& operator[](std::size_t i) const noexcept {
    return samples_.data()[i];
  }
  StoredSample<Scalar>& operator[](std::size_t i) noexcept { return samples_.data()[i]; }
  const StoredSample<Scalar>* data() const noexcept { return samples_.data(); }

 private:
  detail::StoreBuffer<StoredSample<Scalar>, Capacity> samples_{};
  std::size_t size_{0};
};

// Read-only view of a store's samples, whatever its capacity. The batch solvers (ellipsoid
// refinement, misalignment, one-step fit) take this view, so each is compiled once per scalar
// type instead of once per store capacity (a one-step fit costs about a minute of compile time).
template <typename Scalar>
class SampleView {
 public:
  template <std::size_t Capacity>
  SampleView(const SampleStore<Scalar, Capacity>& store) noexcept  // NOLINT: a store is a view
      : data_(store.data()), size_(store.size()) {}

  std::size_t size() const noexcept { return size_; }
  const StoredSample<Scalar>& operator[](std::size_t i) const noexcept { return data_[i]; }

 private:
  const StoredSample<Scalar>* data_;
  std::size_t size_;
};

}  // namespace magvec::core
