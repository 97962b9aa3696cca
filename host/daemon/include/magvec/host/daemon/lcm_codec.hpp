// Conversions between the HAL/core types and the LCM messages of host/lcm/*.lcm (package
// magvec_lcm). Every double is carried as the same IEEE-754 value, so a decoded sample is
// bit-identical to the one published (the basis of exact replay).
#pragma once

#include <cstdint>
#include <magvec_lcm/attitude.hpp>
#include <magvec_lcm/calibrated_vector.hpp>
#include <magvec_lcm/calibration_state.hpp>
#include <magvec_lcm/command.hpp>
#include <magvec_lcm/command_reply.hpp>
#include <magvec_lcm/health.hpp>
#include <magvec_lcm/mag_sample.hpp>
#include <magvec_lcm/mag_sample_batch.hpp>
#include <magvec_lcm/pipeline_event.hpp>

#include "magvec/core/sensor_model.hpp"
#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/record_sink.hpp"
#include "magvec/host/daemon/pipeline.hpp"
#include "magvec/host/daemon/scalar_health.hpp"

namespace magvec::host::daemon {

magvec_lcm::mag_sample to_lcm(const hal::MagnetometerSample& s, double f_ref_nT) noexcept;
hal::MagnetometerSample from_lcm(const magvec_lcm::mag_sample& m) noexcept;

magvec_lcm::attitude to_lcm(const hal::AttitudeSample& a) noexcept;
hal::AttitudeSample from_lcm(const magvec_lcm::attitude& m) noexcept;

magvec_lcm::calibrated_vector to_lcm(const hal::OutputRecord& r) noexcept;
hal::OutputRecord from_lcm(const magvec_lcm::calibrated_vector& m) noexcept;

// Model <-> (w row-major, o, rm quaternion w x y z), exact.
void model_to_arrays(const core::SensorModel<double>& m, double w[9], double o[3],
                     double q[4]) noexcept;
core::SensorModel<double> model_from_arrays(const double w[9], const double o[3],
                                            const double q[4]) noexcept;

magvec_lcm::pipeline_event session_start_event(std::int64_t sequence, const std::string& config);
magvec_lcm::pipeline_event set_active_event(std::int64_t sequence,
                                            const core::SensorModel<double>& model,
                                            std::uint32_t cal_id, double time_offset_s = 0,
                                            const OutputQuality& output = OutputQuality{});
// The output quality a SET_ACTIVE event carries (logs written before it existed: aligned, NaN).
OutputQuality output_quality_from(const magvec_lcm::pipeline_event& e) noexcept;
magvec_lcm::pipeline_event start_calibration_event(std::int64_t sequence);
magvec_lcm::pipeline_event solve_on_worker_event(std::int64_t sequence);
magvec_lcm::pipeline_event solve_result_event(std::int64_t sequence, const SolveResult& r);
SolveResult solve_result_from(const magvec_lcm::pipeline_event& e) noexcept;
// REFERENCE: F from the model `model` (its name) with 1-sigma `sigma_nT` from now on.
magvec_lcm::pipeline_event reference_event(std::int64_t sequence, const std::string& model,
                                           double sigma_nT);
// The 1-sigma a REFERENCE event carries (NaN when it carries none: the event is ignored).
double reference_sigma_from(const magvec_lcm::pipeline_event& e) noexcept;

magvec_lcm::calibration_state to_lcm(const CalibrationStatus& s, std::uint64_t t_us,
                                     std::uint32_t persisted_cal_id);

// The device counters of a health message: the magnetometer's, the INS driver's and, when
// `scalar` is given, the scalar magnetometer's (scalar_present; all 0 and false without one).
// The pipeline's, the loop's and the link's counters are the daemon's to set.
void set_device_health(magvec_lcm::health& h, const hal::MagCounters& mag,
                       const hal::AttitudeCounters& att, const ScalarHealth* scalar) noexcept;

// Bitwise equality of two records (NaN == NaN when the bits match).
bool bit_identical(const hal::OutputRecord& a, const hal::OutputRecord& b) noexcept;

}  // namespace magvec::host::daemon
