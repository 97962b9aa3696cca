#include "magvec/core/sine_fit.hpp"

#include <gtest/gtest.h>

#include <cstdio>
#include <random>

#include "li_setup.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using test_setup::kNaN;

using test_setup::kDeg;
using test_setup::sd;

// Jia et al. 2019 section 3.1 / docs/equations.md E-Sine-6.
SineParams<double> paper_sine() {
  SineParams<double> p;
  p.alpha_rad = 1.35 * kDeg;
  p.beta_rad = 32.7 * kDeg;
  p.gamma_rad = 1.07 * kDeg;
  p.k = {0.909, 1.146, 1.103};
  p.b0 = {143, 97.4, 123.7};
  return p;
}
constexpr double kField = 50000, kIncl = 43 * kDeg;

Vec3<double> field_enu(double decl) {
  const double bh = kField * std::cos(kIncl);
  return {bh * std::sin(decl), bh * std::cos(decl), -kField * std::sin(kIncl)};
}

// Mounting of the XZ sweep: body components of Up.
Mat3<double> xz_mount(const SineParams<double>& p, SineFixture fixture) {
  if (fixture == SineFixture::kHousingY) return rot_x(kPi<double> / 2);  // housing +y up
  const Vec3<double> zm(std::cos(p.beta_rad) * std::sin(p.gamma_rad),
                        std::sin(p.beta_rad) * std::sin(p.gamma_rad), std::cos(p.gamma_rad));
  const Vec3<double> n = Vec3<double>::UnitX().cross(zm).normalized();
  Mat3<double> r0;
  r0 << Vec3<double>::UnitX(), n.cross(Vec3<double>::UnitX()), n;
  return r0;
}

void sweep(const SineParams<double>& p, SineFixture fixture, double sigma, double dir,
           std::mt19937_64& rng, SineSweep<double>* xy, SineSweep<double>* xz) {
  const SensorModel<double> m = from_sine(p);
  const Vec3<double> h = field_enu(0.4);
  std::normal_distribution<double> n(0, sigma);
  const Mat3<double> mount = xz_mount(p, fixture);
  for (int i = 0; i < 36; ++i) {
    const double th = dir * i * 10.0 * kDeg;
    const Vec3<double> noise1(n(rng), n(rng), n(rng)), noise2(n(rng), n(rng), n(rng));
    xy->add(th, m.predict_raw(rot_z(th), h) + noise1);
    xz->add(th, m.predict_raw(Mat3<double>(mount * rot_z(th)), h) + noise2);
  }
}

TEST(SineFit, NoiseFreeRecoveryBothFixturesBothDirections) {
  const SineParams<double> t = paper_sine();
  for (SineFixture fx : {SineFixture::kHousingY, SineFixture::kPlaneNormal}) {
    for (double dir : {1.0, -1.0}) {
      std::mt19937_64 rng(1);
      SineSweep<double> xy, xz;
      sweep(t, fx, 0, dir, rng, &xy, &xz);
      SineFitOptions<double> opt;
      opt.xz_fixture = fx;
      opt.field_nT = kField;
      const SineSolution<double> s = solve_sine(xy, xz, opt);
      ASSERT_EQ(s.status, SineStatus::kOk);
      EXPECT_NEAR(s.params.alpha_rad, t.alpha_rad, 1e-9);
      EXPECT_NEAR(s.params.beta_rad, t.beta_rad, 1e-9);
      EXPECT_NEAR(s.params.gamma_rad, t.gamma_rad, 1e-9);
      EXPECT_LT(((s.params.k - t.k).array() / t.k.array()).abs().maxCoeff(), 1e-9);
      EXPECT_LT((s.params.b0 - t.b0).cwiseAbs().maxCoeff(), 1e-9 * kField);
      EXPECT_NEAR(s.inclination_rad, kIncl, 1e-9);
    }
  }
}

TEST(SineFit, XyOffsetOfZIsNotTheZOffset) {
  // docs/equations.md E-Sine-1: D_z of the XY sweep carries kz cos(gamma) B_vertical (about -37
  // uT).
  std::mt19937_64 rng(2);
  SineSweep<double> xy, xz;
  sweep(paper_sine(), SineFixture::kHousingY, 0, 1, rng, &xy, &xz);
  EXPECT_NEAR(xy.fit().offset(2), -37.5e3, 1e3);
  // docs/equations.md E-Sine-4: with the housing-y fixture D'_z is off B0z by kz sin(b) sin(g)
  // B_vertical.
  EXPECT_NEAR(xz.fit().offset(2) - 123.7, -379, 2);
}

TEST(SineFit, MonteCarloAlphaScatterMatchesErrata) {
  const SineParams<double> t = paper_sine();
  const double sigmas[2] = {5, 40}, expected[2] = {0.0025, 0.020};
  for (int c = 0; c < 2; ++c) {
    std::vector<double> alpha, beta;
    for (int seed = 0; seed < 400; ++seed) {
      std::mt19937_64 rng(7000 + static_cast<unsigned>(seed));
      SineSweep<double> xy, xz;
      sweep(t, SineFixture::kHousingY, sigmas[c], 1, rng, &xy, &xz);
      SineFitOptions<double> opt;
      opt.field_nT = kField;
      const SineSolution<double> s = solve_sine(xy, xz, opt);
      ASSERT_EQ(s.status, SineStatus::kOk);
      alpha.push_back((s.params.alpha_rad - t.alpha_rad) / kDeg);
      beta.push_back((s.params.beta_rad - t.beta_rad) / kDeg);
    }
    std::printf("noise %.0f nT: alpha SD %.5f deg, beta SD %.4f deg\n", sigmas[c], sd(alpha),
                sd(beta));
    EXPECT_LT(sd(alpha), 1.3 * expected[c]);
    EXPECT_GT(sd(alpha), expected[c] / 1.3);
  }
}

TEST(SineFit, BadInputIsSkippedAndDegenerateSweepRefused) {
  SineSweep<double> xy, xz;
  EXPECT_FALSE(xy.add(kNaN, Vec3<double>(1, 2, 3)));
  EXPECT_FALSE(xy.add(0.1, Vec3<double>(1, kNaN, 3)));
  EXPECT_EQ(xy.skipped(), 2U);
  for (int i = 0; i < 10; ++i) {
    xy.add(0.5, Vec3<double>(1, 2, 3));  // one angle only
    xz.add(0.1 * i, Vec3<double>(1, 2, 3));
  }
  SineFitOptions<double> opt;
  opt.field_nT = kField;
  EXPECT_EQ(solve_sine(xy, xz, opt).status, SineStatus::kDegenerateSweep);
}

TEST(SineFit, DoesNotAllocate) {
  std::mt19937_64 rng(3);
  SineSweep<double> xy, xz;
  SineFitOptions<double> opt;
  opt.field_nT = kField;
  magvec::test::AllocationScope scope;
  Eigen::internal::set_is_malloc_allowed(false);
  sweep(paper_sine(), SineFixture::kHousingY, 5, 1, rng, &xy, &xz);
  const SineSolution<double> s = solve_sine(xy, xz, opt);
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(scope.count(), 0U);
  EXPECT_EQ(s.status, SineStatus::kOk);
}

}  // namespace
}  // namespace magvec::core
