#include "magvec/core/frames.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace magvec::core {
namespace {

constexpr double kDeg = kPi<double> / 180.0;

TEST(Frames, ElementaryRotationsArePassive) {
  // A frame rotated by +90 deg about Up sees East along its -y axis: passive (frame) rotation.
  const Vec3<double> east(1, 0, 0);
  const Vec3<double> v = rot_z(90 * kDeg) * east;
  EXPECT_NEAR(v.x(), 0, 1e-15);
  EXPECT_NEAR(v.y(), -1, 1e-15);
  EXPECT_NEAR((rot_x(0.3) * rot_x(-0.3) - Mat3<double>::Identity()).norm(), 0, 1e-15);
  EXPECT_NEAR(rot_y(0.2)(0, 2), -std::sin(0.2), 1e-15);
}

TEST(Frames, LiEulerRoundTrip) {
  std::mt19937_64 rng(7);
  std::uniform_real_distribution<double> heading(-179.9, 179.9), tilt(-89, 89), roll(-179.9, 179.9);
  for (int i = 0; i < 500; ++i) {
    const LiEuler<double> e{heading(rng) * kDeg, tilt(rng) * kDeg, roll(rng) * kDeg};
    const Mat3<double> r = r_bn_from_li(e);
    EXPECT_NEAR((r * r.transpose() - Mat3<double>::Identity()).norm(), 0, 1e-14);
    EXPECT_NEAR(r.determinant(), 1, 1e-14);
    const LiEuler<double> back = li_from_r_bn(r);
    EXPECT_NEAR(back.alpha, e.alpha, 1e-12);
    EXPECT_NEAR(back.beta, e.beta, 1e-12);
    EXPECT_NEAR(back.gamma, e.gamma, 1e-12);
  }
}

TEST(Frames, AerospaceAnglesMatchLiConventionThroughNedFrdSwap) {
  std::mt19937_64 rng(11);
  std::uniform_real_distribution<double> u(-80, 80);
  const Mat3<double> p = enu_ned_swap<double>();
  for (int i = 0; i < 200; ++i) {
    const YawPitchRoll<double> a{u(rng) * kDeg, u(rng) * kDeg, u(rng) * kDeg};
    // R_bn (ENU -> RFU) = P_body * C_frd_ned * P_nav with the same signed permutation.
    const Mat3<double> expected = p * c_frd_ned_from_ypr(a) * p;
    EXPECT_NEAR((r_bn_from_ypr(a) - expected).norm(), 0, 1e-14);
    const YawPitchRoll<double> back = ypr_from_r_bn(r_bn_from_ypr(a));
    EXPECT_NEAR(back.yaw, a.yaw, 1e-12);
    EXPECT_NEAR(back.pitch, a.pitch, 1e-12);
    EXPECT_NEAR(back.roll, a.roll, 1e-12);
  }
}

TEST(Frames, HeadingClockwiseFromNorthIsNegativeAlpha) {
  // Vehicle heading East (yaw = +90 deg): its Forward axis (body y in RFU) sees the East component.
  const Mat3<double> r = r_bn_from_ypr(YawPitchRoll<double>{90 * kDeg, 0, 0});
  const Vec3<double> h_b = r * Vec3<double>(1, 0, 0);  // unit East field
  EXPECT_NEAR(h_b.y(), 1, 1e-15);
  EXPECT_NEAR(h_b.x(), 0, 1e-15);
  // Nose up 10 deg: Forward axis picks up part of the Up component.
  const Mat3<double> rp = r_bn_from_ypr(YawPitchRoll<double>{0, 10 * kDeg, 0});
  EXPECT_NEAR((rp * Vec3<double>(0, 0, 1)).y(), std::sin(10 * kDeg), 1e-15);
}

TEST(Frames, QuaternionRotatesBodyIntoEnu) {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> n(0, 1);
  for (int i = 0; i < 200; ++i) {
    Quat<double> q(n(rng), n(rng), n(rng), n(rng));
    q.normalize();
    const Mat3<double> r_bn = r_bn_from_quat(q);
    const Vec3<double> h_b(n(rng), n(rng), n(rng));
    const Vec3<double> h_n = q * h_b;  // active rotation of a body vector into ENU
    EXPECT_NEAR((r_bn * h_n - h_b).norm(), 0, 1e-13);
    const Quat<double> back = quat_from_r_bn(r_bn);
    EXPECT_GE(back.w(), 0);
    EXPECT_NEAR(std::abs(back.dot(q)), 1, 1e-13);
  }
}

TEST(Frames, WrapPi) {
  EXPECT_NEAR(wrap_pi(3 * kPi<double>), kPi<double>, 1e-12);
  EXPECT_NEAR(wrap_pi(-kPi<double>), kPi<double>, 1e-12);
  EXPECT_NEAR(wrap_pi(0.5), 0.5, 1e-15);
  EXPECT_NEAR(wrap_pi(-7.0), -7.0 + 2 * kPi<double>, 1e-12);
}

TEST(Frames, RotationAngleBetweenIsAccurateFromZeroToPi) {
  std::mt19937 rng(31);
  std::normal_distribution<double> n(0, 1);
  for (int i = 0; i < 300; ++i) {
    Quat<double> q(n(rng), n(rng), n(rng), n(rng));
    q.normalize();
    const Mat3<double> a = r_bn_from_quat(q);
    const Vec3<double> axis = Vec3<double>(n(rng), n(rng), n(rng)).normalized();
    // Angles from 1e-9 rad (acos of the trace would give 0 or 2e-8 there) to just below pi.
    const double angle = i < 100 ? std::pow(10.0, -9 + 0.08 * i) : 3.14159 * (i - 100) / 200.0;
    const Mat3<double> b = a * Eigen::AngleAxis<double>(angle, axis).toRotationMatrix();
    const double got = rotation_angle_between(a, b);
    EXPECT_NEAR(got, angle, 1e-12 + 1e-9 * angle) << i;
    EXPECT_NEAR(rotation_angle_between(b, a), got, 1e-12 + 1e-9 * angle);
  }
  EXPECT_EQ(
      rotation_angle_between(Mat3<double>::Identity().eval(), Mat3<double>::Identity().eval()),
      0.0);
  const Mat3<float> af = Mat3<float>::Identity();
  const Mat3<float> bf = Eigen::AngleAxis<float>(1e-4f, Vec3<float>::UnitZ()).toRotationMatrix();
  EXPECT_NEAR(rotation_angle_between(af, bf), 1e-4f, 1e-8f);
}

// The n-frame rate from two quaternions is the one from their rotation matrices, whatever the
// quaternions' signs, and a known turn about the n-frame's up axis gives its rate.
TEST(Frames, RateFromQuaternionsIsTheRateFromTheirAttitudes) {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> g(0.0, 1.0);
  for (int i = 0; i < 200; ++i) {
    const Quat<double> q0 = Quat<double>(g(rng), g(rng), g(rng), g(rng)).normalized();
    // rad, n frame: from a milliradian to half a radian (the series below 0.1 rad, atan2 above).
    const Vec3<double> turn =
        std::pow(10.0, -3.0 + 2.7 * (i % 10) / 9.0) * Vec3<double>(g(rng), g(rng), g(rng));
    const Quat<double> q1 =
        (Quat<double>(Eigen::AngleAxis<double>(turn.norm(), turn.normalized())) * q0).normalized();
    const Vec3<double> want = rate_n_from_attitudes(r_bn_from_quat(q0), r_bn_from_quat(q1), 0.02);
    const Quat<double> q1_neg(-q1.w(), -q1.x(), -q1.y(), -q1.z());
    for (const Quat<double>& b : {q1, q1_neg}) {
      const Vec3<double> got = rate_n_from_quats(q0, b, 0.02);
      EXPECT_LT((got - want).norm(), 1e-9 * want.norm()) << i;
      EXPECT_LT((got - turn / 0.02).norm(), 1e-9 * want.norm()) << i;
    }
  }
  const Quat<float> a = Quat<float>::Identity();
  const Quat<float> b(Eigen::AngleAxis<float>(0.01f, Vec3<float>::UnitZ()));
  const Vec3<float> r = rate_n_from_quats(a, b, 0.02f);
  EXPECT_NEAR(r.z(), 0.5f, 1e-5f);
  EXPECT_NEAR(r.head<2>().norm(), 0.0f, 1e-6f);
  EXPECT_EQ(rate_n_from_quats(a, b, 0.0f), Vec3<float>::Zero());
}

// The small-rotation polynomials (E-Att-2) are the library's rotation to double rounding on both
// sides of their 0.2 rad threshold, as matrix and as quaternion, and float follows.
TEST(Frames, SmallRotationsAreTheLibrarysRotation) {
  std::mt19937_64 rng(4);
  std::normal_distribution<double> g(0.0, 1.0);
  for (int i = 0; i < 400; ++i) {
    // 1e-9 to 3 rad, every decade and around the threshold.
    const double a = i % 40 == 0 ? 0.2 * (1.0 + 1e-12 * (i % 80 == 0 ? -1 : 1))
                                 : std::pow(10.0, -9.0 + 9.48 * (i % 37) / 36.0);
    const Vec3<double> axis = Vec3<double>(g(rng), g(rng), g(rng)).normalized();
    const Vec3<double> v = a * axis;
    const Eigen::AngleAxis<double> aa(a, axis);
    EXPECT_LT((exp_so3(v) - aa.toRotationMatrix()).cwiseAbs().maxCoeff(), 1e-15) << a;
    const Quat<double> q = quat_exp(v);
    EXPECT_LT((q.coeffs() - Quat<double>(aa).coeffs()).cwiseAbs().maxCoeff(), 1e-15) << a;
    EXPECT_LT(std::abs(q.norm() - 1.0), 1e-15) << a;
    // sin(a)/a and (1 - cos a)/a^2 keep their relative digits where the library's forms lose them.
    const RotationCoefficients<double> c = rotation_coefficients(a * a);
    EXPECT_NEAR(c.cos, std::cos(a), 1e-15) << a;
    EXPECT_NEAR(c.sinc, std::sin(a) / a, 1e-15) << a;
    if (a > 1e-3) {
      EXPECT_NEAR(c.vers, 2.0 * std::pow(std::sin(0.5 * a), 2) / (a * a), 1e-15) << a;
    }
    if (a < 1e-6) {
      EXPECT_NEAR(c.vers, 0.5 - a * a / 24.0, 1e-16) << a;  // where 1 - cos a has no digits
    }
    const Mat3<float> rf = exp_so3(Vec3<float>(v.cast<float>()));
    EXPECT_LT((rf.cast<double>() - aa.toRotationMatrix()).cwiseAbs().maxCoeff(), 3e-7) << a;
  }
  const Vec3<double> zero = Vec3<double>::Zero();
  EXPECT_EQ(exp_so3(zero), Mat3<double>::Identity());
  EXPECT_EQ(quat_exp(zero).coeffs(), Quat<double>::Identity().coeffs());
  // atan(t)/t to rounding below its threshold.
  for (double t : {0.0, 1e-8, 1e-4, 0.01, 0.03, 0.0499}) {
    const double want = t > 0 ? std::atan(t) / t : 1.0;
    EXPECT_NEAR(atan_over_t(t * t), want, 1e-15) << t;
  }
}

TEST(Frames, FloatInstantiation) {
  const Mat3<float> r = r_bn_from_li(LiEuler<float>{0.1f, 0.2f, 0.3f});
  const LiEuler<float> e = li_from_r_bn(r);
  EXPECT_NEAR(e.alpha, 0.1f, 1e-6f);
  EXPECT_NEAR(e.beta, 0.2f, 1e-6f);
  EXPECT_NEAR(e.gamma, 0.3f, 1e-6f);
}

}  // namespace
}  // namespace magvec::core
