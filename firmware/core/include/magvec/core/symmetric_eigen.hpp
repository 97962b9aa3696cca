// Eigen-decomposition of small fixed-size symmetric matrices without a heap (the ellipsoid fit's
// quadric, the conditioning of normal matrices, the misalignment fit's 9x9 moment matrix).
#pragma once

#include <cmath>
#include <limits>
#include <utility>

#include "magvec/core/types.hpp"

namespace magvec::core {

// Eigen-decomposition of a small symmetric matrix by cyclic Jacobi rotations (Golub & Van Loan,
// "Matrix Computations", 4th ed., algorithm 8.5.3), eigenvalues ascending with their eigenvectors
// as columns. Why not Eigen::SelfAdjointEigenSolver for N > 3: its Householder tridiagonalisation
// runs on runtime-sized blocks whose temporaries have a heap fallback, which the firmware image
// must not link. Jacobi is fixed-size and at least as accurate (small eigenvalues to high relative
// accuracy). False if the sweeps do not converge or a value is not finite.
template <typename Scalar, int N>
bool symmetric_eigen_jacobi(const Mat<Scalar, N, N>& a_in, Vec<Scalar, N>* evals,
                            Mat<Scalar, N, N>* evecs) noexcept {
  Mat<Scalar, N, N> a = a_in;
  Mat<Scalar, N, N> v = Mat<Scalar, N, N>::Identity();
  if (!a.allFinite()) return false;
  const Scalar tol = std::numeric_limits<Scalar>::epsilon() * a.norm();
  bool converged = false;
  for (int sweep = 0; sweep < 50 && !converged; ++sweep) {
    Scalar off{0};
    for (int p = 0; p < N; ++p)
      for (int q = p + 1; q < N; ++q)
        off += a(p, q) * a(p, q);
    if (std::sqrt(Scalar(2) * off) <= tol) {
      converged = true;
      break;
    }
    for (int p = 0; p < N - 1; ++p) {
      for (int q = p + 1; q < N; ++q) {
        if (a(p, q) == Scalar(0)) continue;
        // Symmetric Schur 2x2: c, s zero a(p, q) (G&V algorithm 8.5.1).
        const Scalar tau = (a(q, q) - a(p, p)) / (Scalar(2) * a(p, q));
        const Scalar t = (tau >= 0 ? Scalar(1) : Scalar(-1)) /
                         (std::abs(tau) + std::sqrt(Scalar(1) + tau * tau));
        const Scalar c = Scalar(1) / std::sqrt(Scalar(1) + t * t);
        const Scalar s = t * c;
        for (int k = 0; k < N; ++k) {  // A <- A J (columns p, q)
          const Scalar akp = a(k, p), akq = a(k, q);
          a(k, p) = c * akp - s * akq;
          a(k, q) = s * akp + c * akq;
        }
        for (int k = 0; k < N; ++k) {  // A <- J^T A (rows p, q)
          const Scalar apk = a(p, k), aqk = a(q, k);
          a(p, k) = c * apk - s * aqk;
          a(q, k) = s * apk + c * aqk;
        }
        for (int k = 0; k < N; ++k) {  // V <- V J
          const Scalar vkp = v(k, p), vkq = v(k, q);
          v(k, p) = c * vkp - s * vkq;
          v(k, q) = s * vkp + c * vkq;
        }
      }
    }
  }
  if (!converged || !a.allFinite() || !v.allFinite()) return false;
  // Sort ascending (selection sort: N is small).
  Vec<Scalar, N> d = a.diagonal();
  for (int i = 0; i < N - 1; ++i) {
    int m = i;
    for (int j = i + 1; j < N; ++j)
      if (d(j) < d(m)) m = j;
    if (m != i) {
      std::swap(d(i), d(m));
      v.col(i).swap(v.col(m));
    }
  }
  *evals = d;
  *evecs = v;
  return true;
}

}  // namespace magvec::core
