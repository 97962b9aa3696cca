// Simulation CSV writer for the CLI (see sim_csv.hpp).
#include "sim_csv.hpp"

#include <array>
#include <cmath>
#include <stdexcept>

#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/host/io/csv.hpp"
#include "magvec/version.hpp"

namespace magvec::host::cli {
namespace {

using drivers::sim::ScenarioConfig;
using io::format_double;

std::string vec(const core::Vec3<double>& v) {
  return "[" + format_double(v(0)) + ", " + format_double(v(1)) + ", " + format_double(v(2)) + "]";
}
std::string vec_deg(const core::Vec3<double>& v_rad) {
  return vec(v_rad * (180.0 / core::kPi<double>));
}
std::string mat(const core::Mat3<double>& m) {
  return "[" + vec(m.row(0).transpose()) + ", " + vec(m.row(1).transpose()) + ", " +
         vec(m.row(2).transpose()) + "]";
}
std::string deg(double rad) {
  return format_double(core::rad_to_deg(rad));
}

constexpr std::size_t kColumns = 21;

}  // namespace

const std::vector<std::string>& scenario_names() {
  static const std::vector<std::string> names = {"li2023", "ge2017", "sine-xy", "sine-xz",
                                                 "survey"};
  return names;
}

ScenarioConfig scenario_by_name(const std::string& name, drivers::sim::Fixture fixture) {
  if (name == "li2023") return drivers::sim::scenario_li2023();
  if (name == "ge2017") return drivers::sim::scenario_ge2017();
  if (name == "sine-xy") return drivers::sim::scenario_sine_xy();
  if (name == "sine-xz") return drivers::sim::scenario_sine_xz(fixture);
  if (name == "survey") return drivers::sim::scenario_survey();
  throw std::invalid_argument("unknown scenario '" + name + "'");
}

const std::vector<std::string>& sim_csv_columns() {
  static const std::vector<std::string> columns = {
      "t_s",           "hx_nT",      "hy_nT",          "hz_nT",
      "F_nT",          "alpha_deg",  "beta_deg",       "gamma_deg",
      "theta_deg",     "t_ins_s",    "flags",          "temperature_degC",
      "hx_true_nT",    "hy_true_nT", "hz_true_nT",     "hE_true_nT",
      "hN_true_nT",    "hU_true_nT", "alpha_true_deg", "beta_true_deg",
      "gamma_true_deg"};
  return columns;
}

std::vector<std::string> sim_csv_comments(const ScenarioConfig& c, std::uint64_t seed) {
  std::vector<std::string> out;
  out.push_back(std::string("magvec ") + kVersion + " simulate: scenario " + c.name + ", seed " +
                std::to_string(seed) + ", " + std::to_string(c.num_samples) + " samples at " +
                format_double(c.rate_hz) + " Hz");
  out.push_back(
      "model: m = A Rm R_bn h_n + o + noise (docs/conventions.md: ENU, passive rotations, "
      "R_bn = Ry(gamma) Rx(beta) Rz(alpha))");
  out.push_back("noise: magnetometer " + format_double(c.mag_noise_nT) + " nT/axis SD, INS " +
                format_double(c.ins_noise_deg) + " deg/angle SD, F " + format_double(c.f_noise_nT) +
                " nT SD; INS latency " + format_double(c.ins_latency_s) + " s; INS " +
                (c.ins ? "present" : "absent (attitude columns nan)") + "; scalar reference " +
                (c.scalar_reference ? "present" : "absent"));
  out.push_back("faults: spike probability " + format_double(c.spike_probability) + " amplitude " +
                format_double(c.spike_amplitude_nT) + " nT; dropout probability " +
                format_double(c.dropout_probability));
  out.push_back("truth h_n (ENU) nT: " + vec(c.h_n_nT) +
                ", |h_n| = " + format_double(c.h_n_nT.norm()) + "; diurnal " + vec(c.diurnal_nT) +
                " nT period " + format_double(c.diurnal_period_s) + " s; step " + vec(c.step_nT) +
                " nT at t = " + format_double(c.step_time_s) + " s");
  out.push_back("truth offset temperature coefficients nT/degC: " + vec(c.offset_drift_nT_per_c) +
                ", o(T) = o + coefficients * (T - " + format_double(c.temp_ref_c) +
                " degC), T(t) = " + format_double(c.temp_start_c) + " + " +
                format_double(c.temp_rate_c_per_s) + " * (t - " + format_double(c.start_time_s) +
                " s) degC (column temperature_degC)");
  const core::SensorModel<double>& m = c.truth;
  out.push_back("truth canonical: W = A^-1 = " + mat(m.w) + ", o_nT = " + vec(m.o) +
                ", Rm quaternion (w, x, y, z) = [" + format_double(m.rm.w()) + ", " +
                format_double(m.rm.x()) + ", " + format_double(m.rm.y()) + ", " +
                format_double(m.rm.z()) + "]");
  core::LiParams<double> li;
  if (core::to_li(m, &li) == core::ConversionStatus::kOk) {
    out.push_back("truth Li 2023: Ks = " + vec(li.ks) + ", O_deg = " + vec_deg(li.o_rad) +
                  ", Kof_nT = " + vec(li.kof) +
                  ", Rm_deg (alpha_m, beta_m, gamma_m) = " + vec_deg(li.rm_rad));
  }
  const core::GeParams<double> ge = core::to_ge(m);
  out.push_back("truth Ge 2017: C = " + mat(ge.c_inv.inverse()) + ", C^-1 = " + mat(ge.c_inv) +
                ", b_nT = " + vec(ge.b) +
                " (C maps the INS-body field to the raw reading; G = C^-T C^-1)");
  core::SineParams<double> sp;
  core::Mat3<double> fixture;
  if (core::to_sine(m, &sp, &fixture) == core::ConversionStatus::kOk) {
    out.push_back("truth sine fit: k = " + vec(sp.k) + ", alpha_deg = " + deg(sp.alpha_rad) +
                  ", beta_deg = " + deg(sp.beta_rad) + ", gamma_deg = " + deg(sp.gamma_rad) +
                  ", B0_nT = " + vec(sp.b0) +
                  ", fixture rotation (K frame <- INS body) = " + mat(fixture));
  }
  if (c.pattern == drivers::sim::AttitudePattern::kTurntable) {
    out.push_back("turntable: R_bn = mount * Rz(theta), mount = " + mat(c.turntable_mount) +
                  ", step " + format_double(c.turntable_step_deg) + " deg every " +
                  std::to_string(c.samples_per_attitude) + " samples");
  }
  out.push_back(
      "columns: hx/hy/hz_nT raw reading (nan = dropout); F_nT scalar reference; "
      "alpha/beta/gamma_deg "
      "INS attitude (Li) referring to t_ins_s; flags bits 1 spike, 2 dropout, 4 field step, 8 no "
      "INS; "
      "*_true_* noise-free truth (hE/hN/hU = h_n ENU)");
  return out;
}

std::uint64_t write_sim_csv(drivers::sim::Simulator* sim, const std::string& path) {
  io::CsvWriter w(path, sim_csv_columns(), sim_csv_comments(sim->config(), sim->seed()));
  drivers::sim::SimSample s;
  std::array<double, kColumns> row{};
  static_assert(kColumns == 21);
  while (sim->next(&s)) {
    const core::LiEuler<double> ins = core::li_from_r_bn(s.r_bn_ins);  // NaN in, NaN out
    const core::LiEuler<double> tru = core::li_from_r_bn(s.r_bn_true);
    const bool has_ins = (s.flags & drivers::sim::kFlagNoIns) == 0;
    const double nan = std::nan("");
    row = {s.t_s,
           s.m_nT(0),
           s.m_nT(1),
           s.m_nT(2),
           s.f_nT,
           has_ins ? core::rad_to_deg(ins.alpha) : nan,
           has_ins ? core::rad_to_deg(ins.beta) : nan,
           has_ins ? core::rad_to_deg(ins.gamma) : nan,
           s.theta_deg,
           s.t_ins_s,
           static_cast<double>(s.flags),
           s.temperature_c,
           s.m_true_nT(0),
           s.m_true_nT(1),
           s.m_true_nT(2),
           s.h_n_true_nT(0),
           s.h_n_true_nT(1),
           s.h_n_true_nT(2),
           core::rad_to_deg(tru.alpha),
           core::rad_to_deg(tru.beta),
           core::rad_to_deg(tru.gamma)};
    w.write_row(row);
  }
  w.commit();
  return w.rows();
}

}  // namespace magvec::host::cli
