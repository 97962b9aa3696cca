// EkfCalibrator (SensorLoop adapter of the scalar EKF + misalignment step) with simulator data:
// on the survey's manoeuvre it becomes ready and returns a model aligned to the INS (the
// body-frame map Rm^T W and the offset match the truth); without the alignment step the model is
// flagged not aligned and only G = W^T W is right; spikes are gated, bad samples rejected, and a
// heading-only manoeuvre cannot be aligned (refused with its code).
#include "magvec/core/ekf_calibrator.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
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

// E-Acc-3: the |h| 1-sigma over the survey envelope from the filter's covariance against the
// Monte Carlo scatter of the error it predicts. Each run's solved model compensates noise-free
// readings of the true field at the attitudes of its own envelope (the tilts it saw, every
// heading), scored against the true |h_n|. RMS over the runs of the predicted and of the actual.
struct EnvelopeScatter {
  double predicted_nT = 0;
  double actual_nT = 0;
  double predicted_enu_nT = 0;  // per axis
  double actual_enu_nT = 0;
  int runs = 0;
};

EnvelopeScatter envelope_scatter(std::uint32_t relinearise_after, int runs, std::uint32_t updates) {
  const drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  double p2 = 0, a2 = 0, pv2 = 0, av2 = 0;
  EnvelopeScatter out;
  for (int run = 0; run < runs; ++run) {
    EkfCalibratorConfig<double> c = config(true);
    c.ekf.relinearise_start_after = relinearise_after;
    auto cal = std::make_unique<Cal>(c);
    drivers::sim::Simulator sim(sc, 5000 + static_cast<std::uint64_t>(run));
    drivers::sim::SimSample s{};
    while (cal->updates() < updates && sim.next(&s))
      cal->add(s.m_nT, s.f_nT, &s.r_bn_ins);
    if (cal->updates() < updates) {
      ADD_FAILURE() << "run " << run << ": only " << cal->updates() << " updates";
      continue;
    }
    SensorModel<double> model;
    const CalibratorSolve r = cal->solve(&model);
    if (!r.ok) {
      ADD_FAILURE() << "run " << run << ": " << ekf_cal_code_name(r.code);
      continue;
    }
    // The figures the solve gives (relinearised); of the covariance as it stands otherwise.
    const Cal::OutputSigmas sig = cal->output_sigmas(model, cal->alignment().h_n);
    const double predicted = sig.f_nT;
    if (relinearise_after > 0) {
      EXPECT_NEAR(r.calibration_sigma_f_nT, predicted, 1e-6 * predicted);
      EXPECT_NEAR(r.calibration_sigma_enu_nT, sig.enu_nT, 1e-6 * sig.enu_nT);
    } else {
      EXPECT_TRUE(std::isnan(r.calibration_sigma_f_nT)) << "an optimistic figure was given";
    }
    double e2 = 0, v2 = 0;
    int n = 0;
    for_each_envelope_attitude(cal->tilt_moments(), [&](const Mat3<double>& r_bn) {
      const Vec3<double> m = sc.truth.predict_raw(r_bn, sc.h_n_nT);
      const double e = (model.w * (m - model.o)).norm() - sc.h_n_nT.norm();
      e2 += e * e;
      const Vec3<double> g =
          r_bn.transpose() * model.rm_matrix().transpose() * model.w * (m - model.o);
      v2 += (g - sc.h_n_nT).squaredNorm() / 3;
      ++n;
    });
    if (n != kEnvelopeAttitudes) {
      ADD_FAILURE() << "run " << run << ": " << n << " envelope attitudes";
      continue;
    }
    p2 += predicted * predicted;
    a2 += e2 / n;
    const double enu = static_cast<double>(r.calibration_sigma_enu_nT);
    pv2 += enu * enu;
    av2 += v2 / n;
    ++out.runs;
  }
  out.predicted_nT = std::sqrt(p2 / out.runs);
  out.actual_nT = std::sqrt(a2 / out.runs);
  out.predicted_enu_nT = std::sqrt(pv2 / out.runs);
  out.actual_enu_nT = std::sqrt(av2 / out.runs);
  return out;
}

// The default readiness (2 000 updates, all 60 runs ready there) and later. |h|: from 3 000 updates
// on within 25 % of the scatter; at readiness the error has a heavy tail (over 240 runs the worst
// two at 4.6 and 7.8 sigma: the filter's first updates were linearised about a start still off),
// 1.3-1.5x, and there the test asks what the change is for: a smaller scatter and a closer figure
// than the filter with its start as a Gaussian, which is 2x optimistic. E/N/U (the filter's error
// through the alignment fit, and the fit's own): within 25 % at every stage.
TEST(EkfCalibrator, OutputSigmasOverTheEnvelopeMatchTheScatter) {
  const EnvelopeScatter gaussian = envelope_scatter(0, 60, 2000);
  const EnvelopeScatter at_ready = envelope_scatter(250, 60, 2000);
  ASSERT_EQ(gaussian.runs, 60);
  ASSERT_EQ(at_ready.runs, 60);
  std::printf(
      "2000 updates: predicted %.4f nT, scatter %.4f nT (ratio %.2f); start as a Gaussian: "
      "%.4f, %.4f (%.2f)\n",
      at_ready.predicted_nT, at_ready.actual_nT, at_ready.actual_nT / at_ready.predicted_nT,
      gaussian.predicted_nT, gaussian.actual_nT, gaussian.actual_nT / gaussian.predicted_nT);
  std::printf("2000 updates: E/N/U predicted %.4f nT, scatter %.4f nT (ratio %.2f)\n",
              at_ready.predicted_enu_nT, at_ready.actual_enu_nT,
              at_ready.actual_enu_nT / at_ready.predicted_enu_nT);
  EXPECT_GT(gaussian.actual_nT / gaussian.predicted_nT, 1.5) << "the old filter was consistent?";
  EXPECT_LT(at_ready.actual_nT, gaussian.actual_nT);
  EXPECT_LT(at_ready.actual_nT / at_ready.predicted_nT, gaussian.actual_nT / gaussian.predicted_nT);
  EXPECT_NEAR(at_ready.actual_enu_nT / at_ready.predicted_enu_nT, 1.0, 0.25);
  for (const std::uint32_t updates : {3000u, 4000u, 8000u}) {
    const EnvelopeScatter e = envelope_scatter(250, 60, updates);
    ASSERT_EQ(e.runs, 60);
    std::printf(
        "%u updates: predicted %.4f nT, scatter %.4f nT (ratio %.2f); E/N/U %.4f, %.4f "
        "(%.2f)\n",
        updates, e.predicted_nT, e.actual_nT, e.actual_nT / e.predicted_nT, e.predicted_enu_nT,
        e.actual_enu_nT, e.actual_enu_nT / e.predicted_enu_nT);
    EXPECT_NEAR(e.actual_nT / e.predicted_nT, 1.0, 0.25) << updates << " updates";
    EXPECT_NEAR(e.actual_enu_nT / e.predicted_enu_nT, 1.0, 0.25) << updates << " updates, E/N/U";
  }
}

// With process noise the filter forgets part of its start, so the start's term cannot be swapped
// whole: no relinearisation, and no 1-sigma from a covariance that stayed optimistic.
TEST(EkfCalibrator, WithProcessNoiseTheStartIsNotRelinearisedAndNoFigureIsGiven) {
  EkfCalibratorConfig<double> c = config(true);
  c.ekf.q.tail<3>().setConstant(1e-6);  // offset drift, nT^2 per update
  auto cal = std::make_unique<Cal>(c);
  ASSERT_GT(feed(cal.get(), 14, 0.0), 0u);
  EXPECT_EQ(cal->filter().counters().start_relinearisations, 0u);
  EXPECT_FALSE(cal->filter().start_relinearised());
  SensorModel<double> model;
  const CalibratorSolve r = cal->solve(&model);
  ASSERT_TRUE(r.ok) << ekf_cal_code_name(r.code);
  EXPECT_TRUE(std::isnan(r.calibration_sigma_f_nT));
  EXPECT_TRUE(std::isnan(r.calibration_sigma_enu_nT));
}

}  // namespace
}  // namespace magvec::core
