// Before/after figures of a calibration over a recording, shared by the calibration runners and
// the CLI summaries: intensity residual |m| - F (raw) and |W(m - o)| - F (compensated), the spread
// of the E/N/U components (raw R_bn^T m vs. R_bn^T Rm^T W (m - o), docs/conventions.md compensation
// chain), and the direction coverage of the compensated field over 32 equal-area cells of the
// sphere (core/coverage.hpp, the grid of every calibrator, so figures of all methods are
// comparable).
#pragma once

#include <cstdint>

#include "magvec/core/coverage.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::host {

struct Evaluation {
  std::uint64_t n_intensity{0};  // samples with a reference F
  double intensity_rms_before_nT{0};
  double intensity_rms_after_nT{0};
  double intensity_mean_after_nT{0};
  bool has_enu{false};  // attitude present and the method determines W fully (not EKF)
  std::uint64_t n_enu{0};
  core::Vec3<double> enu_sd_before_nT = core::Vec3<double>::Zero();  // SD about the mean
  core::Vec3<double> enu_sd_after_nT = core::Vec3<double>::Zero();
  double coverage{0};  // fraction of 32 equal-area direction cells hit by h_s
};

class Evaluator {
 public:
  // vector_valid: the model's W is determined up to nothing (not only up to a rotation), so the
  // E/N/U components mean something.
  Evaluator(const core::SensorModel<double>& model, bool vector_valid);

  // f_nT: NaN when not available; r_bn: null when no attitude. Non-finite m is ignored.
  void add(const core::Vec3<double>& m_nT, double f_nT, const core::Mat3<double>* r_bn);
  Evaluation result() const;

 private:
  struct Welford {
    std::uint64_t n{0};
    core::Vec3<double> mean = core::Vec3<double>::Zero();
    core::Vec3<double> m2 = core::Vec3<double>::Zero();
    void add(const core::Vec3<double>& x);
    core::Vec3<double> sd() const;
  };
  core::SensorModel<double> model_;
  core::Mat3<double> rm_t_;
  bool vector_valid_;
  std::uint64_t n_f_{0};
  double sse_before_{0}, sse_after_{0}, sum_after_{0};
  Welford enu_before_, enu_after_;
  core::CoverageGrid cells_{};
};

}  // namespace magvec::host
