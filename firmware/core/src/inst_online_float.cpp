// Core template instantiations (online path) for float; see inst_online.inc.
#define MAGVEC_INST_SCALAR float
#include "inst_online.inc"

// The online vector calibration filter and its calibrator in the sensor loop and the sample
// pipeline, in float (the M4F's scalar), with the Cortex-M flags and under clang-tidy.
#include "magvec/core/vector_calibration_filter.hpp"
#include "magvec/core/vector_calibrator.hpp"

namespace magvec::core {
template class VectorCalibrationFilter<float>;
template class VectorCalibrator<float>;
template class SensorLoop<float, VectorCalibrator<float>>;
template class SamplePipeline<float, VectorCalibrator<float>>;
}  // namespace magvec::core
