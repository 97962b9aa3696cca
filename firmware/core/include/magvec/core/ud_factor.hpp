// U-D covariance factor P = U D U^T (U unit upper triangular, D diagonal) and its updates, shared
// by the filters (the scalar EKF and the vector calibration filter): Bierman's scalar measurement
// update and the Agee-Turner rank-one update (G. J. Bierman, "Factorization Methods for Discrete
// Sequential Estimation", 1977; docs/equations.md references). Fixed size N, no heap; every loop
// touches the strict upper triangle of U only, so its diagonal stays 1 and its lower triangle 0.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>

#include "magvec/core/types.hpp"

namespace magvec::core {

// U^T h: N(N-1)/2 multiply-adds instead of the N^2 of a full product (per sample, in every update).
// kSparse, `first`: h is zero before it (a sparse row, a pseudo-measurement of an information
// fold), so is U^T h (U is upper triangular) and only the trailing block is computed. Without
// kSparse `first` is 0 at compile time: a dense caller pays nothing for it.
template <typename Scalar, int N, bool kSparse = false>
Vec<Scalar, N> ud_ut_times(const Mat<Scalar, N, N>& u, const Vec<Scalar, N>& h,
                           int first = 0) noexcept {
  if constexpr (!kSparse) first = 0;
  Vec<Scalar, N> f;
  for (int j = 0; j < first; ++j)
    f(j) = Scalar(0);
  for (int j = first; j < N; ++j) {
    Scalar acc = h(j);
    for (int i = first; i < j; ++i)
      acc += u(i, j) * h(i);
    f(j) = acc;
  }
  return f;
}

// U^T h for the three rows of a vector measurement at once: each element of U is loaded once for
// all three (the M4F's loads dominate the single product), each sum in ud_ut_times's order, so
// the results are those of three ud_ut_times calls bit for bit.
template <typename Scalar, int N>
void ud_ut_times_rows(const Mat<Scalar, N, N>& u, const Mat<Scalar, 3, N>& h,
                      std::array<Vec<Scalar, N>, 3>* f) noexcept {
  Vec<Scalar, N>&f0 = (*f)[0], &f1 = (*f)[1], &f2 = (*f)[2];
  for (int j = 0; j < N; ++j) {
    Scalar a0 = h(0, j), a1 = h(1, j), a2 = h(2, j);
    for (int i = 0; i < j; ++i) {
      const Scalar uij = u(i, j);
      a0 += uij * h(0, i);
      a1 += uij * h(1, i);
      a2 += uij * h(2, i);
    }
    f0(j) = a0;
    f1(j) = a1;
    f2(j) = a2;
  }
}

// The same, and C = H P H^T = F^T D F (F = [f0 f1 f2], P = U D U^T) from one pass over F and D
// with its six sums in registers (no D f temporaries); the callers' gate reads its diagonal.
template <typename Scalar, int N>
void ud_ut_times_rows(const Mat<Scalar, N, N>& u, const Vec<Scalar, N>& d,
                      const Mat<Scalar, 3, N>& h, std::array<Vec<Scalar, N>, 3>* f,
                      Mat3<Scalar>* c) noexcept {
  ud_ut_times_rows<Scalar, N>(u, h, f);
  const Vec<Scalar, N>&f0 = (*f)[0], &f1 = (*f)[1], &f2 = (*f)[2];
  Scalar c00{0}, c01{0}, c02{0}, c11{0}, c12{0}, c22{0};
  for (int j = 0; j < N; ++j) {
    const Scalar a0 = f0(j), a1 = f1(j), a2 = f2(j);
    const Scalar d0 = d(j) * a0, d1 = d(j) * a1, d2 = d(j) * a2;
    c00 += a0 * d0;
    c01 += a0 * d1;
    c02 += a0 * d2;
    c11 += a1 * d1;
    c12 += a1 * d2;
    c22 += a2 * d2;
  }
  *c << c00, c01, c02, c01, c11, c12, c02, c12, c22;
}

// All of U finite, tested on the strict upper triangle only (the rest never changes): v * 0 is 0
// for a finite v but NaN for inf/NaN, an exact test at one multiply-add per element.
template <typename Scalar, int N>
bool ud_upper_finite(const Mat<Scalar, N, N>& u) noexcept {
  Scalar probe{0};
  for (int j = 1; j < N; ++j)
    for (int i = 0; i < j; ++i)
      probe += u(i, j) * Scalar(0);
  return probe == Scalar(0);
}

// diag(U D U^T)_i = sum_{j >= i} U_ij^2 D_j.
template <typename Scalar, int N>
Vec<Scalar, N> ud_variances(const Mat<Scalar, N, N>& u, const Vec<Scalar, N>& d) noexcept {
  Vec<Scalar, N> v;
  for (int i = 0; i < N; ++i) {
    Scalar acc{0};
    for (int j = i; j < N; ++j)
      acc += u(i, j) * u(i, j) * d(j);
    v(i) = std::max(acc, Scalar(0));
  }
  return v;
}

// Agee-Turner: U D U^T + c e_k e_k^T for c > 0, O(k^2).
template <typename Scalar, int N>
void ud_add_diagonal_noise(Mat<Scalar, N, N>& u, Vec<Scalar, N>& d, int k, Scalar c) noexcept {
  Vec<Scalar, N> a = Vec<Scalar, N>::Zero();
  a(k) = Scalar(1);
  for (int j = k; j > 0; --j) {
    const Scalar s = a(j);
    const Scalar dj = d(j) + c * s * s;
    const Scalar beta = c * s / dj;
    c = c * d(j) / dj;
    d(j) = dj;
    for (int i = 0; i < j; ++i) {
      a(i) -= s * u(i, j);
      u(i, j) += beta * a(i);
    }
  }
  d(0) += c * a(0) * a(0);
}

// Bierman's scalar update of U, D for a measurement with f = U^T h^T and variance r: the
// unnormalised gain k (K = k / s) into *k_out (not f or d), the innovation variance
// s = h P h^T + r into *s_out. kSparse (the vector filter): f is zero before `first` (ud_ut_times
// with the same `first`), and those steps change nothing and are skipped (the gain still has every
// component); so are the later steps whose f(j) is 0 (exact no-ops: lambda = v(j) = 0, d(j)
// unchanged: states unmeasured and uncorrelated, the temperature coefficients without a
// temperature input). Without kSparse (the 9-state EKF) `first` is 0 at compile time and no step
// is tested.
template <typename Scalar, int N, bool kSparse = false>
void ud_bierman_update(Mat<Scalar, N, N>& u, Vec<Scalar, N>& d, const Vec<Scalar, N>& f, Scalar r,
                       Vec<Scalar, N>* k_out, Scalar* s_out, int first = 0) noexcept {
  if constexpr (!kSparse) first = 0;
  const Vec<Scalar, N> v = d.cwiseProduct(f);
  // Built in place, not zeroed: k(j) is set at step j, before any later step adds to it (zeroing
  // a local and copying it out were two library calls on the M4F's per-sample path: 120
  // instructions per calibrating sample of the EKF image; the 19-state filter's update takes ~3 %
  // more this way, its image is far from its budget either way).
  Vec<Scalar, N>& k = *k_out;
  for (int j = 0; j < first; ++j)
    k(j) = Scalar(0);
  Scalar alpha = r + f(first) * v(first);
  d(first) *= r / alpha;
  k(first) = v(first);
  for (int j = first + 1; j < N; ++j) {
    if constexpr (kSparse) {
      if (f(j) == Scalar(0)) {
        k(j) = Scalar(0);
        continue;
      }
    }
    const Scalar beta = alpha;
    alpha += f(j) * v(j);
    const Scalar lambda = -f(j) / beta;
    d(j) *= beta / alpha;
    for (int i = 0; i < j; ++i) {
      const Scalar uij = u(i, j);
      u(i, j) = uij + lambda * k(i);
      k(i) += v(j) * uij;
    }
    k(j) = v(j);
  }
  *s_out = alpha;
}

// The information P^-1 = U^-T D^-1 U^-1 of P = U D U^T, without inverting P: U^-1 (unit upper
// triangular) by back substitution column by column, then the symmetric product.
template <typename Scalar, int N>
Mat<Scalar, N, N> ud_information(const Mat<Scalar, N, N>& u, const Vec<Scalar, N>& d) noexcept {
  Mat<Scalar, N, N> ui = Mat<Scalar, N, N>::Identity();
  for (int j = 0; j < N; ++j)
    for (int i = j - 1; i >= 0; --i) {
      Scalar v{0};
      for (int k = i + 1; k <= j; ++k)
        v += u(i, k) * ui(k, j);
      ui(i, j) = -v;
    }
  Mat<Scalar, N, N> info;
  for (int j = 0; j < N; ++j)
    for (int i = j; i < N; ++i) {
      Scalar v{0};
      for (int k = 0; k <= j; ++k)
        v += ui(k, i) * ui(k, j) / d(k);
      info(i, j) = v;
      info(j, i) = v;
    }
  return info;
}

// P = U D U^T. False (u, d untouched) unless P is positive definite.
template <typename Scalar, int N>
bool ud_factorise(const Mat<Scalar, N, N>& p, Mat<Scalar, N, N>* u_out,
                  Vec<Scalar, N>* d_out) noexcept {
  Mat<Scalar, N, N> u = Mat<Scalar, N, N>::Identity();
  Vec<Scalar, N> d = Vec<Scalar, N>::Zero();
  for (int j = N - 1; j >= 0; --j) {
    Scalar dj = p(j, j);
    for (int k = j + 1; k < N; ++k)
      dj -= d(k) * u(j, k) * u(j, k);
    if (!(dj > Scalar(0))) return false;
    d(j) = dj;
    for (int i = 0; i < j; ++i) {
      Scalar a = p(i, j);
      for (int k = j + 1; k < N; ++k)
        a -= d(k) * u(i, k) * u(j, k);
      u(i, j) = a / dj;
    }
  }
  *u_out = u;
  *d_out = d;
  return true;
}

}  // namespace magvec::core
