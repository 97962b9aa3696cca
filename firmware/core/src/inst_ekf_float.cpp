// The scalar EKF in float (ScalarEkfBase, which serves every start-up capacity, and the
// default-capacity ScalarEkf), compiled once for the host (see the end of scalar_ekf.hpp): the
// float recording runner and the float tests call it.
#include "magvec/core/scalar_ekf.hpp"

namespace magvec::core {
template class ScalarEkfBase<float>;
template class ScalarEkf<float>;
}  // namespace magvec::core
