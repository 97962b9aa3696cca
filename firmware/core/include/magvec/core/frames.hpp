// Frames and attitude conventions (docs/conventions.md).
// Navigation frame n = ENU. Rotation matrices are passive (frame rotations). R_bn maps n-frame
// components to INS body components: h_b = R_bn h_n. Li et al. 2023 eq. (2):
// R_bn = Ry(gamma) Rx(beta) Rz(alpha), body axes Right-Forward-Up, alpha right-handed about Up.
// Euler angles exist only at the edges (files, drivers, paper reproduction).
#pragma once

#include <cmath>
#include <type_traits>

#include "magvec/core/types.hpp"

namespace magvec::core {

// Passive elementary rotations.
template <typename Scalar>
Mat3<Scalar> rot_x(Scalar a) noexcept {
  const Scalar c = std::cos(a), s = std::sin(a);
  Mat3<Scalar> r;
  r << 1, 0, 0, 0, c, s, 0, -s, c;
  return r;
}
template <typename Scalar>
Mat3<Scalar> rot_y(Scalar a) noexcept {
  const Scalar c = std::cos(a), s = std::sin(a);
  Mat3<Scalar> r;
  r << c, 0, -s, 0, 1, 0, s, 0, c;
  return r;
}
template <typename Scalar>
Mat3<Scalar> rot_z(Scalar a) noexcept {
  const Scalar c = std::cos(a), s = std::sin(a);
  Mat3<Scalar> r;
  r << c, s, 0, -s, c, 0, 0, 0, 1;
  return r;
}

// Li's Euler angles in radians: alpha heading (about Up, right-handed), beta pitch, gamma roll.
template <typename Scalar>
struct LiEuler {
  Scalar alpha{0};
  Scalar beta{0};
  Scalar gamma{0};
};

// Aerospace angles in radians: yaw clockwise from North, pitch nose up, roll right wing down;
// navigation NED, body Forward-Right-Down.
template <typename Scalar>
struct YawPitchRoll {
  Scalar yaw{0};
  Scalar pitch{0};
  Scalar roll{0};
};

template <typename Scalar>
Mat3<Scalar> r_bn_from_li(const LiEuler<Scalar>& e) noexcept {
  return rot_y(e.gamma) * rot_x(e.beta) * rot_z(e.alpha);
}

// Inverse of r_bn_from_li for |beta| < 90 deg. From the product
// R = [[cg ca - sg sb sa, cg sa + sg sb ca, -sg cb], [-cb sa, cb ca, sb], [..., ..., cg cb]].
template <typename Scalar>
LiEuler<Scalar> li_from_r_bn(const Mat3<Scalar>& r) noexcept {
  using std::asin;
  using std::atan2;
  const Scalar sb = r(1, 2) > Scalar(1) ? Scalar(1) : (r(1, 2) < Scalar(-1) ? Scalar(-1) : r(1, 2));
  return {atan2(-r(1, 0), r(1, 1)), asin(sb), atan2(-r(0, 2), r(2, 2))};
}

// ENU <-> NED and RFU <-> FRD are the same signed permutation: swap the first two axes, negate the
// third.
template <typename Scalar>
Mat3<Scalar> enu_ned_swap() noexcept {
  Mat3<Scalar> p;
  p << 0, 1, 0, 1, 0, 0, 0, 0, -1;
  return p;
}

// Aerospace (NED, FRD) attitude to R_bn (ENU -> RFU). C_frd_ned = Rx(roll) Ry(pitch) Rz(yaw), and
// P C P = Ry(roll) Rx(pitch) Rz(-yaw): Li's (alpha, beta, gamma) = (-yaw, pitch, roll) exactly.
template <typename Scalar>
Mat3<Scalar> r_bn_from_ypr(const YawPitchRoll<Scalar>& a) noexcept {
  return r_bn_from_li(LiEuler<Scalar>{-a.yaw, a.pitch, a.roll});
}
template <typename Scalar>
YawPitchRoll<Scalar> ypr_from_r_bn(const Mat3<Scalar>& r) noexcept {
  const LiEuler<Scalar> e = li_from_r_bn(r);
  return {-e.alpha, e.beta, e.gamma};
}
// The aerospace direction cosine matrix C_frd_ned itself (for drivers that deal in NED/FRD).
template <typename Scalar>
Mat3<Scalar> c_frd_ned_from_ypr(const YawPitchRoll<Scalar>& a) noexcept {
  return rot_x(a.roll) * rot_y(a.pitch) * rot_z(a.yaw);
}

// A unit quaternion q that rotates body vectors into ENU (h_n = q h_b q^-1) is R_bn^T.
template <typename Scalar>
Mat3<Scalar> r_bn_from_quat(const Quat<Scalar>& q_nb) noexcept {
  return q_nb.normalized().toRotationMatrix().transpose();
}
// Inverse of r_bn_from_quat, with the sign fixed so that w >= 0.
template <typename Scalar>
Quat<Scalar> quat_from_r_bn(const Mat3<Scalar>& r_bn) noexcept {
  Quat<Scalar> q(Mat3<Scalar>(r_bn.transpose()));
  q.normalize();
  if (q.w() < Scalar(0)) q.coeffs() = -q.coeffs();
  return q;
}

// Wraps an angle in radians to (-pi, pi].
template <typename Scalar>
Scalar wrap_pi(Scalar a) noexcept {
  const Scalar two_pi = Scalar(2) * kPi<Scalar>;
  a = std::fmod(a, two_pi);
  if (a <= -kPi<Scalar>) a += two_pi;
  if (a > kPi<Scalar>) a -= two_pi;
  return a;
}

// Angle of the rotation R = r_a^T r_b in radians: the distance between two attitudes (the one
// implementation: motion decimation of the calibrators, tests, evaluation). atan2 of
// sin = |vee(R - R^T)| / 2 and cos = (tr R - 1) / 2 is accurate at 0 and at pi alike, where
// acos of the trace alone loses half the digits near 0; 27 multiplications, no matrix product.
template <typename Scalar>
Scalar rotation_angle_between(const Mat3<Scalar>& r_a, const Mat3<Scalar>& r_b) noexcept {
  const Scalar c = (r_a.cwiseProduct(r_b).sum() - Scalar(1)) * Scalar(0.5);
  // R(i, j) = r_a.col(i) . r_b.col(j)
  const Scalar sx = r_a.col(2).dot(r_b.col(1)) - r_a.col(1).dot(r_b.col(2));
  const Scalar sy = r_a.col(0).dot(r_b.col(2)) - r_a.col(2).dot(r_b.col(0));
  const Scalar sz = r_a.col(1).dot(r_b.col(0)) - r_a.col(0).dot(r_b.col(1));
  const Scalar s = Scalar(0.5) * std::sqrt(sx * sx + sy * sy + sz * sz);
  return std::atan2(s, c);
}

// [v x]: the matrix of the cross product, [v x] u = v x u.
template <typename Scalar>
Mat3<Scalar> skew(const Vec3<Scalar>& v) noexcept {
  Mat3<Scalar> m;
  m << Scalar(0), -v(2), v(1), v(2), Scalar(0), -v(0), -v(1), v(0), Scalar(0);
  return m;
}

// Small rotations without the library's trigonometry (docs/equations.md E-Att-2): the
// rotations between INS epochs, across a time offset and of the misalignment's error state are a
// few milliradians, where sinf, cosf and atan2f cost ~100 instructions each on the M4F and these
// polynomials a few. Below a = 0.2 rad the Taylor polynomials to a^10 leave out terms below
// a^12 / 12! = 1e-17: they are exact to double rounding (in float, to a^6: below 1e-11). Larger
// angles go to the library.
constexpr double kSmallRotationSq = 0.04;  // a^2 below which the polynomials are taken
template <typename Scalar>
struct RotationCoefficients {
  Scalar cos;   // cos a
  Scalar sinc;  // sin(a) / a
  Scalar vers;  // (1 - cos a) / a^2
};
// Above the threshold: the library (kept out of line, so that the polynomials inline).
template <typename Scalar>
RotationCoefficients<Scalar> rotation_coefficients_library(Scalar a2) noexcept {
  const Scalar a = std::sqrt(a2);
  const Scalar cos_a = std::cos(a);
  return {cos_a, std::sin(a) / a, (Scalar(1) - cos_a) / a2};
}
// From a^2 (no square root on the small-angle side).
template <typename Scalar>
inline RotationCoefficients<Scalar> rotation_coefficients(Scalar a2) noexcept {
  if (!(a2 < Scalar(kSmallRotationSq))) return rotation_coefficients_library(a2);
  // Horner forms: each term over the previous one is -a^2 / ((2k + 1)(2k + 2)) and so on. In
  // float the series stop at a^6: the first term left out, a^8 / 9!, is below 1e-11.
  const Scalar x = a2;
  if constexpr (std::is_same_v<Scalar, float>) {
    const Scalar sinc =
        Scalar(1) - x * Scalar(1.0 / 6) *
                        (Scalar(1) - x * Scalar(1.0 / 20) * (Scalar(1) - x * Scalar(1.0 / 42)));
    const Scalar vers =
        Scalar(0.5) *
        (Scalar(1) - x * Scalar(1.0 / 12) *
                         (Scalar(1) - x * Scalar(1.0 / 30) * (Scalar(1) - x * Scalar(1.0 / 56))));
    return {Scalar(1) - x * vers, sinc, vers};
  } else {
    const Scalar sinc =
        Scalar(1) -
        x * Scalar(1.0 / 6) *
            (Scalar(1) -
             x * Scalar(1.0 / 20) *
                 (Scalar(1) -
                  x * Scalar(1.0 / 42) *
                      (Scalar(1) - x * Scalar(1.0 / 72) * (Scalar(1) - x * Scalar(1.0 / 110)))));
    const Scalar vers =
        Scalar(0.5) *
        (Scalar(1) -
         x * Scalar(1.0 / 12) *
             (Scalar(1) -
              x * Scalar(1.0 / 30) *
                  (Scalar(1) -
                   x * Scalar(1.0 / 56) *
                       (Scalar(1) - x * Scalar(1.0 / 90) * (Scalar(1) - x * Scalar(1.0 / 132))))));
    return {Scalar(1) - x * vers, sinc, vers};
  }
}
// atan(t) / t from t^2 for t^2 < kSmallAtanSq (t < 0.05: the first term left out, t^12 / 13, is
// below 2e-17; in float the series stops at t^6, leaving out t^8 / 9 < 5e-12); callers take
// std::atan2 above.
constexpr double kSmallAtanSq = 0.0025;
template <typename Scalar>
Scalar atan_over_t(Scalar t2) noexcept {
  if constexpr (std::is_same_v<Scalar, float>) {
    return Scalar(1) - t2 * (Scalar(1.0 / 3) - t2 * (Scalar(0.2) - t2 * Scalar(1.0 / 7)));
  } else {
    return Scalar(1) -
           t2 * (Scalar(1.0 / 3) -
                 t2 * (Scalar(0.2) -
                       t2 * (Scalar(1.0 / 7) - t2 * (Scalar(1.0 / 9) - t2 * Scalar(1.0 / 11)))));
  }
}

// Active rotation matrix of a rotation vector v = a k (Rodrigues): Exp(a [k x]) =
// cos a I + sinc(a) [v x] + vers(a) v v^T.
template <typename Scalar>
Mat3<Scalar> exp_so3(const Vec3<Scalar>& v) noexcept {
  const Scalar a2 = v.squaredNorm();
  if (!(a2 > Scalar(0))) return Mat3<Scalar>::Identity();
  const RotationCoefficients<Scalar> c = rotation_coefficients(a2);
  const Scalar x = v(0), y = v(1), z = v(2);
  const Scalar bxy = c.vers * x * y, bxz = c.vers * x * z, byz = c.vers * y * z;
  const Scalar sx = c.sinc * x, sy = c.sinc * y, sz = c.sinc * z;
  Mat3<Scalar> r;
  r << c.cos + c.vers * x * x, bxy - sz, bxz + sy,  //
      bxy + sz, c.cos + c.vers * y * y, byz - sx,   //
      bxz - sy, byz + sx, c.cos + c.vers * z * z;
  return r;
}
// The same as a unit quaternion: (cos(a/2), sin(a/2) k) = (cos b, sinc(b) v / 2), b = a / 2.
template <typename Scalar>
Quat<Scalar> quat_exp(const Vec3<Scalar>& v) noexcept {
  const Scalar a2 = v.squaredNorm();
  if (!(a2 > Scalar(0))) return Quat<Scalar>::Identity();
  const RotationCoefficients<Scalar> c = rotation_coefficients(Scalar(0.25) * a2);
  const Scalar h = Scalar(0.5) * c.sinc;
  return Quat<Scalar>(c.cos, h * v(0), h * v(1), h * v(2));
}

// Rotation rate in n-frame axes from a body rate (gyro): Omega = R_bn^T omega_b (E-TO-1; the vector
// filter E-VF-5).
template <typename Scalar>
Vec3<Scalar> rate_n_from_body(const Mat3<Scalar>& r_bn, const Vec3<Scalar>& omega_b) noexcept {
  return r_bn.transpose() * omega_b;
}
// Rotation vector of a quaternion dq = (w, v), Log: v 2 atan(t) / (t |w|) with t = |v| / |w|. Below
// t = 0.05 (0.1 rad) atan's series (atan_over_t) instead of the arctangent and a square root (the
// vector calibrator takes one per sample).
template <typename Scalar>
Vec3<Scalar> rotation_vector(const Quat<Scalar>& dq) noexcept {
  const Scalar w = std::abs(dq.w());
  const Scalar w2 = w * w;
  const Scalar v2 = dq.vec().squaredNorm();
  if (v2 < Scalar(kSmallAtanSq) * w2) {
    const Scalar sign = dq.w() < Scalar(0) ? Scalar(-1) : Scalar(1);
    return dq.vec() * (sign * Scalar(2) * atan_over_t(v2 / w2) / w);
  }
  const Eigen::AngleAxis<Scalar> aa(dq);
  return aa.axis() * aa.angle();
}
// Rotation rate from the attitudes before and after a sample: Log(R_+^T R_-) / (t_+ - t_-).
template <typename Scalar>
Vec3<Scalar> rate_n_from_attitudes(const Mat3<Scalar>& r_bn_before, const Mat3<Scalar>& r_bn_after,
                                   Scalar span_s) noexcept {
  if (!(span_s > Scalar(0))) return Vec3<Scalar>::Zero();
  return rotation_vector(Quat<Scalar>(Mat3<Scalar>(r_bn_after.transpose() * r_bn_before))) / span_s;
}
// The same from the INS quaternions q_nb (r_bn = R(q_nb)^T): R_+^T R_- = R(q_+ q_-^*), without
// the two rotation matrices and the matrix-to-quaternion step.
template <typename Scalar>
Vec3<Scalar> rate_n_from_quats(const Quat<Scalar>& q_nb_before, const Quat<Scalar>& q_nb_after,
                               Scalar span_s) noexcept {
  if (!(span_s > Scalar(0))) return Vec3<Scalar>::Zero();
  return rotation_vector(
             Quat<Scalar>(q_nb_after.normalized() * q_nb_before.normalized().conjugate())) /
         span_s;
}

}  // namespace magvec::core
