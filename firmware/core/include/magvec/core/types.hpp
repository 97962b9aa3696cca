// Fixed-size linear-algebra vocabulary of the firmware core.
// Everything in magvec::core is templated on Scalar (float on Cortex-M4F, double elsewhere),
// uses only fixed-size Eigen types, never allocates and never throws.
#pragma once

#include <Eigen/Core>
#include <Eigen/Geometry>
#include <cstdint>
#include <type_traits>

namespace magvec::core {

template <typename Scalar>
using Vec3 = Eigen::Matrix<Scalar, 3, 1>;
template <typename Scalar>
using Mat3 = Eigen::Matrix<Scalar, 3, 3>;
template <typename Scalar>
using Quat = Eigen::Quaternion<Scalar>;
template <typename Scalar, int N>
using Vec = Eigen::Matrix<Scalar, N, 1>;
template <typename Scalar, int Rows, int Cols>
using Mat = Eigen::Matrix<Scalar, Rows, Cols>;

template <typename Scalar>
inline constexpr Scalar kPi = static_cast<Scalar>(3.14159265358979323846264338327950288);

template <typename Scalar>
constexpr Scalar deg_to_rad(Scalar deg) noexcept {
  return deg * (kPi<Scalar> / Scalar(180));
}
template <typename Scalar>
constexpr Scalar rad_to_deg(Scalar rad) noexcept {
  return rad * (Scalar(180) / kPi<Scalar>);
}

template <typename Scalar>
concept CoreScalar = std::is_same_v<Scalar, float> || std::is_same_v<Scalar, double>;

// True when every component is finite (no NaN, no inf): v * 0 is (+-)0 for a finite v and NaN
// for inf or NaN, so one multiply-add per component decides it exactly (no build uses
// -ffast-math, which would fold it). Eigen's allFinite() forms v - v and tests every component
// in a loop of its own, out of line on the M4F (tests/mcu/insn_count.py: ~290 instructions per
// calibrating sample of the EKF image for its three vectors of 12).
// A plain matrix of more than 16 components (where Eigen's reduction is a loop) is probed over its
// storage, two components per step; anything else through Eigen's unrolled reduction.
template <typename Derived>
bool all_finite(const Eigen::MatrixBase<Derived>& m) noexcept {
  using S = typename Derived::Scalar;
  constexpr int kSize = Derived::SizeAtCompileTime;
  if constexpr (std::is_base_of_v<Eigen::PlainObjectBase<Derived>, Derived> &&
                (kSize == Eigen::Dynamic || kSize > 16)) {
    const S* p = m.derived().data();
    const Eigen::Index n = m.size();
    S a{0}, b{0};
    Eigen::Index i = 0;
    for (; i + 1 < n; i += 2) {
      a += p[i] * S(0);
      b += p[i + 1] * S(0);
    }
    if (i < n) a += p[i] * S(0);
    return a + b == S(0);
  } else {
    return (m.array() * S(0)).sum() == S(0);
  }
}

}  // namespace magvec::core
