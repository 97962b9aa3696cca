// The firmware image's run, as configuration: its scenario (the survey manoeuvre and one survey
// line at 50 Hz from a fixed seed), the rig's fluxgate electronics, the calibrators and the
// pipeline. firmware/app/src/app_main.cpp runs it on the MCU and in its host twins; `magvec run
// --profile mcu` (host/cli) runs the same configuration through HilSession, and with the same
// numerics (docs/architecture.md#numerics) the double-precision records are bit-identical to the
// M7 image's and its twin's (tests/mcu). One definition, so the runs cannot drift apart.
// Header-only; it may include the core, the pipeline and the simulated devices' configuration.
#pragma once

#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/sample_pipeline.hpp"
#include "magvec/core/vector_calibrator.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/pipeline/device_pipeline.hpp"

namespace magvec::app {

inline constexpr std::uint64_t kSeed = 20170817;
inline constexpr double kRateHz = 50.0;
inline constexpr std::uint32_t kRecordEvery = 100;  // survey samples between two record lines
inline constexpr std::uint32_t kInsLatencyCompUs = 500;
inline constexpr std::uint32_t kFusionHorizonUs = 50'000;
// The solve's result is installed this many records after the one that raised the ticket
// (pipeline::SolveSchedule; the image solves in idle time meanwhile).
inline constexpr std::uint32_t kSolveInstallRecords = 8;

// Alignment store of the EKF calibrator (misalignment fit): 128 decimated samples (2 deg apart)
// keep core + loop within the 16 KiB RAM budget in float (256 would need 13 KiB for the store).
inline constexpr std::size_t kAlignCapacity = 128;
// The vector filter's replay store (E-VF-1): 128 samples (6.5 KiB in float) instead of the
// host's 512; its start-up set as on the host.
inline constexpr int kVectorReplay = 128;
// The vector calibrator's hold ring: 2 x (20 ms rate half span + an offset up to 140 ms) at 50 Hz.
inline constexpr int kVectorHold = 16;

template <typename Scalar>
using EkfImageCalibrator = core::EkfCalibrator<Scalar, kAlignCapacity>;
template <typename Scalar>
using VectorImageCalibrator = core::VectorCalibrator<Scalar, 64, kVectorReplay, kVectorHold>;

inline drivers::sim::ScenarioConfig make_scenario() noexcept {
  drivers::sim::ScenarioConfig c = drivers::sim::scenario_survey();
  c.name = "survey50";
  c.rate_hz = kRateHz;
  // The calibration manoeuvre and one survey line.
  c.num_samples = static_cast<std::uint32_t>((c.survey.manoeuvre_s + c.survey.line_s) * kRateHz);
  return c;
}

// Fluxgate electronics 100 uT/V: +/-120 uT at ADC gain 1 (LSB 0.014 nT, well under the noise).
inline drivers::sim::SimRigConfig make_rig_config() noexcept {
  drivers::sim::SimRigConfig r;
  r.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  return r;
}

// The EKF image (calibrator mode `ekf`): the filter is given the scenario's noise figure.
template <typename Scalar>
core::EkfCalibratorConfig<Scalar> ekf_calibrator_config(
    const drivers::sim::ScenarioConfig& s) noexcept {
  core::EkfCalibratorConfig<Scalar> c;
  c.ekf.noise_sigma_nT = static_cast<Scalar>(s.mag_noise_nT);
  // The 60 s manoeuvre at 50 Hz is 3000 samples: initial fit (~100), filter updates, the solve,
  // then 200 held-out validation samples must all fit in it.
  c.min_updates = 1500;
  return c;
}

// The vector image (calibrator mode `vector-ekf`). Defaults, as a user gets them: the noise is
// estimated from the data, the scenario's per-sample scalar reference ties the field.
template <typename Scalar>
core::VectorCalibratorConfig<Scalar> vector_calibrator_config(
    const drivers::sim::ScenarioConfig& s) noexcept {
  core::VectorCalibratorConfig<Scalar> c;
  c.filter.sample_interval_s = static_cast<Scalar>(1.0 / s.rate_hz);
  // Information folds of 16 samples (E-VF-B): the per-sample Bierman updates (three of the
  // 19-state filter's, ~2 300 instructions each on the M4F, plus their U^T products) become sums,
  // and every 16 samples the block's mean and trend enter as seven pseudo-measurements. Folds of
  // 32 would halve that share, but the filter then tracked a 300 nT offset drift too late and its
  // float32 moved more than 0.1 sigma from double (vector_calibration_filter_test).
  c.filter.fold_samples = 16;
  // The output envelope's readiness check (~150 000 instructions before its closed form, ~46 000
  // since, E-VF-10) every 256 samples, 5.1 s at
  // 50 Hz, instead of every 64: 1 800 instructions per sample less. Readiness waits on the noise
  // figures' 5 % rule here (noise samples every 2nd, E-VF-B), which the calibrator checks at every
  // sample against the envelope's last figure.
  c.refresh_every = 256;
  return c;
}

// vector: the vector image's pipeline (its loop is told no noise figures).
template <typename Scalar>
core::PipelineConfig<Scalar> pipeline_config(const drivers::sim::ScenarioConfig& s,
                                             bool vector) noexcept {
  core::PipelineConfig<Scalar> c;
  if (vector) {
    // Not told either: the loop judges the candidate by the noise its calibrator estimated.
    c.loop.noise_nT = std::numeric_limits<Scalar>::quiet_NaN();
    c.loop.attitude_noise_deg = std::numeric_limits<Scalar>::quiet_NaN();
  } else {
    c.loop.noise_nT = static_cast<Scalar>(s.mag_noise_nT > 0 ? s.mag_noise_nT : 1.0);
    c.loop.attitude_noise_deg = static_cast<Scalar>(s.ins_noise_deg > 0 ? s.ins_noise_deg : 0.01);
  }
  c.ins_latency_us = kInsLatencyCompUs;
  c.horizon_us = kFusionHorizonUs;
  c.mag_period_us = pipeline::period_us_from_hz(s.rate_hz);
  c.ins_period_us = pipeline::period_us_from_hz(make_rig_config().ins.rate_hz);
  // The solve runs off the per-sample path (pipeline::SolveSchedule).
  c.loop.external_solve = true;
  // The spike screen runs with the pipeline's defaults, as in magvecd and `magvec run`. It costs
  // ~150 instructions per sample, and its wait for each sample's successor moves the attitude
  // lookup off its exact-time fast path: 5 334 per calibrating sample against the budget of 5 000
  // when first measured, 4 836 since the lookup searches from the newest end, the interpolation
  // fraction avoids soft double and the EKF's finiteness checks and W copies got cheaper.
  return c;
}

}  // namespace magvec::app
