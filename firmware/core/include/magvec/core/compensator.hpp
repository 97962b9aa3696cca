// Per-sample compensation with the canonical model (docs/conventions.md#canonical-sensor-model):
//   h_s = W (m - o)   orthogonal sensor frame, |h_s| the calibrated total field
//   h_b = Rm^T h_s    INS body frame
//   h_n = R_bn^T h_b  navigation frame (ENU)
// Equivalent to Li et al. 2023 eq. (8)/(15) and Ge et al. 2017 eq. (14).
#pragma once

#include <cmath>

#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

template <typename Scalar>
struct Compensated {
  Vec3<Scalar> h_s = Vec3<Scalar>::Zero();
  Vec3<Scalar> h_b = Vec3<Scalar>::Zero();
  Scalar intensity{0};
};

template <typename Scalar>
class Compensator {
 public:
  Compensator() noexcept = default;
  explicit Compensator(const SensorModel<Scalar>& model) noexcept { set_model(model); }

  void set_model(const SensorModel<Scalar>& model) noexcept {
    model_ = model;
    w_ = model.w;
    o_ = model.o;
    rm_t_ = model.rm_matrix().transpose();
  }
  const SensorModel<Scalar>& model() const noexcept { return model_; }

  // Returns false (and leaves *out untouched) when the raw sample is not finite.
  bool compensate(const Vec3<Scalar>& m, Compensated<Scalar>* out) const noexcept {
    if (!all_finite(m)) return false;
    out->h_s = w_ * (m - o_);
    out->h_b = rm_t_ * out->h_s;
    out->intensity = out->h_s.norm();
    return true;
  }

  static Vec3<Scalar> to_nav(const Vec3<Scalar>& h_b, const Mat3<Scalar>& r_bn) noexcept {
    return r_bn.transpose() * h_b;
  }

 private:
  SensorModel<Scalar> model_{};
  Mat3<Scalar> w_ = Mat3<Scalar>::Identity();
  Vec3<Scalar> o_ = Vec3<Scalar>::Zero();
  Mat3<Scalar> rm_t_ = Mat3<Scalar>::Identity();
};

}  // namespace magvec::core
