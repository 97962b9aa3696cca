// VectorLoopCalibrator: core::VectorCalibrator<double> (compiled in magvec::core_vector_double)
// behind a plain class; see vector_loop_calibrator.hpp.
#include "magvec/host/hil/vector_loop_calibrator.hpp"

namespace magvec::host::hil {

VectorLoopCalibrator::VectorLoopCalibrator(const Config& config)
    : impl_(std::make_unique<Impl>(config)) {}
VectorLoopCalibrator::VectorLoopCalibrator(const VectorLoopCalibrator& other)
    : impl_(std::make_unique<Impl>(*other.impl_)) {}
VectorLoopCalibrator& VectorLoopCalibrator::operator=(const VectorLoopCalibrator& other) {
  if (this != &other) *impl_ = *other.impl_;
  return *this;
}
VectorLoopCalibrator::~VectorLoopCalibrator() = default;

void VectorLoopCalibrator::begin() noexcept {
  impl_->begin();
}
core::CalibratorAdd VectorLoopCalibrator::add(const core::MagSample<double>& s,
                                              const core::Mat3<double>* r_bn) noexcept {
  return impl_->add(s, r_bn);
}
double VectorLoopCalibrator::progress() const noexcept {
  return impl_->progress();
}
bool VectorLoopCalibrator::ready() const noexcept {
  return impl_->ready();
}
core::CalibratorSolve VectorLoopCalibrator::solve(core::SensorModel<double>* out) const noexcept {
  return impl_->solve(out);
}
const VectorLoopCalibrator::Config& VectorLoopCalibrator::config() const noexcept {
  return impl_->config();
}

VectorLoopCalibrator::Diagnostics VectorLoopCalibrator::diagnostics() const noexcept {
  const Impl& c = *impl_;
  const auto& f = c.filter();
  Diagnostics d;
  d.counts = c.counts();
  d.filter_counters = f.counters();
  d.noise_known = c.noise_known();
  d.noise = c.noise();
  d.noise_samples = c.noise_samples();
  d.samples_needed = c.samples_needed();
  d.startup_samples = f.startup_samples();
  d.needs_reference = !(c.config().filter.reference_field_nT > 0);
  d.initialised = f.initialised();
  d.heading_held = f.heading_held();
  if (d.initialised) {
    d.model = f.model();
    d.h_n_nT = f.h_n_nT();
    d.time_offset_s = f.time_offset_s();
    d.sigmas = f.sigmas();
  }
  d.output = c.output_uncertainty();
  d.readiness_ratio = c.readiness_ratio();
  d.parameter_ratio = c.parameter_ratio();
  return d;
}

}  // namespace magvec::host::hil
