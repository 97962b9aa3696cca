// Runs the online scalar EKF of Ge et al. 2017 (core::ScalarEkf, ERRATA 002) over a CSV recording,
// optionally several passes through the same filter and with a per-sample trace, and fills a
// CalibrationFile. The EKF observes |H| only, so it determines G = W^T W and b but W only up to a
// rotation (ERRATA 002-2): the cal.json holds W = C^-1, o = b, Rm = identity; its li block is the
// Li-structured form of that W (canonicalize_li), whose Rm_deg is that unobservable rotation, not
// a misalignment to the INS.
#pragma once

#include <cstdint>
#include <optional>
#include <string>

#include "calibration/calibration_file.hpp"
#include "calibration/evaluation.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/scalar_ekf.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host {

struct EkfRunOptions {
  bool paper_settings = false;       // EkfConfig::paper() (the printed, failing settings)
  bool float32 = false;              // run ScalarEkf<float>
  int passes = 1;                    // re-run the data this many times through the same filter
  double noise_nT = 10.0;            // magnetometer noise per axis (1-sigma), unless paper_settings
  std::optional<double> field_nT;    // reference F for rows without one
  std::string trace_path;            // per-sample trace CSV ("" = none)
  double min_coverage = 0.2;         // fraction of 32 direction cells (as the batch methods)
  double max_relative_sigma = 0.02;  // refuse when a b or C^-1 1-sigma exceeds this (b / F)
};

// Outcome of the samples of one pass (the last one is reported).
struct EkfPassCounts {
  std::uint64_t accepted{0};  // measurement updates, including the one completing the initial fit
  std::uint64_t gated{0};
  std::uint64_t rejected_nonfinite{0};  // NaN/inf reading or unusable reference
};

struct EkfRun {
  core::SensorModel<double> model;  // W = C^-1, o = b, Rm = I
  core::Vec<double, 12> state = core::Vec<double, 12>::Zero();
  core::Vec<double, 12> sigma = core::Vec<double, 12>::Zero();
  core::Mat<double, 12, 12> covariance = core::Mat<double, 12, 12>::Zero();
  bool li_ok{false};
  core::LiParams<double> li;        // canonicalize_li of the model
  core::LiSigmas<double> li_sigma;  // ks, o_rad, kof propagated from the covariance
  core::EkfCounters counters;
  const char* last_reset{"none"};
  bool initialised{false};
  double field_scale_nT{0};
  EkfPassCounts last_pass;
  std::uint64_t rows{0};  // rows per pass
  std::uint64_t dropouts{0};
  std::uint64_t trace_rows{0};
  double condition{0};  // of the normalised covariance (max / min eigenvalue)
  std::string verdict, reason;
  Evaluation eval;
  CalibrationFile cal;
};

const char* ekf_status_name(core::EkfStatus s) noexcept;
const char* ekf_reset_name(core::EkfResetReason r) noexcept;

// Throws io::CsvError on malformed input, std::invalid_argument on bad options, std::system_error
// if the trace cannot be written.
EkfRun run_ekf(const std::string& path, const io::CsvReaderOptions& reader_options,
               const EkfRunOptions& opt);

}  // namespace magvec::host
