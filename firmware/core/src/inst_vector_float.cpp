// The online vector calibration filter and its calibrator in float (the M4F's scalar): the one
// instantiation every float user links (magvec::core_vector_float), compiled with the Cortex-M
// flags on the MCU presets and checked by clang-tidy.
#include "magvec/core/vector_calibration_filter.hpp"
#include "magvec/core/vector_calibrator.hpp"

namespace magvec::core {
template class VectorCalibrationFilter<float>;
template class VectorCalibrator<float>;
}  // namespace magvec::core
