// U-D factor routines (ud_factor.hpp) against the covariance they factor, P = U D U^T, formed
// explicitly.
#include "magvec/core/ud_factor.hpp"

#include <gtest/gtest.h>

#include <array>
#include <random>

namespace magvec::core {
namespace {

constexpr int kN = 7;

// A matrix of standard normal draws, row by row.
template <int R, int C>
Mat<double, R, C> gaussian(std::mt19937_64& rng, std::normal_distribution<double>& g) {
  Mat<double, R, C> a;
  for (int i = 0; i < R; ++i)
    for (int j = 0; j < C; ++j)
      a(i, j) = g(rng);
  return a;
}

// A random positive-definite P and its factors.
void random_factors(std::mt19937_64& rng, Mat<double, kN, kN>* p, Mat<double, kN, kN>* u,
                    Vec<double, kN>* d) {
  std::normal_distribution<double> g(0.0, 1.0);
  const Mat<double, kN, kN> a = gaussian<kN, kN>(rng, g);
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
    const Mat<double, 3, kN> h = gaussian<3, kN>(rng, g);
    std::array<Vec<double, kN>, 3> f, f2;
    Mat3<double> c;
    ud_ut_times_rows<double, kN>(u, h, &f);
    ud_ut_times_rows<double, kN>(u, d, h, &f2, &c);
    for (int i = 0; i < 3; ++i) {
      const Vec<double, kN> one = ud_ut_times<double, kN>(u, h.row(i).transpose());
      // The blocked single product is the one-column-at-a-time sum bit for bit, dense and sparse.
      for (int first : {0, 2, 5}) {
        Vec<double, kN> hs = h.row(i).transpose();
        hs.head(first).setZero();
        Vec<double, kN> plain;
        for (int j = 0; j < kN; ++j) {
          double acc = j < first ? 0.0 : hs(j);
          for (int k = first; k < j; ++k)
            acc += u(k, j) * hs(k);
          plain(j) = acc;
        }
        EXPECT_EQ((ud_ut_times<double, kN, true>(u, hs, first)), plain) << first;
        if (first == 0) {
          EXPECT_EQ(one, plain);
        }
      }
      EXPECT_EQ(f[static_cast<std::size_t>(i)], one) << i;
      EXPECT_EQ(f2[static_cast<std::size_t>(i)], one) << i;
    }
    const Mat3<double> want = h * p * h.transpose();
    EXPECT_LT((c - want).cwiseAbs().maxCoeff(), 1e-11 * want.cwiseAbs().maxCoeff()) << trial;
    EXPECT_EQ(c, c.transpose());
  }
}

// Bierman's update one step at a time, as published (the reference for the paired steps).
template <int N>
void bierman_one_at_a_time(Mat<double, N, N>& u, Vec<double, N>& d, const Vec<double, N>& f,
                           double r, Vec<double, N>* k, double* s) {
  const Vec<double, N> v = d.cwiseProduct(f);
  double alpha = r + f(0) * v(0);
  d(0) *= r / alpha;
  (*k)(0) = v(0);
  for (int j = 1; j < N; ++j) {
    if (f(j) == 0.0) {
      (*k)(j) = 0.0;
      continue;
    }
    const double beta = alpha;
    alpha += f(j) * v(j);
    const double lambda = -f(j) / beta;
    d(j) *= beta / alpha;
    for (int i = 0; i < j; ++i) {
      const double uij = u(i, j);
      u(i, j) = uij + lambda * (*k)(i);
      (*k)(i) += v(j) * uij;
    }
    (*k)(j) = v(j);
  }
  *s = alpha;
}

// The paired steps give the one-at-a-time results bit for bit, with f zero at an even and at an
// odd step (the sparse form skips those) and dense, and the updated factors are the updated
// covariance P - P h h^T P / s.
TEST(UdFactor, PairedBiermanStepsAreTheOneAtATimeUpdate) {
  std::mt19937_64 rng(3);
  std::normal_distribution<double> g(0.0, 1.0);
  for (int trial = 0; trial < 30; ++trial) {
    Mat<double, kN, kN> p, u;
    Vec<double, kN> d;
    random_factors(rng, &p, &u, &d);
    const Vec<double, kN> h = gaussian<kN, 1>(rng, g);
    Vec<double, kN> f = ud_ut_times<double, kN>(u, h);
    if (trial % 3 == 1) f(2) = 0.0;  // a skipped step at an even index, paired with the next
    if (trial % 3 == 2) f(5) = 0.0;  // at an odd index
    const double r = 0.5;
    Mat<double, kN, kN> u1 = u, u2 = u;
    Vec<double, kN> d1 = d, d2 = d, k1, k2;
    double s1 = 0, s2 = 0;
    bierman_one_at_a_time<kN>(u1, d1, f, r, &k1, &s1);
    ud_bierman_update<double, kN, true>(u2, d2, f, r, &k2, &s2);
    EXPECT_EQ(u1, u2) << trial;
    EXPECT_EQ(d1, d2) << trial;
    EXPECT_EQ(k1, k2) << trial;
    EXPECT_EQ(s1, s2) << trial;
    if (trial % 3 == 0) {
      // Dense: the factors of the updated covariance, the gain P h^T.
      Mat<double, kN, kN> u3 = u;
      Vec<double, kN> d3 = d, k3;
      double s3 = 0;
      ud_bierman_update<double, kN>(u3, d3, f, r, &k3, &s3);
      EXPECT_EQ(u3, u1) << trial;
      const Vec<double, kN> ph = p * h;
      const double s_want = h.dot(ph) + r;
      EXPECT_NEAR(s3, s_want, 1e-12 * s_want);
      const Mat<double, kN, kN> want = p - ph * ph.transpose() / s_want;
      const Mat<double, kN, kN> got = u3 * d3.asDiagonal() * u3.transpose();
      EXPECT_LT((got - want).cwiseAbs().maxCoeff(), 1e-11 * p.cwiseAbs().maxCoeff()) << trial;
      EXPECT_LT((k3 - ph).cwiseAbs().maxCoeff(), 1e-11 * ph.cwiseAbs().maxCoeff()) << trial;
    }
  }
}

}  // namespace
}  // namespace magvec::core
