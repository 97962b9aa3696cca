#include "magvec/core/sensor_model.hpp"

#include <gtest/gtest.h>

#include <random>

namespace magvec::core {
namespace {

constexpr double kDeg = kPi<double> / 180.0;
constexpr int kCases = 300;

LiParams<double> random_li(std::mt19937_64& rng) {
  std::uniform_real_distribution<double> ks(0.8, 1.2), ang(-6, 6), off(-2000, 2000), mis(-15, 15);
  LiParams<double> p;
  p.ks = {ks(rng), ks(rng), ks(rng)};
  p.o_rad = Vec3<double>(ang(rng), ang(rng), ang(rng)) * kDeg;
  p.kof = {off(rng), off(rng), off(rng)};
  p.rm_rad =
      Vec3<double>(mis(rng) * 10, mis(rng), mis(rng)) * kDeg;  // heading misalignment up to 150 deg
  return p;
}

SineParams<double> random_sine(std::mt19937_64& rng) {
  std::uniform_real_distribution<double> k(0.8, 1.2), small(-6, 6), az(-179, 179), g(0.3, 8),
      off(-500, 500);
  SineParams<double> p;
  p.k = {k(rng), k(rng), k(rng)};
  p.alpha_rad = small(rng) * kDeg;
  p.beta_rad = az(rng) * kDeg;
  p.gamma_rad = g(rng) * kDeg;
  p.b0 = {off(rng), off(rng), off(rng)};
  return p;
}

// Two models are physically the same when they give the same body-frame field for every reading.
void expect_same_body_field(const SensorModel<double>& a, const SensorModel<double>& b,
                            double tol) {
  const Mat3<double> ma = a.rm_matrix().transpose() * a.w;
  const Mat3<double> mb = b.rm_matrix().transpose() * b.w;
  EXPECT_LT((ma - mb).norm() / ma.norm(), tol);
  EXPECT_LT((a.o - b.o).norm(), tol * (1 + a.o.norm()));
}

TEST(SensorModel, LiRoundTripsToMachinePrecision) {
  std::mt19937_64 rng(2023);
  for (int i = 0; i < kCases; ++i) {
    const LiParams<double> p = random_li(rng);
    LiParams<double> back;
    ASSERT_EQ(to_li(from_li(p), &back), ConversionStatus::kOk);
    EXPECT_LT((back.ks - p.ks).cwiseAbs().maxCoeff(), 1e-12) << i;
    EXPECT_LT((back.o_rad - p.o_rad).cwiseAbs().maxCoeff(), 1e-12) << i;
    EXPECT_LT((back.kof - p.kof).cwiseAbs().maxCoeff(), 1e-12 * 2000) << i;
    EXPECT_LT((back.rm_rad - p.rm_rad).cwiseAbs().maxCoeff(), 1e-12) << i;
  }
}

TEST(SensorModel, LiDecompositionFollowsErrataNotPrintedShortcut) {
  // Paper setup: O = [1.7, 3.5, 2.1] deg, Ks = diag(1.08, 1.02, 1.033).
  LiParams<double> p;
  p.ks = {1.08, 1.02, 1.033};
  p.o_rad = Vec3<double>(1.7, 3.5, 2.1) * kDeg;
  const SensorModel<double> m = from_li(p);
  const Mat3<double> g = m.g();
  const Mat3<double> g_inv = g.inverse();
  for (int i = 0; i < 3; ++i) {
    EXPECT_NEAR(std::sqrt(g_inv(i, i)), p.ks(i), 1e-13);  // docs/equations.md E-Li-1
  }
  // The printed shortcut ks = 1/sqrt(G_ii) is off by 0.1-0.25 % here.
  const double shortcut_err_y = std::abs(1.0 / std::sqrt(g(1, 1)) - p.ks(1)) / p.ks(1);
  EXPECT_GT(shortcut_err_y, 1e-3);
  // Eq. (5) rows are unit vectors; Ks Ko in axis order (x, z, y) is lower triangular.
  const Mat3<double> ko = li_ko(p.o_rad);
  for (int i = 0; i < 3; ++i)
    EXPECT_NEAR(ko.row(i).norm(), 1, 1e-15);
  EXPECT_EQ(ko(0, 1), 0);
  EXPECT_EQ(ko(0, 2), 0);
  EXPECT_EQ(ko(2, 1), 0);
  EXPECT_NEAR(ko(2, 0), 0.0297, 5e-5);  // printed Ko(3,1)
  EXPECT_NEAR(ko(2, 2), 0.9996, 5e-5);  // printed Ko(3,3)
}

TEST(SensorModel, GeRoundTripsAndIsPhysicallyEquivalent) {
  std::mt19937_64 rng(2017);
  std::uniform_real_distribution<double> diag(0.7, 1.4), off(-0.05, 0.05), b(-20000, 20000);
  for (int i = 0; i < kCases; ++i) {
    GeParams<double> p;
    Mat3<double> c;
    c << diag(rng), off(rng), off(rng), off(rng), diag(rng), off(rng), off(rng), off(rng),
        diag(rng);
    p.c_inv = c.inverse();
    p.b = {b(rng), b(rng), b(rng)};
    const GeParams<double> back = to_ge(from_ge(p));
    EXPECT_LT((back.c_inv - p.c_inv).cwiseAbs().maxCoeff(), 1e-12);
    EXPECT_LT((back.b - p.b).cwiseAbs().maxCoeff(), 1e-12 * 2e4);

    // Any model (with misalignment) -> Ge -> model keeps the body-frame output.
    const SensorModel<double> li = from_li(random_li(rng));
    expect_same_body_field(li, from_ge(to_ge(li)), 1e-12);
    // And a Ge model -> Li structure keeps it as well (the rotation moves into Rm).
    SensorModel<double> canon;
    ASSERT_EQ(canonicalize_li(from_ge(p), &canon), ConversionStatus::kOk);
    expect_same_body_field(from_ge(p), canon, 1e-12);
  }
}

TEST(SensorModel, SineRoundTripsToMachinePrecision) {
  std::mt19937_64 rng(1);
  for (int i = 0; i < kCases; ++i) {
    const SineParams<double> p = random_sine(rng);
    SineParams<double> back;
    Mat3<double> q;
    ASSERT_EQ(to_sine(from_sine(p), &back, &q), ConversionStatus::kOk);
    EXPECT_LT((back.k - p.k).cwiseAbs().maxCoeff(), 1e-12) << i;
    EXPECT_NEAR(back.alpha_rad, p.alpha_rad, 1e-12) << i;
    EXPECT_NEAR(wrap_pi(back.beta_rad - p.beta_rad), 0, 1e-10) << i;  // gamma >= 0.3 deg
    EXPECT_NEAR(back.gamma_rad, p.gamma_rad, 1e-12) << i;
    EXPECT_LT((back.b0 - p.b0).cwiseAbs().maxCoeff(), 1e-12 * 500) << i;
    EXPECT_LT((q - Mat3<double>::Identity()).norm(), 1e-12);
  }
}

TEST(SensorModel, SinePaperParametersMatchItsMatrix) {
  SineParams<double> p;
  p.k = {0.909, 1.146, 1.103};
  p.alpha_rad = 1.35 * kDeg;
  p.beta_rad = 32.7 * kDeg;
  p.gamma_rad = 1.07 * kDeg;
  const Mat3<double> k = sine_k(p);
  EXPECT_NEAR(k(1, 0), 1.146 * std::sin(1.35 * kDeg), 1e-15);
  EXPECT_NEAR(k(2, 1), 1.103 * std::sin(32.7 * kDeg) * std::sin(1.07 * kDeg), 1e-15);
  EXPECT_EQ(k(0, 1), 0);
  EXPECT_EQ(k(1, 2), 0);
}

TEST(SensorModel, RefusesSingularAndReflectedModels) {
  SensorModel<double> m;
  m.w = Mat3<double>::Zero();
  LiParams<double> li;
  SineParams<double> sine;
  EXPECT_NE(to_li(m, &li), ConversionStatus::kOk);
  EXPECT_NE(to_sine(m, &sine), ConversionStatus::kOk);
  m.w = Mat3<double>::Identity();
  m.w(2, 2) = -1;  // a reflection: no rotation reproduces it
  EXPECT_EQ(to_li(m, &li), ConversionStatus::kReflection);
  EXPECT_EQ(to_sine(m, &sine), ConversionStatus::kReflection);
  m.w(2, 2) = std::numeric_limits<double>::quiet_NaN();
  EXPECT_EQ(to_li(m, &li), ConversionStatus::kNotPositiveDefinite);
}

TEST(SensorModel, FloatConversionsAgreeWithDouble) {
  std::mt19937_64 rng(5);
  const LiParams<double> p = random_li(rng);
  LiParams<float> pf;
  pf.ks = p.ks.cast<float>();
  pf.o_rad = p.o_rad.cast<float>();
  pf.kof = p.kof.cast<float>();
  pf.rm_rad = p.rm_rad.cast<float>();
  LiParams<float> back;
  ASSERT_EQ(to_li(from_li(pf), &back), ConversionStatus::kOk);
  EXPECT_LT((back.ks - pf.ks).cwiseAbs().maxCoeff(), 1e-5f);
  EXPECT_LT((back.rm_rad - pf.rm_rad).cwiseAbs().maxCoeff(), 1e-4f);
}

}  // namespace
}  // namespace magvec::core
