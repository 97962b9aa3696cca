// BatchCalibrator<float, 64>, the vector filter's start from data (see the end of
// batch_calibrator.hpp), compiled once. On the MCU presets this unit is compiled together with
// inst_batch_float.cpp (one unity unit, firmware/core/CMakeLists.txt), so the float solvers both
// call are compiled once.
#include "magvec/core/batch_calibrator.hpp"

namespace magvec::core {
template class BatchCalibrator<float, 64>;
// What the units linking this library also only call (the end of ellipsoid_fit.hpp); in the MCU
// presets' unity unit inst_batch_float.cpp (MAGVEC_INST_SCALAR) has instantiated them already.
#ifndef MAGVEC_INST_SCALAR
template class EllipsoidFit<float>;
template EllipsoidSolution<float> refine_ellipsoid_geometric<float>(SampleView<float>,
                                                                    const Normalization<float>&,
                                                                    const EllipsoidSolution<float>&,
                                                                    int) noexcept;
#endif
}  // namespace magvec::core
