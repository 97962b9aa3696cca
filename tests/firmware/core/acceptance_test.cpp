// The one acceptance policy (acceptance.hpp): the order of its checks, and every verdict forced
// through the batch calibrator by data of its own.
#include "magvec/core/acceptance.hpp"

#include <gtest/gtest.h>

#include <memory>
#include <random>

#include "li_setup.hpp"
#include "magvec/core/batch_calibrator.hpp"

namespace magvec::core {
namespace {

using namespace test_setup;
using Calibrator = BatchCalibrator<double, kDynamicCapacity>;

AcceptanceEvidence<double> good_evidence() {
  AcceptanceEvidence<double> e;
  e.rows = 100;
  e.usable = 100;
  e.median_norm_nT = 50000;
  e.median_f_nT = 50000;
  e.coverage = 0.8;
  e.tilt_spread_deg = 30;
  e.chi2_per_dof = 1;
  e.tail_ratio = 1;
  e.noise_nT = 1;
  e.min_scale = 0.98;
  e.max_scale = 1.02;
  return e;
}

TEST(Acceptance, ChecksCausesInTheirOrder) {
  const AcceptanceLimits<double> l;
  AcceptanceEvidence<double> e = good_evidence();
  EXPECT_EQ(judge(e, l), Verdict::kOk);
  // Everything wrong at once: the first cause in the order wins, then the next, ...
  e.converged = false;
  e.not_an_ellipsoid = true;
  e.coverage = 0.05;
  e.median_norm_nT = 50;  // uT under an nT header
  e.rows = 0;
  EXPECT_EQ(judge(e, l), Verdict::kNoData);
  e.rows = 100;
  EXPECT_EQ(judge(e, l), Verdict::kUnitMismatch);
  e.median_norm_nT = 50000;
  EXPECT_EQ(judge(e, l), Verdict::kInsufficientCoverage);
  e.has_prior = true;  // a prior supplies what the data do not determine
  EXPECT_EQ(judge(e, l), Verdict::kNotAnEllipsoid);
  e.not_an_ellipsoid = false;
  EXPECT_EQ(judge(e, l), Verdict::kNotConverged);
  e.converged = true;
  e.tail_ratio = 5;
  EXPECT_EQ(judge(e, l), Verdict::kResidualTooLarge);
  e.tail_ratio = 1;
  e.max_scale = 3;
  EXPECT_EQ(judge(e, l), Verdict::kFieldMismatch);
}

TEST(Acceptance, GivenNoiseIsJudgedByChiSquareEstimatedByTails) {
  const AcceptanceLimits<double> l;
  AcceptanceEvidence<double> e = good_evidence();
  e.chi2_per_dof = 100;
  EXPECT_EQ(judge(e, l), Verdict::kOk);  // estimated noise: chi2/dof is 1 by construction
  e.noise_given = true;
  EXPECT_EQ(judge(e, l), Verdict::kResidualTooLarge);
  e.noise_given = false;
  e.noise_nT = 0.1 * e.median_norm_nT;  // "noise" of 10 % of the field
  EXPECT_EQ(judge(e, l), Verdict::kResidualTooLarge);
}

std::unique_ptr<Calibrator> calibrator(const std::vector<Sample>& data, bool attitude,
                                       BatchConfig<double> cfg = {}, double m_scale = 1.0) {
  auto cal = std::make_unique<Calibrator>(cfg);
  for (const Sample& s : data) {
    if (attitude) {
      cal->add_sample(Vec3<double>(s.m * m_scale), s.f, s.r_meas);
    } else {
      cal->add_sample(Vec3<double>(s.m * m_scale), s.f);
    }
  }
  return cal;
}

std::vector<Sample> full_sphere(int n, unsigned seed, double sm = 0.3, double sa_deg = 0.015) {
  std::mt19937_64 rng(seed);
  return simulate(from_li(paper_li()), paper_h_n(), random_attitudes(n, rng), sm, sa_deg * kDeg,
                  rng);
}

// Attitudes within a cone of half-angle 15 degrees about one attitude: a 30-degree cap.
std::vector<Mat3<double>> cap_attitudes(int n, std::mt19937_64& rng) {
  std::normal_distribution<double> g(0, 1);
  std::uniform_real_distribution<double> u(0, 1);
  const Mat3<double> base = r_bn_from_li(LiEuler<double>{0.4, 0.2, -0.1});
  std::vector<Mat3<double>> a;
  for (int i = 0; i < n; ++i) {
    const Vec3<double> axis = Vec3<double>(g(rng), g(rng), g(rng)).normalized();
    const double angle = 15.0 * kDeg * std::sqrt(u(rng));
    a.push_back(Eigen::AngleAxisd(angle, axis).toRotationMatrix() * base);
  }
  return a;
}

TEST(Acceptance, NoDataRows) {
  auto cal = std::make_unique<Calibrator>();
  EXPECT_EQ(cal->solve().verdict, Verdict::kNoData);
  EXPECT_FALSE(cal->solve().has_model);
}

TEST(Acceptance, MicroteslaUnderAnNanoteslaHeaderIsAUnitMismatch) {
  const auto data = full_sphere(200, 1);
  for (bool att : {true, false}) {
    auto cal = calibrator(data, att, {}, 1e-3);
    const BatchResult<double> r =
        cal->solve(att ? BatchMethod::kOneStep : BatchMethod::kEllipsoidOnly);
    EXPECT_EQ(r.verdict, Verdict::kUnitMismatch);
    EXPECT_FALSE(r.has_model);
  }
}

TEST(Acceptance, TooFewSamples) {
  auto data = full_sphere(200, 2);
  data.resize(8);
  EXPECT_EQ(calibrator(data, true)->solve().verdict, Verdict::kTooFewSamples);
}

TEST(Acceptance, ACapIsInsufficientCoverageBeforeAnyFit) {
  std::mt19937_64 rng(3);
  const auto data =
      simulate(from_li(paper_li()), paper_h_n(), cap_attitudes(600, rng), 0.3, 0.015 * kDeg, rng);
  for (BatchMethod m : {BatchMethod::kOneStep, BatchMethod::kEllipsoidOnly, BatchMethod::kJoint}) {
    const BatchResult<double> r = calibrator(data, true)->solve(m);
    EXPECT_EQ(r.verdict, Verdict::kInsufficientCoverage) << verdict_name(r.verdict);
    EXPECT_LT(r.quality.coverage, 0.2);
  }
}

TEST(Acceptance, AHyperboloidIsNotAnEllipsoid) {
  // Readings on x^2 + y^2 - z^2/2 = F^2 (no sensor is like that): directions cover most of the
  // sphere, the quadric fit finds the hyperboloid exactly.
  std::mt19937_64 rng(4);
  std::normal_distribution<double> g(0, 1);
  std::vector<Sample> data;
  const double f = 50000;
  while (data.size() < 400) {
    const Vec3<double> d = Vec3<double>(g(rng), g(rng), g(rng)).normalized();
    const double q = d(0) * d(0) + d(1) * d(1) - 0.5 * d(2) * d(2);
    if (!(q > 0.05)) continue;
    Sample s{d * (f / std::sqrt(q)), Vec3<double>::Zero(), Mat3<double>::Identity(),
             Mat3<double>::Identity(), f};
    data.push_back(s);
  }
  const BatchResult<double> r = calibrator(data, false)->solve(BatchMethod::kEllipsoidOnly);
  EXPECT_EQ(r.verdict, Verdict::kNotAnEllipsoid) << verdict_name(r.verdict);
  EXPECT_GT(r.quality.coverage, 0.5);
}

TEST(Acceptance, AFitStoppedEarlyIsNotConverged) {
  const auto data = full_sphere(300, 5, 5.0, 0.05);
  BatchConfig<double> cfg;
  cfg.estimate_noise = true;
  cfg.max_iterations = 1;
  const BatchResult<double> r = calibrator(data, true, cfg)->solve();
  EXPECT_EQ(r.verdict, Verdict::kNotConverged) << verdict_name(r.verdict);
  EXPECT_FALSE(r.converged);
  cfg.max_iterations = 50;
  const BatchResult<double> ok = calibrator(data, true, cfg)->solve();
  EXPECT_EQ(ok.verdict, Verdict::kOk) << verdict_name(ok.verdict);
}

TEST(Acceptance, AGivenNoiseTenTimesTooSmallIsResidualTooLarge) {
  const auto data = full_sphere(300, 6, 3.0, 0.05);
  BatchConfig<double> cfg;
  cfg.estimate_noise = false;
  cfg.mag_noise_nT = 0.3;
  cfg.attitude_noise_deg = 0.005;
  const BatchResult<double> r = calibrator(data, true, cfg)->solve();
  EXPECT_EQ(r.verdict, Verdict::kResidualTooLarge) << verdict_name(r.verdict);
  cfg.estimate_noise = true;  // the same data with the noise taken from them
  EXPECT_EQ(calibrator(data, true, cfg)->solve().verdict, Verdict::kOk);
}

TEST(Acceptance, HeavyTailsAreResidualTooLarge) {
  // A third of the recording in a different field (a disturbance the screen cannot remove as
  // isolated spikes): with estimated noise the residuals are not Gaussian.
  auto data = full_sphere(600, 7, 1.0, 0.02);
  std::mt19937_64 rng(8);
  std::normal_distribution<double> g(0, 1);
  for (std::size_t i = 0; i < data.size(); i += 3)
    data[i].m += 300.0 * Vec3<double>(g(rng), g(rng), g(rng));
  BatchConfig<double> cfg;
  cfg.estimate_noise = true;
  cfg.outlier_k = 1e9;  // no outlier screen: show the policy, not the screen
  const BatchResult<double> r = calibrator(data, true, cfg)->solve();
  EXPECT_EQ(r.verdict, Verdict::kResidualTooLarge) << verdict_name(r.verdict);
  EXPECT_GT(r.quality.tail_ratio, 3.0);
}

TEST(Acceptance, AReferenceFieldOffByThreeIsAFieldMismatch) {
  auto data = full_sphere(300, 9);
  for (Sample& s : data)
    s.f *= 3;
  BatchConfig<double> cfg;
  cfg.estimate_noise = true;
  const BatchResult<double> r = calibrator(data, true, cfg)->solve();
  EXPECT_EQ(r.verdict, Verdict::kFieldMismatch) << verdict_name(r.verdict);
  EXPECT_TRUE(r.has_model);
}

TEST(Acceptance, ACapWithAPriorIsAcceptedAndUpdatesWhatItDetermines) {
  std::mt19937_64 rng(10);
  const LiParams<double> t = paper_li();
  const auto data =
      simulate(from_li(t), paper_h_n(), cap_attitudes(600, rng), 0.3, 0.015 * kDeg, rng);
  OneStepPrior<double> prior;
  prior.mean = t;
  prior.mean.kof += Vec3<double>(3, -2, 2);  // an older calibration, a little off
  prior.mean.rm_rad += Vec3<double>(0.02, -0.01, 0.01) * kDeg;
  prior.sigma.ks = Vec3<double>::Constant(2e-4);
  prior.sigma.o_rad = Vec3<double>::Constant(0.01 * kDeg);
  prior.sigma.kof = Vec3<double>::Constant(3.0);
  prior.sigma.rm_rad = Vec3<double>::Constant(0.05 * kDeg);
  BatchConfig<double> cfg;
  cfg.estimate_noise = true;
  cfg.prior = &prior;
  const BatchResult<double> r = calibrator(data, true, cfg)->solve();
  ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict);
  EXPECT_NE(r.quality.updated, 0U);              // the cap determines some directions...
  EXPECT_NE(r.quality.updated, (1U << 12) - 1);  // ...not all of them
  // The posterior is no worse than the prior on every parameter, against the truth.
  for (int k = 0; k < 3; ++k) {
    EXPECT_LE(std::abs(r.li.kof(k) - t.kof(k)),
              std::abs(prior.mean.kof(k) - t.kof(k)) + 3 * r.sigma.kof(k));
  }
  cfg.prior = nullptr;
  EXPECT_EQ(calibrator(data, true, cfg)->solve().verdict, Verdict::kInsufficientCoverage);
}

}  // namespace
}  // namespace magvec::core
