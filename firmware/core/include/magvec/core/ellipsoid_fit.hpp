// Ellipsoid fit with a scalar reference field: Li et al. 2023 eq. (9)-(15), decomposition of G into
// Ks, Ko (docs/equations.md E-Li-1, via li_scale_and_angles) and Kof.
//
//   (m_i - o)^T G (m_i - o) = F_i^2,   G = W^T W,   |W (m_i - o)| = F_i
//
// Streaming algebraic stage: each sample adds psi psi^T to an 11x11 accumulator, psi = [phi; F^2],
// phi = [x^2, y^2, z^2, 2xy, 2xz, 2yz, x, y, z, 1] of the normalised reading x = (m - c) / s
// (c, s from the first sample or set explicitly). The 10x10 phi block is the classic quadric
// scatter matrix; the extra column carries the per-sample reference field. O(1) memory, any N.
// Solve: (1) the quadric of least algebraic distance with tr G = 1 (a 9x9 linear least-squares
// problem in the 10x10 block), scaled to the mean F^2; (2) Gauss-Newton on the 9 ellipsoid
// parameters (G, centre u) of the exact algebraic residual e_i = (x_i - u)^T G (x_i - u) - f_i^2,
// whose sum of squares is a quadratic form in the accumulator, so a per-sample F is honoured
// exactly and noise-free data is recovered exactly. Optional geometric refinement (Gauss-Newton on
// |W(m - o)| - F) over a fixed-capacity SampleStore.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/LU>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <type_traits>

#include "magvec/core/sample_store.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/symmetric_eigen.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

enum class EllipsoidStatus : std::uint8_t {
  kOk,
  kTooFewSamples,   // fewer than kMinSamples usable samples
  kNotAnEllipsoid,  // fitted quadric is not an ellipsoid (G not positive definite)
  kIllConditioned,  // normal matrix numerically singular (data on a plane, a ring, ...)
  kNotConverged,
};

template <typename Scalar>
struct EllipsoidSolution {
  EllipsoidStatus status = EllipsoidStatus::kTooFewSamples;
  Mat3<Scalar> g = Mat3<Scalar>::Identity();  // G = W^T W
  Mat3<Scalar> w = Mat3<Scalar>::Identity();  // W = (Ks Ko)^-1, Li structure
  Vec3<Scalar> o = Vec3<Scalar>::Zero();      // offset Kof [nT]
  LiParams<Scalar> li{};                      // ks, O, Kof (rm_rad stays zero)
  Scalar rcond{0};                            // reciprocal condition of the scaled normal matrix
  Scalar rms{0};  // algebraic: RMS of e_i / 2 [normalised]; geometric: RMS of |h_s| - F [nT]
  int iterations{0};

  SensorModel<Scalar> model() const noexcept {
    SensorModel<Scalar> m;
    m.w = w;
    m.o = o;
    return m;
  }
};

namespace detail {

template <typename Scalar>
Scalar default_tolerance() noexcept {
  // Step size, in normalised units, below which an iteration has converged.
  return std::sqrt(std::numeric_limits<Scalar>::epsilon()) * Scalar(1e-3);
}

// Reciprocal condition number of a symmetric positive semi-definite matrix after scaling it to a
// unit diagonal (so it measures correlation between parameters, not their units). Optionally
// returns the eigenvector of the smallest eigenvalue (in the scaled parameters).
template <typename Scalar, int N>
Scalar scaled_rcond(const Mat<Scalar, N, N>& a, Vec<Scalar, N>* weakest = nullptr) noexcept {
  Vec<Scalar, N> d;
  for (int i = 0; i < N; ++i) {
    d(i) = a(i, i) > Scalar(0) ? Scalar(1) / std::sqrt(a(i, i)) : Scalar(0);
  }
  const Mat<Scalar, N, N> s = d.asDiagonal() * a * d.asDiagonal();
  Vec<Scalar, N> evals;
  Mat<Scalar, N, N> evecs;
  if (!symmetric_eigen_jacobi<Scalar, N>(s, &evals, &evecs)) return Scalar(0);
  const Scalar lmax = evals(N - 1);
  const Scalar lmin = evals(0);
  if (weakest != nullptr) *weakest = evecs.col(0);
  if (!(lmax > Scalar(0))) return Scalar(0);
  return lmin > Scalar(0) ? lmin / lmax : Scalar(0);
}

template <typename Scalar>
Mat3<Scalar> sym_from6(const Vec<Scalar, 6>& v) noexcept {
  Mat3<Scalar> g;
  g << v(0), v(3), v(4), v(3), v(1), v(5), v(4), v(5), v(2);
  return g;
}

// Li decomposition of G (docs/equations.md E-Li-1); fills w, li; false when G^-1 is not positive
// definite.
template <typename Scalar>
bool decompose_g(const Mat3<Scalar>& g, const Vec3<Scalar>& o,
                 EllipsoidSolution<Scalar>* out) noexcept {
  Mat3<Scalar> ksko;
  LiParams<Scalar> li;
  if (!g.allFinite() ||
      li_scale_and_angles<Scalar>(g.inverse(), &li.ks, &li.o_rad, &ksko) != ConversionStatus::kOk) {
    return false;
  }
  li.kof = o;
  out->g = g;
  out->o = o;
  out->w = ksko.inverse();
  out->li = li;
  return true;
}

}  // namespace detail

template <typename Scalar>
class EllipsoidFit {
 public:
  static constexpr int kCoeffs = 10;  // quadric coefficients
  static constexpr int kAug = 11;     // quadric coefficients + the F^2 column
  static constexpr int kParams = 9;   // G (6 entries) and the centre (3)
  static constexpr std::size_t kMinSamples = 9;
  // Parameter indices of the algebraic Gauss-Newton stage.
  static constexpr int kIdxG = 0;
  static constexpr int kIdxCentre = 6;
  static_assert(kIdxCentre + 3 == kParams, "parameter layout");

  using Accumulator = Mat<Scalar, kAug, kAug>;

  void reset() noexcept {
    s_.setZero();
    n_ = 0;
    has_norm_ = false;
  }
  // Fixes the normalisation before the first sample (otherwise the first sample sets it).
  void set_normalization(const Normalization<Scalar>& norm) noexcept {
    norm_ = norm;
    has_norm_ = true;
  }
  const Normalization<Scalar>& normalization() const noexcept { return norm_; }
  std::size_t count() const noexcept { return n_; }
  const Accumulator& accumulator() const noexcept { return s_; }

  // Adds one reading m [nT] with its reference field f [nT]. Refuses (returns false) non-finite
  // input or a non-positive field; the accumulator is then unchanged.
  bool add(const Vec3<Scalar>& m, Scalar f) noexcept {
    if (!m.allFinite() || !std::isfinite(f) || !(f > Scalar(0))) return false;
    if (!has_norm_) {
      norm_.centre = m;
      norm_.scale = f;
      has_norm_ = true;
    }
    const Vec3<Scalar> x = norm_.to_unit(m);
    const Scalar fn = f / norm_.scale;
    Vec<Scalar, kAug> psi;
    psi << x(0) * x(0), x(1) * x(1), x(2) * x(2), Scalar(2) * x(0) * x(1), Scalar(2) * x(0) * x(2),
        Scalar(2) * x(1) * x(2), x(0), x(1), x(2), Scalar(1), fn * fn;
    s_.template selfadjointView<Eigen::Upper>().rankUpdate(psi);
    ++n_;
    return true;
  }

  // Stage (1) alone (docs/equations.md E-Ell-2): the quadric of least algebraic distance under
  // tr G = 1, centre and scale, in the normalised coordinates: (x - u)^T G (x - u) = mean(f^2).
  // kOk, kTooFewSamples, kIllConditioned (data on a plane, a ring, ...) or kNotAnEllipsoid.
  EllipsoidStatus algebraic_start(Mat3<Scalar>* g, Vec3<Scalar>* u) const noexcept;

  EllipsoidSolution<Scalar> solve(int max_iterations = 50) const noexcept;

  // theta~(p) = [G entries (6), b = -2 G u (3), d = u^T G u, -1] and its Jacobian (11 x 9).
  static Vec<Scalar, kAug> theta(const Vec<Scalar, kParams>& p,
                                 Mat<Scalar, kAug, kParams>* jac) noexcept {
    const Mat3<Scalar> g = detail::sym_from6<Scalar>(p.template head<6>());
    const Vec3<Scalar> u = p.template segment<3>(kIdxCentre);
    const Vec3<Scalar> gu = g * u;
    Vec<Scalar, kAug> th;
    th << p.template head<6>(), Scalar(-2) * gu, u.dot(gu), Scalar(-1);
    if (jac != nullptr) {
      Mat<Scalar, kAug, kParams>& d = *jac;
      d.setZero();
      // Entry k of the symmetric G at (r, c): indices (0,0) (1,1) (2,2) (0,1) (0,2) (1,2).
      constexpr int kRow[6] = {0, 1, 2, 0, 0, 1};
      constexpr int kCol[6] = {0, 1, 2, 1, 2, 2};
      for (int k = 0; k < 6; ++k) {
        const int r = kRow[k], c = kCol[k];
        d(k, k) = Scalar(1);
        if (r == c) {
          d(6 + r, k) = Scalar(-2) * u(r);
          d(9, k) = u(r) * u(r);
        } else {
          d(6 + r, k) = Scalar(-2) * u(c);
          d(6 + c, k) = Scalar(-2) * u(r);
          d(9, k) = Scalar(2) * u(r) * u(c);
        }
      }
      d.template block<3, 3>(6, kIdxCentre) = Scalar(-2) * g;
      d.template block<1, 3>(9, kIdxCentre) = Scalar(2) * gu.transpose();
    }
    return th;
  }

 private:
  static Scalar algebraic_cost(const Accumulator& s, const Vec<Scalar, kParams>& p) noexcept {
    const Vec<Scalar, kAug> th = theta(p, nullptr);
    return th.dot(s * th);
  }

  Accumulator s_ = Accumulator::Zero();
  Normalization<Scalar> norm_{};
  std::size_t n_{0};
  bool has_norm_{false};
};

// Out of the class: a unit that links the library compiling EllipsoidFit (see the end of this
// file) calls these instead of instantiating them.
template <typename Scalar>
EllipsoidStatus EllipsoidFit<Scalar>::algebraic_start(Mat3<Scalar>* g,
                                                      Vec3<Scalar>* u) const noexcept {
  if (n_ < kMinSamples) return EllipsoidStatus::kTooFewSamples;
  const Accumulator s = s_.template selfadjointView<Eigen::Upper>();
  const Mat<Scalar, kCoeffs, kCoeffs> m = s.template topLeftCorner<kCoeffs, kCoeffs>();
  // q = e_2 + T^T q': G22 = 1 - G00 - G11, the other nine coefficients free. A linear
  // least-squares problem (no eigen-solver), well posed for any ellipsoid (tr G > 0).
  Mat<Scalar, kCoeffs - 1, kCoeffs> t = Mat<Scalar, kCoeffs - 1, kCoeffs>::Zero();
  t(0, 0) = 1;
  t(0, 2) = -1;
  t(1, 1) = 1;
  t(1, 2) = -1;
  for (int i = 2; i < kCoeffs - 1; ++i)
    t(i, i + 1) = 1;
  const Mat<Scalar, kCoeffs - 1, kCoeffs - 1> a = t * m * t.transpose();
  const Vec<Scalar, kCoeffs - 1> rhs = -(t * m.col(2));
  const Eigen::LDLT<Mat<Scalar, kCoeffs - 1, kCoeffs - 1>> ldlt(a);
  if (ldlt.info() != Eigen::Success) return EllipsoidStatus::kIllConditioned;
  const Vec<Scalar, kCoeffs - 1> qp = ldlt.solve(rhs);
  if (!qp.allFinite()) return EllipsoidStatus::kIllConditioned;
  Vec<Scalar, kCoeffs> q = t.transpose() * qp;
  q(2) += 1;
  Mat3<Scalar> g0 = detail::sym_from6<Scalar>(q.template head<6>());
  const Eigen::LLT<Mat3<Scalar>> llt(g0);
  if (llt.info() != Eigen::Success) return EllipsoidStatus::kNotAnEllipsoid;
  *u = Scalar(-0.5) * llt.solve(Vec3<Scalar>(q.template segment<3>(6)));
  const Scalar r2 = u->dot(g0 * *u) - q(9);
  const Scalar mean_f2 = s(9, 10) / s(9, 9);
  if (!(r2 > Scalar(0)) || !(mean_f2 > Scalar(0))) return EllipsoidStatus::kNotAnEllipsoid;
  *g = g0 * (mean_f2 / r2);
  return g->allFinite() && u->allFinite() ? EllipsoidStatus::kOk : EllipsoidStatus::kNotAnEllipsoid;
}

template <typename Scalar>
EllipsoidSolution<Scalar> EllipsoidFit<Scalar>::solve(int max_iterations) const noexcept {
  EllipsoidSolution<Scalar> out;
  if (n_ < kMinSamples) return out;
  const Accumulator s = s_.template selfadjointView<Eigen::Upper>();
  // (1) Algebraic start.
  Mat3<Scalar> g;
  Vec3<Scalar> u;
  out.status = algebraic_start(&g, &u);
  if (out.status != EllipsoidStatus::kOk) return out;

  // (2) Gauss-Newton on (G, u) with the exact algebraic residual.
  Vec<Scalar, kParams> p;
  p << g(0, 0), g(1, 1), g(2, 2), g(0, 1), g(0, 2), g(1, 2), u;
  Scalar cost = algebraic_cost(s, p);
  Mat<Scalar, kParams, kParams> h = Mat<Scalar, kParams, kParams>::Identity();
  bool converged = false;
  const Scalar tol = detail::default_tolerance<Scalar>();
  int it = 0;
  for (; it < max_iterations; ++it) {
    Mat<Scalar, kAug, kParams> d;
    const Vec<Scalar, kAug> th = theta(p, &d);
    h = d.transpose() * s * d;
    const Vec<Scalar, kParams> grad = d.transpose() * (s * th);
    const Eigen::LDLT<Mat<Scalar, kParams, kParams>> ldlt(h);
    if (ldlt.info() != Eigen::Success) break;
    Vec<Scalar, kParams> step = -ldlt.solve(grad);
    if (!step.allFinite()) break;
    // Backtracking keeps the cost monotone when the start is far off.
    Scalar new_cost = algebraic_cost(s, p + step);
    int halvings = 0;
    while (!(new_cost <= cost) && halvings < 20) {
      step *= Scalar(0.5);
      new_cost = algebraic_cost(s, p + step);
      ++halvings;
    }
    if (!(new_cost <= cost)) {
      converged = true;  // no descent left at working precision
      break;
    }
    p += step;
    const bool small = step.template lpNorm<Eigen::Infinity>() < tol;
    const bool flat = cost - new_cost <= std::numeric_limits<Scalar>::epsilon() * cost;
    cost = new_cost;
    if (small || flat) {
      converged = true;
      ++it;
      break;
    }
  }
  out.iterations = it;
  out.rcond = detail::scaled_rcond<Scalar, kParams>(h);
  out.rms = std::sqrt(std::max(cost, Scalar(0)) / static_cast<Scalar>(n_)) / Scalar(2);
  g = detail::sym_from6<Scalar>(p.template head<6>());
  u = p.template segment<3>(kIdxCentre);
  if (Eigen::LLT<Mat3<Scalar>>(g).info() != Eigen::Success ||
      !detail::decompose_g<Scalar>(g, norm_.to_nt(u), &out)) {
    out.status = EllipsoidStatus::kNotAnEllipsoid;
    return out;
  }
  if (!(out.rcond > std::numeric_limits<Scalar>::epsilon() * Scalar(100))) {
    out.status = EllipsoidStatus::kIllConditioned;
  } else {
    out.status = converged ? EllipsoidStatus::kOk : EllipsoidStatus::kNotConverged;
  }
  return out;
}

// Geometric refinement: Gauss-Newton on r_i = |W (m_i - o)| - F_i over the stored samples that are
// not flagged as outliers, with A = W^-1 = Ks Ko parameterised by its six structural non-zeros
// (rows x: (0,0); y: (1,0),(1,1),(1,2); z: (2,0),(2,2)) and the offset. Returns the refined
// solution (status kNotConverged keeps the last iterate).
template <typename Scalar>
EllipsoidSolution<Scalar> refine_ellipsoid_geometric(SampleView<std::type_identity_t<Scalar>> store,
                                                     const Normalization<Scalar>& norm,
                                                     const EllipsoidSolution<Scalar>& init,
                                                     int max_iterations = 30) noexcept {
  constexpr int kP = 9;
  constexpr int kAr[6] = {0, 1, 1, 1, 2, 2};
  constexpr int kAc[6] = {0, 0, 1, 2, 0, 2};
  EllipsoidSolution<Scalar> out = init;
  if (init.status != EllipsoidStatus::kOk && init.status != EllipsoidStatus::kNotConverged)
    return out;
  Mat3<Scalar> a = init.w.inverse();
  Vec3<Scalar> u = norm.to_unit(init.o);
  const Scalar tol = detail::default_tolerance<Scalar>();
  Mat<Scalar, kP, kP> n = Mat<Scalar, kP, kP>::Zero();
  Scalar sse{0};
  std::size_t count = 0;
  bool converged = false;
  int it = 0;
  for (; it < max_iterations; ++it) {
    const Mat3<Scalar> w = a.inverse();
    n.setZero();
    Vec<Scalar, kP> g = Vec<Scalar, kP>::Zero();
    sse = Scalar(0);
    count = 0;
    for (std::size_t i = 0; i < store.size(); ++i) {
      const StoredSample<Scalar>& smp = store[i];
      if (smp.outlier()) continue;
      const Vec3<Scalar> h = w * (norm.to_unit(smp.raw()) - u);
      const Scalar hn = h.norm();
      if (!(hn > Scalar(0))) continue;
      const Scalar r = hn - smp.f / norm.scale;
      const Vec3<Scalar> v = w.transpose() * (h / hn);
      Vec<Scalar, kP> j;
      for (int k = 0; k < 6; ++k)
        j(k) = -v(kAr[k]) * h(kAc[k]);
      j.template tail<3>() = -v;
      n.template selfadjointView<Eigen::Upper>().rankUpdate(j);
      g += j * r;
      sse += r * r;
      ++count;
    }
    if (count < EllipsoidFit<Scalar>::kMinSamples) {
      out.status = EllipsoidStatus::kTooFewSamples;
      return out;
    }
    n = n.template selfadjointView<Eigen::Upper>();
    const Eigen::LDLT<Mat<Scalar, kP, kP>> ldlt(n);
    const Vec<Scalar, kP> step = -ldlt.solve(g);
    if (ldlt.info() != Eigen::Success || !step.allFinite()) break;
    for (int k = 0; k < 6; ++k)
      a(kAr[k], kAc[k]) += step(k);
    u += step.template tail<3>();
    if (step.template lpNorm<Eigen::Infinity>() < tol) {
      converged = true;
      ++it;
      break;
    }
  }
  out.iterations = it;
  out.rcond = detail::scaled_rcond<Scalar, kP>(n);
  out.rms = std::sqrt(sse / static_cast<Scalar>(count > 0 ? count : 1)) * norm.scale;
  const Mat3<Scalar> w = a.inverse();
  if (!detail::decompose_g<Scalar>(Mat3<Scalar>(w.transpose() * w), norm.to_nt(u), &out)) {
    out.status = EllipsoidStatus::kNotAnEllipsoid;
  } else if (!(out.rcond > std::numeric_limits<Scalar>::epsilon() * Scalar(100))) {
    out.status = EllipsoidStatus::kIllConditioned;
  } else {
    out.status = converged ? EllipsoidStatus::kOk : EllipsoidStatus::kNotConverged;
  }
  return out;
}

// Compiled once for the host with the batch calibrator (inst_batch_calibrator_<scalar>.cpp, the
// magvec::core_batch_<scalar> libraries): the units that link one only call these.
#ifdef MAGVEC_CORE_BATCH_DOUBLE_COMPILED
extern template class EllipsoidFit<double>;
extern template EllipsoidSolution<double> refine_ellipsoid_geometric<double>(
    SampleView<double>, const Normalization<double>&, const EllipsoidSolution<double>&,
    int) noexcept;
#endif
#ifdef MAGVEC_CORE_BATCH_FLOAT_COMPILED
extern template class EllipsoidFit<float>;
extern template EllipsoidSolution<float> refine_ellipsoid_geometric<float>(
    SampleView<float>, const Normalization<float>&, const EllipsoidSolution<float>&, int) noexcept;
#endif

}  // namespace magvec::core
