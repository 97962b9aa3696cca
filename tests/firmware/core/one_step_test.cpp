#include "magvec/core/one_step.hpp"

#include <gtest/gtest.h>

#include <cstdio>
#include <memory>
#include <random>

#include "li_setup.hpp"
#include "magvec/core/batch_calibrator.hpp"

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

// Monte Carlo of the paper setup (ERRATA 000-7/8 floors): 60 random attitudes, 0.3 nT, 0.015 deg.
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

}  // namespace
}  // namespace magvec::core
