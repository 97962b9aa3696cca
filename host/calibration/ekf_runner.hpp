// Runs the online scalar EKF of Ge et al. 2017 (core::ScalarEkf, docs/equations.md E-Ge) over a CSV
// recording, optionally several passes through the same filter and with a per-sample trace, and
// fills a CalibrationFile. The EKF observes |H| only, so it determines G = W^T W and b but W only
// up to a rotation (docs/equations.md E-Ge-2): the cal.json holds W = C^-1, o = b, Rm = identity;
// its li block is the Li-structured form of that W (canonicalize_li), whose Rm_deg is that
// unobservable rotation, not a misalignment to the INS. Without a given noise the filter estimates
// the magnetometer noise from the data (start-up fit residuals, then innovations) and uses it for
// weighting, debias and gating; a given noise that disagrees with the data's estimate by more than
// 2x gets a warning. The verdict is core::judge() (acceptance.hpp) over evidence gathered from the
// filter and an evaluation pass.
#pragma once

#include <cstdint>
#include <optional>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "calibration/evaluation.hpp"
#include "magvec/core/acceptance.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/scalar_ekf.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host {

struct EkfRunOptions {
  bool paper_settings = false;  // EkfConfig::paper() (the printed, failing settings)
  bool float32 = false;         // run ScalarEkf<float>
  int passes = 1;               // re-run the data this many times through the same filter
  // Magnetometer noise per axis (1-sigma) as given; none: estimated from the data, starting from
  // noise_guess_nT.
  std::optional<double> noise_nT;
  double noise_guess_nT = 10.0;
  std::optional<double> field_nT;  // reference F for rows without one
  std::string trace_path;          // per-sample trace CSV ("" = none)
  core::AcceptanceLimits<double> limits{};
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
  // Noise: in use (given or estimated), and the data's estimate with its 1-sigma (NaN if none).
  double noise_nT{0};
  bool noise_estimated{false};
  double noise_estimate_nT{0}, noise_estimate_sigma_nT{0};
  // Start-up: the last initial-fit try and the start-up set's size at the end.
  core::EkfInitReport<double> init_report;
  int startup_samples{0};
  std::uint64_t last_reinit_row{0};  // row (1-based, last pass) of the last restart; 0: none
  core::AcceptanceEvidence<double> evidence;
  core::Verdict verdict_code{core::Verdict::kOk};
  std::string verdict, reason;
  std::vector<std::string> warnings;  // e.g. a given noise the data disagree with
  Evaluation eval;
  CalibrationFile cal;
};

const char* ekf_status_name(core::EkfStatus s) noexcept;
const char* ekf_reset_name(core::EkfResetReason r) noexcept;
const char* ekf_init_failure_name(core::EkfInitFailure f) noexcept;
// "Cinv_xy", "b_z", ... for state index 0..11.
const char* ekf_state_name(int k) noexcept;

// Throws io::CsvError on malformed input, std::invalid_argument on bad options, std::system_error
// if the trace cannot be written.
EkfRun run_ekf(const std::string& path, const io::CsvReaderOptions& reader_options,
               const EkfRunOptions& opt);

}  // namespace magvec::host
