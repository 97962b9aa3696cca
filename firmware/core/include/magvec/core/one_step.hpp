// One-step (efficient) calibration, ERRATA 000-6: a weighted least-squares fit of all 14 parameters
// of Li et al. 2023 eq. (7) at once,
//   ks (3), O (3), Kof (3), Rm angles (3), direction of h_n (2; its magnitude is tied to the scalar
//   reference: h_n(i) = F_i d, |d| = 1),
// with the vector residual of every sample in the geographic frame
//   r_i = R_i^T Rm^T W (m_i - Kof) - F_i d,          W = (Ks Ko)^-1,
// weighted by its covariance from the magnetometer noise and the INS angle noise:
//   Sigma_i = s_m^2 P P^T + s_att^2 sum_k (a_k x h_n)(a_k x h_n)^T,   P = R_i^T Rm^T W,
// where a_k are the geographic rotation axes of the INS angles (Li Euler: Up; Rz(alpha)^T e1;
// R_i^T e2), or isotropic attitude noise. The attitude noise acts only across h_n, the magnetometer
// noise in all directions, so the intensity (0.3 nT) and the direction (~14 nT) are weighted apart:
// this is the first-order maximum-likelihood estimator. Gauss-Newton started from the two-step
// result; each iteration is one pass over the samples (linear in N, O(1) memory beyond the store).
// 1-sigma of every parameter from the inverse normal matrix, scaled by the a-posteriori variance
// factor chi^2 / dof.
#pragma once

#include <Eigen/Cholesky>
#include <Eigen/Eigenvalues>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/sample_store.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

enum class AttitudeNoiseModel : std::uint8_t {
  kLiEuler,    // independent noise on Li's heading, pitch, roll (INS reporting Euler angles)
  kIsotropic,  // independent small-rotation noise about three orthogonal axes
};

// Standard deviations of Li's parameters (same layout as LiParams).
template <typename Scalar>
struct LiSigmas {
  Vec3<Scalar> ks = Vec3<Scalar>::Zero();
  Vec3<Scalar> o_rad = Vec3<Scalar>::Zero();
  Vec3<Scalar> kof = Vec3<Scalar>::Zero();  // [nT]
  Vec3<Scalar> rm_rad = Vec3<Scalar>::Zero();
};

enum class OneStepStatus : std::uint8_t {
  kOk,
  kTooFewSamples,
  kUnobservableHeading,
  kIllConditioned,
  kNotConverged,
};

template <typename Scalar>
struct OneStepOptions {
  Scalar mag_noise_nT = Scalar(0.3);
  Scalar attitude_noise_rad = deg_to_rad(Scalar(0.015));
  AttitudeNoiseModel attitude_model = AttitudeNoiseModel::kLiEuler;
  bool fix_heading = false;  // hold am at the start value (ERRATA 000-4)
  bool scale_sigma_by_residual = true;
  Scalar max_rm_sigma_rad = deg_to_rad(Scalar(0.5));
  Scalar min_rcond = std::sqrt(std::numeric_limits<Scalar>::epsilon()) * Scalar(1e-2);
  int max_iterations = 30;
};

template <typename Scalar>
struct OneStepSolution {
  OneStepStatus status = OneStepStatus::kTooFewSamples;
  LiParams<Scalar> li{};
  LiSigmas<Scalar> sigma{};
  Vec3<Scalar> h_n = Vec3<Scalar>::Zero();        // F_mean * d [nT]
  Vec3<Scalar> h_n_sigma = Vec3<Scalar>::Zero();  // [nT]
  Scalar chi2_per_dof{0};
  Scalar rcond{0};
  std::size_t samples{0};
  int iterations{0};
  bool heading_fixed = false;
};

template <typename Scalar>
class OneStepFit {
 public:
  static constexpr int kParams = 14;
  static constexpr int kIdxKs = 0;
  static constexpr int kIdxO = 3;
  static constexpr int kIdxKof = 6;
  static constexpr int kIdxRm = 9;
  static constexpr int kIdxDir = 12;
  static_assert(kIdxDir + 2 == kParams, "14 parameters: Ks, O, Kof, Rm, direction of h_n");
  using MatP = Mat<Scalar, kParams, kParams>;
  using VecP = Vec<Scalar, kParams>;

  // start: two-step Li parameters (Kof in nT); d_start: direction of h_n (any length > 0).
  template <std::size_t Capacity>
  static OneStepSolution<Scalar> solve(const SampleStore<Scalar, Capacity>& store,
                                       const Normalization<Scalar>& norm,
                                       const LiParams<Scalar>& start, const Vec3<Scalar>& d_start,
                                       const OneStepOptions<Scalar>& opt) noexcept {
    OneStepSolution<Scalar> out;
    out.heading_fixed = opt.fix_heading;
    Vec3<Scalar> ks = start.ks, o_rad = start.o_rad, u = norm.to_unit(start.kof), rm = start.rm_rad;
    Vec3<Scalar> d = d_start.normalized();
    const Scalar sm = opt.mag_noise_nT / norm.scale;
    const Scalar sa2 = opt.attitude_noise_rad * opt.attitude_noise_rad;
    const Scalar tol = detail::default_tolerance<Scalar>();
    MatP n = MatP::Identity();
    Vec3<Scalar> t1, t2;
    Scalar chi2{0}, prev_chi2 = std::numeric_limits<Scalar>::infinity();
    Scalar fsum{0};
    std::size_t count = 0;
    VecP last_step = VecP::Zero();
    bool converged = false;
    int it = 0;
    for (; it < opt.max_iterations; ++it) {
      tangent_basis(d, &t1, &t2);
      VecP g;
      pass(store, norm, ks, o_rad, u, rm, d, t1, t2, sm, sa2, opt.attitude_model, &n, &g, &chi2,
           &fsum, &count);
      if (count < 5) return out;
      if (!(chi2 <= prev_chi2 * (Scalar(1) + Scalar(1e-6))) && it > 0 && last_step.norm() > tol) {
        // The last step overshot: go back half of it and re-evaluate.
        last_step *= Scalar(-0.5);
        apply(last_step, &ks, &o_rad, &u, &rm, &d, t1, t2);
        continue;
      }
      prev_chi2 = chi2;
      MatP a = n;
      if (opt.fix_heading) {
        a.row(kIdxRm + kRmAlpha).setZero();
        a.col(kIdxRm + kRmAlpha).setZero();
        a(kIdxRm + kRmAlpha, kIdxRm + kRmAlpha) = Scalar(1);
        g(kIdxRm + kRmAlpha) = Scalar(0);
      }
      const Eigen::LDLT<MatP> ldlt(a);
      VecP step = -ldlt.solve(g);
      if (ldlt.info() != Eigen::Success || !step.allFinite()) break;
      if (step.template segment<3>(kIdxRm).norm() > Scalar(1)) break;  // degenerate direction
      apply(step, &ks, &o_rad, &u, &rm, &d, t1, t2);
      last_step = step;
      // Converged when every change is tiny in absolute terms or against its own uncertainty.
      bool small = true;
      for (int k = 0; k < kParams; ++k) {
        const Scalar sig = a(k, k) > Scalar(0) ? Scalar(1) / std::sqrt(a(k, k)) : Scalar(0);
        if (std::abs(step(k)) > tol && std::abs(step(k)) > Scalar(1e-4) * sig) small = false;
      }
      if (small) {
        converged = true;
        ++it;
        break;
      }
    }
    out.iterations = it;
    out.samples = count;
    out.li.ks = ks;
    out.li.o_rad = o_rad;
    out.li.kof = norm.to_nt(u);
    out.li.rm_rad = Vec3<Scalar>(wrap_pi(rm(0)), wrap_pi(rm(1)), wrap_pi(rm(2)));
    const Scalar fmean = fsum / static_cast<Scalar>(count > 0 ? count : 1);
    out.h_n = d * fmean;
    const int active = opt.fix_heading ? kParams - 1 : kParams;
    const Scalar dof = Scalar(3) * static_cast<Scalar>(count) - Scalar(active);
    out.chi2_per_dof = dof > Scalar(0) ? chi2 / dof : Scalar(0);
    out.status = converged ? OneStepStatus::kOk : OneStepStatus::kNotConverged;

    // Covariance and observability on the active parameters.
    MatP a = n;
    if (opt.fix_heading) {
      a.row(kIdxRm + kRmAlpha).setZero();
      a.col(kIdxRm + kRmAlpha).setZero();
      a(kIdxRm + kRmAlpha, kIdxRm + kRmAlpha) = Scalar(1);
    }
    VecP weakest;
    out.rcond = detail::scaled_rcond<Scalar, kParams>(a, &weakest);
    const Scalar factor = opt.scale_sigma_by_residual ? out.chi2_per_dof : Scalar(1);
    const Eigen::LDLT<MatP> ldlt(a);
    MatP cov = ldlt.solve(MatP::Identity()) * factor;
    if (opt.fix_heading) cov(kIdxRm + kRmAlpha, kIdxRm + kRmAlpha) = Scalar(0);
    VecP sd;
    for (int k = 0; k < kParams; ++k)
      sd(k) = std::sqrt(std::max(cov(k, k), Scalar(0)));
    out.sigma.ks = sd.template segment<3>(kIdxKs);
    out.sigma.o_rad = sd.template segment<3>(kIdxO);
    out.sigma.kof = sd.template segment<3>(kIdxKof) * norm.scale;
    out.sigma.rm_rad = sd.template segment<3>(kIdxRm);
    Mat<Scalar, 3, 2> tb;
    tb << t1, t2;
    const Mat3<Scalar> cov_h =
        tb * cov.template block<2, 2>(kIdxDir, kIdxDir) * tb.transpose() * (fmean * fmean);
    out.h_n_sigma = cov_h.diagonal().cwiseMax(Scalar(0)).cwiseSqrt();

    // Unit-free predicted SD of the angles (noise model only) decides observability.
    const MatP cov_model = ldlt.solve(MatP::Identity());
    Scalar worst_rm{0};
    for (int k = opt.fix_heading ? 1 : 0; k < 3; ++k) {
      worst_rm =
          std::max(worst_rm, std::sqrt(std::max(cov_model(kIdxRm + k, kIdxRm + k), Scalar(0))));
    }
    const bool rm_weak = weakest.template segment<3>(kIdxRm).squaredNorm() > Scalar(0.5);
    if (!(out.rcond >= opt.min_rcond) || !ldlt.isPositive() || ldlt.info() != Eigen::Success) {
      out.status = rm_weak ? OneStepStatus::kUnobservableHeading : OneStepStatus::kIllConditioned;
    } else if (!(worst_rm <= opt.max_rm_sigma_rad)) {
      out.status = OneStepStatus::kUnobservableHeading;
    }
    return out;
  }

  // Intensity and per-sample covariance-weighted pass; public for benchmarks and tests.
  template <std::size_t Capacity>
  static void pass(const SampleStore<Scalar, Capacity>& store, const Normalization<Scalar>& norm,
                   const Vec3<Scalar>& ks, const Vec3<Scalar>& o_rad, const Vec3<Scalar>& u,
                   const Vec3<Scalar>& rm_ang, const Vec3<Scalar>& d, const Vec3<Scalar>& t1,
                   const Vec3<Scalar>& t2, Scalar sm, Scalar sa2, AttitudeNoiseModel model, MatP* n,
                   VecP* g, Scalar* chi2, Scalar* fsum, std::size_t* count) noexcept {
    using std::cos;
    using std::sin;
    const Mat3<Scalar> ko = li_ko(o_rad);
    const Mat3<Scalar> w = (ks.asDiagonal() * ko).inverse();
    std::array<Mat3<Scalar>, 3> drm;
    const Mat3<Scalar> rmt = li_rm_with_derivatives(rm_ang, &drm).transpose();
    std::array<Mat3<Scalar>, 3> drmt;
    for (std::size_t k = 0; k < 3; ++k)
      drmt[k] = drm[k].transpose();
    // Rows of dKo/dO_k that are non-zero: O1 -> row z, O2 and O3 -> row y.
    const Vec3<Scalar> dko1(cos(o_rad(0)), 0, -sin(o_rad(0)));
    const Vec3<Scalar> dko2(-sin(o_rad(1)) * sin(o_rad(2)), -sin(o_rad(1)) * cos(o_rad(2)),
                            cos(o_rad(1)));
    const Vec3<Scalar> dko3(cos(o_rad(1)) * cos(o_rad(2)), -cos(o_rad(1)) * sin(o_rad(2)), 0);
    n->setZero();
    g->setZero();
    *chi2 = Scalar(0);
    *fsum = Scalar(0);
    *count = 0;
    for (std::size_t i = 0; i < store.size(); ++i) {
      const StoredSample<Scalar>& s = store[i];
      if (!detail::usable(s)) continue;
      const Mat3<Scalar> r = s.r_bn();
      const Mat3<Scalar> mt = r.transpose() * rmt;  // R^T Rm^T
      const Mat3<Scalar> p = mt * w;
      const Vec3<Scalar> hs = w * (norm.to_unit(s.raw()) - u);
      const Scalar fn = s.f / norm.scale;
      const Vec3<Scalar> hn = fn * d;
      const Vec3<Scalar> res = mt * hs - hn;
      Mat<Scalar, 3, kParams> j;
      for (int k = 0; k < 3; ++k)
        j.col(kIdxKs + k) = -p.col(k) * ko.row(k).dot(hs);
      j.col(kIdxO + 0) = -p.col(2) * (ks(2) * dko1.dot(hs));
      j.col(kIdxO + 1) = -p.col(1) * (ks(1) * dko2.dot(hs));
      j.col(kIdxO + 2) = -p.col(1) * (ks(1) * dko3.dot(hs));
      j.template block<3, 3>(0, kIdxKof) = -p;
      for (int k = 0; k < 3; ++k)
        j.col(kIdxRm + k) = r.transpose() * (drmt[static_cast<std::size_t>(k)] * hs);
      j.col(kIdxDir) = -fn * t1;
      j.col(kIdxDir + 1) = -fn * t2;
      // Residual covariance.
      Mat3<Scalar> cov = (sm * sm) * (p * p.transpose());
      if (model == AttitudeNoiseModel::kLiEuler) {
        const Scalar hx = r(1, 1), hy = -r(1, 0);
        const Scalar hl = std::sqrt(hx * hx + hy * hy);
        const Vec3<Scalar> a1 =
            hl > Scalar(0) ? Vec3<Scalar>(hx / hl, hy / hl, 0) : Vec3<Scalar>::UnitX();
        const Vec3<Scalar> c0 = Vec3<Scalar>::UnitZ().cross(hn);
        const Vec3<Scalar> c1 = a1.cross(hn);
        const Vec3<Scalar> c2 = Vec3<Scalar>(r.row(1).transpose()).cross(hn);
        cov += sa2 * (c0 * c0.transpose() + c1 * c1.transpose() + c2 * c2.transpose());
      } else {
        cov += sa2 * (hn.squaredNorm() * Mat3<Scalar>::Identity() - hn * hn.transpose());
      }
      const Eigen::LLT<Mat3<Scalar>> llt(cov);
      if (llt.info() != Eigen::Success) continue;
      const Mat<Scalar, 3, kParams> jw = llt.matrixL().solve(j);
      const Vec3<Scalar> rw = llt.matrixL().solve(res);
      n->template selfadjointView<Eigen::Upper>().rankUpdate(jw.transpose());
      *g += jw.transpose() * rw;
      *chi2 += rw.squaredNorm();
      *fsum += s.f;
      ++*count;
    }
    *n = n->template selfadjointView<Eigen::Upper>();
  }

  static void tangent_basis(const Vec3<Scalar>& d, Vec3<Scalar>* t1, Vec3<Scalar>* t2) noexcept {
    const Vec3<Scalar> ref =
        std::abs(d(0)) < Scalar(0.9) ? Vec3<Scalar>::UnitX() : Vec3<Scalar>::UnitY();
    *t1 = d.cross(ref).normalized();
    *t2 = d.cross(*t1);
  }

 private:
  static void apply(const VecP& step, Vec3<Scalar>* ks, Vec3<Scalar>* o_rad, Vec3<Scalar>* u,
                    Vec3<Scalar>* rm, Vec3<Scalar>* d, const Vec3<Scalar>& t1,
                    const Vec3<Scalar>& t2) noexcept {
    *ks += step.template segment<3>(kIdxKs);
    *o_rad += step.template segment<3>(kIdxO);
    *u += step.template segment<3>(kIdxKof);
    *rm += step.template segment<3>(kIdxRm);
    *d = (*d + step(kIdxDir) * t1 + step(kIdxDir + 1) * t2).normalized();
  }
};

}  // namespace magvec::core
