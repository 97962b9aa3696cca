// Runs the batch calibration of Li et al. 2023 (core::BatchCalibrator) over a CSV recording and
// fills a CalibrationFile (cal.json): shared by `magvec calibrate`, the daemon and reports.
//
// What the recording can tell is taken from it (docs/equations.md "Noise from the data" and
// "Time offset"):
// - the noise of the magnetometer and of the attitude (variance components of the fit), unless
//   given; a given value that disagrees with the data by more than a factor of 2 is warned about;
// - the magnetometer-INS time offset: the attitude of each sample is interpolated (slerp between
//   neighbouring rows) at t - tau, and tau minimises the fit's cost (a scan at a fixed calibration,
//   then the profile of the refitted cost near its minimum, whose curvature gives the 1-sigma);
// - the total field when the file has no F_nT column and none is given: the median |m| (the
//   absolute scale is then relative to it, which the summary says).
// Input is streamed: memory grows with the rows kept; beyond max_rows_kept the kept set is thinned
// to every 2nd, 4th, ... row (stays spread over the whole recording), and the summary says so.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <optional>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "calibration/evaluation.hpp"
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host {

struct BatchRunOptions {
  core::BatchMethod method = core::BatchMethod::kOneStep;
  // config.field_nT: F for rows without one (NaN: the median |m|); config.mag_noise_nT /
  // attitude_noise_deg: used as given when mag_noise_given / ins_noise_given, else estimated.
  core::BatchConfig<double> config{};
  bool mag_noise_given = false;
  bool ins_noise_given = false;
  // Time offset: estimated when the method uses attitude and the recording rotates, unless fixed.
  std::optional<double> fixed_time_offset_s;
  double max_time_offset_s = 0.1;  // search range +-
  std::size_t max_rows_kept = 200000;
  std::string method_name = "li-ml";  // as written to provenance.method
};

struct TimeOffsetEstimate {
  bool estimated = false;  // false: fixed, not observable, or not applicable
  double offset_s = 0;     // magnetometer stamp minus INS time (positive: magnetometer lags)
  double sigma_s = std::numeric_limits<double>::quiet_NaN();
  std::size_t samples = 0;  // samples whose attitude could be interpolated over the search range
  std::string note;         // why not estimated, or how
};

struct BatchRun {
  core::BatchResult<double> result;
  std::uint64_t rows{0};                   // data rows read
  std::uint64_t rows_without_attitude{0};  // rows with a reading but no attitude
  std::uint64_t rows_kept{0};              // rows offered to the fit
  std::uint64_t keep_stride{1};            // every keep_stride-th row kept
  bool needs_attitude{true};
  bool field_from_data{false};  // no F: the median |m| stands for it (relative scale)
  double field_nT{std::numeric_limits<double>::quiet_NaN()};
  TimeOffsetEstimate time_offset;
  core::BatchNoise<double> data_noise;  // the data's own estimate (also when a value was given)
  std::vector<std::string> warnings;
  std::string reason;   // human explanation of the verdict
  Evaluation eval;      // over the samples the fit used
  CalibrationFile cal;  // provenance.magvec_version / created_utc left to the caller
};

// Name of a method as accepted by the CLI: li-ml, li, li-joint, ellipsoid.
const char* batch_method_name(core::BatchMethod m) noexcept;

// Human explanation of a batch verdict: its actual cause with the figures, and what to do.
std::string batch_verdict_reason(const core::BatchResult<double>& r,
                                 const core::BatchConfig<double>& cfg, bool noise_given);

// Reads every row of `reader`, solves with opt.method and evaluates the result. Throws
// io::CsvError for malformed input.
BatchRun run_batch(io::CsvReader& reader, const BatchRunOptions& opt);

// Parameter names the one-step fit's `undetermined` bits refer to, comma-separated.
std::string parameter_names(std::uint32_t bits);

}  // namespace magvec::host
