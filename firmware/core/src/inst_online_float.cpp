// Core template instantiations (online path) for float; see inst_online.inc.
#define MAGVEC_INST_SCALAR float
#include "inst_online.inc"

// The vector calibration filter's calibrator in the sensor loop and the sample pipeline, in float
// (the M4F's scalar); the filter and the calibrator themselves are in inst_vector_float.cpp.
#include "magvec/core/vector_calibrator.hpp"

namespace magvec::core {
template class SensorLoop<float, VectorCalibrator<float>>;
template class SamplePipeline<float, VectorCalibrator<float>>;
}  // namespace magvec::core
