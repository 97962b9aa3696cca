#include "magvec/core/ellipsoid_fit.hpp"

#include <gtest/gtest.h>

#include <random>

#include "li_setup.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using namespace test_setup;

TEST(EllipsoidFit, NoiseFreeRecoversGAndOffsetWithConstantField) {
  std::mt19937_64 rng(11);
  const LiParams<double> t = paper_li();
  const SensorModel<double> m = from_li(t);
  EllipsoidFit<double> fit;
  for (const Sample& s : simulate(m, paper_h_n(), random_attitudes(60, rng), 0, 0, rng)) {
    ASSERT_TRUE(fit.add(s.m, s.f));
  }
  const EllipsoidSolution<double> e = fit.solve();
  ASSERT_EQ(e.status, EllipsoidStatus::kOk);
  EXPECT_LT((e.g - m.g()).norm() / m.g().norm(), 1e-9);
  EXPECT_LT((e.o - t.kof).norm(), 1e-9 * paper_h_n().norm());
  EXPECT_LT((e.li.ks - t.ks).cwiseAbs().maxCoeff(), 1e-9);
  EXPECT_LT((e.li.o_rad - t.o_rad).cwiseAbs().maxCoeff(), 1e-9);
}

TEST(EllipsoidFit, PerSampleFieldEntersTheConstraintExactly) {
  // The total field drifts by +-300 nT during the calibration; each sample carries its own F.
  std::mt19937_64 rng(12);
  const LiParams<double> t = paper_li();
  const SensorModel<double> m = from_li(t);
  EllipsoidFit<double> fit;
  std::uniform_real_distribution<double> drift(0.994, 1.006);
  for (int i = 0; i < 80; ++i) {
    const Vec3<double> h = paper_h_n() * drift(rng);
    ASSERT_TRUE(fit.add(m.predict_raw(random_rotation(rng), h), h.norm()));
  }
  const EllipsoidSolution<double> e = fit.solve();
  ASSERT_EQ(e.status, EllipsoidStatus::kOk);
  EXPECT_LT((e.g - m.g()).norm() / m.g().norm(), 1e-9);
  EXPECT_LT((e.o - t.kof).norm(), 1e-9 * paper_h_n().norm());
}

TEST(EllipsoidFit, RefusesNonEllipsoidAndBadInput) {
  EllipsoidFit<double> fit;
  EXPECT_FALSE(fit.add(Vec3<double>(kNaN, 0, 0), 50000));
  EXPECT_FALSE(fit.add(Vec3<double>(1, 0, 0), -1));
  EXPECT_EQ(fit.count(), 0U);
  EXPECT_EQ(fit.solve().status, EllipsoidStatus::kTooFewSamples);
  // Points on a hyperboloid x^2 + y^2 - z^2 = F^2 are not an ellipsoid.
  std::mt19937_64 rng(13);
  std::uniform_real_distribution<double> u(-1, 1);
  for (int i = 0; i < 50; ++i) {
    const double a = u(rng) * kPi<double>, zz = u(rng) * 30000;
    const double rr = std::sqrt(50000.0 * 50000.0 + zz * zz);
    ASSERT_TRUE(fit.add(Vec3<double>(rr * std::cos(a), rr * std::sin(a), zz), 50000));
  }
  const EllipsoidStatus st = fit.solve().status;
  EXPECT_TRUE(st == EllipsoidStatus::kNotAnEllipsoid) << static_cast<int>(st);
}

TEST(EllipsoidFit, GeometricRefinementKeepsExactSolutionAndImprovesNoisyOne) {
  std::mt19937_64 rng(14);
  const LiParams<double> t = paper_li();
  const SensorModel<double> m = from_li(t);
  SampleStore<double, 256> st;
  EllipsoidFit<double> fit;
  for (const Sample& s : simulate(m, paper_h_n(), random_attitudes(200, rng), 0, 0, rng)) {
    st.push(s.m, s.f, nullptr);
    fit.add(s.m, s.f);
  }
  const EllipsoidSolution<double> g =
      refine_ellipsoid_geometric(st, fit.normalization(), fit.solve());
  ASSERT_EQ(g.status, EllipsoidStatus::kOk);
  EXPECT_LT((g.g - m.g()).norm() / m.g().norm(), 1e-9);
  EXPECT_LT((g.o - t.kof).norm(), 1e-9 * paper_h_n().norm());
  EXPECT_LT(g.rms, 1e-6);
}

TEST(EllipsoidFit, FloatMatchesDoubleWithinTheNoise) {
  std::mt19937_64 rng(15);
  const LiParams<double> t = paper_li();
  EllipsoidFit<float> ff;
  EllipsoidFit<double> fd;
  for (const Sample& s :
       simulate(from_li(t), paper_h_n(), random_attitudes(300, rng), 0.3, 0, rng)) {
    ff.add(s.m.cast<float>(), static_cast<float>(s.f));
    fd.add(s.m, s.f);
  }
  const auto ef = ff.solve();
  const auto ed = fd.solve();
  ASSERT_EQ(ef.status, EllipsoidStatus::kOk);
  ASSERT_EQ(ed.status, EllipsoidStatus::kOk);
  EXPECT_LT((ef.o.cast<double>() - ed.o).norm(), 2.0);  // nT; the noise floor is ~0.1 nT per axis
  EXPECT_LT((ef.li.ks.cast<double>() - ed.li.ks).cwiseAbs().maxCoeff(), 5e-5);
}

TEST(EllipsoidFit, AccumulateAndSolveDoNotAllocate) {
  std::mt19937_64 rng(16);
  const auto data =
      simulate(from_li(paper_li()), paper_h_n(), random_attitudes(60, rng), 0.3, 0, rng);
  EllipsoidFit<double> fit;
  magvec::test::AllocationScope scope;
  Eigen::internal::set_is_malloc_allowed(false);
  for (const Sample& s : data)
    fit.add(s.m, s.f);
  const EllipsoidSolution<double> e = fit.solve();
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(scope.count(), 0U);
  EXPECT_EQ(e.status, EllipsoidStatus::kOk);
}

}  // namespace
}  // namespace magvec::core
