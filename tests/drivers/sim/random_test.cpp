// Tests of the portable PRNG and Gaussian generator (drivers/sim/random.hpp).
#include "magvec/drivers/sim/random.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>

namespace magvec::drivers::sim {
namespace {

TEST(SplitMix64, MatchesReferenceOutput) {
  // Reference values of splitmix64 with seed 1234567 (Vigna's splitmix64.c).
  SplitMix64 sm(1234567);
  EXPECT_EQ(sm.next(), 6457827717110365317ULL);
  EXPECT_EQ(sm.next(), 3203168211198807973ULL);
  EXPECT_EQ(sm.next(), 9817491932198370423ULL);
}

TEST(Xoshiro256, IsDeterministicAndSeedDependent) {
  Xoshiro256 a(42), b(42), c(43);
  bool any_diff = false;
  for (int i = 0; i < 1000; ++i) {
    const std::uint64_t x = a.next();
    EXPECT_EQ(x, b.next());
    any_diff = any_diff || (x != c.next());
  }
  EXPECT_TRUE(any_diff);
}

TEST(Xoshiro256, UniformHasExpectedMoments) {
  Xoshiro256 r(7);
  constexpr int kN = 100000;
  double sum = 0.0, sum2 = 0.0, lo = 1.0, hi = 0.0;
  for (int i = 0; i < kN; ++i) {
    const double u = r.uniform();
    ASSERT_GE(u, 0.0);
    ASSERT_LT(u, 1.0);
    sum += u;
    sum2 += u * u;
    lo = std::min(lo, u);
    hi = std::max(hi, u);
  }
  const double mean = sum / kN, var = sum2 / kN - mean * mean;
  // SD of the mean is sqrt(1/12/N) = 0.00091; 5 sigma bounds.
  EXPECT_NEAR(mean, 0.5, 0.0046);
  EXPECT_NEAR(var, 1.0 / 12.0, 0.0015);
  EXPECT_LT(lo, 1e-3);
  EXPECT_GT(hi, 1.0 - 1e-3);
}

TEST(Gaussian, HasStandardNormalStatistics) {
  Gaussian g(2024);
  constexpr int kN = 100000;
  double sum = 0.0, sum2 = 0.0, sum3 = 0.0, sum4 = 0.0;
  int within1 = 0, within2 = 0;
  for (int i = 0; i < kN; ++i) {
    const double x = g.next();
    ASSERT_TRUE(std::isfinite(x));
    sum += x;
    sum2 += x * x;
    sum3 += x * x * x;
    sum4 += x * x * x * x;
    within1 += std::abs(x) < 1.0 ? 1 : 0;
    within2 += std::abs(x) < 2.0 ? 1 : 0;
  }
  const double mean = sum / kN;
  const double sd = std::sqrt(sum2 / kN - mean * mean);
  // 5-sigma bounds: SE(mean) = 1/sqrt(N) = 0.0032, SE(sd) = 1/sqrt(2N) = 0.0022,
  // SE(skew) = sqrt(6/N) = 0.0077, SE(kurtosis) = sqrt(24/N) = 0.015.
  EXPECT_NEAR(mean, 0.0, 0.016);
  EXPECT_NEAR(sd, 1.0, 0.011);
  EXPECT_NEAR(sum3 / kN, 0.0, 0.04);
  EXPECT_NEAR(sum4 / kN, 3.0, 0.08);
  // P(|x|<1) = 0.682689, P(|x|<2) = 0.954500; binomial SE 0.0015 and 0.00066.
  EXPECT_NEAR(within1 / static_cast<double>(kN), 0.682689, 0.0075);
  EXPECT_NEAR(within2 / static_cast<double>(kN), 0.954500, 0.0033);
}

TEST(Gaussian, SameSeedSameSequence) {
  Gaussian a(5), b(5), c(6);
  bool any_diff = false;
  for (int i = 0; i < 1001; ++i) {
    const double x = a.next();
    EXPECT_EQ(x, b.next());
    any_diff = any_diff || x != c.next();
  }
  EXPECT_TRUE(any_diff);
}

}  // namespace
}  // namespace magvec::drivers::sim
