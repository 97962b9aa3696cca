// Tests of firmware/app portable_math: accuracy against the host C library (glibc, whose double
// sin/cos/atan/atan2/asin/acos/log/exp are within 1 ulp), C99 Annex F special values, and the
// identities the simulator relies on. The bit-for-bit agreement with the M7 image is checked by
// tests/mcu (mcu_m7_double_vs_host).
#include "magvec/app/portable_math.hpp"

#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <limits>
#include <random>

namespace pm = magvec::app::portable;

namespace {

// Distance in units in the last place (ordered bit patterns; +0 and -0 are 0 apart).
std::uint64_t ulp_distance(double a, double b) {
  auto ordered = [](double v) {
    const auto u = std::bit_cast<std::int64_t>(v);
    return u < 0 ? std::numeric_limits<std::int64_t>::min() - u : u;
  };
  const std::int64_t ia = ordered(a), ib = ordered(b);
  return ia > ib ? static_cast<std::uint64_t>(ia - ib) : static_cast<std::uint64_t>(ib - ia);
}

constexpr std::uint64_t kMaxUlp = 2;  // vs glibc (itself within 1 ulp of the exact result)
constexpr int kDraws = 200000;

template <typename F, typename G>
void check_unary(F ours, G ref, double lo, double hi, std::uint32_t seed, const char* name) {
  std::mt19937_64 rng(seed);
  std::uniform_real_distribution<double> u(lo, hi);
  std::uint64_t worst = 0;
  double worst_x = 0;
  for (int i = 0; i < kDraws; ++i) {
    const double x = u(rng);
    const std::uint64_t d = ulp_distance(ours(x), ref(x));
    if (d > worst) {
      worst = d;
      worst_x = x;
    }
  }
  EXPECT_LE(worst, kMaxUlp) << name << " at x = " << worst_x;
}

// Log-uniform magnitudes in [2^emin, 2^emax] with both signs.
double log_uniform(std::mt19937_64& rng, int emin, int emax) {
  std::uniform_real_distribution<double> e(emin, emax);
  std::bernoulli_distribution sign(0.5);
  const double v = std::exp2(e(rng));
  return sign(rng) ? -v : v;
}

}  // namespace

TEST(PortableMath, SinCosWithinTwoUlpOfGlibc) {
  check_unary([](double x) { return pm::sin(x); }, [](double x) { return std::sin(x); }, -10.0,
              10.0, 1, "sin");
  check_unary([](double x) { return pm::cos(x); }, [](double x) { return std::cos(x); }, -10.0,
              10.0, 2, "cos");
  check_unary([](double x) { return pm::sin(x); }, [](double x) { return std::sin(x); }, -1e5, 1e5,
              3, "sin large");
  check_unary([](double x) { return pm::cos(x); }, [](double x) { return std::cos(x); }, -1e5, 1e5,
              4, "cos large");
  check_unary([](double x) { return pm::sin(x); }, [](double x) { return std::sin(x); }, -1e-6,
              1e-6, 5, "sin small");
  double s = 0, c = 0;
  pm::sincos(0.7, &s, &c);
  EXPECT_EQ(s, pm::sin(0.7));
  EXPECT_EQ(c, pm::cos(0.7));
}

TEST(PortableMath, SinNearMultiplesOfHalfPiKeepsRelativeAccuracy) {
  // Cancellation in the reduction: sin(k pi) for the double nearest k pi is tiny.
  for (int k = 1; k < 2000; ++k) {
    const double x = k * 3.141592653589793;
    EXPECT_LE(ulp_distance(pm::sin(x), std::sin(x)), kMaxUlp) << "k = " << k;
    const double y = (2 * k + 1) * 1.5707963267948966;
    EXPECT_LE(ulp_distance(pm::cos(y), std::cos(y)), kMaxUlp) << "k = " << k;
  }
}

TEST(PortableMath, AtanFamilyWithinTwoUlpOfGlibc) {
  check_unary([](double x) { return pm::atan(x); }, [](double x) { return std::atan(x); }, -4.0,
              4.0, 6, "atan");
  check_unary([](double x) { return pm::asin(x); }, [](double x) { return std::asin(x); }, -1.0,
              1.0, 7, "asin");
  check_unary([](double x) { return pm::acos(x); }, [](double x) { return std::acos(x); }, -1.0,
              1.0, 8, "acos");
  std::mt19937_64 rng(9);
  std::uint64_t worst = 0;
  for (int i = 0; i < kDraws; ++i) {
    const double y = log_uniform(rng, -30, 30), x = log_uniform(rng, -30, 30);
    const double a = pm::atan2(y, x), b = std::atan2(y, x);
    worst = std::max(worst, ulp_distance(a, b));
    const double z = log_uniform(rng, -60, 60);
    worst = std::max(worst, ulp_distance(pm::atan(z), std::atan(z)));
  }
  EXPECT_LE(worst, kMaxUlp);
}

TEST(PortableMath, LogExpWithinTwoUlpOfGlibc) {
  std::mt19937_64 rng(10);
  std::uint64_t worst_log = 0, worst_exp = 0;
  std::uniform_real_distribution<double> ue(-700.0, 700.0);
  for (int i = 0; i < kDraws; ++i) {
    const double x = std::fabs(log_uniform(rng, -1070, 1020));
    worst_log = std::max(worst_log, ulp_distance(pm::log(x), std::log(x)));
    const double e = ue(rng);
    worst_exp = std::max(worst_exp, ulp_distance(pm::exp(e), std::exp(e)));
  }
  check_unary([](double x) { return pm::log(x); }, [](double x) { return std::log(x); }, 0.5, 2.0,
              11, "log near 1");
  check_unary([](double x) { return pm::exp(x); }, [](double x) { return std::exp(x); }, -1.0, 1.0,
              12, "exp near 0");
  EXPECT_LE(worst_log, kMaxUlp);
  EXPECT_LE(worst_exp, kMaxUlp);
}

TEST(PortableMath, SpecialValues) {
  const double inf = std::numeric_limits<double>::infinity();
  const double nan = std::numeric_limits<double>::quiet_NaN();
  EXPECT_TRUE(std::isnan(pm::sin(inf)));
  EXPECT_TRUE(std::isnan(pm::cos(-inf)));
  EXPECT_TRUE(std::isnan(pm::sin(nan)));
  EXPECT_EQ(std::bit_cast<std::uint64_t>(pm::sin(-0.0)), std::bit_cast<std::uint64_t>(-0.0));
  EXPECT_EQ(pm::cos(0.0), 1.0);
  EXPECT_EQ(pm::atan2(0.0, 1.0), 0.0);
  EXPECT_TRUE(std::signbit(pm::atan2(-0.0, 1.0)));
  EXPECT_EQ(pm::atan2(0.0, -1.0), std::atan2(0.0, -1.0));
  EXPECT_EQ(pm::atan2(-0.0, -0.0), std::atan2(-0.0, -0.0));
  EXPECT_EQ(pm::atan2(1.0, 0.0), std::atan2(1.0, 0.0));
  EXPECT_EQ(pm::atan2(-1.0, 0.0), std::atan2(-1.0, 0.0));
  EXPECT_EQ(pm::atan2(inf, inf), std::atan2(inf, inf));
  EXPECT_EQ(pm::atan2(-inf, -inf), std::atan2(-inf, -inf));
  EXPECT_EQ(pm::atan2(1.0, -inf), std::atan2(1.0, -inf));
  EXPECT_EQ(pm::atan2(1.0, inf), 0.0);
  EXPECT_EQ(pm::atan2(inf, 1.0), std::atan2(inf, 1.0));
  EXPECT_TRUE(std::isnan(pm::atan2(nan, 1.0)));
  EXPECT_EQ(pm::atan(inf), std::atan(inf));
  EXPECT_EQ(pm::asin(1.0), std::asin(1.0));
  EXPECT_EQ(pm::asin(-1.0), std::asin(-1.0));
  EXPECT_EQ(pm::acos(1.0), 0.0);
  EXPECT_EQ(pm::acos(-1.0), std::acos(-1.0));
  EXPECT_TRUE(std::isnan(pm::asin(1.5)));
  EXPECT_TRUE(std::isnan(pm::acos(-1.5)));
  EXPECT_EQ(pm::log(1.0), 0.0);
  EXPECT_EQ(pm::log(0.0), -inf);
  EXPECT_EQ(pm::log(inf), inf);
  EXPECT_TRUE(std::isnan(pm::log(-1.0)));
  EXPECT_LE(ulp_distance(pm::log(std::numeric_limits<double>::denorm_min()),
                         std::log(std::numeric_limits<double>::denorm_min())),
            kMaxUlp);
  EXPECT_EQ(pm::exp(0.0), 1.0);
  EXPECT_EQ(pm::exp(1000.0), inf);
  EXPECT_EQ(pm::exp(-1000.0), 0.0);
  EXPECT_TRUE(std::isnan(pm::exp(nan)));
}
