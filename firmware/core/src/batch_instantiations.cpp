// Explicit instantiation of the batch calibration templates (issue 3) for float and double, so they
// compile (and are warning-checked) on the host and for the Cortex-M targets. The MCU capacity is
// small on purpose: 256 samples of float are ~9 kB of store.
#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/misalignment.hpp"
#include "magvec/core/one_step.hpp"
#include "magvec/core/sample_store.hpp"
#include "magvec/core/sine_fit.hpp"

namespace magvec::core {

inline constexpr std::size_t kMcuBatchCapacity = 256;

template class EllipsoidFit<float>;
template class EllipsoidFit<double>;
template class SampleStore<float, kMcuBatchCapacity>;
template class SampleStore<double, kMcuBatchCapacity>;
template class BatchCalibrator<float, kMcuBatchCapacity>;
template class BatchCalibrator<double, kMcuBatchCapacity>;
template class OneStepFit<float>;
template class OneStepFit<double>;
template class SineSweep<float>;
template class SineSweep<double>;

template EllipsoidSolution<float> refine_ellipsoid_geometric(
    const SampleStore<float, kMcuBatchCapacity>&, const Normalization<float>&,
    const EllipsoidSolution<float>&, int) noexcept;
template EllipsoidSolution<double> refine_ellipsoid_geometric(
    const SampleStore<double, kMcuBatchCapacity>&, const Normalization<double>&,
    const EllipsoidSolution<double>&, int) noexcept;
template MisalignmentSolution<float> plane_compression(const SampleStore<float, kMcuBatchCapacity>&,
                                                       const Mat3<float>&, const Vec3<float>&,
                                                       const MisalignmentOptions<float>&) noexcept;
template MisalignmentSolution<double> plane_compression(
    const SampleStore<double, kMcuBatchCapacity>&, const Mat3<double>&, const Vec3<double>&,
    const MisalignmentOptions<double>&) noexcept;
template MisalignmentSolution<float> joint_rm_hn(const SampleStore<float, kMcuBatchCapacity>&,
                                                 const Mat3<float>&, const Vec3<float>&,
                                                 const MisalignmentOptions<float>&) noexcept;
template MisalignmentSolution<double> joint_rm_hn(const SampleStore<double, kMcuBatchCapacity>&,
                                                  const Mat3<double>&, const Vec3<double>&,
                                                  const MisalignmentOptions<double>&) noexcept;
template OneStepSolution<float> OneStepFit<float>::solve(
    const SampleStore<float, kMcuBatchCapacity>&, const Normalization<float>&,
    const LiParams<float>&, const Vec3<float>&, const OneStepOptions<float>&) noexcept;
template OneStepSolution<double> OneStepFit<double>::solve(
    const SampleStore<double, kMcuBatchCapacity>&, const Normalization<double>&,
    const LiParams<double>&, const Vec3<double>&, const OneStepOptions<double>&) noexcept;
template SineSolution<float> solve_sine(const SineSweep<float>&, const SineSweep<float>&,
                                        const SineFitOptions<float>&) noexcept;
template SineSolution<double> solve_sine(const SineSweep<double>&, const SineSweep<double>&,
                                         const SineFitOptions<double>&) noexcept;

}  // namespace magvec::core
