// Runs the batch calibration of Li et al. 2023 (core::BatchCalibrator, ERRATA 000) over a CSV
// recording and fills a CalibrationFile (cal.json): shared by `magvec calibrate`, the daemon and
// reports. Host only: the sample store has a large fixed capacity (kHostBatchCapacity rows) and is
// allocated once on the heap; more usable rows than that are an error (CapacityError), never a
// silent truncation.
#pragma once

#include <cstddef>
#include <cstdint>
#include <stdexcept>
#include <string>

#include "calibration/calibration_file.hpp"
#include "calibration/evaluation.hpp"
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host {

// Rows a batch calibration holds in memory (80 bytes each: 80 MB).
inline constexpr std::size_t kHostBatchCapacity = 1000000;

class CapacityError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct BatchRunOptions {
  core::BatchMethod method = core::BatchMethod::kOneStep;
  core::BatchConfig<double> config{};  // config.field_nT: F for rows without one
  std::string method_name = "li-ml";   // as written to provenance.method
};

struct BatchRun {
  core::BatchResult<double> result;
  std::uint64_t rows{0};                   // data rows read
  std::uint64_t rows_without_attitude{0};  // rows with a reading but no attitude
  bool needs_attitude{true};
  std::string reason;   // human explanation of the verdict
  Evaluation eval;      // over the samples the fit used
  CalibrationFile cal;  // provenance.magvec_version / created_utc left to the caller
};

// Name of a method as accepted by the CLI: li-ml, li, li-joint, ellipsoid.
const char* batch_method_name(core::BatchMethod m) noexcept;

// Reads every row of `reader` into a BatchCalibrator, solves with opt.method and evaluates the
// result. Throws io::CsvError for malformed input and CapacityError when the file has more usable
// rows than kHostBatchCapacity.
BatchRun run_batch(io::CsvReader& reader, const BatchRunOptions& opt);

// Human explanation of a batch verdict with the figures that led to it.
std::string batch_verdict_reason(const core::BatchResult<double>& r,
                                 const core::BatchConfig<double>& cfg);

}  // namespace magvec::host
