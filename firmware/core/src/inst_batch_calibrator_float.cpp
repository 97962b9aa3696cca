// BatchCalibrator<float, 64>, the vector filter's start from data (see the end of
// batch_calibrator.hpp), compiled once. On the MCU presets this unit is compiled together with
// inst_batch_float.cpp (one unity unit, firmware/core/CMakeLists.txt), so the float solvers both
// call are compiled once.
#include "magvec/core/batch_calibrator.hpp"

namespace magvec::core {
template class BatchCalibrator<float, 64>;
}  // namespace magvec::core
