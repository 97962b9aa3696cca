// BatchCalibrator<double, kDynamicCapacity>, compiled once for the host (see the end of
// batch_calibrator.hpp).
#include "magvec/core/batch_calibrator.hpp"

template class magvec::core::BatchCalibrator<double, magvec::core::kDynamicCapacity>;
