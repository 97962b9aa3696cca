#include "magvec/core/attitude_buffer.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

#include "magvec/core/frames.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using Q = Quat<double>;
Q about_z(double angle) {
  return Q(Eigen::AngleAxis<double>(angle, Vec3<double>::UnitZ()));
}
Q about(const Vec3<double>& axis, double angle) {
  return Q(Eigen::AngleAxis<double>(angle, axis.normalized()));
}
double angle_between(const Q& a, const Q& b) {
  return a.angularDistance(b);
}

TEST(AttitudeBuffer, SlerpIsExactForConstantRateAboutAFixedAxis) {
  const Vec3<double> axis(0.3, -0.5, 0.8);
  AttitudeBuffer<double, 16> buf;
  ASSERT_EQ(buf.insert(1000, about(axis, 0.2)), AttitudeInsert::kAppended);
  ASSERT_EQ(buf.insert(11000, about(axis, 0.7)), AttitudeInsert::kAppended);
  for (int k = 0; k <= 10; ++k) {
    const std::uint64_t t = 1000 + 1000 * static_cast<std::uint64_t>(k);
    const AttitudeQuery<double> r = buf.at(t);
    ASSERT_EQ(r.status, AttitudeQueryStatus::kInterpolated);
    EXPECT_LT(angle_between(r.q_nb, about(axis, 0.2 + 0.05 * k)), 1e-14) << k;
    EXPECT_EQ(r.gap_us, (k == 0 || k == 10) ? 0u : 10000u);  // exactly on a sample: no gap
  }
  // Shortest arc even when the stored quaternions are on opposite hemispheres.
  AttitudeBuffer<double, 4> b2;
  b2.insert(0, about_z(3.0));
  Q far = about_z(-3.0);  // 0.283 rad away the short way round
  far.coeffs() = -far.coeffs();
  b2.insert(100, far);
  EXPECT_LT(angle_between(b2.at(50).q_nb, about_z(core::kPi<double>)), 1e-12);
}

// The same for the small steps between INS epochs, where the slerp takes the polynomials of
// E-Att-2 instead of atan2, sin and cos: a microradian to 0.3 rad, inside the interval and
// extrapolated to three times it, in double and float.
TEST(AttitudeBuffer, SlerpIsExactForSmallStepsAndExtrapolation) {
  std::mt19937_64 rng(5);
  std::normal_distribution<double> g(0.0, 1.0);
  for (int i = 0; i < 300; ++i) {
    const Vec3<double> axis(g(rng), g(rng), g(rng));
    const double a0 = g(rng);
    const double step = std::pow(10.0, -6.0 + 5.5 * (i % 30) / 29.0);
    const Q q0 = about(axis, a0), q1 = about(axis, a0 + step);
    for (double f : {0.0, 0.25, 0.5, 0.9, 1.0, 2.0, 3.0}) {
      const Q want = about(axis, a0 + f * step);
      EXPECT_LT(angle_between(slerp_unit(q0, q1, f), want), 2e-15) << step << " " << f;
      const Quat<float> got_f = slerp_unit(Quat<float>(q0.cast<float>()),
                                           Quat<float>(q1.cast<float>()), static_cast<float>(f));
      EXPECT_LT(angle_between(got_f.cast<double>(), want), 1e-6) << step << " " << f;
    }
  }
}

TEST(AttitudeBuffer, FloatMatchesDouble) {
  AttitudeBuffer<float, 8> bf;
  bf.insert(0, Quat<float>(Eigen::AngleAxis<float>(0.1f, Vec3<float>::UnitX())));
  bf.insert(10000, Quat<float>(Eigen::AngleAxis<float>(0.3f, Vec3<float>::UnitX())));
  const auto r = bf.at(2500);
  ASSERT_EQ(r.status, AttitudeQueryStatus::kInterpolated);
  EXPECT_NEAR(
      r.q_nb.angularDistance(Quat<float>(Eigen::AngleAxis<float>(0.15f, Vec3<float>::UnitX()))),
      0.0f, 2e-6f);
}

TEST(AttitudeBuffer, StalenessGapAndLimits) {
  AttitudeBufferConfig cfg;
  cfg.max_gap_us = 30000;
  cfg.max_extrapolation_us = 15000;
  AttitudeBuffer<double, 8> buf(cfg);
  EXPECT_EQ(buf.at(5).status, AttitudeQueryStatus::kEmpty);
  buf.insert(100000, about_z(0.0));
  buf.insert(110000, about_z(0.01));
  buf.insert(170000, about_z(0.07));  // 60 ms dropout before this one
  EXPECT_EQ(buf.at(99999).status, AttitudeQueryStatus::kTooOld);
  EXPECT_EQ(buf.at(105000).status, AttitudeQueryStatus::kInterpolated);
  const auto gap = buf.at(140000);
  EXPECT_EQ(gap.status, AttitudeQueryStatus::kGap);
  EXPECT_EQ(gap.gap_us, 60000u);
  EXPECT_FALSE(attitude_usable(gap.status));
  EXPECT_EQ(buf.at(170000).status, AttitudeQueryStatus::kInterpolated);  // exactly on a sample
  const auto ex = buf.at(185000);
  EXPECT_EQ(ex.status, AttitudeQueryStatus::kExtrapolated);
  EXPECT_LT(angle_between(ex.q_nb, about_z(0.07)), 1e-15);  // hold mode
  EXPECT_EQ(buf.at(185001).status, AttitudeQueryStatus::kTooNew);
}

TEST(AttitudeBuffer, ConstantRateExtrapolation) {
  AttitudeBufferConfig cfg;
  cfg.extrapolation = ExtrapolationMode::kConstantRate;
  cfg.max_extrapolation_us = 20000;
  AttitudeBuffer<double, 8> buf(cfg);
  buf.insert(0, about_z(0.10));
  buf.insert(10000, about_z(0.12));
  const auto r = buf.at(15000);
  ASSERT_EQ(r.status, AttitudeQueryStatus::kExtrapolated);
  EXPECT_LT(angle_between(r.q_nb, about_z(0.13)), 1e-14);
}

TEST(AttitudeBuffer, OutOfOrderDuplicatesInvalidAndClockReset) {
  AttitudeBuffer<double, 8> buf;
  EXPECT_EQ(buf.insert(1000, about_z(0.1)), AttitudeInsert::kAppended);
  EXPECT_EQ(buf.insert(3000, about_z(0.3)), AttitudeInsert::kAppended);
  EXPECT_EQ(buf.insert(2000, about_z(0.2)), AttitudeInsert::kReordered);
  EXPECT_EQ(buf.insert(2000, about_z(0.9)), AttitudeInsert::kDuplicate);  // first one wins
  EXPECT_EQ(buf.insert(500, about_z(0.05)), AttitudeInsert::kReordered);  // not full: kept
  EXPECT_EQ(buf.size(), 4u);
  EXPECT_EQ(buf.oldest_us(), 500u);
  EXPECT_LT(angle_between(buf.at(2000).q_nb, about_z(0.2)), 1e-15);
  EXPECT_LT(angle_between(buf.at(2500).q_nb, about_z(0.25)), 1e-14);
  Q bad(2, 0, 0, 0);
  EXPECT_EQ(buf.insert(4000, bad), AttitudeInsert::kInvalid);
  EXPECT_EQ(buf.insert(4000, Q(std::nan(""), 0, 0, 0)), AttitudeInsert::kInvalid);
  EXPECT_EQ(buf.counters().reordered, 2u);
  EXPECT_EQ(buf.counters().duplicates, 1u);
  EXPECT_EQ(buf.counters().invalid, 2u);
  EXPECT_EQ(buf.size(), 4u);
  // A 5 s backwards jump (INS reboot / clock reset) restarts the buffer.
  EXPECT_EQ(buf.insert(1'000'000'000, about_z(0.0)), AttitudeInsert::kAppended);
  EXPECT_EQ(buf.insert(995'000'000, about_z(0.5)), AttitudeInsert::kClockReset);
  EXPECT_EQ(buf.size(), 1u);
  EXPECT_EQ(buf.counters().clock_resets, 1u);
}

TEST(AttitudeBuffer, RingWrapAroundKeepsNewestAndOrder) {
  AttitudeBufferConfig cfg;
  cfg.max_gap_us = 20000;
  AttitudeBuffer<double, 5> buf(cfg);
  for (int i = 0; i < 23; ++i) {
    buf.insert(10000u * static_cast<std::uint64_t>(i), about_z(0.01 * i));
  }
  EXPECT_EQ(buf.size(), 5u);
  EXPECT_EQ(buf.oldest_us(), 180000u);
  EXPECT_EQ(buf.newest_us(), 220000u);
  EXPECT_EQ(buf.counters().overwritten, 18u);
  EXPECT_EQ(buf.at(170000).status, AttitudeQueryStatus::kTooOld);
  for (int k = 0; k <= 40; ++k) {
    const std::uint64_t t = 180000 + 1000 * static_cast<std::uint64_t>(k);
    const auto r = buf.at(t);
    ASSERT_EQ(r.status, AttitudeQueryStatus::kInterpolated);
    EXPECT_LT(angle_between(r.q_nb, about_z(0.18 + 0.001 * k)), 1e-13) << k;
  }
  // Full ring: an out-of-order sample older than everything retained is rejected...
  EXPECT_EQ(buf.insert(170000, about_z(0.17)), AttitudeInsert::kTooOld);
  // ...one inside the span is inserted and the oldest retained one is dropped.
  EXPECT_EQ(buf.insert(205000, about_z(0.205)), AttitudeInsert::kReordered);
  EXPECT_EQ(buf.oldest_us(), 190000u);
  EXPECT_EQ(buf.size(), 5u);
  EXPECT_LT(angle_between(buf.at(205000).q_nb, about_z(0.205)), 1e-15);
  EXPECT_LT(angle_between(buf.at(202500).q_nb, about_z(0.2025)), 1e-13);
  EXPECT_LT(angle_between(buf.at(215000).q_nb, about_z(0.215)), 1e-13);
}

TEST(AttitudeBuffer, NoHeapAllocation) {
  AttitudeBuffer<double, 64> buf;
  magvec::test::AllocationScope scope;
  Eigen::internal::set_is_malloc_allowed(false);
  for (int i = 0; i < 1000; ++i) {
    buf.insert(10000u * static_cast<std::uint64_t>(i), about_z(0.001 * i));
    const auto r = buf.at(10000u * static_cast<std::uint64_t>(i) - 5000u);
    if (i > 0) {
      ASSERT_EQ(r.status, AttitudeQueryStatus::kInterpolated);
    }
  }
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(scope.count(), 0u);
}

}  // namespace
}  // namespace magvec::core
