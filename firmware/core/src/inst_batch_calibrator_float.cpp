// BatchCalibrator<float, 64>, the vector filter's start from data (see the end of
// batch_calibrator.hpp), compiled once. On the MCU presets this unit is compiled together with
// inst_batch_float.cpp (one unity unit, firmware/core/CMakeLists.txt), so the float solvers both
// call are compiled once.
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/misalignment.hpp"

namespace magvec::core {
template class BatchCalibrator<float, 64>;
// What the units linking this library also only call (the ends of ellipsoid_fit.hpp and
// misalignment.hpp); in the MCU presets' unity unit inst_batch_float.cpp (MAGVEC_INST_SCALAR) has
// instantiated them already.
#ifndef MAGVEC_INST_SCALAR
template class EllipsoidFit<float>;
template EllipsoidSolution<float> refine_ellipsoid_geometric<float>(SampleView<float>,
                                                                    const Normalization<float>&,
                                                                    const EllipsoidSolution<float>&,
                                                                    int) noexcept;
template MisalignmentSolution<float> plane_compression<float>(
    SampleView<float>, const Mat3<float>&, const Vec3<float>&,
    const MisalignmentOptions<float>&) noexcept;
template MisalignmentSolution<float> joint_rm_hn<float>(SampleView<float>, const Mat3<float>&,
                                                        const Vec3<float>&,
                                                        const MisalignmentOptions<float>&) noexcept;
#endif
}  // namespace magvec::core
