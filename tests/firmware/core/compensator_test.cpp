#include "magvec/core/compensator.hpp"

#include <gtest/gtest.h>

#include <random>

#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

constexpr double kDeg = kPi<double> / 180.0;

SensorModel<double> paper_li_model() {
  LiParams<double> p;
  p.ks = {1.08, 1.02, 1.033};
  p.o_rad = Vec3<double>(1.7, 3.5, 2.1) * kDeg;
  p.kof = {4.9, 3.4, 0.7};
  p.rm_rad = Vec3<double>(5.7, 2.1, 3.5) * kDeg;
  return from_li(p);
}

TEST(Compensator, InvertsTheForwardModelExactly) {
  std::mt19937_64 rng(42);
  std::uniform_real_distribution<double> u(-180, 180), t(-85, 85);
  const SensorModel<double> truth = paper_li_model();
  const Vec3<double> h_n(-4053, 25022, 47374);  // ENU, |h| = 53729.2 nT
  const Compensator<double> comp(truth);
  for (int i = 0; i < 1000; ++i) {
    const Mat3<double> r_bn =
        r_bn_from_li(LiEuler<double>{u(rng) * kDeg, t(rng) * kDeg, u(rng) * kDeg});
    const Vec3<double> m = truth.predict_raw(r_bn, h_n);
    Compensated<double> c;
    ASSERT_TRUE(comp.compensate(m, &c));
    EXPECT_LT((Compensator<double>::to_nav(c.h_b, r_bn) - h_n).norm() / h_n.norm(), 1e-12);
    EXPECT_NEAR(c.intensity, h_n.norm(), 1e-9 * h_n.norm());
    EXPECT_LT((c.h_b - r_bn * h_n).norm() / h_n.norm(), 1e-12);
  }
}

TEST(Compensator, RejectsNonFiniteSamplesWithoutTouchingOutput) {
  const Compensator<double> comp(paper_li_model());
  Compensated<double> c;
  c.intensity = 123;
  EXPECT_FALSE(comp.compensate(Vec3<double>(1, std::numeric_limits<double>::quiet_NaN(), 3), &c));
  EXPECT_FALSE(comp.compensate(Vec3<double>(std::numeric_limits<double>::infinity(), 0, 0), &c));
  EXPECT_EQ(c.intensity, 123);
}

TEST(Compensator, FloatMatchesDoubleWithinFloatResolution) {
  const SensorModel<double> truth = paper_li_model();
  const Compensator<double> cd(truth);
  const Compensator<float> cf(truth.cast<float>());
  const Vec3<double> m(30000, -12000, 41000);
  Compensated<double> d;
  Compensated<float> f;
  ASSERT_TRUE(cd.compensate(m, &d));
  ASSERT_TRUE(cf.compensate(m.cast<float>(), &f));
  EXPECT_NEAR(static_cast<double>(f.intensity), d.intensity, 0.05);  // ~1e-6 relative of 53 uT
}

TEST(Compensator, PerSamplePathDoesNotAllocate) {
  const SensorModel<double> truth = paper_li_model();
  const Compensator<double> comp(truth);
  const Compensator<float> comp_f(truth.cast<float>());
  const Vec3<double> h_n(-4053, 25022, 47374);
  double sum = 0;
  Eigen::internal::set_is_malloc_allowed(false);
  const test::AllocationScope scope;
  for (int i = 0; i < 100000; ++i) {
    const double a = 0.001 * i;
    const Mat3<double> r_bn =
        r_bn_from_li(LiEuler<double>{a, 0.3 * std::sin(a), 0.2 * std::cos(a)});
    const Vec3<double> m = truth.predict_raw(r_bn, h_n);
    Compensated<double> c;
    Compensated<float> cf;
    if (comp.compensate(m, &c)) sum += Compensator<double>::to_nav(c.h_b, r_bn).x();
    if (comp_f.compensate(m.cast<float>(), &cf)) sum += static_cast<double>(cf.intensity);
  }
  const std::size_t allocations = scope.count();
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(allocations, 0u);
  EXPECT_TRUE(std::isfinite(sum));
}

TEST(AllocationCounter, SeesAnAllocation) {
  // Guards the zero-allocation tests against a counter that cannot count.
  const test::AllocationScope scope;
  auto* p = new int(3);
  EXPECT_EQ(*p, 3);
  delete p;
  EXPECT_GE(scope.count(), 1u);
}

}  // namespace
}  // namespace magvec::core
