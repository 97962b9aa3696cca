// Runs the turntable sine-fitting calibration (Jia et al. 2019 as corrected in docs/equations.md
// E-Sine, core::SineSweep and core::solve_sine) over an XY-sweep and an XZ-sweep recording
// (theta_deg column) and fills a CalibrationFile. 1-sigma of every parameter by linear propagation
// of the per-axis fit residual through solve_sine (numerical derivatives with respect to each
// reading).
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "calibration/calibration_file.hpp"
#include "calibration/evaluation.hpp"
#include "magvec/core/sine_fit.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host {

struct SineRunOptions {
  core::SineFixture fixture = core::SineFixture::kPlaneNormal;
  std::optional<double> field_nT;  // |B|; default: the mean F_nT of both sweeps
  double noise_nT = 5.0;           // stated noise per axis (residual check)
};

struct SineParamSigmas {
  bool available{false};
  core::Vec3<double> k = core::Vec3<double>::Zero();
  double alpha_rad{0}, beta_rad{0}, gamma_rad{0};
  core::Vec3<double> b0 = core::Vec3<double>::Zero();
  double inclination_rad{0};
};

struct SineRun {
  core::SineSolution<double> solution;
  SineParamSigmas sigma;
  std::uint64_t rows_xy{0}, rows_xz{0};
  std::uint64_t skipped_xy{0}, skipped_xz{0};  // nan reading or theta
  double field_nT{0};
  std::string verdict, reason;
  Evaluation eval;  // over both sweeps (intensity, coverage; no E/N/U)
  CalibrationFile cal;
};

const char* sine_status_name(core::SineStatus s) noexcept;

// Throws io::CsvError on malformed input and std::invalid_argument when a sweep has no theta_deg
// column.
SineRun run_sine(io::CsvReader& xy, io::CsvReader& xz, const SineRunOptions& opt);

}  // namespace magvec::host
