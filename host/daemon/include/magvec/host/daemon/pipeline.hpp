// magvecd's Pipeline: raw input events -> hil::LoopCore (AttitudeBuffer + SensorLoop) -> records,
// with the calibrator chosen at run time from the configuration (li | ekf | vector-ekf | none). It
// consumes only raw events (magnetometer samples + scalar reference, INS attitude samples) and the
// pipeline events (start calibration, install a calibration); it has no clock and no I/O besides
// the record sink, so the same events in the same order give bit-identical records. The daemon and
// `magvec replay` both drive it.
#pragma once

#include <cstdint>
#include <functional>
#include <limits>
#include <memory>
#include <string>

#include "calibration/calibration_file.hpp"
#include "magvec/core/calibration_guidance.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/record_sink.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/hil/loop_core.hpp"

namespace magvec::host::daemon {

struct CalibrationStatus {
  std::string calibrator;  // li | ekf | vector-ekf | none
  core::CalState state{core::CalState::kIdle};
  core::CalFailure failure{core::CalFailure::kNone};
  // Why the last candidate failed: the calibrator's verdict when the solver refused, the figures
  // and bound when validation refused ("" otherwise).
  std::string solver_reason;
  double progress{0};
  double validation_rms_nT{0};
  std::uint32_t cal_id{0};
  core::SensorModel<double> active{};
  OutputQuality output{};  // what the records carry with `active` (alignment, 1-sigmas)
  // While collecting: what the calibrator has and needs, the hint (core/calibration_guidance.hpp;
  // progress above is guidance.progress then) and its text (guidance_text.hpp).
  core::Guidance<double> guidance{};
  std::size_t samples{0};
  std::size_t samples_needed{0};
  std::string hint;
  // RMS of |h| - F of the active calibration, exponentially averaged over ~100 readings with a
  // reference (NaN: none yet).
  double residual_nT{std::numeric_limits<double>::quiet_NaN()};
};

// A solve handed off the acquisition path (see Pipeline::take_solve_job).
struct SolveResult {
  std::uint32_t ticket{0};  // the loop's solve ticket (SensorLoop::solve_ticket)
  bool ok{false};
  std::uint8_t code{0};  // the calibrator's refusal code when !ok
  bool aligned{true};    // CalibratorSolve::aligned: the candidate's Rm is an estimate
  float attitude_noise_deg{std::numeric_limits<float>::quiet_NaN()};  // the solve's, NaN: none
  float mag_noise_nT{std::numeric_limits<float>::quiet_NaN()};        // the solve's, NaN: none
  core::SensorModel<double> model{};
};
// Self-contained (owns a copy of the calibrator's data): may run on any thread, and after the
// pipeline that made it is gone.
using SolveJob = std::function<SolveResult()>;

class Pipeline {
 public:
  // Throws ConfigError for an unknown calibration mode.
  static std::unique_ptr<Pipeline> create(const Config& config, hal::RecordSink& sink);
  virtual ~Pipeline() = default;

  // Records go to the sink when their sample is processed (delayed fusion horizon: on a later
  // INS or magnetometer event, or on flush()).
  virtual void on_attitude(const hal::AttitudeSample& a) noexcept = 0;
  virtual void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) noexcept = 0;
  virtual void on_read_error() noexcept = 0;
  virtual void flush() noexcept = 0;
  // The magnetometer<->INS time offset of an installed calibration (ignored when the
  // configuration fixes devices.ins.time_offset_s).
  virtual void set_time_offset_s(double offset_s) noexcept = 0;
  // Fixes the offset from now on, whatever the configuration and later calibrations say
  // (`magvec replay --time-offset-s`).
  virtual void override_time_offset_s(double offset_s) noexcept = 0;
  virtual double time_offset_s() const noexcept = 0;
  virtual void start_calibration() noexcept = 0;
  // The samples' F comes from a geomagnetic model of this 1-sigma from now on (the REFERENCE
  // event; core::LoopConfig::reference_sigma_nT): validation and records treat it as a model's.
  // A calibration in progress starts over, so that all its samples share one reference (li and
  // ekf skipped the samples without F; vector-ekf took them without a scale).
  virtual void set_reference_sigma_nT(double sigma_nT) noexcept = 0;
  // output: the calibration's alignment and 1-sigmas as validated when it was applied (NaN
  // sigmas: not known; the configured noise then stands in for sigma_f).
  virtual void set_active(const core::SensorModel<double>& model, std::uint32_t cal_id,
                          const OutputQuality& output) noexcept = 0;

  // Solving off the acquisition path (magvecd's worker thread). With set_external_solve(true) the
  // loop does not solve itself: once it is solving, take_solve_job() returns the job once (empty
  // otherwise); its result goes back through install_solve (false: stale, e.g. the calibration
  // restarted meanwhile). The records do not depend on where the job ran, only on where in the
  // event order its result is installed.
  virtual void set_external_solve(bool on) noexcept = 0;
  virtual SolveJob take_solve_job() = 0;
  virtual bool install_solve(const SolveResult& r) noexcept = 0;

  virtual CalibrationStatus status() const = 0;
  virtual core::CalState state() const noexcept = 0;  // cheap: for change detection
  virtual const hil::HilCounters& counters() const noexcept = 0;
  virtual const core::LoopHealth& health() const noexcept = 0;
};

}  // namespace magvec::host::daemon
