// LCM <-> HAL conversions; see lcm_codec.hpp.
#include "magvec/host/daemon/lcm_codec.hpp"

#include <algorithm>
#include <cmath>
#include <cstdlib>
#include <cstring>
#include <limits>
#include <sstream>
#include <string>

#include "magvec/host/daemon/guidance_text.hpp"

namespace magvec::host::daemon {

magvec_lcm::mag_sample to_lcm(const hal::MagnetometerSample& s, double f_ref_nT) noexcept {
  magvec_lcm::mag_sample m;
  m.t_us = static_cast<std::int64_t>(s.t_us);
  for (std::size_t i = 0; i < 3; ++i) {
    m.m_nT[i] = s.m_nT[i];
    m.raw[i] = s.raw[i];
  }
  m.flags = static_cast<std::int32_t>(s.flags);
  m.sequence = static_cast<std::int32_t>(s.sequence);
  m.f_ref_nT = f_ref_nT;
  return m;
}

hal::MagnetometerSample from_lcm(const magvec_lcm::mag_sample& m) noexcept {
  hal::MagnetometerSample s;
  s.t_us = static_cast<std::uint64_t>(m.t_us);
  for (std::size_t i = 0; i < 3; ++i) {
    s.m_nT[i] = m.m_nT[i];
    s.raw[i] = m.raw[i];
  }
  s.flags = static_cast<std::uint32_t>(m.flags);
  s.sequence = static_cast<std::uint32_t>(m.sequence);
  return s;
}

magvec_lcm::attitude to_lcm(const hal::AttitudeSample& a) noexcept {
  magvec_lcm::attitude m;
  m.t_us = static_cast<std::int64_t>(a.t_us);
  m.t_ins_us = static_cast<std::int64_t>(a.t_ins_us);
  for (std::size_t i = 0; i < 4; ++i)
    m.q_nb[i] = a.q_nb[i];
  for (std::size_t i = 0; i < 3; ++i)
    m.sigma_rad[i] = a.sigma_rad[i];
  m.flags = static_cast<std::int32_t>(a.flags);
  m.solution_mode = static_cast<std::int8_t>(a.solution_mode);
  return m;
}

hal::AttitudeSample from_lcm(const magvec_lcm::attitude& m) noexcept {
  hal::AttitudeSample a;
  a.t_us = static_cast<std::uint64_t>(m.t_us);
  a.t_ins_us = static_cast<std::uint64_t>(m.t_ins_us);
  for (std::size_t i = 0; i < 4; ++i)
    a.q_nb[i] = m.q_nb[i];
  for (std::size_t i = 0; i < 3; ++i)
    a.sigma_rad[i] = m.sigma_rad[i];
  a.flags = static_cast<std::uint32_t>(m.flags);
  a.solution_mode = static_cast<std::uint8_t>(m.solution_mode);
  return a;
}

magvec_lcm::calibrated_vector to_lcm(const hal::OutputRecord& r) noexcept {
  magvec_lcm::calibrated_vector m;
  m.t_us = static_cast<std::int64_t>(r.t_us);
  for (std::size_t i = 0; i < 3; ++i) {
    m.raw_nT[i] = r.raw_nT[i];
    m.h_s_nT[i] = r.h_s_nT[i];
    m.h_enu_nT[i] = r.h_n_nT[i];
  }
  m.f_nT = r.f_nT;
  m.sigma_f_nT = r.sigma_f_nT;
  m.sigma_enu_nT = r.sigma_enu_nT;
  m.flags = static_cast<std::int32_t>(r.flags);
  m.cal_id = static_cast<std::int32_t>(r.cal_id);
  return m;
}

hal::OutputRecord from_lcm(const magvec_lcm::calibrated_vector& m) noexcept {
  hal::OutputRecord r;
  r.t_us = static_cast<std::uint64_t>(m.t_us);
  for (std::size_t i = 0; i < 3; ++i) {
    r.raw_nT[i] = m.raw_nT[i];
    r.h_s_nT[i] = m.h_s_nT[i];
    r.h_n_nT[i] = m.h_enu_nT[i];
  }
  r.f_nT = m.f_nT;
  r.sigma_f_nT = m.sigma_f_nT;
  r.sigma_enu_nT = m.sigma_enu_nT;
  r.flags = static_cast<std::uint32_t>(m.flags);
  r.cal_id = static_cast<std::uint32_t>(m.cal_id);
  return r;
}

void model_to_arrays(const core::SensorModel<double>& m, double w[9], double o[3],
                     double q[4]) noexcept {
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      w[3 * r + c] = m.w(r, c);
  for (int i = 0; i < 3; ++i)
    o[i] = m.o(i);
  q[0] = m.rm.w();
  q[1] = m.rm.x();
  q[2] = m.rm.y();
  q[3] = m.rm.z();
}

core::SensorModel<double> model_from_arrays(const double w[9], const double o[3],
                                            const double q[4]) noexcept {
  core::SensorModel<double> m;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      m.w(r, c) = w[3 * r + c];
  for (int i = 0; i < 3; ++i)
    m.o(i) = o[i];
  m.rm = core::Quat<double>(q[0], q[1], q[2], q[3]);  // exact: no renormalisation
  return m;
}

namespace {
magvec_lcm::pipeline_event blank_event(std::int8_t kind, std::int64_t sequence) {
  magvec_lcm::pipeline_event e{};
  e.kind = kind;
  e.sequence = sequence;
  const core::SensorModel<double> identity;
  model_to_arrays(identity, e.w, e.o_nT, e.rm_quat);
  e.cal_id = 0;
  return e;
}
// The extras of SET_ACTIVE, SOLVE_RESULT and REFERENCE travel as "key = value" lines in the event's
// text field, which those kinds do not otherwise use: no new field, so the type's fingerprint,
// hence old logs, stay valid.
double extra_number(const std::string& text, const char* key) noexcept {
  const std::string k = std::string(key) + " = ";
  std::size_t at = 0;
  while ((at = text.find(k, at)) != std::string::npos) {
    if (at == 0 || text[at - 1] == '\n') {
      const char* begin = text.c_str() + at + k.size();
      char* end = nullptr;
      const double v = std::strtod(begin, &end);
      return end != begin ? v : std::numeric_limits<double>::quiet_NaN();
    }
    at += k.size();
  }
  return std::numeric_limits<double>::quiet_NaN();
}

bool extra_is(const std::string& text, const char* key, const char* value) noexcept {
  const std::string k = std::string(key) + " = " + value;
  const std::size_t at = text.find(k);
  return at != std::string::npos && (at == 0 || text[at - 1] == '\n');
}
bool extra_false(const std::string& text, const char* key) noexcept {
  return extra_is(text, key, "false");
}
bool extra_true(const std::string& text, const char* key) noexcept {
  return extra_is(text, key, "true");
}

// A finite positive figure, else NaN (a corrupt or hand-edited log never installs a negative
// or infinite sigma).
double positive_or_nan(double v) noexcept {
  return std::isfinite(v) && v > 0 ? v : std::numeric_limits<double>::quiet_NaN();
}

}  // namespace

magvec_lcm::pipeline_event session_start_event(std::int64_t sequence, const std::string& config) {
  magvec_lcm::pipeline_event e = blank_event(magvec_lcm::pipeline_event::SESSION_START, sequence);
  e.config_toml = config;
  return e;
}

magvec_lcm::pipeline_event set_active_event(std::int64_t sequence,
                                            const core::SensorModel<double>& model,
                                            std::uint32_t cal_id, double time_offset_s,
                                            const OutputQuality& output) {
  magvec_lcm::pipeline_event e = blank_event(magvec_lcm::pipeline_event::SET_ACTIVE, sequence);
  model_to_arrays(model, e.w, e.o_nT, e.rm_quat);
  e.cal_id = static_cast<std::int32_t>(cal_id);
  e.time_offset_s = time_offset_s;
  std::ostringstream extra;
  extra.precision(17);  // the records after a replayed SET_ACTIVE are bit-identical
  extra << "aligned = " << (output.aligned ? "true" : "false") << "\n";
  if (std::isfinite(output.sigma_f_nT)) extra << "sigma_f_nT = " << output.sigma_f_nT << "\n";
  if (std::isfinite(output.sigma_enu_nT)) extra << "sigma_enu_nT = " << output.sigma_enu_nT << "\n";
  if (output.model_reference) extra << "model_reference = true\n";
  e.config_toml = extra.str();
  return e;
}

OutputQuality output_quality_from(const magvec_lcm::pipeline_event& e) noexcept {
  OutputQuality q;
  q.aligned = !extra_false(e.config_toml, "aligned");
  q.sigma_f_nT = positive_or_nan(extra_number(e.config_toml, "sigma_f_nT"));
  q.sigma_enu_nT = positive_or_nan(extra_number(e.config_toml, "sigma_enu_nT"));
  q.model_reference = extra_true(e.config_toml, "model_reference");
  return q;
}

magvec_lcm::pipeline_event start_calibration_event(std::int64_t sequence) {
  return blank_event(magvec_lcm::pipeline_event::START_CALIBRATION, sequence);
}

magvec_lcm::pipeline_event solve_on_worker_event(std::int64_t sequence) {
  return blank_event(magvec_lcm::pipeline_event::SOLVE_ON_WORKER, sequence);
}

magvec_lcm::pipeline_event solve_result_event(std::int64_t sequence, const SolveResult& r) {
  magvec_lcm::pipeline_event e = blank_event(magvec_lcm::pipeline_event::SOLVE_RESULT, sequence);
  model_to_arrays(r.model, e.w, e.o_nT, e.rm_quat);
  e.cal_id = static_cast<std::int32_t>(r.ticket);
  e.time_offset_s = r.ok ? -1.0 : static_cast<double>(r.code);
  // The rest of the solve's outcome in the text field (extra_number). 9 digits: a float's exact
  // round trip.
  std::ostringstream extra;
  extra.precision(9);
  extra << "aligned = " << (r.aligned ? "true" : "false") << "\n";
  if (std::isfinite(r.attitude_noise_deg))
    extra << "attitude_noise_deg = " << r.attitude_noise_deg << "\n";
  if (std::isfinite(r.mag_noise_nT)) extra << "mag_noise_nT = " << r.mag_noise_nT << "\n";
  e.config_toml = extra.str();
  return e;
}

SolveResult solve_result_from(const magvec_lcm::pipeline_event& e) noexcept {
  SolveResult r;
  r.ticket = static_cast<std::uint32_t>(e.cal_id);
  r.ok = e.time_offset_s < 0;
  r.code = r.ok || !(e.time_offset_s <= 255) ? std::uint8_t{0}
                                             : static_cast<std::uint8_t>(e.time_offset_s);
  r.model = model_from_arrays(e.w, e.o_nT, e.rm_quat);
  // Logs written before these keys existed: aligned, no noise figures.
  r.aligned = !extra_false(e.config_toml, "aligned");
  r.attitude_noise_deg =
      static_cast<float>(positive_or_nan(extra_number(e.config_toml, "attitude_noise_deg")));
  r.mag_noise_nT = static_cast<float>(positive_or_nan(extra_number(e.config_toml, "mag_noise_nT")));
  return r;
}

magvec_lcm::pipeline_event reference_event(std::int64_t sequence, const std::string& model,
                                           double sigma_nT) {
  magvec_lcm::pipeline_event e = blank_event(magvec_lcm::pipeline_event::REFERENCE, sequence);
  std::ostringstream extra;
  extra.precision(17);
  extra << "model = " << model << "\n";
  extra << "reference_sigma_nT = " << sigma_nT << "\n";
  e.config_toml = extra.str();
  return e;
}

double reference_sigma_from(const magvec_lcm::pipeline_event& e) noexcept {
  return positive_or_nan(extra_number(e.config_toml, "reference_sigma_nT"));
}

magvec_lcm::calibration_state to_lcm(const CalibrationStatus& s, std::uint64_t t_us,
                                     std::uint32_t persisted_cal_id) {
  magvec_lcm::calibration_state m{};
  m.t_us = static_cast<std::int64_t>(t_us);
  m.calibrator = s.calibrator;
  m.state = core::cal_state_name(s.state);
  m.failure = core::cal_failure_name(s.failure);
  m.solver_reason = s.solver_reason;
  m.progress = s.progress;
  m.validation_rms_nT = s.validation_rms_nT;
  m.cal_id = static_cast<std::int32_t>(s.cal_id);
  m.persisted_cal_id = static_cast<std::int32_t>(persisted_cal_id);
  model_to_arrays(s.active, m.w, m.o_nT, m.rm_quat);
  m.coverage_cells = static_cast<std::int32_t>(s.guidance.cells);  // the mask's bits as they are
  m.coverage_needed = s.guidance.cells_needed;
  auto i32 = [](std::size_t n) {
    return static_cast<std::int32_t>(std::min<std::size_t>(n, 0x7FFFFFFF));
  };
  m.samples = i32(s.samples);
  m.samples_needed = i32(s.samples_needed);
  m.hint_code = guidance_hint_name(s.guidance.hint);
  m.hint = s.hint;
  m.residual_nT = s.residual_nT;
  return m;
}

bool bit_identical(const hal::OutputRecord& a, const hal::OutputRecord& b) noexcept {
  auto same = [](double x, double y) { return std::memcmp(&x, &y, sizeof(double)) == 0; };
  if (a.t_us != b.t_us || a.flags != b.flags || a.cal_id != b.cal_id) return false;
  for (std::size_t i = 0; i < 3; ++i) {
    if (!same(a.raw_nT[i], b.raw_nT[i]) || !same(a.h_s_nT[i], b.h_s_nT[i]) ||
        !same(a.h_n_nT[i], b.h_n_nT[i]))
      return false;
  }
  return same(a.f_nT, b.f_nT) && same(a.sigma_f_nT, b.sigma_f_nT) &&
         same(a.sigma_enu_nT, b.sigma_enu_nT);
}

void set_device_health(magvec_lcm::health& h, const hal::MagCounters& mag,
                       const hal::AttitudeCounters& att, const ScalarHealth* scalar) noexcept {
  auto i64 = [](std::uint64_t v) { return static_cast<std::int64_t>(v); };
  h.mag_samples = mag.samples;
  h.mag_crc_errors = mag.crc_errors;
  h.mag_malformed = mag.malformed;
  h.mag_bus_errors = mag.bus_errors;
  h.mag_timeouts = mag.timeouts;
  h.mag_saturated = mag.saturated;
  h.mag_device_resets = mag.device_resets;
  h.att_samples = att.samples;
  h.att_malformed = att.malformed;
  h.att_duplicates = att.duplicates;
  h.scalar_present = scalar != nullptr;
  if (scalar == nullptr) return;
  const hal::ScalarCounters& sc = scalar->source;
  h.scalar_samples = sc.samples;
  h.scalar_malformed = sc.malformed;
  h.scalar_crc_errors = sc.crc_errors;
  h.scalar_out_of_range = sc.out_of_range;
  h.scalar_overflows = sc.overflows;
  h.scalar_garbage_bytes = sc.garbage_bytes;
  h.scalar_low_signal = sc.low_signal;
  h.scalar_bus_errors = sc.bus_errors;
  h.scalar_read_errors = i64(scalar->read_errors);
  h.scalar_timeouts = i64(scalar->timeouts);
  h.scalar_f_interpolated = i64(scalar->f_interpolated);
  h.scalar_f_nearest = i64(scalar->f_nearest);
  h.scalar_f_fallback = i64(scalar->f_fallback);
}

}  // namespace magvec::host::daemon
