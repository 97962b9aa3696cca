// One-step (efficient) calibration, docs/equations.md E-Li-6: a weighted least-squares fit of all
// 14 parameters of Li et al. 2023 eq. (7) at once,
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
#include "magvec/core/frames.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/output_envelope.hpp"
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

// A prior calibration (its parameters and 1-sigmas) for the regularised (MAP) fit: the data update
// what they determine, the prior holds the rest. A sigma of 0 or non-finite: no prior on it.
template <typename Scalar>
struct OneStepPrior {
  LiParams<Scalar> mean{};
  LiSigmas<Scalar> sigma{};
};

template <typename Scalar>
struct OneStepOptions {
  Scalar mag_noise_nT = Scalar(0.3);  // start value when estimate_noise
  Scalar attitude_noise_rad = deg_to_rad(Scalar(0.015));
  AttitudeNoiseModel attitude_model = AttitudeNoiseModel::kLiEuler;
  // Estimate both noise figures from the residuals (variance components, docs/equations.md
  // "Noise from the data"); the values above are then only the start.
  bool estimate_noise = false;
  bool fix_heading = false;  // hold am at the start value (misalignment about the vertical)
  bool scale_sigma_by_residual = true;  // given noise: scale the covariance by chi^2/dof
  Scalar max_rm_sigma_rad = deg_to_rad(Scalar(0.5));
  // A parameter is determined when its 1-sigma is below this fraction of its natural size (scale
  // 1, angle 1 rad, offset F).
  Scalar max_relative_sigma = Scalar(0.02);
  Scalar min_rcond = std::sqrt(std::numeric_limits<Scalar>::epsilon()) * Scalar(1e-2);
  int max_iterations = 50;    // damped steps per noise round
  int max_noise_rounds = 10;  // variance-component rounds
  const OneStepPrior<Scalar>* prior = nullptr;
};

template <typename Scalar>
struct OneStepSolution {
  OneStepStatus status = OneStepStatus::kTooFewSamples;
  bool converged = false;
  LiParams<Scalar> li{};
  LiSigmas<Scalar> sigma{};
  Vec3<Scalar> h_n = Vec3<Scalar>::Zero();        // F_mean * d [nT]
  Vec3<Scalar> h_n_sigma = Vec3<Scalar>::Zero();  // [nT]
  Scalar chi2_per_dof{0};
  Scalar cost{0};  // chi^2 (+ prior term) at the solution, with the final noise figures
  Scalar rcond{0};
  std::size_t samples{0};
  int iterations{0};
  bool heading_fixed = false;
  // Noise figures in use at the solution (estimated, or the given ones) and, when estimated,
  // their 1-sigma.
  bool noise_estimated = false;
  Scalar mag_noise_nT{0};
  Scalar mag_noise_sigma_nT{0};
  Scalar attitude_noise_rad{0};
  Scalar attitude_noise_sigma_rad{0};
  // RMS of the normalised residuals over their median-based scale (1 for Gaussian residuals).
  Scalar tail_ratio{0};
  // What the parameters' covariance does to the outputs over the survey envelope of the data's
  // tilts (OneStepFit::output_uncertainty): per-axis RMS of the E/N/U error and RMS of the |h|
  // error [nT]; NaN when not evaluated.
  Scalar calibration_sigma_enu_nT = std::numeric_limits<Scalar>::quiet_NaN();
  Scalar calibration_sigma_f_nT = std::numeric_limits<Scalar>::quiet_NaN();
  std::uint32_t envelope_attitudes{0};
  // Bit k (parameter index kIdx*): its 1-sigma exceeds the "determined" limit.
  std::uint32_t undetermined{0};
  // With a prior: bit k of `updated` when the data determine parameter k (posterior 1-sigma below
  // half the prior's); bit k of `moved` when it left the prior mean by more than 2 posterior
  // sigmas.
  std::uint32_t updated{0};
  std::uint32_t moved{0};
};

// L^-1 B and L^-T b for the 3x3 Cholesky factor L of a sample's residual covariance, by
// substitution (the one-step pass here and the vector filter's update whiten with these). Eigen's
// triangular solve with a matrix right-hand side takes its blocked general path (packing, run-time
// sizes) even for a fixed 3-row block: with the rank-k update that was about 55 % of a one-step
// pass (perf, 17 000 samples).
template <typename Scalar, int N>
Mat<Scalar, 3, N> lower_solve(const Mat3<Scalar>& l, const Mat<Scalar, 3, N>& b) noexcept {
  // Column by column (contiguous in column-major storage; the row-wise expression cost the M4F
  // about 20 instructions per element through Eigen's strided row access), same operations.
  Mat<Scalar, 3, N> x;
  for (int c = 0; c < N; ++c) {
    const Scalar x0 = b(0, c) / l(0, 0);
    const Scalar x1 = (b(1, c) - l(1, 0) * x0) / l(1, 1);
    x(0, c) = x0;
    x(1, c) = x1;
    x(2, c) = (b(2, c) - l(2, 0) * x0 - l(2, 1) * x1) / l(2, 2);
  }
  return x;
}
template <typename Scalar>
Vec3<Scalar> upper_solve(const Mat3<Scalar>& l, const Vec3<Scalar>& b) noexcept {
  Vec3<Scalar> x;
  x(2) = b(2) / l(2, 2);
  x(1) = (b(1) - l(2, 1) * x(2)) / l(1, 1);
  x(0) = (b(0) - l(1, 0) * x(1) - l(2, 0) * x(2)) / l(0, 0);
  return x;
}

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
  static constexpr int kTailBins = 128;  // histogram of |r_w|^2 over [0, 32) for the median
  using MatP = Mat<Scalar, kParams, kParams>;
  using VecP = Vec<Scalar, kParams>;

  // Parameter names for reports, indexed like the parameter vector.
  static const char* param_name(int k) noexcept {
    static constexpr const char* kNames[kParams] = {
        "ks_x",  "ks_y",  "ks_z",     "O1",      "O2",       "O3",        "Kof_x",
        "Kof_y", "Kof_z", "Rm_alpha", "Rm_beta", "Rm_gamma", "h_n_dir_1", "h_n_dir_2"};
    return k >= 0 && k < kParams ? kNames[k] : "?";
  }

  struct Params {
    Vec3<Scalar> ks, o_rad, u, rm, d;  // u: Kof in normalised units; d: unit direction of h_n
  };

  // Sums of one pass over the samples for given parameters and noise (normalised units).
  struct PassSums {
    MatP n = MatP::Zero();  // J^T Sigma^-1 J
    VecP g = VecP::Zero();  // J^T Sigma^-1 r
    Scalar chi2{0};
    Scalar fsum{0};
    std::size_t count{0};
    // Variance components: q_k = r^T S^-1 V_k S^-1 r and t_k = tr(S^-1 V_k), k = magnetometer
    // (V = P P^T) and attitude (V = C C^T).
    Scalar q_mag{0}, t_mag{0}, q_att{0}, t_att{0};
    // Fisher information of the two variances: 1/2 sum tr(S^-1 V_k S^-1 V_l).
    Scalar f_mm{0}, f_ma{0}, f_aa{0};
    std::array<std::uint32_t, kTailBins> tail{};
  };

  // start: two-step (or prior) Li parameters (Kof in nT); d_start: direction of h_n (any length).
  static OneStepSolution<Scalar> solve(SampleView<Scalar> store, const Normalization<Scalar>& norm,
                                       const LiParams<Scalar>& start, const Vec3<Scalar>& d_start,
                                       const OneStepOptions<Scalar>& opt) noexcept {
    OneStepSolution<Scalar> out;
    out.heading_fixed = opt.fix_heading;
    Params p{start.ks, start.o_rad, norm.to_unit(start.kof), start.rm_rad, d_start.normalized()};
    // Noise in normalised units: sm per axis, sa per angle (rad).
    const Scalar sm_floor = std::sqrt(std::numeric_limits<Scalar>::epsilon()) * Scalar(0.1);
    Scalar sm = std::max(opt.mag_noise_nT / norm.scale, sm_floor);
    Scalar sa = std::max(opt.attitude_noise_rad, sm * Scalar(1e-3));
    PassSums sums;
    bool converged = false;
    int total_it = 0;
    const int rounds = opt.estimate_noise ? opt.max_noise_rounds : 1;
    for (int round = 0; round < rounds; ++round) {
      int it = 0;
      converged = minimise(store, norm, opt, sm, sa, &p, &sums, &it);
      total_it += it;
      if (sums.count < 5) return out;
      if (!opt.estimate_noise || !converged) break;
      // Variance-component update by Fisher scoring (for a covariance linear in the variances:
      // theta <- F^-1 u, u_k = 1/2 r^T S^-1 V_k S^-1 r), with the parameters' share of the
      // residual removed. Converges in a few rounds even when one component hides behind the
      // other (the plain fixed point theta_k q_k / t_k crawls there). No variance falls below a
      // tenth of its value in one round: from a start far below the truth (attitude noise 0.2 deg
      // against the 0.015 deg start) the full step can put the magnetometer variance at zero, the
      // residual covariance is then singular across the field and the next fit diverges. A
      // component held at that bound leaves the other its Fisher step given the held value, so a
      // variance the data put at zero descends while the other still converges
      // (docs/equations.md, variance components).
      const Scalar red =
          Scalar(1) - Scalar(kParams) / (Scalar(3) * static_cast<Scalar>(sums.count));
      const Scalar det = sums.f_mm * sums.f_aa - sums.f_ma * sums.f_ma;
      Scalar sm2 = sm * sm * sums.q_mag / std::max(sums.t_mag * red, Scalar(1e-30));
      Scalar sa2 = sa * sa * sums.q_att / std::max(sums.t_att * red, Scalar(1e-30));
      if (det > Scalar(0)) {
        const Scalar um = Scalar(0.5) * sums.q_mag / red, ua = Scalar(0.5) * sums.q_att / red;
        const Scalar lo_m = Scalar(0.1) * sm * sm, lo_a = Scalar(0.1) * sa * sa;
        sm2 = (sums.f_aa * um - sums.f_ma * ua) / det;
        sa2 = (sums.f_mm * ua - sums.f_ma * um) / det;
        if (sa2 < lo_a) {
          sa2 = lo_a;
          sm2 = (um - sums.f_ma * sa2) / sums.f_mm;
        }
        if (sm2 < lo_m) {
          sm2 = lo_m;
          sa2 = std::max((ua - sums.f_ma * sm2) / sums.f_aa, lo_a);
        }
      }
      const Scalar sm_new = std::max(std::sqrt(std::max(sm2, Scalar(0))), sm_floor);
      const Scalar sa_new = std::max(std::sqrt(std::max(sa2, Scalar(0))), sm_new * Scalar(1e-3));
      const Scalar change =
          std::max(std::abs(sm_new / sm - Scalar(1)), std::abs(sa_new / sa - Scalar(1)));
      sm = sm_new;
      sa = sa_new;
      if (change < Scalar(0.01)) {
        sums = pass(store, norm, p, p, sm, sa * sa, opt.attitude_model);
        break;
      }
    }
    out.converged = converged;
    out.iterations = total_it;
    out.samples = sums.count;
    out.li.ks = p.ks;
    out.li.o_rad = p.o_rad;
    out.li.kof = norm.to_nt(p.u);
    out.li.rm_rad = Vec3<Scalar>(wrap_pi(p.rm(0)), wrap_pi(p.rm(1)), wrap_pi(p.rm(2)));
    const Scalar fmean = sums.fsum / static_cast<Scalar>(sums.count > 0 ? sums.count : 1);
    out.h_n = p.d * fmean;
    const int active = opt.fix_heading ? kParams - 1 : kParams;
    const Scalar dof = Scalar(3) * static_cast<Scalar>(sums.count) - Scalar(active);
    out.chi2_per_dof = dof > Scalar(0) ? sums.chi2 / dof : Scalar(0);
    out.cost = sums.chi2 + prior_cost(opt.prior, norm, p);
    out.status = converged ? OneStepStatus::kOk : OneStepStatus::kNotConverged;
    out.noise_estimated = opt.estimate_noise;
    out.mag_noise_nT = sm * norm.scale;
    out.attitude_noise_rad = sa;
    if (opt.estimate_noise) {
      // Covariance of the variance estimates: the inverse of their Fisher information (which
      // sees how well the two components can be told apart); sigma(s) = sigma(s^2) / (2 s).
      const Scalar det = sums.f_mm * sums.f_aa - sums.f_ma * sums.f_ma;
      if (det > Scalar(0)) {
        const Scalar var_m = sums.f_aa / det, var_a = sums.f_mm / det;
        out.mag_noise_sigma_nT = std::sqrt(var_m) / (Scalar(2) * sm) * norm.scale;
        out.attitude_noise_sigma_rad = std::sqrt(var_a) / (Scalar(2) * sa);
      }
    }
    out.tail_ratio = tail_ratio(sums);

    // Covariance and observability on the active parameters.
    MatP a = sums.n;
    add_prior_information(opt.prior, norm, &a);
    if (opt.fix_heading) hold(kIdxRm + kRmAlpha, &a, nullptr);
    VecP weakest;
    out.rcond = detail::scaled_rcond<Scalar, kParams>(a, &weakest);
    const bool given = !opt.estimate_noise;
    const Scalar factor = given && opt.scale_sigma_by_residual ? out.chi2_per_dof : Scalar(1);
    const Eigen::LDLT<MatP> ldlt(a);
    // Column by column: a matrix right-hand side takes Eigen's blocked triangular solve, whose
    // workspace has a heap fallback the firmware images must not link (vector solves have none).
    MatP cov_model;
    for (int k = 0; k < kParams; ++k)
      cov_model.col(k) = ldlt.solve(VecP::Unit(k));
    MatP cov = cov_model * factor;
    if (opt.fix_heading) cov(kIdxRm + kRmAlpha, kIdxRm + kRmAlpha) = Scalar(0);
    VecP sd;
    for (int k = 0; k < kParams; ++k)
      sd(k) = std::sqrt(std::max(cov(k, k), Scalar(0)));
    out.sigma.ks = sd.template segment<3>(kIdxKs);
    out.sigma.o_rad = sd.template segment<3>(kIdxO);
    out.sigma.kof = sd.template segment<3>(kIdxKof) * norm.scale;
    out.sigma.rm_rad = sd.template segment<3>(kIdxRm);
    Mat<Scalar, 3, 2> tb;
    Vec3<Scalar> t1, t2;
    tangent_basis(p.d, &t1, &t2);
    tb << t1, t2;
    const Mat3<Scalar> cov_h =
        tb * cov.template block<2, 2>(kIdxDir, kIdxDir) * tb.transpose() * (fmean * fmean);
    out.h_n_sigma = cov_h.diagonal().cwiseMax(Scalar(0)).cwiseSqrt();
    output_uncertainty(store, norm, p, cov, fmean / norm.scale, &out);

    // What the data determine: 1-sigma against the parameter's natural size.
    for (int k = 0; k < kParams; ++k) {
      if (opt.fix_heading && k == kIdxRm + kRmAlpha) continue;
      const Scalar limit =
          (k >= kIdxRm && k < kIdxRm + 3) ? opt.max_rm_sigma_rad : opt.max_relative_sigma;
      if (!(sd(k) <= limit)) out.undetermined |= 1U << static_cast<unsigned>(k);
    }
    if (opt.prior != nullptr) {
      const VecP ps = prior_sigmas(*opt.prior, norm);
      const VecP pm = prior_means(*opt.prior, norm);
      const VecP pv = vector_of(p);
      for (int k = 0; k < kIdxDir; ++k) {
        if (!(ps(k) > Scalar(0) && std::isfinite(ps(k)))) continue;
        const auto bit = 1U << static_cast<unsigned>(k);
        if (sd(k) < Scalar(0.5) * ps(k)) out.updated |= bit;
        if (std::abs(pv(k) - pm(k)) > Scalar(2) * std::max(sd(k), Scalar(1e-30))) out.moved |= bit;
      }
    }

    // Unit-free predicted SD of the angles (noise model only) decides observability.
    Scalar worst_rm{0};
    for (int k = opt.fix_heading ? 1 : 0; k < 3; ++k) {
      worst_rm =
          std::max(worst_rm, std::sqrt(std::max(cov_model(kIdxRm + k, kIdxRm + k), Scalar(0))));
    }
    const bool rm_weak = weakest.template segment<3>(kIdxRm).squaredNorm() > Scalar(0.5);
    if (!(out.rcond >= opt.min_rcond) || !ldlt.isPositive() || ldlt.info() != Eigen::Success) {
      out.status = rm_weak ? OneStepStatus::kUnobservableHeading : OneStepStatus::kIllConditioned;
    } else if (!(worst_rm <= opt.max_rm_sigma_rad) && opt.prior == nullptr) {
      out.status = OneStepStatus::kUnobservableHeading;
    }
    return out;
  }

  // Iteratively reweighted, damped Gauss-Newton at fixed noise. The residual covariances depend
  // on the parameters (P = R^T Rm^T W, h_n), so they are frozen for a Levenberg-Marquardt run and
  // re-evaluated after it, until a run starts at its own optimum. Within a run a step is taken
  // only when the cost (chi^2 with the frozen weights, plus the prior term) falls; otherwise the
  // damping grows and the step is recomputed from the same point. A run has converged when every
  // step component is below 1e-4 of its 1-sigma (or the numerical tolerance), or when no step
  // lowers the cost and the Gauss-Newton predicted decrease is below 1e-6 in chi^2 units: both
  // criteria are relative to the noise. On return *sums holds the pass at *p (weights at *p).
  static bool minimise(SampleView<Scalar> store, const Normalization<Scalar>& norm,
                       const OneStepOptions<Scalar>& opt, Scalar sm, Scalar sa, Params* p,
                       PassSums* sums, int* iterations) noexcept {
    constexpr int kMaxReweights = 20;
    bool converged = false;
    *iterations = 0;
    for (int rw = 0; rw < kMaxReweights; ++rw) {
      const Params weights = *p;
      bool settled = false;
      int it = 0;
      converged = run_lm(store, norm, opt, sm, sa, weights, p, sums, &it, &settled);
      *iterations += it;
      if (!converged || settled) break;
      if (rw + 1 == kMaxReweights) converged = false;
    }
    *sums = pass(store, norm, *p, *p, sm, sa * sa, opt.attitude_model);
    return converged;
  }

  // One Levenberg-Marquardt run with the weights frozen at `weights`. *settled: the first step
  // was already negligible (the run started at its optimum).
  static bool run_lm(SampleView<Scalar> store, const Normalization<Scalar>& norm,
                     const OneStepOptions<Scalar>& opt, Scalar sm, Scalar sa, const Params& weights,
                     Params* p, PassSums* sums, int* iterations, bool* settled) noexcept {
    const Scalar sa2 = sa * sa;
    const Scalar tol = detail::default_tolerance<Scalar>();
    *sums = pass(store, norm, *p, weights, sm, sa2, opt.attitude_model);
    *settled = false;
    if (sums->count < 5) return false;
    Scalar cost = sums->chi2 + prior_cost(opt.prior, norm, *p);
    Scalar lambda = Scalar(1e-4);
    constexpr Scalar kMaxLambda = Scalar(1e10);
    int it = 0;
    bool converged = false;
    for (; it < opt.max_iterations && !converged; ++it) {
      MatP a = sums->n;
      VecP g = sums->g;
      add_prior_information(opt.prior, norm, &a);
      add_prior_gradient(opt.prior, norm, *p, &g);
      if (opt.fix_heading) hold(kIdxRm + kRmAlpha, &a, &g);
      // Gauss-Newton predicted decrease g^T A^-1 g (chi^2 units), for the stall test.
      const Eigen::LDLT<MatP> gn(a);
      const VecP gn_step = -gn.solve(g);
      const Scalar predicted =
          gn.info() == Eigen::Success && gn_step.allFinite() ? -g.dot(gn_step) : Scalar(0);
      bool accepted = false;
      while (lambda <= kMaxLambda) {
        MatP b = a;
        for (int k = 0; k < kParams; ++k)
          b(k, k) += lambda * std::max(a(k, k), Scalar(1e-30));
        const Eigen::LDLT<MatP> ldlt(b);
        const VecP step = -ldlt.solve(g);
        if (ldlt.info() != Eigen::Success || !step.allFinite() ||
            step.template segment<3>(kIdxRm).norm() > Scalar(1)) {
          lambda *= Scalar(10);
          continue;
        }
        Params cand = *p;
        apply(step, &cand);
        PassSums cs = pass(store, norm, cand, weights, sm, sa2, opt.attitude_model);
        const Scalar ccost = cs.chi2 + prior_cost(opt.prior, norm, cand);
        if (cs.count == sums->count && ccost <= cost) {
          bool small = true;
          for (int k = 0; k < kParams; ++k) {
            const Scalar sig = a(k, k) > Scalar(0) ? Scalar(1) / std::sqrt(a(k, k)) : Scalar(0);
            if (std::abs(step(k)) > tol && std::abs(step(k)) > Scalar(1e-4) * sig) small = false;
          }
          if (small && it == 0) *settled = true;
          *p = cand;
          *sums = cs;
          cost = ccost;
          lambda = std::max(lambda * Scalar(0.1), Scalar(1e-12));
          accepted = true;
          converged = small;
          break;
        }
        lambda *= Scalar(10);
      }
      if (!accepted) {
        // No step lowers the cost: a minimum to numerical precision if Gauss-Newton predicts
        // (almost) nothing more, else a failure.
        converged = predicted <= Scalar(1e-6) + Scalar(1e-9) * cost;
        if (converged && it == 0) *settled = true;
        ++it;
        break;
      }
    }
    *iterations = it;
    return converged;
  }

  // What the residual's Jacobian needs of the parameters, once per pass.
  struct Linearisation {
    Vec3<Scalar> ks, t1, t2;  // t1, t2: tangent basis at the direction of h_n
    Mat3<Scalar> ko, w, rmt;  // W = (Ks Ko)^-1, Rm^T
    std::array<Mat3<Scalar>, 3> drmt;
    Vec3<Scalar> dko1, dko2, dko3;  // the non-zero rows of dKo/dO_k
  };
  static Linearisation linearisation(const Params& prm) noexcept {
    using std::cos;
    using std::sin;
    Linearisation lz;
    const Vec3<Scalar>& o_rad = prm.o_rad;
    lz.ks = prm.ks;
    tangent_basis(prm.d, &lz.t1, &lz.t2);
    lz.ko = li_ko(o_rad);
    lz.w = (prm.ks.asDiagonal() * lz.ko).inverse();
    std::array<Mat3<Scalar>, 3> drm;
    lz.rmt = li_rm_with_derivatives(prm.rm, &drm).transpose();
    for (std::size_t k = 0; k < 3; ++k)
      lz.drmt[k] = drm[k].transpose();
    // Rows of dKo/dO_k that are non-zero: O1 -> row z, O2 and O3 -> row y.
    lz.dko1 = Vec3<Scalar>(cos(o_rad(0)), 0, -sin(o_rad(0)));
    lz.dko2 =
        Vec3<Scalar>(-sin(o_rad(1)) * sin(o_rad(2)), -sin(o_rad(1)) * cos(o_rad(2)), cos(o_rad(1)));
    lz.dko3 = Vec3<Scalar>(cos(o_rad(1)) * cos(o_rad(2)), -cos(o_rad(1)) * sin(o_rad(2)), 0);
    return lz;
  }
  // Jacobian of one sample's residual r = R^T Rm^T W (m - Kof) - F d (E-Li-6) with respect to the
  // parameters, at hs = W (m - Kof) (normalised), pm = R^T Rm^T W and fn = F (normalised).
  static Mat<Scalar, 3, kParams> jacobian(const Linearisation& lz, const Mat3<Scalar>& r,
                                          const Mat3<Scalar>& pm, const Vec3<Scalar>& hs,
                                          Scalar fn) noexcept {
    Mat<Scalar, 3, kParams> j;
    for (int k = 0; k < 3; ++k)
      j.col(kIdxKs + k) = -pm.col(k) * lz.ko.row(k).dot(hs);
    j.col(kIdxO + 0) = -pm.col(2) * (lz.ks(2) * lz.dko1.dot(hs));
    j.col(kIdxO + 1) = -pm.col(1) * (lz.ks(1) * lz.dko2.dot(hs));
    j.col(kIdxO + 2) = -pm.col(1) * (lz.ks(1) * lz.dko3.dot(hs));
    j.template block<3, 3>(0, kIdxKof) = -pm;
    for (int k = 0; k < 3; ++k)
      j.col(kIdxRm + k) = r.transpose() * (lz.drmt[static_cast<std::size_t>(k)] * hs);
    j.col(kIdxDir) = -fn * lz.t1;
    j.col(kIdxDir + 1) = -fn * lz.t2;
    return j;
  }

  // What the calibration's uncertainty (the covariance of Ks, O, Kof, Rm; normalised units) does
  // to the outputs over the survey envelope of the store's tilts (output_envelope.hpp, E-Acc-3):
  // per-axis RMS of the E/N/U error and RMS of the |h| error [nT]. The output is the residual's
  // first term, so its Jacobian is the residual's without the direction columns, at the reading
  // the fitted model predicts for the field F d there.
  static void output_uncertainty(SampleView<Scalar> store, const Normalization<Scalar>& norm,
                                 const Params& prm, const MatP& cov, Scalar fn,
                                 OneStepSolution<Scalar>* out) noexcept {
    constexpr int kCal = kIdxDir;
    TiltMoments<Scalar> tilts;
    for (std::size_t i = 0; i < store.size(); ++i)
      if (detail::usable(store[i])) tilts.add(store[i].r_bn());
    const Linearisation lz = linearisation(prm);
    const Vec3<Scalar> hn = fn * prm.d;
    EnvelopeGram<Scalar, kCal> gram;
    for_each_envelope_attitude(tilts, [&](const Mat3<Scalar>& r) {
      const Mat3<Scalar> pm = r.transpose() * lz.rmt * lz.w;
      const Vec3<Scalar> hs = lz.rmt.transpose() * (r * hn);  // R^T Rm^T hs = F d
      gram.add(Mat<Scalar, 3, kCal>(jacobian(lz, r, pm, hs, fn).template leftCols<kCal>()), prm.d);
    });
    if (gram.n == 0) return;
    gram.finish();
    const Mat<Scalar, kCal, kCal> c = cov.template topLeftCorner<kCal, kCal>();
    out->envelope_attitudes = static_cast<std::uint32_t>(gram.n);
    out->calibration_sigma_enu_nT = norm.scale * gram.vector_rms(c.cwiseProduct(gram.gv).sum());
    out->calibration_sigma_f_nT = norm.scale * gram.intensity_rms(c.cwiseProduct(gram.gi).sum());
  }

  // One pass over the samples: normal matrix, gradient, chi^2, variance-component sums and the
  // histogram of |r_w|^2. Public for benchmarks and tests.
  static PassSums pass(SampleView<Scalar> store, const Normalization<Scalar>& norm,
                       const Params& prm, const Params& wprm, Scalar sm, Scalar sa2,
                       AttitudeNoiseModel model) noexcept {
    PassSums out;
    const Linearisation lz = linearisation(prm);
    const Vec3<Scalar>&u = prm.u, &d = prm.d;
    const Mat3<Scalar>&w = lz.w, &rmt = lz.rmt;
    // Weights: the covariance at wprm (frozen during a damped run).
    const Mat3<Scalar> w_cov =
        li_rm(wprm.rm).transpose() * (wprm.ks.asDiagonal() * li_ko(wprm.o_rad)).inverse();
    const Scalar sm2 = sm * sm;
    for (std::size_t i = 0; i < store.size(); ++i) {
      const StoredSample<Scalar>& s = store[i];
      if (!detail::usable(s)) continue;
      const Mat3<Scalar> r = s.r_bn();
      const Mat3<Scalar> mt = r.transpose() * rmt;  // R^T Rm^T
      const Mat3<Scalar> pm = mt * w;
      const Mat3<Scalar> pw = r.transpose() * w_cov;  // P for the weights
      const Vec3<Scalar> hs = w * (norm.to_unit(s.raw()) - u);
      const Scalar fn = s.f / norm.scale;
      const Vec3<Scalar> hn = fn * d;
      const Vec3<Scalar> hw = fn * wprm.d;
      const Vec3<Scalar> res = mt * hs - hn;
      const Mat<Scalar, 3, kParams> j = jacobian(lz, r, pm, hs, fn);
      // Residual covariance: sm^2 P P^T + sa^2 C C^T (C: the attitude-noise directions).
      Mat3<Scalar> c;
      if (model == AttitudeNoiseModel::kLiEuler) {
        const Scalar hx = r(1, 1), hy = -r(1, 0);
        const Scalar hl = std::sqrt(hx * hx + hy * hy);
        const Vec3<Scalar> a1 =
            hl > Scalar(0) ? Vec3<Scalar>(hx / hl, hy / hl, 0) : Vec3<Scalar>::UnitX();
        c.col(0) = Vec3<Scalar>::UnitZ().cross(hw);
        c.col(1) = a1.cross(hw);
        c.col(2) = Vec3<Scalar>(r.row(1).transpose()).cross(hw);
      } else {
        c = skew(hw);
      }
      c *= std::sqrt(s.att_var);  // an interpolated attitude averages two records' noise
      const Mat3<Scalar> cov = sm2 * (pw * pw.transpose()) + sa2 * (c * c.transpose());
      const Eigen::LLT<Mat3<Scalar>> llt(cov);
      if (llt.info() != Eigen::Success) continue;
      const Mat3<Scalar> l = llt.matrixL();
      const Mat<Scalar, 3, kParams> jw = lower_solve(l, j);
      const Vec3<Scalar> rw = lower_solve(l, res);
      accumulate(jw, rw, &out);
      const Scalar r2 = rw.squaredNorm();
      out.chi2 += r2;
      out.fsum += s.f;
      ++out.count;
      // Variance components: S^-1 r = L^-T r_w; tr(S^-1 V) = |L^-1 V^(1/2)|_F^2.
      const Vec3<Scalar> sr = upper_solve(l, rw);
      out.q_mag += (pw.transpose() * sr).squaredNorm();
      out.q_att += (c.transpose() * sr).squaredNorm();
      const Mat3<Scalar> lm = lower_solve(l, pw), la = lower_solve(l, c);
      out.t_mag += lm.squaredNorm();
      out.t_att += la.squaredNorm();
      out.f_mm += Scalar(0.5) * Mat3<Scalar>(lm.transpose() * lm).squaredNorm();
      out.f_ma += Scalar(0.5) * Mat3<Scalar>(lm.transpose() * la).squaredNorm();
      out.f_aa += Scalar(0.5) * Mat3<Scalar>(la.transpose() * la).squaredNorm();
      const Scalar bin = r2 * Scalar(kTailBins) / Scalar(32);
      const int b = bin < Scalar(kTailBins - 1) ? static_cast<int>(bin) : kTailBins - 1;
      ++out.tail[static_cast<std::size_t>(b)];
    }
    out.n = out.n.template selfadjointView<Eigen::Upper>();
    return out;
  }

  // n += J_w^T J_w (upper triangle) and g += J_w^T r_w for one sample's whitened 3-row block.
  // Eigen's rank-k update takes its blocked general path (packing, run-time sizes) even for
  // these fixed 3 x 14 blocks, and an expression product stays a chain of small calls without
  // inlining (the sanitizer build is -O1): plain loops over the column-major storage.
  static void accumulate(const Mat<Scalar, 3, kParams>& jw, const Vec3<Scalar>& rw,
                         PassSums* out) noexcept {
    const Scalar* a = jw.data();  // column k at a + 3k
    Scalar* n = out->n.data();
    for (Eigen::Index c = 0; c < kParams; ++c) {
      const Scalar* jc = a + 3 * c;
      Scalar* nc = n + kParams * c;
      for (Eigen::Index r = 0; r <= c; ++r) {
        const Scalar* jr = a + 3 * r;
        nc[r] += jr[0] * jc[0] + jr[1] * jc[1] + jr[2] * jc[2];
      }
      out->g(c) += jc[0] * rw(0) + jc[1] * rw(1) + jc[2] * rw(2);
    }
  }

  // RMS of the normalised residual vectors over the scale their median implies (chi^2 with 3
  // degrees of freedom: mean 3, median 2.366). 1 for Gaussian residuals, larger for heavy tails.
  static Scalar tail_ratio(const PassSums& s) noexcept {
    if (s.count == 0) return Scalar(0);
    const std::uint64_t half = (s.count + 1) / 2;
    std::uint64_t acc = 0;
    Scalar median_r2 = Scalar(32);
    for (int b = 0; b < kTailBins; ++b) {
      const std::uint32_t c = s.tail[static_cast<std::size_t>(b)];
      if (acc + c >= half) {
        const Scalar frac =
            c > 0 ? static_cast<Scalar>(half - acc) / static_cast<Scalar>(c) : Scalar(0);
        median_r2 = (static_cast<Scalar>(b) + frac) * Scalar(32) / Scalar(kTailBins);
        break;
      }
      acc += c;
    }
    const Scalar mean_r2 = s.chi2 / static_cast<Scalar>(s.count);
    if (!(median_r2 > Scalar(0))) return mean_r2 > Scalar(0) ? Scalar(1e6) : Scalar(1);
    return std::sqrt((mean_r2 / Scalar(3)) / (median_r2 / Scalar(2.366)));
  }

  static void tangent_basis(const Vec3<Scalar>& d, Vec3<Scalar>* t1, Vec3<Scalar>* t2) noexcept {
    const Vec3<Scalar> ref =
        std::abs(d(0)) < Scalar(0.9) ? Vec3<Scalar>::UnitX() : Vec3<Scalar>::UnitY();
    *t1 = d.cross(ref).normalized();
    *t2 = d.cross(*t1);
  }

 private:
  static void apply(const VecP& step, Params* p) noexcept {
    Vec3<Scalar> t1, t2;
    tangent_basis(p->d, &t1, &t2);
    p->ks += step.template segment<3>(kIdxKs);
    p->o_rad += step.template segment<3>(kIdxO);
    p->u += step.template segment<3>(kIdxKof);
    p->rm += step.template segment<3>(kIdxRm);
    p->d = (p->d + step(kIdxDir) * t1 + step(kIdxDir + 1) * t2).normalized();
  }

  // Holds parameter k: its row and column removed from the normal equations.
  static void hold(int k, MatP* a, VecP* g) noexcept {
    a->row(k).setZero();
    a->col(k).setZero();
    (*a)(k, k) = Scalar(1);
    if (g != nullptr) (*g)(k) = Scalar(0);
  }

  // The Li parameters as a parameter vector (the direction of h_n left at 0).
  static VecP pack(const Vec3<Scalar>& ks, const Vec3<Scalar>& o_rad, const Vec3<Scalar>& u,
                   const Vec3<Scalar>& rm) noexcept {
    VecP v = VecP::Zero();
    v.template segment<3>(kIdxKs) = ks;
    v.template segment<3>(kIdxO) = o_rad;
    v.template segment<3>(kIdxKof) = u;
    v.template segment<3>(kIdxRm) = rm;
    return v;
  }
  static VecP vector_of(const Params& p) noexcept { return pack(p.ks, p.o_rad, p.u, p.rm); }
  static VecP prior_means(const OneStepPrior<Scalar>& pr,
                          const Normalization<Scalar>& norm) noexcept {
    return pack(pr.mean.ks, pr.mean.o_rad, norm.to_unit(pr.mean.kof), pr.mean.rm_rad);
  }
  // Prior 1-sigmas in the fit's units; 0 where there is none (the direction of h_n never has one).
  static VecP prior_sigmas(const OneStepPrior<Scalar>& pr,
                           const Normalization<Scalar>& norm) noexcept {
    VecP v =
        pack(pr.sigma.ks, pr.sigma.o_rad, Vec3<Scalar>(pr.sigma.kof / norm.scale), pr.sigma.rm_rad);
    for (int k = 0; k < kParams; ++k)
      if (!(std::isfinite(v(k)) && v(k) > Scalar(0))) v(k) = Scalar(0);
    return v;
  }
  static Scalar prior_cost(const OneStepPrior<Scalar>* pr, const Normalization<Scalar>& norm,
                           const Params& p) noexcept {
    if (pr == nullptr) return Scalar(0);
    const VecP s = prior_sigmas(*pr, norm), m = prior_means(*pr, norm), v = vector_of(p);
    Scalar c{0};
    for (int k = 0; k < kParams; ++k) {
      if (s(k) > Scalar(0)) c += (v(k) - m(k)) * (v(k) - m(k)) / (s(k) * s(k));
    }
    return c;
  }
  static void add_prior_information(const OneStepPrior<Scalar>* pr,
                                    const Normalization<Scalar>& norm, MatP* a) noexcept {
    if (pr == nullptr) return;
    const VecP s = prior_sigmas(*pr, norm);
    for (int k = 0; k < kParams; ++k) {
      if (s(k) > Scalar(0)) (*a)(k, k) += Scalar(1) / (s(k) * s(k));
    }
  }
  static void add_prior_gradient(const OneStepPrior<Scalar>* pr, const Normalization<Scalar>& norm,
                                 const Params& p, VecP* g) noexcept {
    if (pr == nullptr) return;
    const VecP s = prior_sigmas(*pr, norm), m = prior_means(*pr, norm), v = vector_of(p);
    for (int k = 0; k < kParams; ++k) {
      if (s(k) > Scalar(0)) (*g)(k) += (v(k) - m(k)) / (s(k) * s(k));
    }
  }
};

}  // namespace magvec::core
