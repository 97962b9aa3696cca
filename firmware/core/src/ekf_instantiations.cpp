// Explicit instantiation of the scalar EKF (Ge et al. 2017, ERRATA 002) for float and double, so
// the whole filter is compiled and warning-checked on the host and with the Cortex-M4F flags.
#include "magvec/core/scalar_ekf.hpp"

namespace magvec::core {

template struct EkfConfig<float>;
template struct EkfConfig<double>;
template class ScalarEkf<float>;
template class ScalarEkf<double>;
template class scalar_ekf_detail::QuadricAccumulator<float>;
template class scalar_ekf_detail::QuadricAccumulator<double>;

}  // namespace magvec::core
