#include "magvec/core/batch_calibrator.hpp"

#include <gtest/gtest.h>

#include <memory>
#include <random>

#include "li_setup.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using namespace test_setup;
using Calibrator = BatchCalibrator<double, 1024>;

TEST(BatchCalibrator, LevelOnlyDataGetsTheUnobservableHeadingVerdict) {
  std::mt19937_64 rng(21);
  auto cal = std::make_unique<Calibrator>();
  for (const Sample& s :
       simulate(from_li(paper_li()), paper_h_n(), level_attitudes(72), 0.3, 0.015 * kDeg, rng)) {
    cal->add_sample(s.m, s.f, s.r_meas);
  }
  for (BatchMethod m :
       {BatchMethod::kOneStep, BatchMethod::kJoint, BatchMethod::kPlaneCompression}) {
    EXPECT_EQ(cal->solve(m).verdict, Verdict::kUnobservableHeadingMisalignment);
  }
}

TEST(BatchCalibrator, TooFewAndNonFiniteSamplesAreCounted) {
  auto cal = std::make_unique<Calibrator>();
  const Mat3<double> r = Mat3<double>::Identity();
  EXPECT_EQ(cal->add_sample(Vec3<double>(kNaN, 1, 1), 50000, r), AddStatus::kSkippedNonFinite);
  EXPECT_EQ(cal->add_sample(Vec3<double>(1, 1, 1), kNaN, r),
            AddStatus::kSkippedNonFinite);  // no default F
  Mat3<double> bad = r;
  bad(0, 0) = kNaN;
  EXPECT_EQ(cal->add_sample(Vec3<double>(1, 1, 1), 50000, bad), AddStatus::kSkippedNonFinite);
  EXPECT_EQ(cal->add_sample(Vec3<double>(20000, 20000, 40000), 50000, r), AddStatus::kAccepted);
  const BatchResult<double> res = cal->solve();
  EXPECT_EQ(res.verdict, Verdict::kTooFewSamples);
  EXPECT_EQ(res.counts.skipped_nonfinite, 3U);
  EXPECT_EQ(res.counts.added, 1U);
}

TEST(BatchCalibrator, ConstantFieldFromConfigAndEllipsoidOnlyMethod) {
  std::mt19937_64 rng(22);
  BatchConfig<double> cfg;
  cfg.field_nT = paper_h_n().norm();
  auto cal = std::make_unique<Calibrator>(cfg);
  const LiParams<double> t = paper_li();
  for (const Sample& s : simulate(from_li(t), paper_h_n(), random_attitudes(60, rng), 0, 0, rng)) {
    ASSERT_EQ(cal->add_sample(s.m, kNaN), AddStatus::kAccepted);
  }
  const BatchResult<double> r = cal->solve(BatchMethod::kEllipsoidOnly);
  ASSERT_EQ(r.verdict, Verdict::kOk) << verdict_name(r.verdict);
  EXPECT_LT((r.li.ks - t.ks).cwiseAbs().maxCoeff(), 1e-9);
  EXPECT_LT((r.li.kof - t.kof).norm(), 1e-9 * cfg.field_nT);
  EXPECT_GT(r.quality.coverage, 0.6);
  // Attitude methods need attitudes.
  EXPECT_EQ(cal->solve(BatchMethod::kOneStep).verdict, Verdict::kTooFewSamples);
}

TEST(BatchCalibrator, PlanarSweepHasInsufficientCoverageOrIsRefused) {
  // All attitudes about a single horizontal axis: h_s sweeps one circle only.
  std::mt19937_64 rng(23);
  std::vector<Mat3<double>> att;
  for (int i = 0; i < 40; ++i)
    att.push_back(r_bn_from_li(LiEuler<double>{0.3, 0, (9.0 * i) * kDeg}));
  auto cal = std::make_unique<Calibrator>();
  for (const Sample& s : simulate(from_li(paper_li()), paper_h_n(), att, 0.3, 0.015 * kDeg, rng)) {
    cal->add_sample(s.m, s.f, s.r_meas);
  }
  const BatchResult<double> r = cal->solve();
  EXPECT_NE(r.verdict, Verdict::kOk);
}

TEST(BatchCalibrator, SpikesAndDropoutsAreRejectedAndCounted) {
  constexpr int kSeeds = 10, kN = 600;
  const LiParams<double> t = paper_li();
  double clean_ss = 0, dirty_ss = 0, clean_int = 0, dirty_int = 0;
  for (int seed = 0; seed < kSeeds; ++seed) {
    std::mt19937_64 rng(500 + static_cast<unsigned>(seed));
    const auto data =
        simulate(from_li(t), paper_h_n(), random_attitudes(kN, rng), 0.3, 0.015 * kDeg, rng);
    auto clean = std::make_unique<Calibrator>();
    auto dirty = std::make_unique<Calibrator>();
    std::size_t spikes = 0, drops = 0;
    std::uniform_int_distribution<int> axis(0, 2);
    for (int i = 0; i < kN; ++i) {
      const Sample& s = data[static_cast<std::size_t>(i)];
      clean->add_sample(s.m, s.f, s.r_meas);
      Vec3<double> m = s.m;
      if (i % 100 == 37) {  // 1 % spikes of 5000 nT
        m(axis(rng)) += (i % 200 == 37 ? 5000.0 : -5000.0);
        ++spikes;
      }
      if (i % 50 == 11) {  // 2 % dropouts
        m(1) = kNaN;
        ++drops;
      }
      dirty->add_sample(m, s.f, s.r_meas);
    }
    const BatchResult<double> rc = clean->solve();
    const BatchResult<double> rd = dirty->solve();
    ASSERT_EQ(rc.verdict, Verdict::kOk);
    ASSERT_EQ(rd.verdict, Verdict::kOk) << verdict_name(rd.verdict);
    EXPECT_EQ(rd.counts.skipped_nonfinite, drops);
    EXPECT_GE(rd.counts.outliers, spikes);
    EXPECT_LE(rd.counts.outliers, spikes + 3);  // at most a few 5-sigma noise rejections
    clean_ss += (rc.li.rm_rad - t.rm_rad).squaredNorm();
    dirty_ss += (rd.li.rm_rad - t.rm_rad).squaredNorm();
    clean_int += (rc.li.kof - t.kof).squaredNorm();
    dirty_int += (rd.li.kof - t.kof).squaredNorm();
  }
  EXPECT_LT(std::sqrt(dirty_ss), 1.5 * std::sqrt(clean_ss));
  EXPECT_LT(std::sqrt(dirty_int), 1.5 * std::sqrt(clean_int));
}

TEST(BatchCalibrator, AddAndSolveDoNotAllocate) {
  std::mt19937_64 rng(24);
  const auto data =
      simulate(from_li(paper_li()), paper_h_n(), random_attitudes(60, rng), 0.3, 0.015 * kDeg, rng);
  auto cal = std::make_unique<Calibrator>();
  magvec::test::AllocationScope scope;
  Eigen::internal::set_is_malloc_allowed(false);
  for (const Sample& s : data)
    cal->add_sample(s.m, s.f, s.r_meas);
  const BatchResult<double> r = cal->solve();
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(scope.count(), 0U);
  EXPECT_EQ(r.verdict, Verdict::kOk);
}

}  // namespace
}  // namespace magvec::core
