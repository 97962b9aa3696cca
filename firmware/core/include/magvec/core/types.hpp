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

// True when every component is finite (no NaN, no inf).
template <typename Derived>
bool all_finite(const Eigen::MatrixBase<Derived>& m) noexcept {
  return m.allFinite();
}

}  // namespace magvec::core
