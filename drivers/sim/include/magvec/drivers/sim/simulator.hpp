// Simulated fluxgate + INS following the canonical model of docs/conventions.md:
//   m(t) = A Rm R_bn(t) h_n(t) + o(t) + noise (+ spikes, dropouts),
// with the papers' simulation setups as scenario presets:
//   Li et al. 2023 (60 random attitudes, INS angle noise), Ge et al. 2017 (1000 random directions,
//   no INS), the sine-fitting turntable paper (XY and XZ sweeps, both XZ fixtures of
//   docs/equations.md E-Sine-4), and a survey (calibration manoeuvre at 200 Hz followed by survey
//   lines with small tilt).
// Deterministic from a seed; heap-free, exception-free and noexcept so it can run in a bare-metal
// image. Each random effect has its own generator stream, so enabling one effect (e.g. spikes) does
// not change the draws of another (e.g. the magnetometer noise).
#pragma once

#include <cstdint>

#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"
#include "magvec/drivers/sim/random.hpp"

namespace magvec::drivers::sim {

// SimSample::flags bits.
inline constexpr std::uint32_t kFlagSpike = 1U << 0;      // a spike was added to m_nT
inline constexpr std::uint32_t kFlagDropout = 1U << 1;    // m_nT is all-NaN
inline constexpr std::uint32_t kFlagFieldStep = 1U << 2;  // first sample at/after the field step
inline constexpr std::uint32_t kFlagNoIns = 1U << 3;      // scenario has no INS: r_bn_ins is NaN

struct SimSample {
  double t_s;                      // magnetometer sample time
  core::Vec3<double> m_nT;         // raw reading with noise/spikes/drift; all-NaN on a dropout
  core::Vec3<double> m_true_nT;    // noise-free raw reading (includes offset drift, field changes)
  double f_nT;                     // scalar reference |h_n(t)| (NaN when the scenario has none)
  core::Vec3<double> h_n_true_nT;  // true local field (ENU) at t_s
  core::Mat3<double> r_bn_true;    // true attitude at t_s
  core::Mat3<double> r_bn_ins;     // INS-reported attitude (with INS angle noise), for time t_ins_s
  double t_ins_s;                  // time the INS attitude refers to (t_s - INS latency)
  double theta_deg;                // turntable angle (NaN for non-turntable scenarios)
  double temperature_c;            // simulated sensor temperature
  std::uint32_t flags;             // kFlag* bits
  std::uint32_t index;             // sample number from 0
};

enum class AttitudePattern : std::uint8_t {
  kRandomAttitudes,  // uniformly random rotations (Shoemake), each held samples_per_attitude
                     // samples
  kTurntable,        // R_bn = mount * Rz(theta): steps of turntable_step_deg about the vertical
  kSurvey,           // smooth calibration manoeuvre, then survey lines with alternating heading
  kRotation,         // continuous rotation: constant heading rate, sinusoidal pitch and roll
};

// XZ-sweep fixture geometry (docs/equations.md E-Sine-4).
enum class Fixture : std::uint8_t {
  kPlaneNormal,  // the turntable axis is the normal of the actual Xm-Zm sensing plane
  kHousingY,     // the turntable axis is the housing (fixture) y axis
};

struct SurveyConfig {
  double manoeuvre_s = 60.0;         // calibration manoeuvre length (a multiple of heading_turn_s)
  double heading_turn_s = 20.0;      // one full heading turn during the manoeuvre
  double manoeuvre_tilt_deg = 30.0;  // pitch/roll amplitude during the manoeuvre
  double pitch_period_s = 7.0;
  double roll_period_s = 11.0;
  double ramp_s = 5.0;         // tilt fades in/out over this time (smooth junctions)
  double line_s = 60.0;        // length of one survey line
  double turn_s = 10.0;        // 180 deg turn between lines
  double line_tilt_deg = 3.0;  // pitch/roll amplitude on the lines
  double line_pitch_period_s = 6.1;
  double line_roll_period_s = 4.3;
};

// Continuous rotation (Li Euler angles): alpha = heading_rate * t, beta = pitch_amp *
// sin(2 pi t / pitch_period), gamma = roll_amp * sin(2 pi t / roll_period + 1); peak pitch rate
// 2 pi pitch_amp / pitch_period (likewise roll).
struct RotationConfig {
  double heading_rate_deg_s = 90.0;
  double pitch_amp_deg = 30.0;
  double pitch_period_s = 2.0944;  // peak pitch rate 90 deg/s
  double roll_amp_deg = 20.0;
  double roll_period_s = 1.3963;  // peak roll rate 90 deg/s
};

struct ScenarioConfig {
  const char* name = "custom";
  // Truth.
  core::SensorModel<double> truth{};
  core::Vec3<double> h_n_nT{0.0, 0.0, 0.0};  // local field, ENU
  bool scalar_reference = true;              // f_nT = |h_n(t)| (+ f_noise); NaN otherwise
  bool ins = true;                           // INS present (r_bn_ins); NaN and kFlagNoIns otherwise
  // Timing and attitude.
  AttitudePattern pattern = AttitudePattern::kRandomAttitudes;
  double rate_hz = 10.0;
  double start_time_s = 0.0;
  std::uint32_t num_samples = 60;
  std::uint32_t samples_per_attitude =
      1;  // random attitudes and turntable steps are held this long
  // Turntable.
  double turntable_step_deg = 10.0;  // negative: the table turns the other way
  double turntable_start_deg = 0.0;
  core::Mat3<double> turntable_mount = core::Mat3<double>::Identity();  // R_bn at theta = 0
  SurveyConfig survey{};
  RotationConfig rotation{};
  // Noise.
  double mag_noise_nT = 0.0;   // white Gaussian, per axis, SD
  double ins_noise_deg = 0.0;  // white Gaussian on each Li Euler angle (alpha, beta, gamma), SD
  double f_noise_nT = 0.0;     // white Gaussian on the scalar reference, SD
  double ins_latency_s = 0.0;  // the INS attitude paired with a sample refers to t_s - latency
  // Offset drift with temperature: o(t) = o + drift * (T(t) - temp_ref_c),
  // T(t) = temp_start_c + temp_rate_c_per_s * (t - start_time_s).
  core::Vec3<double> offset_drift_nT_per_c{0.0, 0.0, 0.0};
  double temp_start_c = 20.0;
  double temp_rate_c_per_s = 0.0;
  double temp_ref_c = 20.0;
  // Field changes: h_n(t) = h_n + diurnal * sin(2 pi (t - start) / period) + (t >= step_time ? step
  // : 0).
  core::Vec3<double> diurnal_nT{0.0, 0.0, 0.0};
  double diurnal_period_s = 86400.0;
  core::Vec3<double> step_nT{0.0, 0.0, 0.0};
  double step_time_s = 1e300;
  // Faults.
  double spike_probability = 0.0;    // per sample
  double spike_amplitude_nT = 0.0;   // added on one random axis with random sign
  double dropout_probability = 0.0;  // per sample: m_nT all-NaN
};

// Paper setups (defaults of the scenario functions).
// Li et al. 2023: Ks diag(1.08, 1.02, 1.033), O = [1.7, 3.5, 2.1] deg, Kof = [4.9, 3.4, 0.7] nT,
// Rm angles [5.7, 2.1, 3.5] deg; Hg1 = [25022, -4053, 47374] read as (N, E, Down) per
// docs/equations.md E-Li-8, i.e. h_n = [-4053, 25022, -47374] ENU (|h| = 53729 nT); 60 random
// attitudes, 0.3 nT, 0.015 deg.
ScenarioConfig scenario_li2023() noexcept;
// Ge et al. 2017: F = 45306 nT (h_n at 60 deg inclination, magnetic north), 1000 random directions,
// b = [600, 700, 750] nT, C per docs/equations.md E-Ge-6 (truth W = C^-1, Rm = I), 200 nT per axis,
// no INS.
ScenarioConfig scenario_ge2017() noexcept;
// Sine-fitting paper: alpha = 1.35, beta = 32.7, gamma = 1.07 deg, k = (0.909, 1.146, 1.103),
// B0 = (143, 97.4, 123.7) nT, |B| = 50000 nT, inclination 43 deg, 36 steps of 10 deg, 5 nT noise.
// Truth W = K^-1, o = B0, Rm = I: the body frame is the fixture frame of eq. (1).
// XY sweep: the table turns about the normal of the Xm-Ym plane (fixture z, vertical).
ScenarioConfig scenario_sine_xy() noexcept;
// XZ sweep with the fixture of docs/equations.md E-Sine-4: turntable_mount maps nav Up to the plane
// normal (Xm x Zm direction flipped to point along +y) or to the housing +y axis.
ScenarioConfig scenario_sine_xz(Fixture fixture = Fixture::kPlaneNormal) noexcept;
// Survey: Li truth and field, 200 Hz, calibration manoeuvre (3 full heading turns, +-30 deg
// pitch/roll) then 4 survey lines with alternating heading N/S and a few degrees of tilt.
ScenarioConfig scenario_survey() noexcept;

// Continuous rotation (heading, pitch and roll rates up to 90 deg/s): Li truth and field, 1 kHz
// magnetometer, 0.3 nT and 0.015 deg noise, 60 s.
ScenarioConfig scenario_rotation() noexcept;

// Total length of the survey pattern (manoeuvre + lines + turns) for `lines` lines.
double survey_duration_s(const SurveyConfig& s, std::uint32_t lines) noexcept;

// Uniformly distributed random rotation number `index` of the stream `seed` (random access).
core::Mat3<double> random_rotation(std::uint64_t seed, std::uint64_t index) noexcept;

class Simulator {
 public:
  explicit Simulator(const ScenarioConfig& config, std::uint64_t seed) noexcept;

  // Produces the next magnetometer sample; false when the scenario is finished (*out untouched).
  bool next(SimSample* out) noexcept;

  // Restarts the scenario from its first sample with the same seed.
  void reset() noexcept;

  // INS attitude at an arbitrary time (for an INS device running at its own rate): the true
  // attitude at t_s - ins_latency_s with fresh INS angle noise (drawn from a stream of its own, so
  // calls do not change what next() produces). NaN when the scenario has no INS.
  core::Mat3<double> ins_attitude_at(double t_s) noexcept;

  // Deterministic truth at an arbitrary time (no noise).
  core::Mat3<double> true_attitude_at(double t_s, double* theta_deg = nullptr) const noexcept;
  core::Vec3<double> true_field_at(double t_s) const noexcept;
  core::Vec3<double> true_offset_at(double t_s) const noexcept;
  double temperature_at(double t_s) const noexcept;

  const ScenarioConfig& config() const noexcept { return config_; }
  std::uint64_t seed() const noexcept { return seed_; }
  std::uint32_t samples_emitted() const noexcept { return index_; }

 private:
  core::Mat3<double> add_ins_noise(const core::Mat3<double>& r, Gaussian* g) const noexcept;

  ScenarioConfig config_;
  std::uint64_t seed_;
  std::uint64_t attitude_seed_;
  core::Mat3<double> a_rm_;  // A Rm, precomputed
  Gaussian mag_noise_;
  Gaussian ins_noise_;
  Gaussian ins_external_noise_;
  Gaussian f_noise_;
  Xoshiro256 faults_;
  std::uint32_t index_ = 0;
  bool step_seen_ = false;
};

}  // namespace magvec::drivers::sim
