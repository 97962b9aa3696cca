// The online vector calibration filter and its calibrator in double (the host's scalar): the one
// instantiation every double user links (magvec::core_vector_double).
#include "magvec/core/vector_calibration_filter.hpp"
#include "magvec/core/vector_calibrator.hpp"

namespace magvec::core {
template class VectorCalibrationFilter<double>;
template class VectorCalibrator<double>;
}  // namespace magvec::core
