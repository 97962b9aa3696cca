// U-D factor routines (ud_factor.hpp) against the covariance they factor, P = U D U^T, formed
// explicitly.
#include "magvec/core/ud_factor.hpp"

#include <gtest/gtest.h>

#include <array>
#include <random>

namespace magvec::core {
namespace {

constexpr int kN = 7;

// A random positive-definite P and its factors.
void random_factors(std::mt19937_64& rng, Mat<double, kN, kN>* p, Mat<double, kN, kN>* u,
                    Vec<double, kN>* d) {
  std::normal_distribution<double> g(0.0, 1.0);
  Mat<double, kN, kN> a;
  for (int i = 0; i < kN; ++i)
    for (int j = 0; j < kN; ++j)
      a(i, j) = g(rng);
  *p = a * a.transpose() + 0.1 * Mat<double, kN, kN>::Identity();
  ASSERT_TRUE((ud_factorise<double, kN>(*p, u, d)));
}

TEST(UdFactor, FactorsReproduceTheCovariance) {
  std::mt19937_64 rng(1);
  Mat<double, kN, kN> p, u;
  Vec<double, kN> d;
  random_factors(rng, &p, &u, &d);
  const Mat<double, kN, kN> back = u * d.asDiagonal() * u.transpose();
  EXPECT_LT((back - p).cwiseAbs().maxCoeff(), 1e-12 * p.cwiseAbs().maxCoeff());
  for (int i = 0; i < kN; ++i)
    EXPECT_EQ(u(i, i), 1.0);
}

// The three rows' U^T h are three single products bit for bit, and the fused C = H P H^T is the
// product with P.
TEST(UdFactor, ThreeRowsAndTheirStatePartMatchTheCovariance) {
  std::mt19937_64 rng(2);
  std::normal_distribution<double> g(0.0, 1.0);
  for (int trial = 0; trial < 20; ++trial) {
    Mat<double, kN, kN> p, u;
    Vec<double, kN> d;
    random_factors(rng, &p, &u, &d);
    Mat<double, 3, kN> h;
    for (int i = 0; i < 3; ++i)
      for (int j = 0; j < kN; ++j)
        h(i, j) = g(rng);
    std::array<Vec<double, kN>, 3> f, f2;
    Mat3<double> c;
    ud_ut_times_rows<double, kN>(u, h, &f);
    ud_ut_times_rows<double, kN>(u, d, h, &f2, &c);
    for (int i = 0; i < 3; ++i) {
      const Vec<double, kN> one = ud_ut_times<double, kN>(u, h.row(i).transpose());
      EXPECT_EQ(f[static_cast<std::size_t>(i)], one) << i;
      EXPECT_EQ(f2[static_cast<std::size_t>(i)], one) << i;
    }
    const Mat3<double> want = h * p * h.transpose();
    EXPECT_LT((c - want).cwiseAbs().maxCoeff(), 1e-11 * want.cwiseAbs().maxCoeff()) << trial;
    EXPECT_EQ(c, c.transpose());
  }
}

}  // namespace
}  // namespace magvec::core
