// BatchCalibrator<double, N> at the host's capacities (see the end of batch_calibrator.hpp),
// compiled once. One unit for all of them: the solvers they call take a SampleView and are
// compiled here once, so each further capacity costs only its thin store-walking members.
#include "magvec/core/batch_calibrator.hpp"

namespace magvec::core {
template class BatchCalibrator<double, 64>;
template class BatchCalibrator<double, 512>;
template class BatchCalibrator<double, 1024>;
template class BatchCalibrator<double, kDynamicCapacity>;
// What the units linking this library also only call (the end of ellipsoid_fit.hpp).
template class EllipsoidFit<double>;
template EllipsoidSolution<double> refine_ellipsoid_geometric<double>(
    SampleView<double>, const Normalization<double>&, const EllipsoidSolution<double>&,
    int) noexcept;
}  // namespace magvec::core
