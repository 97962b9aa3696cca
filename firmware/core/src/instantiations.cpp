// Explicit instantiation of the core templates for both scalar types, so that every template is
// compiled (and warning-checked) on the host and for the MCU targets.
#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/core/compensator.hpp"
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"

namespace magvec::core {

template class BatchLiCalibrator<float, 128>;
template class BatchLiCalibrator<double, 128>;
template class EkfCalibrator<float, 64>;
template class EkfCalibrator<double, 64>;
template class AttitudeBuffer<float, 64>;
template class AttitudeBuffer<double, 64>;
template Quat<float> slerp_unit(const Quat<float>&, const Quat<float>&, float) noexcept;
template Quat<double> slerp_unit(const Quat<double>&, const Quat<double>&, double) noexcept;
template struct SensorModel<float>;
template struct SensorModel<double>;
template class Compensator<float>;
template class Compensator<double>;

template SensorModel<float> from_li(const LiParams<float>&) noexcept;
template SensorModel<double> from_li(const LiParams<double>&) noexcept;
template ConversionStatus to_li(const SensorModel<float>&, LiParams<float>*) noexcept;
template ConversionStatus to_li(const SensorModel<double>&, LiParams<double>*) noexcept;
template SensorModel<float> from_ge(const GeParams<float>&) noexcept;
template SensorModel<double> from_ge(const GeParams<double>&) noexcept;
template GeParams<float> to_ge(const SensorModel<float>&) noexcept;
template GeParams<double> to_ge(const SensorModel<double>&) noexcept;
template SensorModel<float> from_sine(const SineParams<float>&) noexcept;
template SensorModel<double> from_sine(const SineParams<double>&) noexcept;
template ConversionStatus to_sine(const SensorModel<float>&, SineParams<float>*,
                                  Mat3<float>*) noexcept;
template ConversionStatus to_sine(const SensorModel<double>&, SineParams<double>*,
                                  Mat3<double>*) noexcept;
template Mat3<float> r_bn_from_quat(const Quat<float>&) noexcept;
template Mat3<double> r_bn_from_quat(const Quat<double>&) noexcept;
template Quat<float> quat_from_r_bn(const Mat3<float>&) noexcept;
template Quat<double> quat_from_r_bn(const Mat3<double>&) noexcept;

}  // namespace magvec::core
