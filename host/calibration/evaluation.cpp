// Before/after figures of a calibration (see evaluation.hpp).
#include "calibration/evaluation.hpp"

#include <algorithm>
#include <bit>
#include <cmath>

namespace magvec::host {

int coverage_cell(const core::Vec3<double>& h) {
  constexpr int kBands = 4, kSectors = 8;
  const double len = h.norm();
  if (!(len > 0) || !std::isfinite(len)) return -1;
  const core::Vec3<double> d = h / len;
  const int band = std::clamp(static_cast<int>((d(2) + 1.0) * 0.5 * kBands), 0, kBands - 1);
  const double az = std::atan2(d(1), d(0)) + core::kPi<double>;
  const int sector =
      std::clamp(static_cast<int>(az / (2.0 * core::kPi<double>)*kSectors), 0, kSectors - 1);
  return band * kSectors + sector;
}

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
  const int cell = coverage_cell(h_s);
  if (cell >= 0) cells_ |= 1U << static_cast<unsigned>(cell);
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
  e.coverage = static_cast<double>(std::popcount(cells_)) / 32.0;
  return e;
}

}  // namespace magvec::host
