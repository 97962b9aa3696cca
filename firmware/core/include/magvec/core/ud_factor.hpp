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
  // Four columns of U at a time: each h(i) loaded once for four multiply-adds; every sum in
  // ascending i, as one column at a time.
  const Scalar* up = u.data();  // column-major: u(., j) at up + N j
  Eigen::Index j = first;
  for (; j + 4 <= N; j += 4) {
    const Scalar* ua = up + N * j;
    const Scalar* ub = ua + N;
    const Scalar* uc = ub + N;
    const Scalar* ud = uc + N;
    Scalar a = h(j), b = h(j + 1), c = h(j + 2), e = h(j + 3);
    for (Eigen::Index i = first; i < j; ++i) {
      const Scalar x = h(i);
      a += ua[i] * x;
      b += ub[i] * x;
      c += uc[i] * x;
      e += ud[i] * x;
    }
    b += ub[j] * h(j);
    c += uc[j] * h(j);
    c += uc[j + 1] * h(j + 1);
    e += ud[j] * h(j);
    e += ud[j + 1] * h(j + 1);
    e += ud[j + 2] * h(j + 2);
    f(j) = a;
    f(j + 1) = b;
    f(j + 2) = c;
    f(j + 3) = e;
  }
  // The columns left over (none when the dense N is a multiple of four: the loop is left out
  // then, which also keeps GCC from reasoning about an empty loop past the end).
  if constexpr (kSparse || N % 4 != 0) {
    for (; j < N; ++j) {
      Scalar acc = h(j);
      for (Eigen::Index i = first; i < j; ++i)
        acc += u(i, j) * h(i);
      f(j) = acc;
    }
  }
  return f;
}

// U^T h for the three rows of a vector measurement at once, four columns of U at a time: each
// element of h is loaded once for twelve multiply-adds and each element of U once for three (the
// M4F's loads dominate the single product: ~2 000 instructions a call one column at a time). Every
// sum runs in ud_ut_times's order (i ascending), so the results are those of three ud_ut_times
// calls bit for bit.
template <typename Scalar, int N>
void ud_ut_times_rows(const Mat<Scalar, N, N>& u, const Mat<Scalar, 3, N>& h,
                      std::array<Vec<Scalar, N>, 3>* f) noexcept {
  Scalar* f0 = (*f)[0].data();
  Scalar* f1 = (*f)[1].data();
  Scalar* f2 = (*f)[2].data();
  const Scalar* hp = h.data();  // column-major: h(., i) at hp + 3 i
  const Scalar* up = u.data();  // column-major: u(., j) at up + N j
  Eigen::Index j = 0;
  for (; j + 4 <= N; j += 4) {
    const Scalar* ua = up + N * j;
    const Scalar* ub = ua + N;
    const Scalar* uc = ub + N;
    const Scalar* ud = uc + N;
    const Scalar* hj = hp + 3 * j;
    Scalar a0 = hj[0], a1 = hj[1], a2 = hj[2];
    Scalar b0 = hj[3], b1 = hj[4], b2 = hj[5];
    Scalar c0 = hj[6], c1 = hj[7], c2 = hj[8];
    Scalar d0 = hj[9], d1 = hj[10], d2 = hj[11];
    for (Eigen::Index i = 0; i < j; ++i) {
      const Scalar x0 = hp[3 * i], x1 = hp[3 * i + 1], x2 = hp[3 * i + 2];
      const Scalar wa = ua[i], wb = ub[i], wc = uc[i], wd = ud[i];
      a0 += wa * x0;
      a1 += wa * x1;
      a2 += wa * x2;
      b0 += wb * x0;
      b1 += wb * x1;
      b2 += wb * x2;
      c0 += wc * x0;
      c1 += wc * x1;
      c2 += wc * x2;
      d0 += wd * x0;
      d1 += wd * x1;
      d2 += wd * x2;
    }
    // The triangle inside the block, still in ascending i.
    b0 += ub[j] * hj[0];
    b1 += ub[j] * hj[1];
    b2 += ub[j] * hj[2];
    c0 += uc[j] * hj[0];
    c1 += uc[j] * hj[1];
    c2 += uc[j] * hj[2];
    c0 += uc[j + 1] * hj[3];
    c1 += uc[j + 1] * hj[4];
    c2 += uc[j + 1] * hj[5];
    d0 += ud[j] * hj[0];
    d1 += ud[j] * hj[1];
    d2 += ud[j] * hj[2];
    d0 += ud[j + 1] * hj[3];
    d1 += ud[j + 1] * hj[4];
    d2 += ud[j + 1] * hj[5];
    d0 += ud[j + 2] * hj[6];
    d1 += ud[j + 2] * hj[7];
    d2 += ud[j + 2] * hj[8];
    f0[j] = a0;
    f1[j] = a1;
    f2[j] = a2;
    f0[j + 1] = b0;
    f1[j + 1] = b1;
    f2[j + 1] = b2;
    f0[j + 2] = c0;
    f1[j + 2] = c1;
    f2[j + 2] = c2;
    f0[j + 3] = d0;
    f1[j + 3] = d1;
    f2[j + 3] = d2;
  }
  if constexpr (N % 4 != 0) {
    for (; j < N; ++j) {
      const Scalar* ua = up + N * j;
      Scalar a0 = hp[3 * j], a1 = hp[3 * j + 1], a2 = hp[3 * j + 2];
      for (Eigen::Index i = 0; i < j; ++i) {
        const Scalar wa = ua[i];
        a0 += wa * hp[3 * i];
        a1 += wa * hp[3 * i + 1];
        a2 += wa * hp[3 * i + 2];
      }
      f0[j] = a0;
      f1[j] = a1;
      f2[j] = a2;
    }
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
  // Two steps at a time where both are taken: k(i) is loaded and stored once for both columns
  // (the M4F's loads and stores dominate; each element sees the same operations in the same order
  // as one step at a time, so the results are the same bit for bit).
  int j = first + 1;
  while (j < N) {
    if constexpr (kSparse) {
      if (f(j) == Scalar(0)) {
        k(j) = Scalar(0);
        ++j;
        continue;
      }
    }
    const bool pair = j + 1 < N && !(kSparse && f(j + 1) == Scalar(0));
    const Scalar beta_a = alpha;
    alpha += f(j) * v(j);
    const Scalar lambda_a = -f(j) / beta_a;
    d(j) *= beta_a / alpha;
    const Scalar va = v(j);
    Scalar* ua = u.data() + static_cast<Eigen::Index>(N) * j;  // column j (column-major)
    if (!pair) {
      for (int i = 0; i < j; ++i) {
        const Scalar uij = ua[i];
        ua[i] = uij + lambda_a * k(i);
        k(i) += va * uij;
      }
      k(j) = va;
      ++j;
      continue;
    }
    const Scalar beta_b = alpha;
    alpha += f(j + 1) * v(j + 1);
    const Scalar lambda_b = -f(j + 1) / beta_b;
    d(j + 1) *= beta_b / alpha;
    const Scalar vb = v(j + 1);
    Scalar* ub = ua + N;  // column j + 1
    for (int i = 0; i < j; ++i) {
      const Scalar uia = ua[i], uib = ub[i];
      Scalar ki = k(i);
      ua[i] = uia + lambda_a * ki;
      ki += va * uia;
      ub[i] = uib + lambda_b * ki;
      k(i) = ki + vb * uib;
    }
    // Column j + 1's element in row j sees k(j) = v(j) from step j.
    const Scalar ujb = ub[j];
    ub[j] = ujb + lambda_b * va;
    k(j) = va + vb * ujb;
    k(j + 1) = vb;
    j += 2;
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
