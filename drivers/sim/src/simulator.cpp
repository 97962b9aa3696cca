// Simulated fluxgate + INS (see simulator.hpp). Scenario presets reproduce the simulation setups of
// Li et al. 2023 (sec. 4), Ge et al. 2017 (sec. 4) and the sine-fitting paper (sec. 3), with the
// corrections of docs/equations.md (E-Li-8 field reading, E-Ge-6 C matrix, E-Sine-4 XZ fixtures).
#include "magvec/drivers/sim/simulator.hpp"

#include <cmath>
#include <limits>

#include "magvec/core/frames.hpp"

namespace magvec::drivers::sim {
namespace {

using core::Mat3;
using core::Vec3;

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kTwoPi = 2.0 * core::kPi<double>;

double deg(double d) noexcept {
  return core::deg_to_rad(d);
}

// Stream identifiers: each random effect draws from its own generator.
constexpr std::uint64_t kStreamAttitude = 0xA77171DE00000001ULL;
constexpr std::uint64_t kStreamMagNoise = 0x4D41474E00000002ULL;
constexpr std::uint64_t kStreamInsNoise = 0x494E534E00000003ULL;
constexpr std::uint64_t kStreamInsExternal = 0x494E534500000004ULL;
constexpr std::uint64_t kStreamFNoise = 0x464E4F4900000005ULL;
constexpr std::uint64_t kStreamFaults = 0x4641554C00000006ULL;

std::uint64_t stream_seed(std::uint64_t seed, std::uint64_t stream) noexcept {
  SplitMix64 sm(seed ^ stream);
  return sm.next();
}

// 0 -> 0, 1 -> 1, zero slope at both ends.
double smoothstep(double x) noexcept {
  if (x <= 0.0) return 0.0;
  if (x >= 1.0) return 1.0;
  return x * x * (3.0 - 2.0 * x);
}

// Index of the held step that contains time t (tolerant to the rounding of i / rate).
std::int64_t step_index(double t_rel, double rate_hz, std::uint32_t hold) noexcept {
  const double h = hold == 0 ? 1.0 : static_cast<double>(hold);
  return static_cast<std::int64_t>(std::floor(t_rel * rate_hz / h + 1e-6));
}

Mat3<double> nan_matrix() noexcept {
  return Mat3<double>::Constant(kNaN);
}

core::SensorModel<double> li_truth() noexcept {
  core::LiParams<double> p;
  p.ks = Vec3<double>(1.08, 1.02, 1.033);
  p.o_rad = Vec3<double>(deg(1.7), deg(3.5), deg(2.1));
  p.kof = Vec3<double>(4.9, 3.4, 0.7);
  p.rm_rad = Vec3<double>(deg(5.7), deg(2.1), deg(3.5));
  return core::from_li(p);
}

// Li's Hg1 = [25022, -4053, 47374] read as (N, E, Down) (docs/equations.md E-Li-8) -> ENU.
Vec3<double> li_field() noexcept {
  return Vec3<double>(-4053.0, 25022.0, -47374.0);
}

core::SineParams<double> sine_truth_params() noexcept {
  core::SineParams<double> p;
  p.k = Vec3<double>(0.909, 1.146, 1.103);
  p.alpha_rad = deg(1.35);
  p.beta_rad = deg(32.7);
  p.gamma_rad = deg(1.07);
  p.b0 = Vec3<double>(143.0, 97.4, 123.7);
  return p;
}

ScenarioConfig sine_common() noexcept {
  ScenarioConfig c;
  c.truth = core::from_sine(sine_truth_params());
  const double b = 50000.0, incl = deg(43.0);
  c.h_n_nT = Vec3<double>(0.0, b * std::cos(incl), -b * std::sin(incl));
  c.scalar_reference = true;
  c.ins = false;
  c.pattern = AttitudePattern::kTurntable;
  c.rate_hz = 1.0;
  c.num_samples = 36;
  c.samples_per_attitude = 1;
  c.turntable_step_deg = 10.0;
  c.mag_noise_nT = 5.0;
  return c;
}

}  // namespace

ScenarioConfig scenario_li2023() noexcept {
  ScenarioConfig c;
  c.name = "li2023";
  c.truth = li_truth();
  c.h_n_nT = li_field();
  c.pattern = AttitudePattern::kRandomAttitudes;
  c.rate_hz = 1.0;
  c.num_samples = 60;
  c.samples_per_attitude = 1;
  c.mag_noise_nT = 0.3;
  c.ins_noise_deg = 0.015;
  return c;
}

ScenarioConfig scenario_ge2017() noexcept {
  ScenarioConfig c;
  c.name = "ge2017";
  Mat3<double> cm;
  cm << 1.362, 0.002, 0.001, 0.001, 0.861, 0.002, 0.002, 0.001, 1.046;
  core::GeParams<double> p;
  p.c_inv = cm.inverse();
  p.b = Vec3<double>(600.0, 700.0, 750.0);
  c.truth = core::from_ge(p);
  const double f = 45306.0, incl = deg(60.0);
  c.h_n_nT = Vec3<double>(0.0, f * std::cos(incl), -f * std::sin(incl));
  c.ins = false;
  c.pattern = AttitudePattern::kRandomAttitudes;
  c.rate_hz = 1.0;
  c.num_samples = 1000;
  c.mag_noise_nT = 200.0;
  return c;
}

ScenarioConfig scenario_sine_xy() noexcept {
  ScenarioConfig c = sine_common();
  c.name = "sine-xy";
  c.turntable_mount = Mat3<double>::Identity();
  return c;
}

ScenarioConfig scenario_sine_xz(Fixture fixture) noexcept {
  ScenarioConfig c = sine_common();
  const Mat3<double> k = core::sine_k(sine_truth_params());
  // rot_x(90 deg) maps e_z (nav Up at theta = 0) to body +y.
  const Mat3<double> housing_y = core::rot_x(deg(90.0));
  if (fixture == Fixture::kHousingY) {
    c.name = "sine-xz-housing-y";
    c.turntable_mount = housing_y;
  } else {
    c.name = "sine-xz-plane-normal";
    // Sensing directions are the rows of K; the plane normal Zm x Xm points near +y.
    const Vec3<double> x_dir = k.row(0).transpose().normalized();
    const Vec3<double> z_dir = k.row(2).transpose().normalized();
    const Vec3<double> n = z_dir.cross(x_dir).normalized();
    const Mat3<double> align =
        Eigen::Quaternion<double>::FromTwoVectors(Vec3<double>::UnitY(), n).toRotationMatrix();
    c.turntable_mount = align * housing_y;  // R_bn e_Up = n for every theta
  }
  return c;
}

ScenarioConfig scenario_survey() noexcept {
  ScenarioConfig c;
  c.name = "survey";
  c.truth = li_truth();
  c.h_n_nT = li_field();
  c.pattern = AttitudePattern::kSurvey;
  c.rate_hz = 200.0;
  c.num_samples =
      static_cast<std::uint32_t>(std::lround(survey_duration_s(c.survey, 4) * c.rate_hz));
  c.mag_noise_nT = 0.3;
  c.ins_noise_deg = 0.015;
  return c;
}

ScenarioConfig scenario_rotation() noexcept {
  ScenarioConfig c;
  c.name = "rotation";
  c.truth = li_truth();
  c.h_n_nT = li_field();
  c.pattern = AttitudePattern::kRotation;
  c.rate_hz = 1000.0;
  c.num_samples = 60000;
  c.mag_noise_nT = 0.3;
  c.ins_noise_deg = 0.015;
  return c;
}

double survey_duration_s(const SurveyConfig& s, std::uint32_t lines) noexcept {
  if (lines == 0) return s.manoeuvre_s;
  return s.manoeuvre_s + static_cast<double>(lines) * s.line_s +
         static_cast<double>(lines - 1) * s.turn_s;
}

Mat3<double> random_rotation(std::uint64_t seed, std::uint64_t index) noexcept {
  // Shoemake's uniform random unit quaternion from three uniforms.
  SplitMix64 sm(seed ^ (index * 0xD1B54A32D192ED03ULL));
  (void)sm.next();
  const double u1 = sm.uniform(), u2 = sm.uniform(), u3 = sm.uniform();
  const double a = std::sqrt(1.0 - u1), b = std::sqrt(u1);
  core::Quat<double> q(b * std::cos(kTwoPi * u3), a * std::sin(kTwoPi * u2),
                       a * std::cos(kTwoPi * u2), b * std::sin(kTwoPi * u3));
  q.normalize();
  return q.toRotationMatrix();
}

Simulator::Simulator(const ScenarioConfig& config, std::uint64_t seed) noexcept
    : config_(config),
      seed_(seed),
      attitude_seed_(stream_seed(seed, kStreamAttitude)),
      a_rm_(config.truth.a() * config.truth.rm_matrix()),
      mag_noise_(stream_seed(seed, kStreamMagNoise)),
      ins_noise_(stream_seed(seed, kStreamInsNoise)),
      ins_external_noise_(stream_seed(seed, kStreamInsExternal)),
      f_noise_(stream_seed(seed, kStreamFNoise)),
      faults_(stream_seed(seed, kStreamFaults)) {}

void Simulator::reset() noexcept {
  *this = Simulator(config_, seed_);
}

double Simulator::temperature_at(double t_s) const noexcept {
  return config_.temp_start_c + config_.temp_rate_c_per_s * (t_s - config_.start_time_s);
}

Vec3<double> Simulator::true_offset_at(double t_s) const noexcept {
  return config_.truth.o +
         config_.offset_drift_nT_per_c * (temperature_at(t_s) - config_.temp_ref_c);
}

Vec3<double> Simulator::true_field_at(double t_s) const noexcept {
  Vec3<double> h = config_.h_n_nT;
  if (config_.diurnal_period_s > 0.0) {
    h += config_.diurnal_nT *
         std::sin(kTwoPi * (t_s - config_.start_time_s) / config_.diurnal_period_s);
  }
  if (t_s >= config_.step_time_s) h += config_.step_nT;
  return h;
}

Mat3<double> Simulator::true_attitude_at(double t_s, double* theta_deg) const noexcept {
  const double t_rel = t_s - config_.start_time_s;
  if (theta_deg != nullptr) *theta_deg = kNaN;
  switch (config_.pattern) {
    case AttitudePattern::kRandomAttitudes: {
      const std::int64_t k = step_index(t_rel, config_.rate_hz, config_.samples_per_attitude);
      return random_rotation(attitude_seed_, static_cast<std::uint64_t>(k));
    }
    case AttitudePattern::kTurntable: {
      const std::int64_t k = step_index(t_rel, config_.rate_hz, config_.samples_per_attitude);
      const double theta =
          config_.turntable_start_deg + static_cast<double>(k) * config_.turntable_step_deg;
      if (theta_deg != nullptr) *theta_deg = theta;
      return config_.turntable_mount * core::rot_z(deg(theta));
    }
    case AttitudePattern::kRotation: {
      const RotationConfig& r = config_.rotation;
      core::LiEuler<double> e;
      e.alpha = deg(r.heading_rate_deg_s) * t_rel;
      e.beta = deg(r.pitch_amp_deg) * std::sin(kTwoPi * t_rel / r.pitch_period_s);
      e.gamma = deg(r.roll_amp_deg) * std::sin(kTwoPi * t_rel / r.roll_period_s + 1.0);
      return core::r_bn_from_li(e);
    }
    case AttitudePattern::kSurvey:
    default: {
      const SurveyConfig& s = config_.survey;
      core::LiEuler<double> e;
      if (t_rel < s.manoeuvre_s) {
        // Full heading turns with +-tilt pitch/roll at incommensurate periods, faded in and out.
        const double w =
            smoothstep(t_rel / s.ramp_s) * smoothstep((s.manoeuvre_s - t_rel) / s.ramp_s);
        const double tilt = deg(s.manoeuvre_tilt_deg) * w;
        e.alpha = kTwoPi * t_rel / s.heading_turn_s;
        e.beta = tilt * std::sin(kTwoPi * t_rel / s.pitch_period_s);
        e.gamma = tilt * std::sin(kTwoPi * t_rel / s.roll_period_s);
      } else {
        // Racetrack: lines alternate North/South headings joined by smooth 180 deg turns.
        const double tau = t_rel - s.manoeuvre_s;
        const double period = s.line_s + s.turn_s;
        const double k = std::floor(tau / period);
        const double in_period = tau - k * period;
        const double turn = s.turn_s > 0.0 ? smoothstep((in_period - s.line_s) / s.turn_s) : 0.0;
        e.alpha = core::kPi<double> * (k + turn);
        const double tilt = deg(s.line_tilt_deg) * smoothstep(tau / s.ramp_s);
        e.beta = tilt * std::sin(kTwoPi * tau / s.line_pitch_period_s);
        e.gamma = tilt * std::sin(kTwoPi * tau / s.line_roll_period_s + 1.0);
      }
      return core::r_bn_from_li(e);
    }
  }
}

Mat3<double> Simulator::add_ins_noise(const Mat3<double>& r, Gaussian* g) const noexcept {
  // Noise on each of the INS's Euler angles (Li convention), as in Li et al. 2023 sec. 4.
  const double s = deg(config_.ins_noise_deg);
  const double n1 = g->next(), n2 = g->next(), n3 = g->next();  // always drawn: fixed stream use
  if (s == 0.0) return r;
  core::LiEuler<double> e = core::li_from_r_bn(r);
  e.alpha += s * n1;
  e.beta += s * n2;
  e.gamma += s * n3;
  return core::r_bn_from_li(e);
}

Mat3<double> Simulator::ins_attitude_at(double t_s) noexcept {
  if (!config_.ins) return nan_matrix();
  return add_ins_noise(true_attitude_at(t_s - config_.ins_latency_s), &ins_external_noise_);
}

bool Simulator::next(SimSample* out) noexcept {
  if (index_ >= config_.num_samples || !(config_.rate_hz > 0.0)) return false;
  SimSample s;
  s.index = index_;
  s.t_s = config_.start_time_s + static_cast<double>(index_) / config_.rate_hz;
  s.flags = 0;
  s.r_bn_true = true_attitude_at(s.t_s, &s.theta_deg);
  s.h_n_true_nT = true_field_at(s.t_s);
  s.temperature_c = temperature_at(s.t_s);
  s.m_true_nT = a_rm_ * (s.r_bn_true * s.h_n_true_nT) + true_offset_at(s.t_s);

  // Every stream is advanced by a fixed amount per sample whatever the configuration.
  // Sequenced draws: the evaluation order of function arguments is unspecified (GCC evaluates
  // Vec3(next(), next(), next()) right to left on x86-64 but not on arm-none-eabi, which swapped
  // the x and z noise between the firmware image and its host twin). z, y, x keeps the stream
  // assignment the host always had.
  const double noise_z = mag_noise_.next();
  const double noise_y = mag_noise_.next();
  const double noise_x = mag_noise_.next();
  const Vec3<double> noise(noise_x, noise_y, noise_z);
  const double u_spike = faults_.uniform(), u_drop = faults_.uniform();
  const double u_axis = faults_.uniform(), u_sign = faults_.uniform();
  const double f_noise = f_noise_.next();

  s.m_nT = s.m_true_nT + config_.mag_noise_nT * noise;
  if (u_spike < config_.spike_probability) {
    const int axis = u_axis < 1.0 / 3.0 ? 0 : (u_axis < 2.0 / 3.0 ? 1 : 2);
    s.m_nT(axis) += (u_sign < 0.5 ? -1.0 : 1.0) * config_.spike_amplitude_nT;
    s.flags |= kFlagSpike;
  }
  if (u_drop < config_.dropout_probability) {
    s.m_nT = Vec3<double>::Constant(kNaN);
    s.flags |= kFlagDropout;
  }
  s.f_nT = config_.scalar_reference ? s.h_n_true_nT.norm() + config_.f_noise_nT * f_noise : kNaN;

  if (config_.ins) {
    s.t_ins_s = s.t_s - config_.ins_latency_s;
    s.r_bn_ins = add_ins_noise(true_attitude_at(s.t_ins_s), &ins_noise_);
  } else {
    s.t_ins_s = kNaN;
    s.r_bn_ins = nan_matrix();
    s.flags |= kFlagNoIns;
  }
  if (!step_seen_ && s.t_s >= config_.step_time_s) {
    step_seen_ = true;
    s.flags |= kFlagFieldStep;
  }
  *out = s;
  ++index_;
  return true;
}

}  // namespace magvec::drivers::sim
