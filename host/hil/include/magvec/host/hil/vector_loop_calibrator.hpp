// VectorLoopCalibrator: the host's `vector-ekf` calibrator, core::VectorCalibrator<double>
// (firmware/core/.../vector_calibrator.hpp, docs/equations.md E-VF) behind a plain class.
//
// The calibrator itself is compiled once (magvec::core_vector_double); this wrapper keeps its
// configuration and a Diagnostics snapshot of plain values in one place for magvec run, magvec demo
// and magvecd, whose sample pipelines hold it like the other calibrator modes. The estimation is
// the core's, unchanged.
#pragma once

#include <cstdint>
#include <memory>

#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"
#include "magvec/core/vector_calibrator.hpp"

namespace magvec::host::hil {

class VectorLoopCalibrator {
 public:
  using Impl = core::VectorCalibrator<double>;
  using Config = core::VectorCalibratorConfig<double>;

  explicit VectorLoopCalibrator(const Config& config);
  VectorLoopCalibrator(const VectorLoopCalibrator& other);  // a copy solves the same (worker)
  VectorLoopCalibrator& operator=(const VectorLoopCalibrator& other);
  ~VectorLoopCalibrator();

  // SensorLoop Calibrator contract (the extended add, sensor_loop.hpp).
  void begin() noexcept;
  core::CalibratorAdd add(const core::MagSample<double>& s,
                          const core::Mat3<double>* r_bn) noexcept;
  double progress() const noexcept;
  bool ready() const noexcept;
  core::CalibratorSolve solve(core::SensorModel<double>* out) const noexcept;

  // What reports, status and guidance show of the calibrator and its filter.
  struct Diagnostics {
    core::VectorCalibratorCounts counts{};
    core::VfCounters filter_counters{};
    bool noise_known{false};
    core::BatchNoise<double> noise{};
    int noise_samples{0};        // kept for the noise estimate so far
    int samples_needed{0};       // the start-up set's size
    int startup_samples{0};      // the filter's start-up store so far
    bool needs_reference{true};  // no constant reference configured: samples must carry F
    bool initialised{false};
    bool heading_held{true};
    core::SensorModel<double> model{};  // valid when initialised
    core::Vec3<double> h_n_nT = core::Vec3<double>::Zero();
    double time_offset_s{0};
    core::VfSigmas<double> sigmas{};
    // The calibration's output uncertainty over the survey envelope (E-VF-10).
    core::VfOutputUncertainty<double> output{};
    double readiness_ratio{0};  // the output 1-sigma over its readiness limit (ready at 1)
    double parameter_ratio{0};  // largest parameter 1-sigma over k times its noise (a report)
  };
  Diagnostics diagnostics() const noexcept;

  const Config& config() const noexcept;

 private:
  std::unique_ptr<Impl> impl_;
};

}  // namespace magvec::host::hil
