// Misalignment Rm between the INS body frame and the orthogonalised magnetometer frame, given the
// sensor model (W, o) from the ellipsoid fit. Li et al. 2023 eq. (15)-(21) as corrected in
// docs/equations.md:
//  * Plane compression (000-2, 000-3): f_i = (R_i e3)^T Rm^T h_s(i), the Up component of the
//    calibrated field in the geographic frame; cost sum_{i<j} (f_i - f_j)^2 = N sum (f_i - mean
//    f)^2, accumulated in one O(N) pass per Gauss-Newton iteration (O(1) memory).
//  * Joint fit (000-5): R_i^T Rm^T h_s(i) = h_n for all i, rotation + field vector, using all
//    components (~1.5x more precise, insensitive to vertical-field changes; yields declination).
// Rm = Ry(gm) Rx(bm) Rz(am) (Li eq. 3). Every h_s(i) is divided by its reference F_i, so a change
// of the field's intensity during the calibration does not bias either fit.
// Observability (000-4): with no pitch/roll variety the rotation about the vertical cannot be
// determined. The solvers measure it from their normal equations (predicted 1-sigma of the weakest
// direction) and refuse with kUnobservableHeading, or fix am on request (options.fix_heading).
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <Eigen/SVD>
#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <type_traits>
#include <utility>

#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sample_store.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

// Indices of Li's misalignment angles.
inline constexpr int kRmAlpha = 0;  // am, about the body z axis (the vertical when level)
inline constexpr int kRmBeta = 1;
inline constexpr int kRmGamma = 2;

// Rm(am, bm, gm) = Ry(gm) Rx(bm) Rz(am) and its partial derivatives.
template <typename Scalar>
Mat3<Scalar> li_rm_with_derivatives(const Vec3<Scalar>& ang,
                                    std::array<Mat3<Scalar>, 3>* d) noexcept {
  using std::cos;
  using std::sin;
  const Mat3<Scalar> rz = rot_z(ang(kRmAlpha)), rx = rot_x(ang(kRmBeta)), ry = rot_y(ang(kRmGamma));
  if (d != nullptr) {
    const Scalar ca = cos(ang(0)), sa = sin(ang(0)), cb = cos(ang(1)), sb = sin(ang(1));
    const Scalar cg = cos(ang(2)), sg = sin(ang(2));
    Mat3<Scalar> drz, drx, dry;
    drz << -sa, ca, 0, -ca, -sa, 0, 0, 0, 0;
    drx << 0, 0, 0, 0, -sb, cb, 0, -cb, -sb;
    dry << -sg, 0, -cg, 0, 0, 0, cg, 0, -sg;
    (*d)[kRmAlpha] = ry * rx * drz;
    (*d)[kRmBeta] = ry * drx * rz;
    (*d)[kRmGamma] = dry * rx * rz;
  }
  return ry * rx * rz;
}

// Body-frame rotation axis that a change of each Li angle produces (for naming a weak direction).
template <typename Scalar>
Mat3<Scalar> li_rm_axes_body(const Vec3<Scalar>& ang) noexcept {
  Mat3<Scalar> axes;
  axes.col(0) = Vec3<Scalar>::UnitZ();
  axes.col(1) = rot_z(ang(0)).transpose() * Vec3<Scalar>::UnitX();
  axes.col(2) = (rot_x(ang(1)) * rot_z(ang(0))).transpose() * Vec3<Scalar>::UnitY();
  return axes;
}

enum class MisalignmentStatus : std::uint8_t {
  kOk,
  kTooFewSamples,
  kUnobservableHeading,  // no pitch/roll variety: rotation about the vertical undetermined
  kIllConditioned,
  kNotConverged,
};

template <typename Scalar>
struct MisalignmentOptions {
  bool fix_heading = false;  // hold am at fixed_heading_rad (for level-only data)
  Scalar fixed_heading_rad{0};
  Scalar max_sigma_rad = deg_to_rad(Scalar(0.5));  // weakest direction's 1-sigma limit
  // Floor of the per-sample residual SD [normalised, i.e. relative to F] used by the
  // observability test, so noise-free degenerate data is still refused.
  Scalar noise_floor = Scalar(1e-5);
  int max_iterations = 30;
};

template <typename Scalar>
struct MisalignmentSolution {
  MisalignmentStatus status = MisalignmentStatus::kTooFewSamples;
  Vec3<Scalar> rm_rad = Vec3<Scalar>::Zero();
  Vec3<Scalar> rm_sigma_rad = Vec3<Scalar>::Zero();
  bool has_h_n = false;
  Vec3<Scalar> h_n = Vec3<Scalar>::Zero();        // [nT] (joint fit; plane compression: mean)
  Vec3<Scalar> h_n_sigma = Vec3<Scalar>::Zero();  // [nT] (joint fit)
  Vec3<Scalar> weak_axis_body =
      Vec3<Scalar>::Zero();  // body rotation axis of the weakest direction
  Scalar weak_sigma_rad{0};  // predicted 1-sigma along it
  Scalar residual_rms{0};    // normalised (relative to F)
  Scalar rcond{0};
  bool heading_fixed = false;
  int iterations{0};
};

namespace detail {

// Calibrated field divided by its reference: h~ = W (m - o) / F (unit length when calibrated).
template <typename Scalar>
Vec3<Scalar> unit_field(const StoredSample<Scalar>& s, const Mat3<Scalar>& w,
                        const Vec3<Scalar>& o) noexcept {
  return w * (s.raw() - o) / s.f;
}

template <typename Scalar>
bool usable(const StoredSample<Scalar>& s) noexcept {
  return s.has_attitude() && !s.outlier();
}

// Closed-form start: u_i^T X h~_i = const is linear in X = Rm^T (up to scale); X is the smallest
// eigenvector of the centred 9x9 scatter of vec(u_i h~_i^T), projected onto SO(3). Returns false
// when that eigenvector is not well separated (degenerate attitudes).
template <typename Scalar>
bool rm_linear_start(SampleView<std::type_identity_t<Scalar>> store, const Mat3<Scalar>& w,
                     const Vec3<Scalar>& o, Vec3<Scalar>* ang) noexcept {
  Mat<Scalar, 9, 9> c = Mat<Scalar, 9, 9>::Zero();
  Vec<Scalar, 9> sum = Vec<Scalar, 9>::Zero();
  std::size_t n = 0;
  for (std::size_t i = 0; i < store.size(); ++i) {
    if (!usable(store[i])) continue;
    const Vec3<Scalar> u = store[i].r_bn().col(2);
    const Vec3<Scalar> h = unit_field(store[i], w, o);
    Vec<Scalar, 9> a;
    for (int r = 0; r < 3; ++r)
      a.template segment<3>(3 * r) = u(r) * h;
    c.template selfadjointView<Eigen::Upper>().rankUpdate(a);
    sum += a;
    ++n;
  }
  if (n < 9) return false;
  c = c.template selfadjointView<Eigen::Upper>();
  c -= sum * sum.transpose() / static_cast<Scalar>(n);
  Vec<Scalar, 9> evals;
  Mat<Scalar, 9, 9> evecs;
  if (!core::symmetric_eigen_jacobi<Scalar, 9>(c, &evals, &evecs)) return false;
  if (!(evals(0) < Scalar(1e-2) * evals(1))) return false;
  Mat3<Scalar> x;
  for (int r = 0; r < 3; ++r)
    x.row(r) = evecs.col(0).template segment<3>(3 * r).transpose();
  if (x.determinant() < Scalar(0)) x = -x;
  const Eigen::JacobiSVD<Mat3<Scalar>> svd(x, Eigen::ComputeFullU | Eigen::ComputeFullV);
  Mat3<Scalar> rot = svd.matrixU() * svd.matrixV().transpose();
  if (rot.determinant() < Scalar(0)) return false;
  const LiEuler<Scalar> e = li_from_r_bn<Scalar>(Mat3<Scalar>(rot.transpose()));
  *ang = Vec3<Scalar>(e.alpha, e.beta, e.gamma);
  return ang->allFinite();
}

// Observability of the active angle block of a (Schur-complemented) normal matrix.
template <typename Scalar>
void assess_angles(const Mat3<Scalar>& n_aa, Scalar sigma2, const Vec3<Scalar>& ang,
                   const MisalignmentOptions<Scalar>& opt,
                   MisalignmentSolution<Scalar>* out) noexcept {
  const int first = opt.fix_heading ? 1 : 0;
  const int dim = 3 - first;
  Mat3<Scalar> a = n_aa;
  if (opt.fix_heading) {
    a.row(0).setZero();
    a.col(0).setZero();
    a(0, 0) = Scalar(1);
  }
  const Eigen::SelfAdjointEigenSolver<Mat3<Scalar>> es(a);
  // Eigenvalues ascending; with am fixed the artificial unit eigenvalue is skipped.
  int weakest = 0;
  if (opt.fix_heading) {
    weakest = std::abs(es.eigenvectors()(0, 0)) > Scalar(0.5) ? 1 : 0;
  }
  const Scalar lmin = es.eigenvalues()(weakest);
  const Scalar lmax = es.eigenvalues()(2);
  out->rcond = (lmax > Scalar(0) && lmin > Scalar(0)) ? lmin / lmax : Scalar(0);
  out->weak_sigma_rad =
      lmin > Scalar(0) ? std::sqrt(sigma2 / lmin) : std::numeric_limits<Scalar>::infinity();
  const Vec3<Scalar> v = es.eigenvectors().col(weakest);
  const Vec3<Scalar> axis = li_rm_axes_body(ang) * v;
  out->weak_axis_body = axis.norm() > Scalar(0) ? Vec3<Scalar>(axis.normalized()) : axis;
  out->rm_sigma_rad.setZero();
  if (lmin > Scalar(0)) {
    const Mat3<Scalar> cov = es.eigenvectors() * es.eigenvalues().cwiseInverse().asDiagonal() *
                             es.eigenvectors().transpose() * sigma2;
    for (int k = first; k < 3; ++k)
      out->rm_sigma_rad(k) = std::sqrt(cov(k, k));
  }
  (void)dim;
  if (!(out->weak_sigma_rad <= opt.max_sigma_rad)) {
    out->status = MisalignmentStatus::kUnobservableHeading;
  }
}

}  // namespace detail

// Li's plane compression in its O(N) form. w, o: sensor model from the ellipsoid fit.
template <typename Scalar>
MisalignmentSolution<Scalar> plane_compression(
    SampleView<std::type_identity_t<Scalar>> store, const Mat3<Scalar>& w, const Vec3<Scalar>& o,
    const MisalignmentOptions<Scalar>& opt = {}) noexcept {
  MisalignmentSolution<Scalar> out;
  out.heading_fixed = opt.fix_heading;
  Vec3<Scalar> ang = Vec3<Scalar>::Zero();
  if (!detail::rm_linear_start(store, w, o, &ang)) ang.setZero();
  if (opt.fix_heading) ang(kRmAlpha) = opt.fixed_heading_rad;
  const Scalar tol = detail::default_tolerance<Scalar>();
  Mat3<Scalar> nmat = Mat3<Scalar>::Zero();
  Scalar cost{0};
  std::size_t n = 0;
  bool converged = false;
  int it = 0;
  for (; it < opt.max_iterations; ++it) {
    std::array<Mat3<Scalar>, 3> d;
    const Mat3<Scalar> rm = li_rm_with_derivatives(ang, &d);
    Mat3<Scalar> sjj = Mat3<Scalar>::Zero();
    Vec3<Scalar> sj = Vec3<Scalar>::Zero(), sfj = Vec3<Scalar>::Zero();
    Scalar sf{0}, sff{0};
    n = 0;
    for (std::size_t i = 0; i < store.size(); ++i) {
      const StoredSample<Scalar>& s = store[i];
      if (!detail::usable(s)) continue;
      const Vec3<Scalar> u = s.r_bn().col(2);  // Up in body components
      const Vec3<Scalar> h = detail::unit_field(s, w, o);
      const Scalar f = u.dot(rm.transpose() * h);
      Vec3<Scalar> j;
      for (int k = 0; k < 3; ++k)
        j(k) = u.dot(d[static_cast<std::size_t>(k)].transpose() * h);
      sjj.template selfadjointView<Eigen::Upper>().rankUpdate(j);
      sj += j;
      sfj += f * j;
      sf += f;
      sff += f * f;
      ++n;
    }
    if (n < 4) return out;
    const Scalar nn = static_cast<Scalar>(n);
    nmat = Mat3<Scalar>(sjj.template selfadjointView<Eigen::Upper>()) - sj * sj.transpose() / nn;
    Vec3<Scalar> g = sfj - sf * sj / nn;
    cost = std::max(sff - sf * sf / nn, Scalar(0));
    Mat3<Scalar> a = nmat;
    if (opt.fix_heading) {
      a.row(0).setZero();
      a.col(0).setZero();
      a(0, 0) = Scalar(1);
      g(0) = Scalar(0);
    }
    const Eigen::LDLT<Mat3<Scalar>> ldlt(a);
    const Vec3<Scalar> step = -ldlt.solve(g);
    if (ldlt.info() != Eigen::Success || !step.allFinite()) break;
    // A direction the data cannot see must not wander: stop on a degenerate system.
    if (step.norm() > Scalar(1)) break;
    ang += step;
    if (step.template lpNorm<Eigen::Infinity>() < tol) {
      converged = true;
      ++it;
      break;
    }
  }
  out.iterations = it;
  out.rm_rad = Vec3<Scalar>(wrap_pi(ang(0)), wrap_pi(ang(1)), wrap_pi(ang(2)));
  const Scalar dof = static_cast<Scalar>(n) - Scalar(opt.fix_heading ? 3 : 4);
  const Scalar var = dof > Scalar(0) ? cost / dof : Scalar(0);
  out.residual_rms = std::sqrt(cost / static_cast<Scalar>(n > 0 ? n : 1));
  out.status = converged ? MisalignmentStatus::kOk : MisalignmentStatus::kNotConverged;
  detail::assess_angles(nmat, std::max(var, opt.noise_floor * opt.noise_floor), ang, opt, &out);
  // Field vector implied by the solution: mean of the compensated geographic field.
  const Mat3<Scalar> rm = li_rm(out.rm_rad);
  Vec3<Scalar> hsum = Vec3<Scalar>::Zero();
  for (std::size_t i = 0; i < store.size(); ++i) {
    if (!detail::usable(store[i])) continue;
    hsum += store[i].r_bn().transpose() * (rm.transpose() * (w * (store[i].raw() - o)));
  }
  out.has_h_n = n > 0;
  out.h_n = hsum / static_cast<Scalar>(n > 0 ? n : 1);
  return out;
}

// Joint fit of Rm and the field direction/vector: r_i = R_i^T Rm^T h~_i - d, d a free 3-vector
// (h_n = d * mean F). Gauss-Newton on 6 parameters, streaming normal equations.
template <typename Scalar>
MisalignmentSolution<Scalar> joint_rm_hn(SampleView<std::type_identity_t<Scalar>> store,
                                         const Mat3<Scalar>& w, const Vec3<Scalar>& o,
                                         const MisalignmentOptions<Scalar>& opt = {}) noexcept {
  constexpr int kP = 6;
  MisalignmentSolution<Scalar> out;
  out.heading_fixed = opt.fix_heading;
  Vec3<Scalar> ang = Vec3<Scalar>::Zero();
  if (!detail::rm_linear_start(store, w, o, &ang)) ang.setZero();
  if (opt.fix_heading) ang(kRmAlpha) = opt.fixed_heading_rad;
  // Start d at the mean of the rotated samples.
  Vec3<Scalar> dvec = Vec3<Scalar>::Zero();
  Scalar fsum{0};
  std::size_t n = 0;
  {
    const Mat3<Scalar> rm = li_rm(ang);
    for (std::size_t i = 0; i < store.size(); ++i) {
      if (!detail::usable(store[i])) continue;
      dvec += store[i].r_bn().transpose() * (rm.transpose() * detail::unit_field(store[i], w, o));
      fsum += store[i].f;
      ++n;
    }
  }
  if (n < 4) return out;
  const Scalar nn = static_cast<Scalar>(n);
  dvec /= nn;
  const Scalar fmean = fsum / nn;
  const Scalar tol = detail::default_tolerance<Scalar>();
  Mat<Scalar, kP, kP> nmat = Mat<Scalar, kP, kP>::Zero();
  Scalar sse{0};
  bool converged = false;
  int it = 0;
  for (; it < opt.max_iterations; ++it) {
    std::array<Mat3<Scalar>, 3> d;
    const Mat3<Scalar> rm = li_rm_with_derivatives(ang, &d);
    nmat.setZero();
    Vec<Scalar, kP> g = Vec<Scalar, kP>::Zero();
    sse = Scalar(0);
    for (std::size_t i = 0; i < store.size(); ++i) {
      const StoredSample<Scalar>& s = store[i];
      if (!detail::usable(s)) continue;
      const Mat3<Scalar> rt = s.r_bn().transpose();
      const Vec3<Scalar> h = detail::unit_field(s, w, o);
      const Vec3<Scalar> r = rt * (rm.transpose() * h) - dvec;
      Mat<Scalar, 3, kP> j;
      for (int k = 0; k < 3; ++k)
        j.col(k) = rt * (d[static_cast<std::size_t>(k)].transpose() * h);
      j.template rightCols<3>() = -Mat3<Scalar>::Identity();
      nmat.noalias() += j.transpose().lazyProduct(j);  // fixed-size, heap-free (not rankUpdate:
                                                       // its blocked kernel has a heap fallback)
      g += j.transpose() * r;
      sse += r.squaredNorm();
    }
    nmat = nmat.template selfadjointView<Eigen::Upper>();
    Mat<Scalar, kP, kP> a = nmat;
    if (opt.fix_heading) {
      a.row(0).setZero();
      a.col(0).setZero();
      a(0, 0) = Scalar(1);
      g(0) = Scalar(0);
    }
    const Eigen::LDLT<Mat<Scalar, kP, kP>> ldlt(a);
    const Vec<Scalar, kP> step = -ldlt.solve(g);
    if (ldlt.info() != Eigen::Success || !step.allFinite()) break;
    if (step.template head<3>().norm() > Scalar(1)) break;
    ang += step.template head<3>();
    dvec += step.template tail<3>();
    if (step.template lpNorm<Eigen::Infinity>() < tol) {
      converged = true;
      ++it;
      break;
    }
  }
  out.iterations = it;
  out.rm_rad = Vec3<Scalar>(wrap_pi(ang(0)), wrap_pi(ang(1)), wrap_pi(ang(2)));
  const Scalar dof = Scalar(3) * nn - Scalar(opt.fix_heading ? 5 : 6);
  const Scalar var = dof > Scalar(0) ? sse / dof : Scalar(0);
  out.residual_rms = std::sqrt(sse / (Scalar(3) * nn));
  out.status = converged ? MisalignmentStatus::kOk : MisalignmentStatus::kNotConverged;
  // Angle block after eliminating d (Schur complement; N_dd = n I).
  const Mat3<Scalar> n_ad = nmat.template block<3, 3>(0, 3);
  const Mat3<Scalar> schur = nmat.template topLeftCorner<3, 3>() - n_ad * n_ad.transpose() / nn;
  const Scalar sigma2 = std::max(var, opt.noise_floor * opt.noise_floor);
  detail::assess_angles(schur, sigma2, ang, opt, &out);
  out.has_h_n = true;
  out.h_n = dvec * fmean;
  // d is the mean of the rotated samples at the solution: its SD is sigma / sqrt(n) per component
  // plus the angle uncertainty, which is second order for it; report the first term.
  out.h_n_sigma = Vec3<Scalar>::Constant(std::sqrt(sigma2 / nn) * fmean);
  return out;
}

// Compiled once for the host with the batch calibrator (inst_batch_calibrator_<scalar>.cpp, the
// magvec::core_batch_<scalar> libraries): the units that link one only call these.
#ifdef MAGVEC_CORE_BATCH_DOUBLE_COMPILED
extern template MisalignmentSolution<double> plane_compression<double>(
    SampleView<double>, const Mat3<double>&, const Vec3<double>&,
    const MisalignmentOptions<double>&) noexcept;
extern template MisalignmentSolution<double> joint_rm_hn<double>(
    SampleView<double>, const Mat3<double>&, const Vec3<double>&,
    const MisalignmentOptions<double>&) noexcept;
#endif
#ifdef MAGVEC_CORE_BATCH_FLOAT_COMPILED
extern template MisalignmentSolution<float> plane_compression<float>(
    SampleView<float>, const Mat3<float>&, const Vec3<float>&,
    const MisalignmentOptions<float>&) noexcept;
extern template MisalignmentSolution<float> joint_rm_hn<float>(
    SampleView<float>, const Mat3<float>&, const Vec3<float>&,
    const MisalignmentOptions<float>&) noexcept;
#endif

}  // namespace magvec::core
