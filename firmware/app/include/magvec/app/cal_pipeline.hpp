// Per-sample calibration + compensation pipeline of the firmware image (issue 8): ScalarEkf (Ge et
// al. 2017 per ERRATA 002) fed with every magnetometer sample and its scalar reference, and the
// Compensator (DESIGN.md "Canonical sensor model") applied with the ACTIVE model, as the
// SensorLoop does (the active model changes only when a calibration is installed).
// Kept deliberately small and free of any driver/OS type: it is the piece that
// core::SensorLoop<Scalar, EkfCalibrator> replaces once the calibrator adapter exists (same
// per-sample work: calibrator update + compensation + navigation-frame rotation).
#pragma once

#include <cstdint>

#include "magvec/core/compensator.hpp"
#include "magvec/core/scalar_ekf.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::app {

template <typename Scalar>
struct PipelineOutput {
  core::Compensated<Scalar> c{};
  core::Vec3<Scalar> h_n = core::Vec3<Scalar>::Zero();
  bool valid{false};    // compensated values exist (finite raw sample)
  bool has_nav{false};  // h_n computed (an attitude was available)
};

template <typename Scalar>
class CalPipeline {
 public:
  using Ekf = core::ScalarEkf<Scalar>;

  explicit CalPipeline(const core::EkfConfig<Scalar>& ekf_config) noexcept : ekf_(ekf_config) {}

  // One magnetometer sample m [nT] with scalar reference f [nT] and the attitude aligned to its
  // time (nullptr when none). calibrate = false skips the estimator (survey after calibration).
  PipelineOutput<Scalar> step(const core::Vec3<Scalar>& m, Scalar f_ref_nT,
                              const core::Mat3<Scalar>* r_bn, bool calibrate) noexcept {
    PipelineOutput<Scalar> out;
    if (calibrate) last_status_ = ekf_.update(m, f_ref_nT);
    out.valid = active_.compensate(m, &out.c);
    if (out.valid && r_bn != nullptr) {
      out.h_n = core::Compensator<Scalar>::to_nav(out.c.h_b, *r_bn);
      out.has_nav = true;
    }
    return out;
  }

  void install(const core::SensorModel<Scalar>& model) noexcept { active_.set_model(model); }
  const core::SensorModel<Scalar>& active() const noexcept { return active_.model(); }
  const Ekf& ekf() const noexcept { return ekf_; }
  core::EkfStatus last_status() const noexcept { return last_status_; }

 private:
  Ekf ekf_;
  core::Compensator<Scalar> active_{};
  core::EkfStatus last_status_{core::EkfStatus::kCollecting};
};

}  // namespace magvec::app
