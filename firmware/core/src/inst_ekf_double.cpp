// The scalar EKF in double (ScalarEkfBase, which serves every start-up capacity, and the
// default-capacity ScalarEkf) and its calibrator, compiled once (see the end of scalar_ekf.hpp).
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/scalar_ekf.hpp"

namespace magvec::core {
template class ScalarEkfBase<double>;
template class ScalarEkf<double>;
template class EkfCalibrator<double>;
}  // namespace magvec::core
