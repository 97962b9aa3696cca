#include "magvec/core/misalignment.hpp"

#include <gtest/gtest.h>

#include <memory>
#include <random>

#include "li_setup.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using namespace test_setup;
using Store = SampleStore<double, 512>;

std::unique_ptr<Store> store_of(const std::vector<Sample>& data) {
  auto st = std::make_unique<Store>();
  for (const Sample& s : data)
    EXPECT_TRUE(st->push(s.m, s.f, &s.r_meas));
  return st;
}

TEST(Misalignment, PlaneCompressionAndJointRecoverRmExactly) {
  std::mt19937_64 rng(5);
  const LiParams<double> t = paper_li();
  const SensorModel<double> m = from_li(t);
  auto st = store_of(simulate(m, paper_h_n(), random_attitudes(60, rng), 0, 0, rng));
  const MisalignmentSolution<double> pc = plane_compression(*st, m.w, m.o);
  ASSERT_EQ(pc.status, MisalignmentStatus::kOk);
  EXPECT_LT((pc.rm_rad - t.rm_rad).cwiseAbs().maxCoeff(), 1e-10);
  const MisalignmentSolution<double> j = joint_rm_hn(*st, m.w, m.o);
  ASSERT_EQ(j.status, MisalignmentStatus::kOk);
  EXPECT_LT((j.rm_rad - t.rm_rad).cwiseAbs().maxCoeff(), 1e-10);
  EXPECT_LT((j.h_n - paper_h_n()).norm(), 1e-6);
}

TEST(Misalignment, LevelOnlyDataIsRefusedOrSolvedWithHeadingFixed) {
  std::mt19937_64 rng(6);
  const LiParams<double> t = paper_li();
  const SensorModel<double> m = from_li(t);
  auto st = store_of(simulate(m, paper_h_n(), level_attitudes(36), 0, 0, rng));
  EXPECT_EQ(plane_compression(*st, m.w, m.o).status, MisalignmentStatus::kUnobservableHeading);
  const MisalignmentSolution<double> j = joint_rm_hn(*st, m.w, m.o);
  EXPECT_EQ(j.status, MisalignmentStatus::kUnobservableHeading);
  EXPECT_GT(std::abs(j.weak_axis_body(2)), 0.9) << "the weak direction is the vertical";
  MisalignmentOptions<double> opt;
  opt.fix_heading = true;
  opt.fixed_heading_rad = t.rm_rad(0);
  for (const auto& s : {plane_compression(*st, m.w, m.o, opt), joint_rm_hn(*st, m.w, m.o, opt)}) {
    ASSERT_EQ(s.status, MisalignmentStatus::kOk);
    EXPECT_TRUE(s.heading_fixed);
    EXPECT_LT((s.rm_rad - t.rm_rad).cwiseAbs().maxCoeff(), 1e-10);
  }
}

TEST(Misalignment, JointFitIsMorePreciseThanPlaneCompression) {
  const LiParams<double> t = paper_li();
  const SensorModel<double> m = from_li(t);
  std::vector<double> pc_err, j_err;
  for (int seed = 0; seed < 60; ++seed) {
    std::mt19937_64 rng(300 + static_cast<unsigned>(seed));
    auto st = store_of(simulate(m, paper_h_n(), random_attitudes(60, rng), 0.3, 0.015 * kDeg, rng));
    const auto pc = plane_compression(*st, m.w, m.o);
    const auto j = joint_rm_hn(*st, m.w, m.o);
    ASSERT_EQ(pc.status, MisalignmentStatus::kOk);
    ASSERT_EQ(j.status, MisalignmentStatus::kOk);
    pc_err.push_back(pc.rm_rad(1) - t.rm_rad(1));
    j_err.push_back(j.rm_rad(1) - t.rm_rad(1));
  }
  EXPECT_LT(sd(j_err), sd(pc_err));
}

TEST(Misalignment, SolversDoNotAllocate) {
  std::mt19937_64 rng(7);
  const SensorModel<double> m = from_li(paper_li());
  auto st = store_of(simulate(m, paper_h_n(), random_attitudes(60, rng), 0.3, 0.015 * kDeg, rng));
  magvec::test::AllocationScope scope;
  Eigen::internal::set_is_malloc_allowed(false);
  const auto pc = plane_compression(*st, m.w, m.o);
  const auto j = joint_rm_hn(*st, m.w, m.o);
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(scope.count(), 0U);
  EXPECT_EQ(pc.status, MisalignmentStatus::kOk);
  EXPECT_EQ(j.status, MisalignmentStatus::kOk);
}

}  // namespace
}  // namespace magvec::core
