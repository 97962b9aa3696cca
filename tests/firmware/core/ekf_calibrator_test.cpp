// EkfCalibrator (SensorLoop adapter of the scalar EKF + misalignment step) with simulator data:
// on the survey's manoeuvre it becomes ready and returns a model aligned to the INS (the
// body-frame map Rm^T W and the offset match the truth); without the alignment step the model is
// flagged not aligned and only G = W^T W is right; spikes are gated, bad samples rejected, and a
// heading-only manoeuvre cannot be aligned (refused with its code).
#include "magvec/core/ekf_calibrator.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <memory>
#include <random>

#include "li_setup.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using test_setup::kNaN;

using Cal = EkfCalibrator<double, 256>;

EkfCalibratorConfig<double> config(bool align) {
  EkfCalibratorConfig<double> c;
  c.ekf.noise_sigma_nT = 0.3;
  c.align = align;
  return c;
}

// Feeds the survey manoeuvre (with `spike_p` spikes) until ready(); returns the sample count used.
std::uint32_t feed(Cal* cal, std::uint64_t seed, double spike_p, std::uint32_t* gated = nullptr) {
  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.num_samples = static_cast<std::uint32_t>(sc.survey.manoeuvre_s * sc.rate_hz);
  sc.spike_probability = spike_p;
  sc.spike_amplitude_nT = 500;
  drivers::sim::Simulator sim(sc, seed);
  drivers::sim::SimSample s{};
  std::uint32_t n = 0;
  while (sim.next(&s)) {
    ++n;
    const CalibratorAdd a = cal->add(s.m_nT, s.f_nT, &s.r_bn_ins);
    if (gated != nullptr && a == CalibratorAdd::kGated) ++*gated;
    if (cal->ready()) return n;
  }
  return 0;
}

// Body-frame map of a model: h_b = Rm^T W (m - o).
Mat3<double> body_map(const SensorModel<double>& m) {
  return m.rm_matrix().transpose() * m.w;
}

TEST(EkfCalibrator, SurveyManoeuvreGivesAnAlignedModel) {
  auto cal = std::make_unique<Cal>(config(true));
  const std::uint32_t n = feed(cal.get(), 11, 0.0);
  ASSERT_GT(n, 0u) << "never ready: updates " << cal->updates() << ", sigma_f " << cal->sigma_f_nT()
                   << ", align samples " << cal->align_samples();
  EXPECT_LE(cal->sigma_f_nT(), 0.1);
  EXPECT_GE(cal->updates(), 2000u);
  SensorModel<double> model;
  const CalibratorSolve r = cal->solve(&model);
  ASSERT_TRUE(r.ok) << ekf_cal_code_name(r.code);
  EXPECT_TRUE(cal->aligned());
  const SensorModel<double> truth = from_li(test_setup::paper_li());
  // Rm^T W: relative error 2e-4 ~ 0.01 deg / 200 ppm (the field is 53.7 uT: ~10 nT).
  EXPECT_LT((body_map(model) - body_map(truth)).norm(), 3e-4) << body_map(model) - body_map(truth);
  EXPECT_LT((model.o - truth.o).norm(), 5.0);
  // Returned in Li form: the misalignment angles themselves are close to the truth.
  LiParams<double> li;
  ASSERT_EQ(to_li(model, &li), ConversionStatus::kOk);
  EXPECT_LT((li.rm_rad - test_setup::paper_li().rm_rad).norm(), 0.02 * test_setup::kDeg);
}

TEST(EkfCalibrator, WithoutAlignmentTheModelIsFlaggedAndOnlyGIsRight) {
  auto cal = std::make_unique<Cal>(config(false));
  ASSERT_GT(feed(cal.get(), 12, 0.0), 0u);
  SensorModel<double> model;
  ASSERT_TRUE(cal->solve(&model).ok);
  EXPECT_FALSE(cal->aligned());
  EXPECT_TRUE(model.rm_matrix().isIdentity(1e-12));
  const SensorModel<double> truth = from_li(test_setup::paper_li());
  EXPECT_LT((model.g() - truth.g()).norm(), 5e-4);
  // The honest part: W itself is rotated away from the truth (not usable for h_n).
  EXPECT_GT((body_map(model) - body_map(truth)).norm(), 1e-2);
}

TEST(EkfCalibrator, SpikesAreGatedAndBadSamplesRejected) {
  auto cal = std::make_unique<Cal>(config(true));
  std::uint32_t gated = 0;
  ASSERT_GT(feed(cal.get(), 13, 0.01, &gated), 0u);
  EXPECT_GT(gated, 10u);
  EXPECT_EQ(gated, cal->filter().counters().gated);
  const Mat3<double> r = Mat3<double>::Identity();
  EXPECT_EQ(cal->add(Vec3<double>(kNaN, 0, 0), 53729, &r), CalibratorAdd::kRejected);
  EXPECT_EQ(cal->add(Vec3<double>(1e4, 0, 0), kNaN, &r), CalibratorAdd::kRejected);
  EXPECT_EQ(cal->add(Vec3<double>(1e4, 0, 0), -1, nullptr), CalibratorAdd::kRejected);
  SensorModel<double> model;
  EXPECT_TRUE(cal->solve(&model).ok);
}

TEST(EkfCalibrator, NotInitialisedOrHeadingOnlyIsRefused) {
  auto cal = std::make_unique<Cal>(config(true));
  SensorModel<double> model;
  CalibratorSolve r = cal->solve(&model);
  EXPECT_FALSE(r.ok);
  EXPECT_EQ(static_cast<EkfCalCode>(r.code), EkfCalCode::kNotInitialised);
  // Random directions for the EKF (scalar only, no attitude) then a level heading-only sweep for
  // the alignment store: the filter converges, the rotation about the vertical is unobservable.
  const SensorModel<double> truth = from_li(test_setup::paper_li());
  const Vec3<double> h_n = test_setup::paper_h_n();
  std::mt19937_64 rng(4);
  std::normal_distribution<double> nd(0.0, 0.3);
  for (int i = 0; i < 3000; ++i) {
    const Mat3<double> rr = test_setup::random_rotation(rng);
    cal->add(truth.predict_raw(rr, h_n) + Vec3<double>(nd(rng), nd(rng), nd(rng)), h_n.norm(),
             nullptr);
  }
  for (int i = 0; i < 3000 && !cal->ready(); ++i) {
    const Mat3<double> rz = rot_z(0.01 * i);
    cal->add(truth.predict_raw(rz, h_n) + Vec3<double>(nd(rng), nd(rng), nd(rng)), h_n.norm(), &rz);
  }
  ASSERT_TRUE(cal->ready());
  r = cal->solve(&model);
  EXPECT_FALSE(r.ok);
  EXPECT_EQ(static_cast<EkfCalCode>(r.code), EkfCalCode::kAlignUnobservable)
      << ekf_cal_code_name(r.code);
}

TEST(EkfCalibrator, AddDoesNotAllocate) {
  auto cal = std::make_unique<Cal>(config(true));
  drivers::sim::Simulator sim(drivers::sim::scenario_survey(), 9);
  drivers::sim::SimSample s{};
  test::AllocationScope scope;
  // The whole manoeuvre: buffering, the initial fit, then filter updates.
  for (int i = 0; i < 12000 && sim.next(&s); ++i)
    cal->add(s.m_nT, s.f_nT, &s.r_bn_ins);
  EXPECT_EQ(scope.count(), 0u);
  EXPECT_TRUE(cal->filter().initialised());
  EXPECT_GT(cal->updates(), 1000u);
}

}  // namespace
}  // namespace magvec::core
