// Runs the online vector calibration filter (core::VectorCalibrationFilter, docs/equations.md
// E-VF-A .. E-VF-8) once over a CSV recording with attitude and fills a CalibrationFile. Per row:
// the reading, R_bn, the n-frame rotation rate from the neighbouring rows' attitudes
// (rate_n_from_attitudes, E-VF-5), the row interval, the scalar reference F (the F_nT column, else
// the given or the data's field for every row, as the batch methods use it) and the temperature
// (a `temperature_degC` column when the recording has one, else none).
// Noise: the filter weights and gates with the magnetometer and INS noise; unless given, both come
// from the data as the one-step fit's variance components (batch_runner.hpp, a bounded subset of
// the rows), since the filter cannot estimate them itself. Everything the filter estimates (W, o,
// Rm, h_n, the time offset, the temperature coefficients) is its own, with 1-sigmas from its
// covariance. The verdict is core::judge() (acceptance.hpp) over evidence from the filter and an
// evaluation pass; a filter that is not running at the end of the data is refused with its cause.
#pragma once

#include <array>
#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "calibration/evaluation.hpp"
#include "magvec/core/acceptance.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/vector_calibration_filter.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host {

struct VectorEkfRunOptions {
  bool float32 = false;                 // run VectorCalibrationFilter<float>
  std::optional<double> noise_nT;       // magnetometer noise per axis; none: from the data
  std::optional<double> ins_noise_deg;  // INS noise per angle; none: from the data
  std::optional<double> field_nT;  // F for rows without one; none: the F_nT column or median |m|
  std::optional<double> time_offset_s;  // fixes the time offset (not estimated)
  std::string trace_path;               // per-sample trace CSV ("" = none)
  std::uint64_t trace_max_rows = 2000;  // the trace keeps every k-th row to stay under this
  // Rows the noise estimate's one-step fit keeps (thinned evenly over the recording beyond it).
  std::size_t noise_rows = 20000;
  core::AcceptanceLimits<double> limits{};
};

// The trace's 19 state columns (interface units; Rm as Li angles in degrees).
inline constexpr int kVfTraceStates = 19;
// Column names of the states, in trace order ("W00", ..., "c_z_nT_per_degC").
const std::array<const char*, kVfTraceStates>& vf_trace_state_names() noexcept;

struct VectorEkfRun {
  bool initialised{false};          // the filter is running at the end of the data
  core::SensorModel<double> model;  // W, offset at the reference temperature, Rm
  core::Vec3<double> h_n_nT = core::Vec3<double>::Zero();
  core::Vec3<double> h_n_sigma_nT = core::Vec3<double>::Zero();
  double time_offset_s{0}, time_offset_sigma_s{0};
  core::Vec3<double> tc_nT_per_degC = core::Vec3<double>::Zero();
  core::Vec3<double> tc_sigma_nT_per_degC = core::Vec3<double>::Zero();
  double temperature_ref_degC{0};  // NaN: no temperature seen
  bool li_ok{false};
  core::LiParams<double> li;
  core::LiSigmas<double> li_sigma;
  bool heading_held{false};  // the rotation about body z never became observable (E-VF-7)
  double tilt_spread_deg{0};
  core::VfCounters counters;
  std::string last_reset{"none"};
  std::uint64_t last_reset_row{0};  // 1-based data row of the last full reset; 0: none
  std::string last_init_verdict{"no_data"};
  int startup_samples{0};
  std::uint64_t rows{0}, dropouts{0}, rows_without_attitude{0}, rows_with_temperature{0};
  std::uint64_t rows_without_reference{0};
  std::uint64_t accepted{0}, gated{0};
  bool field_from_data{false};  // no F: the median |m| stood for it
  double field_nT{0};
  // Noise in use and where it came from (the one-step fit's estimate with its 1-sigma, or given).
  double noise_nT{0}, ins_noise_deg{0};
  bool noise_estimated{false}, ins_noise_estimated{false};
  double noise_sigma_nT{0}, ins_noise_sigma_deg{0};
  std::uint64_t trace_rows{0}, trace_stride{1};
  core::AcceptanceEvidence<double> evidence;
  core::Verdict verdict_code{core::Verdict::kOk};
  std::string verdict, reason;
  std::vector<std::string> warnings;
  Evaluation eval;
  CalibrationFile cal;
};

// Throws io::CsvError on malformed input, std::invalid_argument on bad options or a recording the
// filter cannot use (no attitude columns, no t_s), std::system_error if the trace cannot be
// written.
VectorEkfRun run_vector_ekf(const std::string& path, const io::CsvReaderOptions& reader_options,
                            const VectorEkfRunOptions& opt);

const char* vf_status_name(core::VfStatus s) noexcept;

}  // namespace magvec::host
