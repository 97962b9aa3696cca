// Before/after figures of a calibration (see evaluation.hpp).
#include "calibration/evaluation.hpp"

#include <algorithm>
#include <cmath>

namespace magvec::host {

void Evaluator::Welford::add(const core::Vec3<double>& x) {
  ++n;
  const core::Vec3<double> d = x - mean;
  mean += d / static_cast<double>(n);
  m2 += d.cwiseProduct(x - mean);
}

core::Vec3<double> Evaluator::Welford::sd() const {
  if (n < 2) return core::Vec3<double>::Zero();
  return (m2 / static_cast<double>(n - 1)).cwiseSqrt();
}

Evaluator::Evaluator(const core::SensorModel<double>& model, bool vector_valid)
    : model_(model), rm_t_(model.rm_matrix().transpose()), vector_valid_(vector_valid) {}

void Evaluator::add(const core::Vec3<double>& m, double f_nT, const core::Mat3<double>* r_bn) {
  if (!m.allFinite()) return;
  const core::Vec3<double> h_s = model_.w * (m - model_.o);
  if (!h_s.allFinite()) return;
  cells_.add(h_s);
  if (std::isfinite(f_nT)) {
    const double before = m.norm() - f_nT, after = h_s.norm() - f_nT;
    sse_before_ += before * before;
    sse_after_ += after * after;
    sum_after_ += after;
    ++n_f_;
  }
  if (r_bn != nullptr && r_bn->allFinite()) {
    enu_before_.add(r_bn->transpose() * m);
    enu_after_.add(r_bn->transpose() * (rm_t_ * h_s));
  }
}

Evaluation Evaluator::result() const {
  Evaluation e;
  e.n_intensity = n_f_;
  if (n_f_ > 0) {
    const double n = static_cast<double>(n_f_);
    e.intensity_rms_before_nT = std::sqrt(sse_before_ / n);
    e.intensity_rms_after_nT = std::sqrt(sse_after_ / n);
    e.intensity_mean_after_nT = sum_after_ / n;
  }
  e.has_enu = vector_valid_ && enu_before_.n > 1;
  e.n_enu = enu_before_.n;
  if (e.has_enu) {
    e.enu_sd_before_nT = enu_before_.sd();
    e.enu_sd_after_nT = enu_after_.sd();
  }
  e.coverage = cells_.fraction<double>();
  return e;
}

}  // namespace magvec::host
