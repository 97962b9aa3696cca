// Runs the batch calibration of Li et al. 2023 (core::BatchCalibrator, ERRATA 000) over a CSV
// recording and fills a CalibrationFile (cal.json): shared by `magvec calibrate`, the daemon and
// reports. Host only: the sample store has a large fixed capacity (kHostBatchCapacity rows) and is
// allocated once on the heap; more usable rows than that are an error (CapacityError), never a
// silent truncation.
#pragma once

#include <cmath>
#include <cstddef>
#include <cstdint>
#include <memory>
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

// Human explanation of a batch verdict with the figures that led to it.
std::string batch_verdict_reason(const core::BatchResult<double>& r,
                                 const core::BatchConfig<double>& cfg);

// Reads every row of `reader` into a BatchCalibrator, solves with opt.method and evaluates the
// result. Throws io::CsvError for malformed input and CapacityError when the file has more usable
// rows than kHostBatchCapacity.
BatchRun run_batch(io::CsvReader& reader, const BatchRunOptions& opt);

// The same with another store capacity (tests use a small one to exercise CapacityError).
template <std::size_t Capacity>
BatchRun run_batch_with_capacity(io::CsvReader& reader, const BatchRunOptions& opt);

namespace detail {
// Fills run->eval and run->cal from run->result (after the solve) and the samples in use.
void fill_batch_file(const io::CsvReader& reader, const BatchRunOptions& opt, BatchRun* run);
}  // namespace detail

template <std::size_t Capacity>
BatchRun run_batch_with_capacity(io::CsvReader& reader, const BatchRunOptions& opt) {
  BatchRun run;
  run.needs_attitude = opt.method != core::BatchMethod::kEllipsoidOnly;
  // A BatchCalibrator is a large fixed-size object (Capacity samples): one heap block.
  auto cal = std::make_unique<core::BatchCalibrator<double, Capacity>>(opt.config);
  io::CsvRecord rec;
  while (reader.next(&rec)) {
    ++run.rows;
    const double f = rec.f_nT ? *rec.f_nT : std::nan("");
    if (run.needs_attitude && rec.r_bn) {
      cal->add_sample(rec.m_nT, f, *rec.r_bn);
    } else {
      if (run.needs_attitude && !rec.dropout) ++run.rows_without_attitude;
      cal->add_sample(rec.m_nT, f);
    }
  }
  if (cal->counts().dropped_full > 0) {
    throw CapacityError(
        reader.path() + ": " + std::to_string(cal->counts().added + cal->counts().dropped_full) +
        " usable rows, more than the batch capacity of " + std::to_string(Capacity) + " rows (" +
        std::to_string(cal->counts().dropped_full) +
        " would be dropped): decimate or split the recording");
  }
  run.result = cal->solve(opt.method);
  run.reason = batch_verdict_reason(run.result, opt.config);
  // Evaluate over the samples the fit used (outliers and, for attitude methods, rows without
  // attitude excluded).
  Evaluator ev(run.result.model, run.needs_attitude);
  const auto& store = cal->store();
  for (std::size_t i = 0; i < store.size(); ++i) {
    const auto& s = store[i];
    if (s.outlier() || (run.needs_attitude && !s.has_attitude())) continue;
    const core::Mat3<double> r_bn = s.r_bn();
    ev.add(s.raw(), s.f, s.has_attitude() ? &r_bn : nullptr);
  }
  run.eval = ev.result();
  detail::fill_batch_file(reader, opt, &run);
  return run;
}

}  // namespace magvec::host
