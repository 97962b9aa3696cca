#include "magvec/core/one_step.hpp"

#include <gtest/gtest.h>

#include <Eigen/Dense>
#include <cstdio>
#include <memory>
#include <random>

#include "li_setup.hpp"
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/output_envelope.hpp"

namespace magvec::core {
namespace {

using namespace test_setup;
using Calibrator = BatchCalibrator<double, 1024>;

std::unique_ptr<Calibrator> fill(const std::vector<Sample>& data,
                                 const BatchConfig<double>& cfg = {}) {
  auto cal = std::make_unique<Calibrator>(cfg);
  for (const Sample& s : data)
    EXPECT_EQ(cal->add_sample(s.m, s.f, s.r_meas), AddStatus::kAccepted);
  return cal;
}

void expect_exact(const BatchResult<double>& r, const LiParams<double>& t,
                  const Vec3<double>& h_n) {
  const double f = h_n.norm();
  EXPECT_LT((r.li.ks - t.ks).cwiseAbs().maxCoeff(), 1e-9);
  EXPECT_LT((r.li.o_rad - t.o_rad).cwiseAbs().maxCoeff(), 1e-9);
  EXPECT_LT((r.li.kof - t.kof).cwiseAbs().maxCoeff(), 1e-9 * f);
  EXPECT_LT((r.li.rm_rad - t.rm_rad).cwiseAbs().maxCoeff(), 1e-9);
  EXPECT_LT((r.h_n_nT - h_n).norm(), 1e-9 * f);
}

TEST(OneStep, NoiseFreeLiSetupIsRecoveredExactly) {
  std::mt19937_64 rng(1);
  const LiParams<double> t = paper_li();
  const auto data = simulate(from_li(t), paper_h_n(), random_attitudes(60, rng), 0, 0, rng);
  auto cal = fill(data);
  for (BatchMethod m :
       {BatchMethod::kOneStep, BatchMethod::kJoint, BatchMethod::kPlaneCompression}) {
    const BatchResult<double> r = cal->solve(m);
    ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict);
    expect_exact(r, t, paper_h_n());
  }
}

TEST(OneStep, NoiseFreeCalibrationBoxIsRecoveredExactly) {
  std::mt19937_64 rng(2);
  LiParams<double> t = paper_li();
  t.rm_rad = Vec3<double>(-40, 3, -2) * kDeg;  // large heading misalignment
  t.kof = {-350, 820, 120};
  const Vec3<double> h_n(1200, 21000, -43000);
  const auto data = simulate(from_li(t), h_n, box_attitudes(), 0, 0, rng);
  auto cal = fill(data);
  const BatchResult<double> r = cal->solve();
  ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict);
  expect_exact(r, t, h_n);
  EXPECT_EQ(r.counts.used, 18U);
}

// Monte Carlo of the paper setup (docs/equations.md E-Li-7/E-Li-8 floors): 60 random attitudes, 0.3
// nT, 0.015 deg.
TEST(OneStep, MonteCarloReachesTheStatisticalFloor) {
  constexpr int kSeeds = 200;
  const LiParams<double> t = paper_li();
  const SensorModel<double> truth = from_li(t);
  std::vector<double> err[3], err_pc[3];
  double intensity_ss = 0, sigma_ss[3] = {0, 0, 0};
  int intensity_n = 0;
  for (int seed = 0; seed < kSeeds; ++seed) {
    std::mt19937_64 rng(1000 + static_cast<unsigned>(seed));
    const auto data =
        simulate(truth, paper_h_n(), random_attitudes(60, rng), 0.3, 0.015 * kDeg, rng);
    auto cal = fill(data);
    const BatchResult<double> r = cal->solve(BatchMethod::kOneStep);
    ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict) << " seed " << seed;
    const BatchResult<double> pc = cal->solve(BatchMethod::kPlaneCompression);
    ASSERT_EQ(pc.verdict, Verdict::kOk) << verdict_name(pc.verdict) << " seed " << seed;
    for (int k = 0; k < 3; ++k) {
      err[k].push_back(r.li.rm_rad(k) - t.rm_rad(k));
      err_pc[k].push_back(pc.li.rm_rad(k) - t.rm_rad(k));
      sigma_ss[k] += r.sigma.rm_rad(k) * r.sigma.rm_rad(k);
    }
    // Parameter-induced intensity error: estimated parameters applied to noise-free data.
    for (const Sample& s : data) {
      const double e = (r.model.w * (s.m_true - r.model.o)).norm() - s.f;
      intensity_ss += e * e;
      ++intensity_n;
    }
  }
  double worst = 0, worst_pc = 0;
  for (int k = 0; k < 3; ++k) {
    const double s = sd(err[k]) / kDeg, s_pc = sd(err_pc[k]) / kDeg;
    const double predicted = std::sqrt(sigma_ss[k] / kSeeds) / kDeg;
    std::printf(
        "angle %d: one-step SD %.5f deg (predicted 1-sigma %.5f), plane compression SD %.5f deg\n",
        k, s, predicted, s_pc);
    EXPECT_NEAR(predicted / s, 1.0, 0.2) << "reported sigma must match the scatter";
    worst = std::max(worst, s);
    worst_pc = std::max(worst_pc, s_pc);
  }
  const double rmse = std::sqrt(intensity_ss / intensity_n);
  std::printf("parameter-induced intensity RMSE %.4f nT\n", rmse);
  EXPECT_LT(worst, 1.3 * 0.0022);
  EXPECT_GT(worst, 0.0022 / 1.3);
  EXPECT_LT(worst_pc, 1.3 * 0.0031);
  EXPECT_GT(worst_pc, 0.0031 / 1.3);
  EXPECT_LT(rmse, 1.3 * 0.11);
  EXPECT_GT(rmse, 0.11 / 1.3);
}

// The fit's own 1-sigma of the outputs over the survey envelope (E-Acc-3) against the Monte Carlo
// scatter of the errors it predicts: each realisation's fitted model compensates the noise-free
// readings of the true field at the envelope attitudes of its data's tilts, and the E/N/U and |h|
// errors against the true field are averaged over the realisations. The reported figures must
// agree with that scatter within 25 % (the online filter's criterion for its own 1-sigma).
void envelope_sigma_vs_scatter(bool level_survey, int seeds) {
  const LiParams<double> t = paper_li();
  const SensorModel<double> truth = from_li(t);
  const Vec3<double> h_n = paper_h_n();
  double pred_v = 0, pred_f = 0, err_v = 0, err_f = 0;
  int n_err = 0;
  for (int seed = 0; seed < seeds; ++seed) {
    std::mt19937_64 rng(7000 + static_cast<unsigned>(seed));
    std::vector<Mat3<double>> att;
    if (level_survey) {
      // Survey-like: every heading, tilts within +-15 deg (the heading misalignment observable).
      std::uniform_real_distribution<double> u(-1, 1);
      for (int i = 0; i < 120; ++i)
        att.push_back(r_bn_from_li(
            LiEuler<double>{kPi<double> * u(rng), 15 * kDeg * u(rng), 15 * kDeg * u(rng)}));
    } else {
      att = random_attitudes(60, rng);
    }
    const auto data = simulate(truth, h_n, att, 0.3, 0.015 * kDeg, rng);
    auto cal = fill(data);
    const BatchResult<double> r = cal->solve(BatchMethod::kOneStep);
    ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict) << " seed " << seed;
    ASSERT_TRUE(std::isfinite(r.calibration_sigma_enu_nT) &&
                std::isfinite(r.calibration_sigma_f_nT));
    pred_v += r.calibration_sigma_enu_nT * r.calibration_sigma_enu_nT;
    pred_f += r.calibration_sigma_f_nT * r.calibration_sigma_f_nT;
    TiltMoments<double> tilts;
    for (const Sample& s : data)
      tilts.add(s.r_meas);
    const Mat3<double> m_out = r.model.rm_matrix().transpose() * r.model.w;
    ASSERT_TRUE(for_each_envelope_attitude(tilts, [&](const Mat3<double>& rb) {
      const Vec3<double> m = truth.predict_raw(rb, h_n);
      const Vec3<double> out = rb.transpose() * (m_out * (m - r.model.o));
      err_v += (out - h_n).squaredNorm() / 3;
      err_f += (out.norm() - h_n.norm()) * (out.norm() - h_n.norm());
      ++n_err;
    }));
  }
  const double sv = std::sqrt(pred_v / seeds), sf = std::sqrt(pred_f / seeds);
  const double ev = std::sqrt(err_v / n_err), ef = std::sqrt(err_f / n_err);
  std::printf(
      "%s: E/N/U per axis: reported %.4f nT, scatter %.4f nT (ratio %.3f); |h|: reported "
      "%.4f nT, scatter %.4f nT (ratio %.3f)\n",
      level_survey ? "survey attitudes" : "Li set-up", sv, ev, sv / ev, sf, ef, sf / ef);
  EXPECT_NEAR(sv / ev, 1.0, 0.25);
  EXPECT_NEAR(sf / ef, 1.0, 0.25);
}

TEST(OneStep, OutputSigmaOverTheEnvelopeMatchesTheScatterOnTheLiSetup) {
  envelope_sigma_vs_scatter(false, 100);
}
TEST(OneStep, OutputSigmaOverTheEnvelopeMatchesTheScatterOnSurveyAttitudes) {
  envelope_sigma_vs_scatter(true, 100);
}

// An independent reference for the one-step estimator: the same statistical model (vector residual
// in the geographic frame, covariance from the magnetometer and Li-Euler attitude noise, weights
// re-evaluated at the current parameters), solved a different way: the general matrix M = Rm^T W
// (9 free entries) instead of Li's structured parameters, the offset, and the direction of h_n as
// azimuth/elevation; dense, finite-difference Jacobians, Levenberg-Marquardt on the full stacked
// system. Slow and simple on purpose.
struct Reference {
  Mat3<double> m;  // Rm^T W
  Vec3<double> o;
  double az, el;
};

Vec3<double> ref_dir(double az, double el) {
  return {std::cos(el) * std::cos(az), std::cos(el) * std::sin(az), std::sin(el)};
}

Eigen::VectorXd ref_pack(const Reference& r) {
  Eigen::VectorXd p(14);
  for (int i = 0; i < 9; ++i)
    p(i) = r.m(i / 3, i % 3);
  p.segment<3>(9) = r.o;
  p(12) = r.az;
  p(13) = r.el;
  return p;
}
Reference ref_unpack(const Eigen::VectorXd& p) {
  Reference r;
  for (int i = 0; i < 9; ++i)
    r.m(i / 3, i % 3) = p(i);
  r.o = p.segment<3>(9);
  r.az = p(12);
  r.el = p(13);
  return r;
}

// Whitened residuals of all samples with the weights (Cholesky factors) held fixed.
Eigen::VectorXd ref_residuals(const std::vector<Sample>& data, const Eigen::VectorXd& p,
                              const std::vector<Mat3<double>>& l_inv) {
  const Reference r = ref_unpack(p);
  const Vec3<double> d = ref_dir(r.az, r.el);
  Eigen::VectorXd out(3 * static_cast<Eigen::Index>(data.size()));
  for (std::size_t i = 0; i < data.size(); ++i) {
    const Vec3<double> e = data[i].r_meas.transpose() * (r.m * (data[i].m - r.o)) - data[i].f * d;
    out.segment<3>(3 * static_cast<Eigen::Index>(i)) = l_inv[i] * e;
  }
  return out;
}

std::vector<Mat3<double>> ref_weights(const std::vector<Sample>& data, const Reference& r,
                                      double sm, double sa) {
  std::vector<Mat3<double>> l_inv;
  const Vec3<double> d = ref_dir(r.az, r.el);
  for (const Sample& s : data) {
    const Mat3<double> p = s.r_meas.transpose() * r.m;
    const Vec3<double> hn = s.f * d;
    const double hx = s.r_meas(1, 1), hy = -s.r_meas(1, 0), hl = std::hypot(hx, hy);
    const Vec3<double> a1(hx / hl, hy / hl, 0);
    Mat3<double> c;
    c.col(0) = Vec3<double>::UnitZ().cross(hn);
    c.col(1) = a1.cross(hn);
    c.col(2) = Vec3<double>(s.r_meas.row(1).transpose()).cross(hn);
    const Mat3<double> cov = sm * sm * p * p.transpose() + sa * sa * c * c.transpose();
    const Eigen::LLT<Mat3<double>> llt(cov);
    l_inv.push_back(llt.matrixL().solve(Mat3<double>::Identity()));
  }
  return l_inv;
}

Reference reference_fit(const std::vector<Sample>& data, Reference start, double sm, double sa) {
  Eigen::VectorXd p = ref_pack(start);
  for (int outer = 0; outer < 8; ++outer) {
    const auto w = ref_weights(data, ref_unpack(p), sm, sa);
    double lambda = 1e-3;
    Eigen::VectorXd r = ref_residuals(data, p, w);
    for (int it = 0; it < 100; ++it) {
      Eigen::MatrixXd j(r.size(), 14);
      for (int k = 0; k < 14; ++k) {
        const double h = 1e-6 * std::max(1.0, std::abs(p(k)));
        Eigen::VectorXd pp = p, pm = p;
        pp(k) += h;
        pm(k) -= h;
        j.col(k) = (ref_residuals(data, pp, w) - ref_residuals(data, pm, w)) / (2 * h);
      }
      const Eigen::MatrixXd n = j.transpose() * j;
      const Eigen::VectorXd g = j.transpose() * r;
      bool better = false;
      while (lambda < 1e12) {
        Eigen::MatrixXd b = n;
        b.diagonal() *= 1 + lambda;
        const Eigen::VectorXd step = -b.ldlt().solve(g);
        const Eigen::VectorXd rc = ref_residuals(data, p + step, w);
        if (rc.squaredNorm() < r.squaredNorm()) {
          p += step;
          r = rc;
          lambda = std::max(lambda / 10, 1e-12);
          better = true;
          break;
        }
        lambda *= 10;
      }
      if (!better) break;
    }
  }
  return ref_unpack(p);
}

// The one-step fit converges to the estimator's optimum: every Li parameter and the direction of
// h_n agree with the independent reference within 0.1 of their reported 1-sigma.
TEST(OneStep, AgreesWithAnIndependentReferenceOptimiserWithinATenthSigma) {
  std::mt19937_64 rng(77);
  const LiParams<double> t = paper_li();
  const double sm = 0.3, sa = 0.015 * kDeg;
  const auto data = simulate(from_li(t), paper_h_n(), random_attitudes(150, rng), sm, sa, rng);
  BatchConfig<double> cfg;
  cfg.mag_noise_nT = sm;
  cfg.attitude_noise_deg = 0.015;
  auto cal = fill(data, cfg);
  const BatchResult<double> r = cal->solve(BatchMethod::kOneStep);
  ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict);
  ASSERT_TRUE(r.converged);

  // Start the reference from the truth perturbed, not from the fit under test.
  Reference start;
  const SensorModel<double> truth = from_li(t);
  start.m = truth.rm_matrix().transpose() * truth.w + 0.01 * Mat3<double>::Ones();
  start.o = truth.o + Vec3<double>(30, -20, 10);
  const Vec3<double> d = paper_h_n().normalized();
  start.az = std::atan2(d(1), d(0)) + 0.01;
  start.el = std::asin(d(2)) - 0.01;
  const Reference ref = reference_fit(data, start, sm, sa);
  SensorModel<double> rm;
  rm.w = ref.m;  // Rm^T W as a whole; to_li splits it into Ks Ko and Rm
  rm.o = ref.o;
  LiParams<double> li;
  ASSERT_EQ(to_li(rm, &li), ConversionStatus::kOk);
  for (int k = 0; k < 3; ++k) {
    EXPECT_LT(std::abs(r.li.ks(k) - li.ks(k)), 0.1 * r.sigma.ks(k)) << "ks " << k;
    EXPECT_LT(std::abs(r.li.o_rad(k) - li.o_rad(k)), 0.1 * r.sigma.o_rad(k)) << "O " << k;
    EXPECT_LT(std::abs(r.li.kof(k) - li.kof(k)), 0.1 * r.sigma.kof(k)) << "Kof " << k;
    EXPECT_LT(std::abs(r.li.rm_rad(k) - li.rm_rad(k)), 0.1 * r.sigma.rm_rad(k)) << "Rm " << k;
  }
  const Vec3<double> d_ref = ref_dir(ref.az, ref.el);
  const double angle = std::acos(std::min(1.0, r.h_n_nT.normalized().dot(d_ref)));
  const double dir_sigma = r.h_n_sigma_nT.norm() / r.h_n_nT.norm();
  EXPECT_LT(angle, 0.1 * dir_sigma);
}

// Noise from the data: the variance components recover the magnetometer and attitude noise of a
// fluxgate and of a MEMS magnetometer, within a few of their reported 1-sigmas.
TEST(OneStep, EstimatesBothNoiseFiguresFromTheData) {
  struct Case {
    double sm_nT, sa_deg;
  };
  for (const Case c : {Case{0.3, 0.015}, Case{700.0, 0.04}, Case{5.0, 0.2}}) {
    std::mt19937_64 rng(91);
    const auto data = simulate(from_li(paper_li()), paper_h_n(), random_attitudes(1000, rng),
                               c.sm_nT, c.sa_deg * kDeg, rng);
    BatchConfig<double> cfg;
    cfg.estimate_noise = true;  // start values 0.3 nT / 0.015 deg, far from the MEMS truth
    auto cal = std::make_unique<Calibrator>(cfg);
    for (const Sample& s : data)
      cal->add_sample(s.m, s.f, s.r_meas);
    const BatchResult<double> r = cal->solve(BatchMethod::kOneStep);
    ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict) << " " << c.sm_nT;
    ASSERT_TRUE(r.noise.estimated);
    std::printf("truth %.3f nT %.4f deg: estimated %.3f +- %.3f nT, %.4f +- %.4f deg\n", c.sm_nT,
                c.sa_deg, r.noise.mag_nT, r.noise.mag_sigma_nT, r.noise.attitude_deg,
                r.noise.attitude_sigma_deg);
    EXPECT_LT(std::abs(r.noise.mag_nT - c.sm_nT), 4 * r.noise.mag_sigma_nT + 0.02 * c.sm_nT);
    EXPECT_LT(std::abs(r.noise.attitude_deg - c.sa_deg),
              4 * r.noise.attitude_sigma_deg + 0.02 * c.sa_deg);
    EXPECT_NEAR(r.quality.chi2_per_dof, 1.0, 0.1);
    EXPECT_LT(r.quality.tail_ratio, 1.2);
  }
}

// The variance-component step from a start far below the truth (attitude noise 0.2 or 0.5 deg
// against the 0.015 deg start): undamped, Fisher scoring could put the magnetometer variance at
// zero in one round (first seen on the 5 nT / 0.2 deg case above with the noise drawn in clang's
// order), after which the residual covariance is singular across the field and the fit diverged.
// Before the fix, of the seeds run here, not_converged came on seed 5 of 16 at 5 nT / 0.2 deg, on
// seed 2 of 4 at 50 nT / 0.5 deg and on seeds 1, 2 and 4 of 4 at 5 nT / 0.5 deg (7 of 16 seeds).
// Now every realisation converges and the attitude figure lands within 4 of its sigmas.
// So does the magnetometer figure, except at 5 nT / 0.5 deg, where it also carries the attitude
// noise's second-order part along the field, F sa^2 = 3.5 nT (docs/equations.md).
TEST(OneStep, NoiseEstimateFromAFarStartConvergesOnEveryRealisation) {
  struct Case {
    double sm_nT, sa_deg;
    bool judge_mag;
  };
  for (const Case c : {Case{5.0, 0.2, true}, Case{50.0, 0.5, true}, Case{5.0, 0.5, false}}) {
    for (std::uint64_t seed = 1; seed <= (c.sa_deg > 0.3 ? 4U : 16U); ++seed) {
      std::mt19937_64 rng(seed);
      const auto data = simulate(from_li(paper_li()), paper_h_n(), random_attitudes(1000, rng),
                                 c.sm_nT, c.sa_deg * kDeg, rng);
      BatchConfig<double> cfg;
      cfg.estimate_noise = true;
      auto cal = std::make_unique<Calibrator>(cfg);
      for (const Sample& s : data)
        cal->add_sample(s.m, s.f, s.r_meas);
      const BatchResult<double> r = cal->solve(BatchMethod::kOneStep);
      ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict) << " " << c.sm_nT << " nT "
                                         << c.sa_deg << " deg seed " << seed;
      EXPECT_LT(std::abs(r.noise.attitude_deg - c.sa_deg), 4 * r.noise.attitude_sigma_deg)
          << c.sa_deg << " deg seed " << seed << ": " << r.noise.attitude_deg;
      if (c.judge_mag) {
        EXPECT_LT(std::abs(r.noise.mag_nT - c.sm_nT), 4 * r.noise.mag_sigma_nT)
            << c.sm_nT << " nT seed " << seed << ": " << r.noise.mag_nT;
      }
    }
  }
}

}  // namespace
}  // namespace magvec::core
