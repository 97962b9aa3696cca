// Canonical sensor model (docs/conventions.md) and exact conversions to each paper's parameters.
//   m = A Rm R_bn h_n + o,   stored as W = A^-1, o, Rm (unit quaternion, INS body -> sensor frame).
// Li et al. 2023 eq. (4)-(7): A = Ks Ko, o = Kof, Rm = Ry(gm) Rx(bm) Rz(am); G decomposed per
// docs/equations.md E-Li-1 (ks_i = sqrt((G^-1)_ii), not the printed 1/sqrt(G_ii)).
// Ge et al. 2017 eq. (13)-(14): Hm = C Hi + b with Hi in the carrier (INS body) frame: C^-1 = Rm^T
// W. Sine-fitting paper eq. (1): m = K B + B0, K lower triangular, B in the fixture frame.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/LU>
#include <cmath>

#include "magvec/core/frames.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

template <typename Scalar>
struct SensorModel {
  Mat3<Scalar> w = Mat3<Scalar>::Identity();   // A^-1: raw (offset-free) -> orthogonal sensor frame
  Vec3<Scalar> o = Vec3<Scalar>::Zero();       // offset [nT]
  Quat<Scalar> rm = Quat<Scalar>::Identity();  // misalignment: h_s = Rm h_b

  Mat3<Scalar> rm_matrix() const noexcept { return rm.toRotationMatrix(); }
  Mat3<Scalar> a() const noexcept { return w.inverse(); }
  // G = W^T W: the ellipsoid matrix, the only part of W a scalar (|H|) method can determine.
  Mat3<Scalar> g() const noexcept { return w.transpose() * w; }

  // Raw reading predicted for a field h_n seen at attitude R_bn (the forward model, noise-free).
  Vec3<Scalar> predict_raw(const Mat3<Scalar>& r_bn, const Vec3<Scalar>& h_n) const noexcept {
    return a() * (rm_matrix() * (r_bn * h_n)) + o;
  }

  template <typename Other>
  SensorModel<Other> cast() const noexcept {
    SensorModel<Other> m;
    m.w = w.template cast<Other>();
    m.o = o.template cast<Other>();
    m.rm = rm.template cast<Other>();
    return m;
  }
};

// Outcome of a conversion into a structured parameterisation.
enum class ConversionStatus : std::uint8_t {
  kOk,
  kNotPositiveDefinite,  // A A^T is not positive definite (W singular or not finite)
  kReflection,           // W contains a reflection: no rotation Rm reproduces it
};

// ---------------------------------------------------------------------------------------------
// Li et al. 2023
template <typename Scalar>
struct LiParams {
  Vec3<Scalar> ks = Vec3<Scalar>::Ones();      // scale factors Ksx, Ksy, Ksz
  Vec3<Scalar> o_rad = Vec3<Scalar>::Zero();   // non-orthogonality O1, O2, O3
  Vec3<Scalar> kof = Vec3<Scalar>::Zero();     // offset Kof [nT]
  Vec3<Scalar> rm_rad = Vec3<Scalar>::Zero();  // misalignment alpha_m, beta_m, gamma_m
};

// Eq. (5): rows are the unit sensing directions of the magnetometer axes.
template <typename Scalar>
Mat3<Scalar> li_ko(const Vec3<Scalar>& o_rad) noexcept {
  using std::cos;
  using std::sin;
  Mat3<Scalar> ko;
  ko << 1, 0, 0,                                                                    //
      cos(o_rad(1)) * sin(o_rad(2)), cos(o_rad(1)) * cos(o_rad(2)), sin(o_rad(1)),  //
      sin(o_rad(0)), 0, cos(o_rad(0));
  return ko;
}

template <typename Scalar>
Mat3<Scalar> li_rm(const Vec3<Scalar>& rm_rad) noexcept {
  return r_bn_from_li(LiEuler<Scalar>{rm_rad(0), rm_rad(1), rm_rad(2)});
}

template <typename Scalar>
SensorModel<Scalar> from_li(const LiParams<Scalar>& p) noexcept {
  SensorModel<Scalar> m;
  const Mat3<Scalar> a = p.ks.asDiagonal() * li_ko(p.o_rad);
  m.w = a.inverse();
  m.o = p.kof;
  m.rm = Quat<Scalar>(li_rm(p.rm_rad));
  m.rm.normalize();
  return m;
}

// Ks and O from G^-1 = A A^T (docs/equations.md E-Li-1); on success also returns Ks Ko in *ksko.
template <typename Scalar>
ConversionStatus li_scale_and_angles(const Mat3<Scalar>& g_inv, Vec3<Scalar>* ks,
                                     Vec3<Scalar>* o_rad, Mat3<Scalar>* ksko) noexcept {
  using std::asin;
  using std::atan2;
  using std::sqrt;
  if (!g_inv.allFinite() || g_inv(0, 0) <= 0 || g_inv(1, 1) <= 0 || g_inv(2, 2) <= 0) {
    return ConversionStatus::kNotPositiveDefinite;
  }
  const Vec3<Scalar> k(sqrt(g_inv(0, 0)), sqrt(g_inv(1, 1)), sqrt(g_inv(2, 2)));
  const Scalar c12 = g_inv(0, 1) / (k(0) * k(1));
  const Scalar c13 = g_inv(0, 2) / (k(0) * k(2));
  const Scalar c23 = g_inv(1, 2) / (k(1) * k(2));
  if (!(std::abs(c13) < Scalar(1))) return ConversionStatus::kNotPositiveDefinite;
  const Scalar o1 = asin(c13);
  const Scalar s2 = (c23 - c12 * c13) / std::cos(o1);
  if (!(std::abs(s2) < Scalar(1))) return ConversionStatus::kNotPositiveDefinite;
  const Scalar o2 = asin(s2);
  const Scalar s3 = c12 / std::cos(o2);
  if (!(std::abs(s3) < Scalar(1))) return ConversionStatus::kNotPositiveDefinite;
  // Row y of Ko has unit norm, so cos O3 = sqrt(1 - s3^2) > 0 (|O3| < 90 deg).
  const Scalar o3 = atan2(s3, sqrt(Scalar(1) - s3 * s3));
  *ks = k;
  *o_rad = Vec3<Scalar>(o1, o2, o3);
  *ksko = k.asDiagonal() * li_ko(*o_rad);
  return ConversionStatus::kOk;
}

// Any model -> Li form: A Rm = (Ks Ko) Rm_li, so Rm_li = (Ks Ko)^-1 A Rm.
template <typename Scalar>
ConversionStatus to_li(const SensorModel<Scalar>& m, LiParams<Scalar>* out) noexcept {
  const Mat3<Scalar> a_total = m.a() * m.rm_matrix();
  Mat3<Scalar> ksko;
  LiParams<Scalar> p;
  const ConversionStatus st =
      li_scale_and_angles<Scalar>(a_total * a_total.transpose(), &p.ks, &p.o_rad, &ksko);
  if (st != ConversionStatus::kOk) return st;
  const Mat3<Scalar> q = ksko.inverse() * a_total;
  if (q.determinant() < 0) return ConversionStatus::kReflection;
  const LiEuler<Scalar> e = li_from_r_bn<Scalar>(q);
  p.rm_rad = Vec3<Scalar>(e.alpha, e.beta, e.gamma);
  p.kof = m.o;
  *out = p;
  return ConversionStatus::kOk;
}

// Re-expresses a model in Li structure (W = (Ks Ko)^-1), moving the remaining rotation into Rm.
// The compensated body-frame field is unchanged; h_s changes by that rotation.
template <typename Scalar>
ConversionStatus canonicalize_li(const SensorModel<Scalar>& m, SensorModel<Scalar>* out) noexcept {
  LiParams<Scalar> p;
  const ConversionStatus st = to_li(m, &p);
  if (st == ConversionStatus::kOk) *out = from_li(p);
  return st;
}

// ---------------------------------------------------------------------------------------------
// Ge et al. 2017
template <typename Scalar>
struct GeParams {
  Mat3<Scalar> c_inv = Mat3<Scalar>::Identity();  // C^-1
  Vec3<Scalar> b = Vec3<Scalar>::Zero();          // b [nT]
};

template <typename Scalar>
SensorModel<Scalar> from_ge(const GeParams<Scalar>& p) noexcept {
  SensorModel<Scalar> m;
  m.w = p.c_inv;
  m.o = p.b;
  return m;
}
template <typename Scalar>
GeParams<Scalar> to_ge(const SensorModel<Scalar>& m) noexcept {
  return {m.rm_matrix().transpose() * m.w, m.o};
}

// ---------------------------------------------------------------------------------------------
// Sine-fitting turntable paper
template <typename Scalar>
struct SineParams {
  Vec3<Scalar> k = Vec3<Scalar>::Ones();   // kx, ky, kz
  Scalar alpha_rad{0};                     // Ym tilt from Y inside the XY plane
  Scalar beta_rad{0};                      // azimuth of Zm's projection on XY, from X
  Scalar gamma_rad{0};                     // angle between Zm and Z
  Vec3<Scalar> b0 = Vec3<Scalar>::Zero();  // offsets Bx0, By0, Bz0 [nT]
};

template <typename Scalar>
Mat3<Scalar> sine_k(const SineParams<Scalar>& p) noexcept {
  using std::cos;
  using std::sin;
  Mat3<Scalar> k;
  k << p.k(0), 0, 0,                                            //
      p.k(1) * sin(p.alpha_rad), p.k(1) * cos(p.alpha_rad), 0,  //
      p.k(2) * cos(p.beta_rad) * sin(p.gamma_rad), p.k(2) * sin(p.beta_rad) * sin(p.gamma_rad),
      p.k(2) * cos(p.gamma_rad);
  return k;
}

template <typename Scalar>
SensorModel<Scalar> from_sine(const SineParams<Scalar>& p) noexcept {
  SensorModel<Scalar> m;
  m.w = sine_k(p).inverse();
  m.o = p.b0;
  return m;
}

// Any model -> sine form: A Rm = K Q with K lower triangular (Cholesky of A A^T); the fixture
// rotation Q is returned in *fixture_rotation when given (identity for a model built by from_sine).
template <typename Scalar>
ConversionStatus to_sine(const SensorModel<Scalar>& m, SineParams<Scalar>* out,
                         Mat3<Scalar>* fixture_rotation = nullptr) noexcept {
  using std::atan2;
  using std::hypot;
  const Mat3<Scalar> a_total = m.a() * m.rm_matrix();
  const Eigen::LLT<Mat3<Scalar>> llt(a_total * a_total.transpose());
  if (llt.info() != Eigen::Success || !a_total.allFinite())
    return ConversionStatus::kNotPositiveDefinite;
  const Mat3<Scalar> k = llt.matrixL();
  const Mat3<Scalar> q = k.inverse() * a_total;
  if (q.determinant() < 0) return ConversionStatus::kReflection;
  SineParams<Scalar> p;
  p.k = Vec3<Scalar>(k(0, 0), k.row(1).norm(), k.row(2).norm());
  p.alpha_rad = atan2(k(1, 0), k(1, 1));
  p.gamma_rad = atan2(hypot(k(2, 0), k(2, 1)), k(2, 2));
  p.beta_rad = atan2(k(2, 1), k(2, 0));
  p.b0 = m.o;
  *out = p;
  if (fixture_rotation != nullptr) *fixture_rotation = q;
  return ConversionStatus::kOk;
}

}  // namespace magvec::core
