// The host's calibrators in the sample pipeline, chosen by name: the one place that maps a
// calibrator mode and the noise figures to a calibrator type and its configuration, for
// `magvec run`, `magvec demo` and magvecd (the MCU image constructs its EkfCalibrator statically).
//   li    core::BatchLiCalibrator: motion-decimated store, Li et al. one-step fit
//         (docs/equations.md E-Li);
//   ekf   core::EkfCalibrator: Ge et al. scalar EKF + misalignment fit (docs/equations.md E-Ge);
//   vector-ekf  VectorLoopCalibrator (core::VectorCalibrator, compiled once): the online vector
//         calibration filter (W, o, Rm, field, time offset, temperature coefficients from every
//         sample; docs/equations.md E-VF);
//   none  NullCalibrator: outputs with the active calibration, never calibrates.
#pragma once

#include <cmath>
#include <cstddef>
#include <limits>
#include <memory>
#include <stdexcept>
#include <string>
#include <type_traits>

#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/vector_calibrator.hpp"
#include "magvec/host/hil/loop_core.hpp"
#include "magvec/host/hil/vector_loop_calibrator.hpp"

namespace magvec::host::hil {

using LiCalibrator = core::BatchLiCalibrator<double, 512>;
using EkfLoopCalibrator = core::EkfCalibrator<double, 256>;

// Noise figures: NaN (the default) means not known, so the calibrator estimates them from its
// data (a survey team rarely knows them); a given figure overrides. li and vector-ekf estimate both
// unless both are given.
struct CalibratorSpec {
  std::string mode{"li"};                                     // li | ekf | vector-ekf | none
  double noise_nT{std::numeric_limits<double>::quiet_NaN()};  // magnetometer noise 1-sigma
  // INS attitude noise 1-sigma (li, vector-ekf)
  double attitude_noise_deg{std::numeric_limits<double>::quiet_NaN()};
  std::size_t li_min_samples{0};  // li: samples before a solve (0: the calibrator's default)
  bool ekf_align{true};           // ekf: fit the misalignment after the filter
};

inline bool is_calibrator_mode(const std::string& mode) {
  return mode == "li" || mode == "ekf" || mode == "vector-ekf" || mode == "none";
}

// The modes, for help texts and error messages.
inline constexpr const char* kCalibratorModes = "li, ekf, vector-ekf or none";

// True for calibrators that calibrate (HilConfig::start_calibration).
template <typename Calibrator>
inline constexpr bool kCalibrates = !std::is_same_v<Calibrator, NullCalibrator>;

inline core::BatchLiCalibratorConfig<double> li_config(const CalibratorSpec& spec) {
  core::BatchLiCalibratorConfig<double> lc;
  lc.batch.estimate_noise =
      !(std::isfinite(spec.noise_nT) && std::isfinite(spec.attitude_noise_deg));
  // Given figures (or the defaults) are the estimator's starting values.
  if (std::isfinite(spec.noise_nT)) lc.batch.mag_noise_nT = spec.noise_nT;
  if (std::isfinite(spec.attitude_noise_deg)) lc.batch.attitude_noise_deg = spec.attitude_noise_deg;
  if (spec.li_min_samples > 0) lc.min_samples = spec.li_min_samples;
  return lc;
}

inline core::EkfCalibratorConfig<double> ekf_config(const CalibratorSpec& spec) {
  core::EkfCalibratorConfig<double> ec;
  ec.ekf.estimate_noise = !std::isfinite(spec.noise_nT);
  if (std::isfinite(spec.noise_nT)) ec.ekf.noise_sigma_nT = spec.noise_nT;
  ec.align = spec.ekf_align;
  return ec;
}

inline core::VectorCalibratorConfig<double> vector_config(const CalibratorSpec& spec) {
  core::VectorCalibratorConfig<double> vc;
  vc.estimate_noise = !(std::isfinite(spec.noise_nT) && std::isfinite(spec.attitude_noise_deg));
  // Given figures (or the defaults) are the noise fit's starting values.
  if (std::isfinite(spec.noise_nT)) vc.filter.mag_noise_nT = spec.noise_nT;
  if (std::isfinite(spec.attitude_noise_deg))
    vc.filter.attitude_noise_rad = core::deg_to_rad(spec.attitude_noise_deg);
  return vc;
}

// Constructs the calibrator of spec.mode and returns fn(std::unique_ptr<Calibrator>) (fn is a
// generic callable; every branch must return the same type). Unknown mode: std::invalid_argument.
template <typename Fn>
auto with_calibrator(const CalibratorSpec& spec, Fn&& fn) {
  if (spec.mode == "li") return fn(std::make_unique<LiCalibrator>(li_config(spec)));
  if (spec.mode == "ekf") return fn(std::make_unique<EkfLoopCalibrator>(ekf_config(spec)));
  if (spec.mode == "vector-ekf")
    return fn(std::make_unique<VectorLoopCalibrator>(vector_config(spec)));
  if (spec.mode == "none") return fn(std::make_unique<NullCalibrator>());
  throw std::invalid_argument("unknown calibrator '" + spec.mode + "' (" + kCalibratorModes + ")");
}

}  // namespace magvec::host::hil
