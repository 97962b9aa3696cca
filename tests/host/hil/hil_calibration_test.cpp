// Host-in-the-loop acceptance test: 10 minutes of simulated survey
// (scenario_survey: fluxgate 200 Hz through the ADS131M04 SPI codec, INS 100 Hz through the SBG
// CAN codec, 0.3 nT and 0.015 deg noise) with a few % of injected faults, calibrated IN THE LOOP
// by the Li batch calibrator (BatchLiCalibrator, one-step fit), then:
//   - E/N/U components within 1.3x of the INS-noise floor and intensity within 1.3x of the
//     magnetometer-noise floor, both scored against the simulator's truth at each record's time.
//     The E/N/U floor comes from the TRUE attitude and field and the configured noise only
//     (enu_floor.hpp: INS angle noise through the interpolation between 100 Hz epochs, plus the
//     magnetometer noise), never from the loop's own attitude; the intensity floor is the true
//     model applied to the same noisy raw reading;
//   - every injected fault counted by the matching health counter;
//   - zero heap allocations per step after start-up (including the solve and validation).
#include <gtest/gtest.h>

#include <cmath>
#include <cstdio>
#include <memory>
#include <string>

#include "enu_floor.hpp"
#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/core/vector_calibrator.hpp"
#include "magvec/host/hil/hil_session.hpp"
#include "support/alloc_counter.hpp"

namespace {

using namespace magvec;
using drivers::sim::ScenarioConfig;
using drivers::sim::SimRigConfig;
using drivers::sim::Simulator;
using host::hil::HilConfig;
using host::hil::HilSession;
using LiCal = core::BatchLiCalibrator<double, 512>;
using Session = HilSession<LiCal>;

struct Rms {
  double sum_sq{0};
  std::uint64_t n{0};
  void add(double e) noexcept {
    sum_sq += e * e;
    ++n;
  }
  double value() const noexcept { return n > 0 ? std::sqrt(sum_sq / static_cast<double>(n)) : 0; }
};

// Scores every calibrated record after the manoeuvre against the simulator's truth at the
// record's own time (records leave the loop when their sample is processed, after the INS
// samples that bracket it arrived). No heap. The floor's interpolation fraction is that of the
// INS epochs around the attitude the pipeline paired (its time offset, and the part of the CAN
// latency it was not told about, move it off the sample's time).
template <typename SessionT>
class ScoringSink final : public hal::RecordSink {
 public:
  ScoringSink(const ScenarioConfig& sc, const SimRigConfig& rc, double t_from_s,
              double unknown_latency_s = 0)
      : sc_(sc), rc_(rc), truth_(sc.truth), t_from_s_(t_from_s), unknown_s_(unknown_latency_s) {}
  void attach(SessionT* s) noexcept { session_ = s; }

  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    ++records;
    last_cal_id = r.cal_id;
    if (r.t_us <= last_t_us_) ++out_of_order;
    last_t_us_ = r.t_us;
    const double t_s =
        (static_cast<double>(r.t_us) - static_cast<double>(rc_.time.epoch_us)) * 1e-6;
    if (r.cal_id == 0 || t_s < t_from_s_ ||
        (r.flags & (core::kOutDropout | core::kOutDeviceError)) != 0) {
      return hal::Status::kOk;
    }
    const drivers::sim::Simulator& sim = session_->rig().simulator();
    const core::Vec3<double> h_n_true = sim.true_field_at(t_s);
    const core::Vec3<double> raw(r.raw_nT[0], r.raw_nT[1], r.raw_nT[2]);
    core::Compensated<double> c;
    if (!truth_.compensate(raw, &c)) return hal::Status::kOk;
    const double f_true = h_n_true.norm();
    f_err.add(r.f_nT - f_true);
    f_floor.add(c.intensity - f_true);
    if ((r.flags & (core::kOutNoAttitude | core::kOutAttExtrapolated)) != 0) {
      ++without_interpolated_attitude;
      return hal::Status::kOk;
    }
    const double offset_s =
        1e-6 * static_cast<double>(session_->core().pipeline().time_offset_us());
    enu.add(core::Vec3<double>(r.h_n_nT[0], r.h_n_nT[1], r.h_n_nT[2]), sim.true_attitude_at(t_s),
            h_n_true, sc_.truth, sc_.mag_noise_nT, sc_.ins_noise_deg,
            test::epoch_fraction(t_s + sc_.ins_latency_s - offset_s - unknown_s_, rc_.ins.rate_hz));
    return hal::Status::kOk;
  }

  Rms f_err, f_floor;
  test::EnuFloorAccumulator enu;
  std::uint64_t records{0}, out_of_order{0}, without_interpolated_attitude{0};
  std::uint32_t last_cal_id{0};

 private:
  ScenarioConfig sc_;
  SimRigConfig rc_;
  core::Compensator<double> truth_;
  double t_from_s_;
  double unknown_s_;
  std::uint64_t last_t_us_{0};
  SessionT* session_{nullptr};
};

TEST(HilCalibration, TenMinuteSurveyCalibratesInTheLoopToTheNoiseFloors) {
  ScenarioConfig sc = drivers::sim::scenario_survey();  // 200 Hz, 0.3 nT, 0.015 deg
  sc.num_samples = static_cast<std::uint32_t>(600.0 * sc.rate_hz);
  sc.dropout_probability = 0.01;
  Simulator sim(sc, 2024);
  SimRigConfig rc;
  rc.link = drivers::sim::MagLink::kSpi;
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  rc.adc.faults.crc_error_probability = 0.02;
  rc.adc.faults.saturation_probability = 0.005;
  rc.ins.faults.corrupt_probability = 0.02;
  rc.ins.faults.gap_start_s = 15.0;  // while the calibrator collects: it must cope
  rc.ins.faults.gap_length_s = 1.0;
  rc.ins.faults.invalid_start_s = 200.0;  // on a survey line
  rc.ins.faults.invalid_length_s = 2.0;
  HilConfig hc;
  hc.loop.noise_nT = sc.mag_noise_nT;

  core::BatchLiCalibratorConfig<double> lc;
  lc.batch.mag_noise_nT = sc.mag_noise_nT;
  lc.batch.attitude_noise_deg = sc.ins_noise_deg;
  auto cal = std::make_unique<LiCal>(lc);
  ScoringSink<Session> sink(sc, rc, sc.survey.manoeuvre_s + 5.0);
  auto hil = std::make_unique<Session>(sim, rc, *cal, sink, hc);
  sink.attach(hil.get());
  ASSERT_EQ(hil->init(), hal::Status::kOk);

  // Start-up: the first steps (first INS frames, buffer fill); then no heap at all.
  ASSERT_EQ(hil->run(200), 200u);
  magvec::test::AllocationScope scope;
  const std::uint64_t steps = hil->run();
  const std::size_t allocations = scope.count();
  EXPECT_EQ(allocations, 0u);
  EXPECT_EQ(steps + 200u, 120000u);

  // Calibration: collected during the manoeuvre, solved, validated, applied once.
  const auto& loop = hil->loop();
  ASSERT_EQ(loop.state(), core::CalState::kApplied)
      << "failure " << static_cast<int>(loop.failure()) << " verdict "
      << core::verdict_name(static_cast<core::Verdict>(loop.solver_code()));
  EXPECT_EQ(loop.cal_id(), 1u);
  EXPECT_EQ(sink.last_cal_id, 1u);
  EXPECT_TRUE(cal->last_result().ok());
  EXPECT_EQ(loop.health().calibrations_applied, 1u);
  EXPECT_EQ(loop.health().calibrations_failed, 0u);
  EXPECT_LT(loop.last_validation_rms_nT(), 3 * sc.mag_noise_nT);

  // Accuracy against the floors of this run.
  EXPECT_EQ(sink.out_of_order, 0u);
  ASSERT_GT(sink.f_err.n, 90000u);
  ASSERT_GT(sink.enu.n, 90000u);
  const char* names[3] = {"E", "N", "U"};
  for (int k = 0; k < 3; ++k) {
    std::printf("%s: RMS error %.3f nT, floor %.3f nT, ratio %.3f\n", names[k], sink.enu.error(k),
                sink.enu.floor(k), sink.enu.error(k) / sink.enu.floor(k));
    EXPECT_LE(sink.enu.error(k), 1.3 * sink.enu.floor(k)) << names[k];
    EXPECT_GT(sink.enu.floor(k), 1.0) << names[k];  // INS noise is there
  }
  std::printf("F: RMS error %.4f nT, floor %.4f nT, ratio %.3f (n = %llu)\n", sink.f_err.value(),
              sink.f_floor.value(), sink.f_err.value() / sink.f_floor.value(),
              static_cast<unsigned long long>(sink.f_err.n));
  EXPECT_LE(sink.f_err.value(), 1.3 * sink.f_floor.value());
  EXPECT_NEAR(sink.f_floor.value(), sc.mag_noise_nT, 0.05);

  // Every injected fault counted.
  const auto& adc = hil->rig().adc().injected();
  const auto& ins = hil->rig().ins().injected();
  const auto& hcn = hil->counters();
  const auto& health = loop.health();
  EXPECT_GT(adc.crc_corrupted, 1000u);
  EXPECT_EQ(hil->mag_counters().crc_errors, adc.crc_corrupted);
  EXPECT_EQ(hcn.mag_read_errors, adc.crc_corrupted);
  EXPECT_LE(hcn.mag_missing, adc.crc_corrupted);
  EXPECT_GE(hcn.mag_missing + 1, adc.crc_corrupted);
  EXPECT_EQ(sink.records, 120000u - adc.crc_corrupted);
  EXPECT_GT(adc.not_fresh, 600u);
  EXPECT_LE(hcn.mag_not_fresh, adc.not_fresh);
  EXPECT_GE(hcn.mag_not_fresh + adc.crc_corrupted, adc.not_fresh);
  EXPECT_EQ(hcn.mag_not_fresh, health.dropouts);
  EXPECT_GT(adc.saturated_frames, 300u);
  EXPECT_EQ(hil->mag_counters().saturated, adc.saturated_frames);
  EXPECT_LE(health.device_errors, adc.saturated_frames);
  EXPECT_GE(health.device_errors + hcn.mag_not_fresh, adc.saturated_frames);
  EXPECT_GT(ins.corrupted_frames, 1000u);
  EXPECT_EQ(hil->attitude_counters().malformed, ins.corrupted_frames);
  EXPECT_EQ(hcn.att_samples, ins.epochs - ins.corrupted_epochs);
  EXPECT_EQ(ins.gap_epochs, 100u);
  EXPECT_EQ(ins.invalid_epochs, 200u);
  EXPECT_LE(hcn.att_invalid, ins.invalid_epochs);
  EXPECT_GE(hcn.att_invalid + ins.corrupted_epochs, ins.invalid_epochs);
  EXPECT_GE(hcn.att_gaps, 2u);
  // No-attitude records: the 1 s gap and the 2 s invalid window (200 Hz), minus lost samples.
  EXPECT_GE(health.no_attitude, 3u * 200u - 60u);
  EXPECT_LE(health.no_attitude, 3u * 200u + 20u);
  EXPECT_EQ(hcn.mag_time_jumps, 0u);
  EXPECT_EQ(hcn.sink_errors, 0u);
  // The calibrator saw attitude-less samples during the gap as rejections, never as data.
  EXPECT_GT(cal->counts().rejected, 0u);
  EXPECT_EQ(health.cal_rejected, cal->counts().rejected);
}

// 180 s of survey (200 Hz, 0.3 nT, 0.015 deg) whose INS CAN frames arrive 10 ms after their epoch
// while the loop is told 0.5 ms (the default): every attitude it pairs is 9.5 ms old. Every
// calibrated record after the manoeuvre is scored against the simulator's truth.
constexpr std::uint32_t kCanLatencyUs = 10'000;
struct LatencyRun {
  core::CalState state{core::CalState::kIdle};
  std::string failure;
  double pipeline_offset_s{0};
  std::uint64_t offset_steps{0};
  double unknown_s{0};
  test::EnuFloorAccumulator enu;
  Rms f_err, f_floor;
};
template <typename Cal>
LatencyRun run_unknown_latency(Cal& cal, std::uint64_t seed, const HilConfig& hc) {
  using S = HilSession<Cal>;
  ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.num_samples = static_cast<std::uint32_t>(180.0 * sc.rate_hz);
  Simulator sim(sc, seed);
  SimRigConfig rc;
  rc.link = drivers::sim::MagLink::kSpi;
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  rc.ins.can_latency_us = kCanLatencyUs;
  LatencyRun out;
  out.unknown_s = 1e-6 * (kCanLatencyUs - hc.ins_latency_comp_us);
  ScoringSink<S> sink(sc, rc, sc.survey.manoeuvre_s + 5.0, out.unknown_s);
  auto hil = std::make_unique<S>(sim, rc, cal, sink, hc);
  sink.attach(hil.get());
  if (hil->init() != hal::Status::kOk) return out;
  hil->run();
  out.state = hil->loop().state();
  out.failure = std::string(core::cal_failure_name(hil->loop().failure())) + " code " +
                std::to_string(hil->loop().solver_code());
  out.pipeline_offset_s = 1e-6 * static_cast<double>(hil->core().pipeline().time_offset_us());
  out.offset_steps = hil->core().pipeline().counters().time_offset_steps;
  out.enu = sink.enu;
  out.f_err = sink.f_err;
  out.f_floor = sink.f_floor;
  return out;
}

void expect_enu_within(const LatencyRun& r, double factor) {
  ASSERT_GT(r.enu.n, 20000u);
  const char* names[3] = {"E", "N", "U"};
  for (int k = 0; k < 3; ++k) {
    std::printf("%s: RMS error %.3f nT, floor %.3f nT, ratio %.3f\n", names[k], r.enu.error(k),
                r.enu.floor(k), r.enu.error(k) / r.enu.floor(k));
    EXPECT_LE(r.enu.error(k), factor * r.enu.floor(k)) << names[k];
  }
}

// The vector-ekf calibrator, told neither noise nor latency, finds the offset (its start-up fit
// regresses the lag out before estimating the noise, and its filter takes each attitude at
// t - tau from the INS samples, E-VF-5); the pipeline pairs the held-out samples and the records
// at that offset. E/N/U within 1.05x of the floor (measured 1.013-1.020; without the start-up
// regression of the lag 1.035-1.053, the offset's 1-sigma 0.30 ms instead of 0.023). Before, the
// filter's offset came out at -9.2 +- 0.3 ms and the held-out vector check refused the candidate
// (vector_validation_failed, `magvec run` seed 3); with the noise given, it was applied with the
// records still paired 9.5 ms off.
TEST(HilCalibration, VectorEkfFindsAnUnknownInsLatencyAndThePipelineAdoptsIt) {
  using VecCal = core::VectorCalibrator<double>;
  HilConfig hc;  // no noise figures, the default 0.5 ms latency compensation
  auto cal = std::make_unique<VecCal>();
  const LatencyRun r = run_unknown_latency(*cal, 2031, hc);
  ASSERT_EQ(r.state, core::CalState::kApplied) << r.failure;
  const double sigma_s = cal->filter().sigmas().dt_s;
  std::printf("pipeline time offset %.3f ms (filter %.4f +- %.4f ms), truth %.3f ms\n",
              r.pipeline_offset_s * 1e3, cal->filter().time_offset_s() * 1e3, sigma_s * 1e3,
              -r.unknown_s * 1e3);
  // The attitude is older than the reading: magnetometer minus INS is negative.
  EXPECT_NEAR(cal->filter().time_offset_s(), -r.unknown_s, std::max(4 * sigma_s, 1e-4));
  EXPECT_EQ(r.offset_steps, 1u);
  expect_enu_within(r, 1.05);
  std::printf("F: RMS error %.4f nT, floor %.4f nT\n", r.f_err.value(), r.f_floor.value());
  EXPECT_LE(r.f_err.value(), 1.1 * r.f_floor.value());

  // An offset configured as known (magvecd ins.time_offset_s, magvec run --time-offset-s) stays.
  HilConfig known = hc;
  known.time_offset_us = -9'500;
  known.adopt_calibration_time_offset = false;
  auto cal2 = std::make_unique<VecCal>();
  const LatencyRun k = run_unknown_latency(*cal2, 2031, known);
  EXPECT_EQ(k.state, core::CalState::kApplied) << k.failure;
  EXPECT_DOUBLE_EQ(k.pipeline_offset_s, -9.5e-3);
  EXPECT_EQ(k.offset_steps, 0u);
  // Fed at the right pairing, the filter finds nothing left.
  EXPECT_NEAR(cal2->filter().time_offset_s(), 0.0,
              std::max(4 * cal2->filter().sigmas().dt_s, 1e-4));
}

// The same with the in-loop Li calibrator (the default of magvecd and magvec run), told no noise:
// its solve regresses the one-step fit's residuals on the kept samples' rates (fit_time_offset,
// E-TO-4), refits, and the pipeline pairs the held-out samples and the records at the offset it
// found. Measured: -9.451 ms, E/N/U 1.005-1.012x the floor. Before (and with
// estimate_time_offset off) the latency went into the calibration: h_n 107 nT off in East (its
// 1-sigma 10 nT), the records at 4.3/2.2/2.1x their E/N/U floor.
TEST(HilCalibration, LiFindsAnUnknownInsLatencyAndThePipelineAdoptsIt) {
  core::BatchLiCalibratorConfig<double> lc;
  lc.batch.estimate_noise = true;
  auto cal = std::make_unique<core::BatchLiCalibrator<double, 512>>(lc);
  const LatencyRun r = run_unknown_latency(*cal, 2032, HilConfig{});
  ASSERT_EQ(r.state, core::CalState::kApplied) << r.failure;
  std::printf("pipeline time offset %.3f ms (the solve's %.3f ms), truth %.3f ms\n",
              r.pipeline_offset_s * 1e3, cal->time_offset_s() * 1e3, -r.unknown_s * 1e3);
  EXPECT_NEAR(r.pipeline_offset_s, -r.unknown_s, 2e-4);
  EXPECT_EQ(r.offset_steps, 1u);
  const ScenarioConfig sc = drivers::sim::scenario_survey();
  const core::Vec3<double> dh = cal->last_result().h_n_nT - sc.h_n_nT;
  const core::Vec3<double> sg = cal->last_result().h_n_sigma_nT;
  std::printf("h_n error %.2f %.2f %.2f nT (1-sigma %.2f %.2f %.2f)\n", dh(0), dh(1), dh(2), sg(0),
              sg(1), sg(2));
  expect_enu_within(r, 1.05);
}

}  // namespace
