// The scalar EKF and its calibrator in double at the host's sizes, compiled once (see the end of
// scalar_ekf.hpp).
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/scalar_ekf.hpp"

namespace magvec::core {
template class ScalarEkfBase<double>;
template class ScalarEkf<double>;
template class EkfCalibrator<double>;
}  // namespace magvec::core
