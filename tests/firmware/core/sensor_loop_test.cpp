#include "magvec/core/sensor_loop.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <random>

#include "magvec/core/frames.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

constexpr double kDeg = kPi<double> / 180.0;

// A calibrator that "solves" to a fixed model after a number of samples; lets the loop's state
// machine be tested independently of any estimator.
struct FakeCalibrator {
  SensorModel<double> result;
  std::uint32_t needed{100};
  std::uint32_t seen{0};
  bool refuse{false};
  bool aligned{true};
  float mag_noise_nT{std::numeric_limits<float>::quiet_NaN()};  // what the "solve" estimated
  // The candidate's own 1-sigma of |h| and E/N/U from its covariance (NaN: not given).
  float cal_sigma_f_nT{std::numeric_limits<float>::quiet_NaN()};
  float cal_sigma_enu_nT{std::numeric_limits<float>::quiet_NaN()};
  // The time offset the "solve" found, relative to the pairing it was fed (NaN: none).
  float time_offset_s{std::numeric_limits<float>::quiet_NaN()};
  int begins{0};
  void begin() noexcept {
    seen = 0;
    ++begins;
  }
  CalibratorAdd add(const Vec3<double>& m, double, const Mat3<double>*) noexcept {
    if (m.norm() > 1e6) return CalibratorAdd::kGated;
    ++seen;
    return CalibratorAdd::kUsed;
  }
  double progress() const noexcept { return std::min(1.0, seen / double(needed)); }
  bool ready() const noexcept { return seen >= needed; }
  CalibratorSolve solve(SensorModel<double>* out) noexcept {
    if (refuse) return {false, 7};
    *out = result;
    CalibratorSolve r{true, 0, aligned};
    r.mag_noise_nT = mag_noise_nT;
    r.calibration_sigma_f_nT = cal_sigma_f_nT;
    r.calibration_sigma_enu_nT = cal_sigma_enu_nT;
    r.time_offset_correction_s = time_offset_s;
    return r;
  }
};

SensorModel<double> truth_model() {
  LiParams<double> p;
  p.ks = {1.08, 1.02, 1.033};
  p.o_rad = Vec3<double>(1.7, 3.5, 2.1) * kDeg;
  p.kof = {400, -300, 250};
  p.rm_rad = Vec3<double>(5.7, 2.1, 3.5) * kDeg;
  return from_li(p);
}

struct Feed {
  std::mt19937_64 rng{9};
  std::normal_distribution<double> noise{0, 0.3};
  std::uniform_real_distribution<double> ang{-170, 170};
  Vec3<double> h_n{-4053, 25022, -47374};
  std::uint64_t t{0};
  MagSample<double> next(const SensorModel<double>& truth, Mat3<double>* r_bn) {
    *r_bn =
        r_bn_from_li(LiEuler<double>{ang(rng) * kDeg, ang(rng) * kDeg / 3, ang(rng) * kDeg / 3});
    MagSample<double> s;
    s.t_us = (t += 5000);
    s.m_nT = truth.predict_raw(*r_bn, h_n) + Vec3<double>(noise(rng), noise(rng), noise(rng));
    s.f_ref_nT = h_n.norm();
    return s;
  }
};

TEST(SensorLoop, AppliesAValidCalibrationAfterValidation) {
  FakeCalibrator cal;
  cal.result = truth_model();
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  EXPECT_EQ(loop.state(), CalState::kIdle);
  OutputRecord<double> rec = loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_TRUE(rec.flags & kOutUncalibrated);
  EXPECT_EQ(rec.cal_id, 0u);
  loop.start_calibration();
  int steps = 0;
  while (loop.state() != CalState::kApplied && loop.state() != CalState::kFailed && steps < 10000) {
    rec = loop.process(feed.next(truth_model(), &r), &r);
    ++steps;
  }
  ASSERT_EQ(loop.state(), CalState::kApplied);
  EXPECT_EQ(steps, 100 + 1 + 200);  // collect, solve, validate
  EXPECT_EQ(loop.cal_id(), 1u);
  EXPECT_LT(loop.last_validation_rms_nT(), 1.0);
  rec = loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(rec.cal_id, 1u);
  EXPECT_FALSE(rec.flags & kOutUncalibrated);
  EXPECT_NEAR(rec.intensity_nT, feed.h_n.norm(), 3.0);
  EXPECT_LT((rec.h_n_nT - feed.h_n).norm(), 20.0);  // noise only (no INS noise here)
  EXPECT_EQ(loop.health().calibrations_applied, 1u);
}

TEST(SensorLoop, KeepsThePreviousCalibrationWhenTheNewOneFailsValidation) {
  FakeCalibrator cal;
  cal.result = truth_model();
  cal.result.o += Vec3<double>(300, 0, 0);  // a bad candidate
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  loop.set_active(truth_model(), 4);
  Feed feed;
  Mat3<double> r;
  loop.start_calibration();
  for (int i = 0; i < 400; ++i)
    (void)loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(loop.state(), CalState::kFailed);
  EXPECT_EQ(loop.failure(), CalFailure::kValidationFailed);
  // What the refusal names: the figure, the bound (3 x 0.3 nT, at least 1 nT) and the noise.
  EXPECT_GT(loop.last_validation_rms_nT(), loop.last_validation_bound_nT());
  EXPECT_DOUBLE_EQ(loop.last_validation_bound_nT(), 1.0);
  EXPECT_DOUBLE_EQ(loop.candidate_noise_nT(), 0.3);
  EXPECT_LT(loop.last_validation_active_rms_nT(), 1.0);             // the active one is the truth
  EXPECT_TRUE(std::isnan(loop.last_validation_vector_bound_nT()));  // not reached
  EXPECT_EQ(loop.cal_id(), 4u);
  EXPECT_LT((loop.active_model().o - truth_model().o).norm(), 1e-12);
  EXPECT_EQ(loop.health().calibrations_failed, 1u);
}

// Records carry cal_id to say which calibration produced them: after a revert to an older
// calibration, the next applied one must not reuse the id of the calibration reverted from.
TEST(SensorLoop, CalibrationIdsAreNeverReusedAfterARevert) {
  FakeCalibrator cal;
  cal.result = truth_model();
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.validate_against_active = false;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  auto calibrate = [&] {
    loop.start_calibration();
    for (int i = 0; i < 400 && loop.state() != CalState::kApplied; ++i)
      (void)loop.process(feed.next(truth_model(), &r), &r);
    return loop.state();
  };
  loop.set_active(truth_model(), 1);  // the persisted calibration
  ASSERT_EQ(calibrate(), CalState::kApplied);
  EXPECT_EQ(loop.cal_id(), 2u);
  loop.set_active(truth_model(), 1);  // revert to the persisted one
  EXPECT_EQ(loop.cal_id(), 1u);
  ASSERT_EQ(calibrate(), CalState::kApplied);
  EXPECT_EQ(loop.cal_id(), 3u);  // not 2 again
}

// A candidate that found a time offset in its data holds only with its samples paired that way:
// the loop asks the pipeline for the step once, when the validation starts, and for the step back
// when the validation refuses the candidate; a solver refusal asks for nothing.
TEST(SensorLoop, ACandidatesTimeOffsetIsAskedOfThePipelineAndTakenBackWhenRefused) {
  const auto run = [](FakeCalibrator& cal, std::int64_t* first_step, std::int64_t* total,
                      int* asks) {
    LoopConfig<double> cfg;
    cfg.noise_nT = 0.3;
    SensorLoop<double, FakeCalibrator> loop(cal, cfg);
    Feed feed;
    Mat3<double> r;
    loop.start_calibration();
    *first_step = 0;
    *total = 0;
    *asks = 0;
    for (int i = 0; i < 400; ++i) {
      (void)loop.process(feed.next(truth_model(), &r), &r);
      const std::int64_t d = loop.take_time_offset_step_us();
      if (d != 0) {
        if (*asks == 0) *first_step = d;
        *total += d;
        ++*asks;
      }
      EXPECT_EQ(loop.take_time_offset_step_us(), 0);  // taken once
    }
    return loop.state();
  };
  std::int64_t first = 0, total = 0;
  int asks = 0;
  FakeCalibrator good;
  good.result = truth_model();
  good.time_offset_s = -0.0095f;
  EXPECT_EQ(run(good, &first, &total, &asks), CalState::kApplied);
  EXPECT_EQ(first, -9500);
  EXPECT_EQ(total, -9500);
  EXPECT_EQ(asks, 1);
  FakeCalibrator bad = good;
  bad.result.o += Vec3<double>(300, 0, 0);  // refused by the held-out check
  EXPECT_EQ(run(bad, &first, &total, &asks), CalState::kFailed);
  EXPECT_EQ(first, -9500);
  EXPECT_EQ(total, 0);
  EXPECT_EQ(asks, 2);
  FakeCalibrator refused = good;
  refused.refuse = true;
  EXPECT_EQ(run(refused, &first, &total, &asks), CalState::kFailed);
  EXPECT_EQ(asks, 0);
  FakeCalibrator none;
  none.result = truth_model();  // no offset (NaN)
  EXPECT_EQ(run(none, &first, &total, &asks), CalState::kApplied);
  EXPECT_EQ(asks, 0);
}

TEST(SensorLoop, ReportsSolverRefusalWithItsCode) {
  FakeCalibrator cal;
  cal.refuse = true;
  SensorLoop<double, FakeCalibrator> loop(cal, LoopConfig<double>{});
  Feed feed;
  Mat3<double> r;
  loop.start_calibration();
  for (int i = 0; i < 150; ++i)
    (void)loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(loop.state(), CalState::kFailed);
  EXPECT_EQ(loop.failure(), CalFailure::kSolverRejected);
  EXPECT_EQ(loop.solver_code(), 7);
}

// External solve (magvecd's worker thread): the loop waits in kSolving without touching the
// calibrator, and the result gives exactly the records of the inline path when it is installed at
// the same point (after the sample following ready, the one the inline loop solves on).
TEST(SensorLoop, ExternalSolveInstalledAtTheInlinePointGivesTheSameRecords) {
  FakeCalibrator cal_inline;
  FakeCalibrator cal_external;
  cal_inline.result = cal_external.result = truth_model();
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  SensorLoop<double, FakeCalibrator> inline_loop(cal_inline, cfg);
  cfg.external_solve = true;
  SensorLoop<double, FakeCalibrator> external_loop(cal_external, cfg);
  inline_loop.start_calibration();
  external_loop.start_calibration();
  Feed feed_a;
  Feed feed_b;
  Mat3<double> ra;
  Mat3<double> rb;
  int installs = 0;
  for (int i = 0; i < 400; ++i) {
    const MagSample<double> sa = feed_a.next(truth_model(), &ra);
    const MagSample<double> sb = feed_b.next(truth_model(), &rb);
    const std::uint32_t seen_before = cal_external.seen;
    const OutputRecord<double> a = inline_loop.process(sa, &ra);
    const OutputRecord<double> b = external_loop.process(sb, &rb);
    ASSERT_EQ(a.flags, b.flags) << i;
    ASSERT_EQ(a.cal_id, b.cal_id) << i;
    ASSERT_EQ(a.intensity_nT, b.intensity_nT) << i;
    // The inline loop solved on this sample; the external one only waited.
    if (external_loop.state() == CalState::kSolving && inline_loop.state() != CalState::kSolving) {
      EXPECT_EQ(cal_external.seen, seen_before);  // frozen while solving
      SensorModel<double> model;
      const CalibratorSolve r = cal_external.solve(&model);
      EXPECT_TRUE(external_loop.install_solve(external_loop.solve_ticket(), r, model));
      ++installs;
    }
  }
  EXPECT_EQ(installs, 1);
  EXPECT_EQ(external_loop.state(), CalState::kApplied);
  EXPECT_EQ(inline_loop.state(), CalState::kApplied);
}

TEST(SensorLoop, ExternalSolveWaitsAndCompensatesWithTheActiveModel) {
  FakeCalibrator cal;
  cal.result = truth_model();
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.external_solve = true;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  EXPECT_EQ(loop.solve_ticket(), 0u);
  loop.start_calibration();
  for (int i = 0; i < 100; ++i)
    (void)loop.process(feed.next(truth_model(), &r), &r);
  ASSERT_EQ(loop.state(), CalState::kSolving);
  EXPECT_EQ(loop.solve_ticket(), 1u);
  // However long the solve takes, samples keep their records, flagged as calibrating.
  for (int i = 0; i < 1000; ++i) {
    const OutputRecord<double> rec = loop.process(feed.next(truth_model(), &r), &r);
    ASSERT_TRUE(rec.flags & kOutCalibrating);
    ASSERT_EQ(rec.cal_id, 0u);
  }
  EXPECT_EQ(loop.state(), CalState::kSolving);
  EXPECT_EQ(cal.seen, 100u);
  EXPECT_FALSE(loop.install_solve(0, {true, 0}, truth_model()));  // a stale ticket
  EXPECT_EQ(loop.state(), CalState::kSolving);
  EXPECT_TRUE(loop.install_solve(1, {true, 0}, truth_model()));
  EXPECT_EQ(loop.state(), CalState::kValidating);
  EXPECT_FALSE(loop.install_solve(1, {true, 0}, truth_model()));  // only once
  for (int i = 0; i < 200; ++i)
    (void)loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(loop.state(), CalState::kApplied);
  EXPECT_EQ(loop.cal_id(), 1u);
}

// A calibration restarted while its solve runs elsewhere: the late result of the old data is not
// installed into the new calibration.
TEST(SensorLoop, ExternalSolveOfARestartedCalibrationIsIgnored) {
  FakeCalibrator cal;
  LoopConfig<double> cfg;
  cfg.external_solve = true;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  loop.start_calibration();
  for (int i = 0; i < 101; ++i)
    (void)loop.process(feed.next(truth_model(), &r), &r);
  ASSERT_EQ(loop.state(), CalState::kSolving);
  const std::uint32_t old_ticket = loop.solve_ticket();
  loop.start_calibration();
  EXPECT_FALSE(loop.install_solve(old_ticket, {false, 7}, truth_model()));
  EXPECT_EQ(loop.state(), CalState::kCollecting);
  EXPECT_EQ(loop.failure(), CalFailure::kNone);
  for (int i = 0; i < 100; ++i)
    (void)loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(loop.state(), CalState::kSolving);
  EXPECT_EQ(loop.solve_ticket(), old_ticket + 1);
  EXPECT_TRUE(loop.install_solve(old_ticket + 1, {false, 7}, truth_model()));
  EXPECT_EQ(loop.state(), CalState::kFailed);
  EXPECT_EQ(loop.solver_code(), 7);
}

TEST(SensorLoop, CountsDropoutsDeviceErrorsMissingAttitudeAndGatedSamples) {
  FakeCalibrator cal;
  SensorLoop<double, FakeCalibrator> loop(cal, LoopConfig<double>{});
  loop.start_calibration();
  MagSample<double> s;
  s.m_nT = Vec3<double>(std::nan(""), 1, 2);
  OutputRecord<double> rec = loop.process(s, nullptr);
  EXPECT_TRUE(rec.flags & kOutDropout);
  s.m_nT = Vec3<double>(1, 2, 3);
  s.device_error = true;
  rec = loop.process(s, nullptr);
  EXPECT_TRUE(rec.flags & kOutDeviceError);
  s.device_error = false;
  rec = loop.process(s, nullptr);
  EXPECT_TRUE(rec.flags & kOutNoAttitude);
  s.m_nT = Vec3<double>(1e7, 0, 0);
  rec = loop.process(s, nullptr);
  EXPECT_TRUE(rec.flags & kOutRejectedByCal);
  const LoopHealth& h = loop.health();
  EXPECT_EQ(h.samples, 4u);
  EXPECT_EQ(h.dropouts, 1u);
  EXPECT_EQ(h.device_errors, 1u);
  EXPECT_EQ(h.no_attitude, 2u);
  EXPECT_EQ(h.cal_gated, 1u);
  EXPECT_EQ(h.cal_used, 1u);
}

TEST(SensorLoop, PerSamplePathDoesNotAllocate) {
  FakeCalibrator cal;
  cal.result = truth_model();
  SensorLoop<double, FakeCalibrator> loop(cal, LoopConfig<double>{});
  Feed feed;
  Mat3<double> r;
  loop.start_calibration();
  Eigen::internal::set_is_malloc_allowed(false);
  const test::AllocationScope scope;
  double sum = 0;
  for (int i = 0; i < 10000; ++i)
    sum += loop.process(feed.next(truth_model(), &r), &r).intensity_nT;
  const std::size_t n = scope.count();
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_EQ(n, 0u);
  EXPECT_TRUE(std::isfinite(sum));
}

// Runs a calibration with the fake calibrator's result to its end (applied or failed).
template <typename Loop>
void run_to_end(Loop& loop, Feed& feed, int max_steps = 2000) {
  Mat3<double> r;
  loop.start_calibration();
  for (int i = 0; i < max_steps; ++i) {
    (void)loop.process(feed.next(truth_model(), &r), &r);
    if (loop.state() == CalState::kApplied || loop.state() == CalState::kFailed) return;
  }
}

// A candidate whose intensity is right but whose misalignment is 1 deg off passes the intensity
// check; its E/N/U turn with the platform, which the vector check on the held-out samples sees.
TEST(SensorLoop, VectorValidationRefusesAWrongMisalignment) {
  FakeCalibrator cal;
  SensorModel<double> wrong = truth_model();
  wrong.rm = (wrong.rm * Quat<double>(Eigen::AngleAxis<double>(1.0 * kDeg, Vec3<double>::UnitX())))
                 .normalized();
  cal.result = wrong;
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.attitude_noise_deg = 0.01;  // the feed's attitudes are exact
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  run_to_end(loop, feed);
  EXPECT_EQ(loop.state(), CalState::kFailed);
  EXPECT_EQ(loop.failure(), CalFailure::kVectorValidationFailed);
  EXPECT_LT(loop.last_validation_rms_nT(), 1.0);           // the intensity was fine
  EXPECT_GT(loop.last_validation_vector_rms_nT(), 300.0);  // ~1 deg of 54 uT over the attitudes
  EXPECT_GT(loop.last_validation_vector_rms_nT(), loop.last_validation_vector_bound_nT());
  EXPECT_GT(loop.last_validation_vector_bound_nT(), 3 * 0.3);  // 3 x the noise and attitude floor

  // The right one passes both, and its scatter is at the noise.
  FakeCalibrator good;
  good.result = truth_model();
  SensorLoop<double, FakeCalibrator> loop2(good, cfg);
  run_to_end(loop2, feed);
  EXPECT_EQ(loop2.state(), CalState::kApplied);
  EXPECT_LT(loop2.last_validation_vector_rms_nT(), 1.0);
  EXPECT_TRUE(loop2.active_aligned());
}

// A calibrator that cannot see the misalignment: applied on its intensity, no vector check, and
// every record says its h_n is not aligned to the INS.
TEST(SensorLoop, UnalignedCalibrationIsFlaggedNotVectorValidated) {
  FakeCalibrator cal;
  SensorModel<double> unaligned = truth_model();
  unaligned.rm = Quat<double>::Identity();
  unaligned.w = truth_model().rm.toRotationMatrix() * unaligned.w;  // same |h|, a rotated W
  cal.result = unaligned;
  cal.aligned = false;
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  EXPECT_NE(loop.process(feed.next(truth_model(), &r), &r).flags & kOutNotAligned, 0u);
  run_to_end(loop, feed);
  ASSERT_EQ(loop.state(), CalState::kApplied);
  EXPECT_FALSE(loop.active_aligned());
  EXPECT_TRUE(std::isnan(loop.last_validation_vector_rms_nT()));
  const OutputRecord<double> rec = loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_NE(rec.flags & kOutNotAligned, 0u);
  EXPECT_EQ(rec.flags & kOutUncalibrated, 0u);
  // An installed calibration says whether it is aligned.
  loop.set_active(truth_model(), 7, true);
  EXPECT_EQ(loop.process(feed.next(truth_model(), &r), &r).flags & kOutNotAligned, 0u);
}

// sigma_F of the records: the configured noise until a calibration is applied, then the
// held-out intensity RMS it achieved (never below the noise).
TEST(SensorLoop, SigmaFComesFromTheValidation) {
  FakeCalibrator cal;
  SensorModel<double> off = truth_model();
  off.o += Vec3<double>(0.6, -0.5, 0.4);  // 0.9 nT offset error: a held-out RMS above the noise
  cal.result = off;
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.validation_min_rms_nT = 2.0;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  EXPECT_EQ(loop.process(feed.next(truth_model(), &r), &r).sigma_f_nT, 0.3);
  run_to_end(loop, feed);
  ASSERT_EQ(loop.state(), CalState::kApplied);
  const double rms = loop.last_validation_rms_nT();
  EXPECT_GT(rms, 0.45);
  EXPECT_EQ(loop.process(feed.next(truth_model(), &r), &r).sigma_f_nT, rms);
  loop.set_active(truth_model(), 9, true, 0.1);  // below the noise: the noise
  EXPECT_EQ(loop.process(feed.next(truth_model(), &r), &r).sigma_f_nT, 0.3);
}

// A solve that gives its candidate's own 1-sigma (from its covariance, as the vector filter does)
// sets a floor under the records' sigma_F and sigma_ENU: the noise and the attitude noise combined
// with it. The held-out window sees only its own attitudes; the covariance speaks for all.
TEST(SensorLoop, TheCalibrationsOwnSigmaFloorsSigmaFAndSigmaEnu) {
  FakeCalibrator cal;
  cal.result = truth_model();
  cal.cal_sigma_f_nT = 0.4f;    // above the held-out RMS of an exact model (the noise, 0.3)
  cal.cal_sigma_enu_nT = 20.f;  // above the attitude noise's 9.4 nT
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.attitude_noise_deg = 0.01;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  run_to_end(loop, feed);
  ASSERT_EQ(loop.state(), CalState::kApplied);
  const double sf = std::hypot(0.3, 0.4);
  EXPECT_NEAR(loop.active_sigma_f_nT(), sf, 1e-6);
  const double att = 0.01 * kDeg * feed.h_n.norm();
  EXPECT_NEAR(loop.active_sigma_enu_nT(), std::sqrt(sf * sf + att * att + 20.0 * 20.0), 1e-4);
  Mat3<double> r;
  const OutputRecord<double> rec = loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(rec.sigma_f_nT, loop.active_sigma_f_nT());
  EXPECT_EQ(rec.sigma_enu_nT, loop.active_sigma_enu_nT());
  // Without the figures (NaN) the loop keeps the held-out ones (the other tests).
}

// A survey team rarely knows its noise. With no configured noise (NaN) a candidate is judged by
// the noise its solve estimated from the data; a configured figure overrides, so a wrong one
// (0.3 nT told, 3 nT real) refuses the calibration rather than hiding the discrepancy.
TEST(SensorLoop, UnknownNoiseIsJudgedByTheNoiseTheSolveEstimated) {
  constexpr double kNoise = 3.0;  // MEMS-level magnetometer noise per axis
  LoopConfig<double> unknown;
  unknown.noise_nT = std::numeric_limits<double>::quiet_NaN();
  unknown.attitude_noise_deg = 0.01;
  FakeCalibrator cal;
  cal.result = truth_model();
  cal.mag_noise_nT = static_cast<float>(kNoise);
  SensorLoop<double, FakeCalibrator> loop(cal, unknown);
  Feed feed;
  feed.noise = std::normal_distribution<double>(0, kNoise);
  Mat3<double> r;
  EXPECT_TRUE(std::isnan(loop.process(feed.next(truth_model(), &r), &r).sigma_f_nT));
  run_to_end(loop, feed);
  ASSERT_EQ(loop.state(), CalState::kApplied) << cal_failure_name(loop.failure());
  EXPECT_GT(loop.last_validation_rms_nT(), 0.8 * kNoise);  // the noise, not below it
  EXPECT_LT(loop.last_validation_rms_nT(), 1.2 * kNoise);
  EXPECT_GE(loop.active_sigma_f_nT(), kNoise);  // never below the estimated noise

  // Told 0.3 nT: the held-out RMS of ~3 nT is out of 3 x 0.3 (and of the 1 nT floor).
  LoopConfig<double> told = unknown;
  told.noise_nT = 0.3;
  FakeCalibrator cal2 = cal;
  SensorLoop<double, FakeCalibrator> loop2(cal2, told);
  run_to_end(loop2, feed);
  EXPECT_EQ(loop2.state(), CalState::kFailed);
  EXPECT_EQ(loop2.failure(), CalFailure::kValidationFailed);

  // Neither configured nor estimated: only the absolute floor (1 nT) is left, which 3 nT noise
  // does not meet.
  FakeCalibrator cal3 = cal;
  cal3.mag_noise_nT = std::numeric_limits<float>::quiet_NaN();
  SensorLoop<double, FakeCalibrator> loop3(cal3, unknown);
  run_to_end(loop3, feed);
  EXPECT_EQ(loop3.state(), CalState::kFailed);
}

// sigma_ENU of the records: NaN until an aligned calibration is applied and for records without
// attitude; then the held-out E/N/U scatter, never below sqrt(sigma_F^2 + (F sigma_att)^2).
TEST(SensorLoop, SigmaEnuFromTheHeldOutVectorScatterAndTheAttitudeNoise) {
  FakeCalibrator cal;
  cal.result = truth_model();
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.attitude_noise_deg = 0.01;  // 9.4 nT at 54 uT: above the feed's exact attitudes' scatter
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  Feed feed;
  Mat3<double> r;
  EXPECT_TRUE(std::isnan(loop.process(feed.next(truth_model(), &r), &r).sigma_enu_nT));
  run_to_end(loop, feed);
  ASSERT_EQ(loop.state(), CalState::kApplied);
  const double f = feed.h_n.norm();
  const double att = 0.01 * kDeg * f;
  const double sf = loop.active_sigma_f_nT();
  EXPECT_GT(loop.last_validation_vector_rms_nT(), 0.0);
  EXPECT_LT(loop.last_validation_vector_rms_nT(), 1.0);
  EXPECT_NEAR(loop.active_sigma_enu_nT(), std::sqrt(sf * sf + att * att), 0.02 * att);
  const OutputRecord<double> rec = loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_EQ(rec.sigma_enu_nT, loop.active_sigma_enu_nT());
  MagSample<double> s = feed.next(truth_model(), &r);
  EXPECT_TRUE(std::isnan(loop.process(s, nullptr).sigma_enu_nT));  // no attitude: no E/N/U
  // A stored calibration brings its own figures; a scatter above the floor is kept.
  loop.set_active(truth_model(), 5, true, 0.5, 40.0);
  EXPECT_EQ(loop.process(feed.next(truth_model(), &r), &r).sigma_enu_nT, 40.0);
  loop.set_active(truth_model(), 6, false, 0.5, 40.0);  // not aligned: h_n is not E/N/U
  EXPECT_TRUE(std::isnan(loop.process(feed.next(truth_model(), &r), &r).sigma_enu_nT));
  // Without its figure (e.g. a `magvec calibrate` file): not known, never sigma_F alone.
  loop.set_active(truth_model(), 7, true, 0.5);
  EXPECT_TRUE(std::isnan(loop.process(feed.next(truth_model(), &r), &r).sigma_enu_nT));
}

// A model reference (a geomagnetic model's F at the INS position): biased by up to its 1-sigma,
// nearly noise-free. The held-out check judges the scatter of |h| - F against the noise and its
// mean against the model's 1-sigma; the applied calibration's sigma_f carries the model's
// 1-sigma and its records are flagged. Truth: |h_n| = 53 729 nT; the model says 90 nT more.
struct ModelFeed : Feed {
  double bias_nT{90};
  MagSample<double> next(const SensorModel<double>& truth, Mat3<double>* r_bn) {
    MagSample<double> s = Feed::next(truth, r_bn);
    s.f_ref_nT += bias_nT;
    return s;
  }
};

template <typename Loop>
void run_model_to_end(Loop& loop, ModelFeed& feed) {
  Mat3<double> r;
  loop.start_calibration();
  for (int i = 0; i < 2000; ++i) {
    (void)loop.process(feed.next(truth_model(), &r), &r);
    if (loop.state() == CalState::kApplied || loop.state() == CalState::kFailed) return;
  }
}

// The candidate a calibrator fits to the model's F: the truth scaled by F_model / F_true.
SensorModel<double> scaled_to(double factor) {
  SensorModel<double> m = truth_model();
  m.w *= factor;
  return m;
}

TEST(SensorLoop, ModelReferenceJudgesScatterByNoiseAndMeanByTheModelSigma) {
  const double f_true = Vec3<double>(-4053, 25022, -47374).norm();
  FakeCalibrator cal;
  cal.result = scaled_to((f_true + 90) / f_true);
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.reference_sigma_nT = 138;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  ModelFeed feed;
  Mat3<double> r;
  EXPECT_FALSE(loop.process(feed.next(truth_model(), &r), &r).flags & kOutModelReference);
  run_model_to_end(loop, feed);
  ASSERT_EQ(loop.state(), CalState::kApplied);
  EXPECT_LT(loop.last_validation_rms_nT(), 1.0);          // the scatter: noise
  EXPECT_NEAR(loop.last_validation_mean_nT(), 0.0, 0.2);  // fitted to the model's F
  EXPECT_TRUE(loop.active_model_reference());
  const OutputRecord<double> rec = loop.process(feed.next(truth_model(), &r), &r);
  EXPECT_TRUE(rec.flags & kOutModelReference);
  // Absolute: the model's 1-sigma dominates; |h| is the model's F, 90 nT above the truth.
  EXPECT_NEAR(rec.sigma_f_nT, std::hypot(0.3, 138.0), 0.01);
  EXPECT_NEAR(rec.intensity_nT - f_true, 90.0, 2.0);
}

TEST(SensorLoop, ModelReferenceAcceptsTheTrueScaleWithinTheModelSigma) {
  // A candidate at the true scale sits 90 nT below the model's F: a measured reference would
  // refuse it (RMS 90 nT against 0.3 nT of noise); a model reference accepts the offset as the
  // model's own error (within 3 x 138 nT) and the noise-level scatter.
  for (const double sigma : {std::numeric_limits<double>::quiet_NaN(), 138.0}) {
    FakeCalibrator cal;
    cal.result = truth_model();
    LoopConfig<double> cfg;
    cfg.noise_nT = 0.3;
    cfg.reference_sigma_nT = sigma;
    SensorLoop<double, FakeCalibrator> loop(cal, cfg);
    ModelFeed feed;
    run_model_to_end(loop, feed);
    if (std::isnan(sigma)) {
      EXPECT_EQ(loop.failure(), CalFailure::kValidationFailed);
      EXPECT_NEAR(loop.last_validation_rms_nT(), 90.0, 0.5);
    } else {
      ASSERT_EQ(loop.state(), CalState::kApplied);
      EXPECT_NEAR(loop.last_validation_mean_nT(), -90.0, 0.5);
      EXPECT_LT(loop.last_validation_rms_nT(), 1.0);
    }
  }
}

TEST(SensorLoop, ModelReferenceRefusesAMeanBeyondThreeModelSigmas) {
  // The model's F is 500 nT off the field the candidate fits (a wrong position or date, a strong
  // anomaly): the scatter is fine, the mean is not.
  FakeCalibrator cal;
  cal.result = truth_model();
  LoopConfig<double> cfg;
  cfg.noise_nT = 0.3;
  cfg.reference_sigma_nT = 138;
  SensorLoop<double, FakeCalibrator> loop(cal, cfg);
  loop.set_active(truth_model(), 3);
  ModelFeed feed;
  feed.bias_nT = 500;
  run_model_to_end(loop, feed);
  EXPECT_EQ(loop.failure(), CalFailure::kReferenceMismatch);
  EXPECT_STREQ(cal_failure_name(loop.failure()), "reference_mismatch");
  EXPECT_EQ(loop.cal_id(), 3u);  // the active one stays
  // An installed calibration says itself whether its scale came from a model.
  loop.set_active(truth_model(), 4, true, 138.0, 140.0, true);
  Mat3<double> r;
  EXPECT_TRUE(loop.process(feed.next(truth_model(), &r), &r).flags & kOutModelReference);
  loop.set_active(truth_model(), 5);
  EXPECT_FALSE(loop.process(feed.next(truth_model(), &r), &r).flags & kOutModelReference);
}

}  // namespace
}  // namespace magvec::core
