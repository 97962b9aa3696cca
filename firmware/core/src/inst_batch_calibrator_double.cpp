// BatchCalibrator<double, N> at the host's capacities (see the end of batch_calibrator.hpp),
// compiled once. One unit for all of them: the solvers they call take a SampleView and are
// compiled here once, so each further capacity costs only its thin store-walking members.
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/misalignment.hpp"

namespace magvec::core {
template class BatchCalibrator<double, 64>;
template class BatchCalibrator<double, 512>;
template class BatchCalibrator<double, 1024>;
template class BatchCalibrator<double, kDynamicCapacity>;
// What the units linking this library also only call (the ends of ellipsoid_fit.hpp and
// misalignment.hpp).
template class EllipsoidFit<double>;
template EllipsoidSolution<double> refine_ellipsoid_geometric<double>(
    SampleView<double>, const Normalization<double>&, const EllipsoidSolution<double>&,
    int) noexcept;
template MisalignmentSolution<double> plane_compression<double>(
    SampleView<double>, const Mat3<double>&, const Vec3<double>&,
    const MisalignmentOptions<double>&) noexcept;
template MisalignmentSolution<double> joint_rm_hn<double>(
    SampleView<double>, const Mat3<double>&, const Vec3<double>&,
    const MisalignmentOptions<double>&) noexcept;
}  // namespace magvec::core
