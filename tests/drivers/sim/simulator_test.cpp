// Tests of the simulated fluxgate + INS (drivers/sim/simulator.hpp): exact model inversion, paper
// setups, determinism, fault rates, fixtures of docs/equations.md E-Sine-4, and no heap use per
// sample.
#include "magvec/drivers/sim/simulator.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <vector>

#include "magvec/core/compensator.hpp"
#include "magvec/core/frames.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::drivers::sim {
namespace {

using core::Mat3;
using core::Vec3;

constexpr double kDeg = core::kPi<double> / 180.0;

std::vector<ScenarioConfig> all_scenarios() {
  return {scenario_li2023(),
          scenario_ge2017(),
          scenario_sine_xy(),
          scenario_sine_xz(Fixture::kPlaneNormal),
          scenario_sine_xz(Fixture::kHousingY),
          scenario_survey()};
}

// Bitwise equality (NaN == NaN) of two samples.
bool same_bits(const SimSample& a, const SimSample& b) {
  auto eq = [](const auto& x, const auto& y) { return std::memcmp(&x, &y, sizeof(x)) == 0; };
  return eq(a.t_s, b.t_s) && eq(a.m_nT, b.m_nT) && eq(a.m_true_nT, b.m_true_nT) &&
         eq(a.f_nT, b.f_nT) && eq(a.h_n_true_nT, b.h_n_true_nT) && eq(a.r_bn_true, b.r_bn_true) &&
         eq(a.r_bn_ins, b.r_bn_ins) && eq(a.t_ins_s, b.t_ins_s) && eq(a.theta_deg, b.theta_deg) &&
         a.flags == b.flags && a.index == b.index;
}

TEST(Simulator, CompensatorInvertsTheModelExactlyOnNoiseFreeDataForEveryScenario) {
  for (const ScenarioConfig& cfg : all_scenarios()) {
    SCOPED_TRACE(cfg.name);
    Simulator sim(cfg, 11);
    const core::Compensator<double> comp(cfg.truth);
    SimSample s;
    std::uint32_t n = 0;
    while (sim.next(&s)) {
      core::Compensated<double> c;
      ASSERT_TRUE(comp.compensate(s.m_true_nT, &c));
      const Vec3<double> h_n = core::Compensator<double>::to_nav(c.h_b, s.r_bn_true);
      ASSERT_LT((h_n - s.h_n_true_nT).norm() / s.h_n_true_nT.norm(), 1e-9) << "sample " << n;
      ASSERT_NEAR(c.intensity, s.h_n_true_nT.norm(), 1e-9 * s.h_n_true_nT.norm());
      if (cfg.scalar_reference) {
        ASSERT_NEAR(s.f_nT, s.h_n_true_nT.norm(), 1e-9 * s.f_nT);
      }
      ++n;
    }
    EXPECT_EQ(n, cfg.num_samples);
    EXPECT_FALSE(sim.next(&s));
  }
}

TEST(Simulator, ZeroNoiseGivesTheTrueReading) {
  ScenarioConfig cfg = scenario_li2023();
  cfg.mag_noise_nT = 0.0;
  cfg.ins_noise_deg = 0.0;
  Simulator sim(cfg, 3);
  SimSample s;
  while (sim.next(&s)) {
    EXPECT_EQ(s.m_nT, s.m_true_nT);
    EXPECT_EQ(s.r_bn_ins, s.r_bn_true);
    EXPECT_EQ(s.flags, 0U);
  }
}

TEST(Simulator, ScenarioTruthsAreThePapersSetups) {
  core::LiParams<double> li;
  ASSERT_EQ(core::to_li(scenario_li2023().truth, &li), core::ConversionStatus::kOk);
  EXPECT_LT((li.ks - Vec3<double>(1.08, 1.02, 1.033)).norm(), 1e-12);
  EXPECT_LT((li.o_rad / kDeg - Vec3<double>(1.7, 3.5, 2.1)).norm(), 1e-10);
  EXPECT_LT((li.kof - Vec3<double>(4.9, 3.4, 0.7)).norm(), 1e-12);
  EXPECT_LT((li.rm_rad / kDeg - Vec3<double>(5.7, 2.1, 3.5)).norm(), 1e-10);
  EXPECT_NEAR(scenario_li2023().h_n_nT.norm(), 53729.2, 0.1);
  EXPECT_EQ(scenario_li2023().h_n_nT, Vec3<double>(-4053, 25022, -47374));
  EXPECT_EQ(scenario_li2023().num_samples, 60U);

  const ScenarioConfig ge = scenario_ge2017();
  Mat3<double> c;
  c << 1.362, 0.002, 0.001, 0.001, 0.861, 0.002, 0.002, 0.001, 1.046;
  EXPECT_LT((core::to_ge(ge.truth).c_inv.inverse() - c).norm(), 1e-12);
  EXPECT_EQ(ge.truth.o, Vec3<double>(600, 700, 750));
  EXPECT_NEAR(ge.h_n_nT.norm(), 45306.0, 1e-9);
  EXPECT_EQ(ge.num_samples, 1000U);
  EXPECT_FALSE(ge.ins);
  EXPECT_EQ(ge.mag_noise_nT, 200.0);

  core::SineParams<double> sp;
  Mat3<double> fixture;
  ASSERT_EQ(core::to_sine(scenario_sine_xy().truth, &sp, &fixture), core::ConversionStatus::kOk);
  EXPECT_LT((sp.k - Vec3<double>(0.909, 1.146, 1.103)).norm(), 1e-12);
  EXPECT_NEAR(sp.alpha_rad / kDeg, 1.35, 1e-10);
  EXPECT_NEAR(sp.beta_rad / kDeg, 32.7, 1e-10);
  EXPECT_NEAR(sp.gamma_rad / kDeg, 1.07, 1e-10);
  EXPECT_LT((sp.b0 - Vec3<double>(143, 97.4, 123.7)).norm(), 1e-12);
  EXPECT_LT((fixture - Mat3<double>::Identity()).norm(), 1e-12);
  EXPECT_NEAR(scenario_sine_xy().h_n_nT.norm(), 50000.0, 1e-9);
  EXPECT_NEAR(std::asin(-scenario_sine_xy().h_n_nT.z() / 50000.0) / kDeg, 43.0, 1e-10);
}

TEST(Simulator, SameSeedSameStreamDifferentSeedDifferentStream) {
  for (const ScenarioConfig& base : all_scenarios()) {
    SCOPED_TRACE(base.name);
    ScenarioConfig cfg = base;
    cfg.spike_probability = 0.05;
    cfg.spike_amplitude_nT = 500;
    cfg.dropout_probability = 0.05;
    cfg.ins_noise_deg = 0.015;
    cfg.num_samples = std::min<std::uint32_t>(cfg.num_samples, 2000);
    Simulator a(cfg, 99), b(cfg, 99), c(cfg, 100);
    SimSample sa, sb, sc;
    int differing = 0;
    while (a.next(&sa)) {
      ASSERT_TRUE(b.next(&sb));
      ASSERT_TRUE(c.next(&sc));
      ASSERT_TRUE(same_bits(sa, sb)) << "sample " << sa.index;
      differing += same_bits(sa, sc) ? 0 : 1;
    }
    EXPECT_FALSE(b.next(&sb));
    EXPECT_EQ(differing, static_cast<int>(cfg.num_samples));  // noise makes every sample differ
    // reset() replays the identical stream.
    a.reset();
    Simulator fresh(cfg, 99);
    for (int i = 0; i < 20 && fresh.next(&sb); ++i) {
      ASSERT_TRUE(a.next(&sa));
      EXPECT_TRUE(same_bits(sa, sb));
    }
  }
}

TEST(Simulator, ExternalInsQueriesDoNotChangeTheSampleStream) {
  const ScenarioConfig cfg = scenario_survey();
  Simulator a(cfg, 5), b(cfg, 5);
  SimSample sa, sb;
  for (int i = 0; i < 500; ++i) {
    ASSERT_TRUE(a.next(&sa));
    ASSERT_TRUE(b.next(&sb));
    const Mat3<double> r = b.ins_attitude_at(sb.t_s + 0.0025);
    EXPECT_LT(core::rotation_angle_between(r, b.true_attitude_at(sb.t_s + 0.0025)), 0.1 * kDeg);
    EXPECT_TRUE(same_bits(sa, sb));
  }
}

TEST(Simulator, MagnetometerNoiseHasConfiguredStandardDeviation) {
  ScenarioConfig cfg = scenario_ge2017();
  cfg.num_samples = 20000;
  Simulator sim(cfg, 1);
  SimSample s;
  double sum = 0, sum2 = 0;
  int n = 0;
  while (sim.next(&s)) {
    for (int k = 0; k < 3; ++k) {
      const double e = s.m_nT(k) - s.m_true_nT(k);
      sum += e;
      sum2 += e * e;
      ++n;
    }
  }
  const double mean = sum / n, sd = std::sqrt(sum2 / n - mean * mean);
  EXPECT_NEAR(mean, 0.0, 5 * 200 / std::sqrt(n));
  EXPECT_NEAR(sd, 200.0, 5 * 200 / std::sqrt(2.0 * n));
}

TEST(Simulator, InsAngleNoiseHasConfiguredStandardDeviationPerAngle) {
  ScenarioConfig cfg = scenario_li2023();
  cfg.num_samples = 20000;
  cfg.ins_noise_deg = 0.5;
  Simulator sim(cfg, 8);
  SimSample s;
  double sum2[3] = {0, 0, 0};
  int n = 0;
  while (sim.next(&s)) {
    const core::LiEuler<double> t = core::li_from_r_bn(s.r_bn_true);
    if (std::abs(t.beta) > 80 * kDeg) continue;  // near gimbal lock alpha/gamma are ill-defined
    const core::LiEuler<double> i = core::li_from_r_bn(s.r_bn_ins);
    const double d[3] = {core::wrap_pi(i.alpha - t.alpha), i.beta - t.beta,
                         core::wrap_pi(i.gamma - t.gamma)};
    for (int k = 0; k < 3; ++k)
      sum2[k] += d[k] * d[k];
    ++n;
  }
  ASSERT_GT(n, 15000);
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(std::sqrt(sum2[k] / n) / kDeg, 0.5, 5 * 0.5 / std::sqrt(2.0 * n)) << "angle " << k;
  }
}

TEST(Simulator, SpikesAndDropoutsAppearAtTheirConfiguredRates) {
  ScenarioConfig cfg = scenario_li2023();
  cfg.num_samples = 100000;
  cfg.mag_noise_nT = 0.0;
  cfg.spike_probability = 0.02;
  cfg.spike_amplitude_nT = 750.0;
  cfg.dropout_probability = 0.01;
  Simulator sim(cfg, 77);
  SimSample s;
  int spikes = 0, dropouts = 0, axis_count[3] = {0, 0, 0}, positive = 0;
  while (sim.next(&s)) {
    ASSERT_TRUE(s.m_true_nT.allFinite());
    if (s.flags & kFlagDropout) {
      ++dropouts;
      EXPECT_TRUE(s.m_nT.array().isNaN().all());
    } else {
      ASSERT_TRUE(s.m_nT.allFinite());
    }
    if (s.flags & kFlagSpike) {
      ++spikes;
      if (!(s.flags & kFlagDropout)) {
        const Vec3<double> d = s.m_nT - s.m_true_nT;
        int axis = -1;
        for (int k = 0; k < 3; ++k) {
          if (d(k) != 0.0) {
            EXPECT_EQ(axis, -1) << "spike on more than one axis";
            axis = k;
            EXPECT_NEAR(std::abs(d(k)), 750.0, 1e-9);
            positive += d(k) > 0 ? 1 : 0;
          }
        }
        ASSERT_GE(axis, 0);
        ++axis_count[axis];
      }
    } else if (!(s.flags & kFlagDropout)) {
      EXPECT_EQ(s.m_nT, s.m_true_nT);
    }
  }
  // Binomial 5-sigma bounds.
  const double n = cfg.num_samples;
  EXPECT_NEAR(spikes, 0.02 * n, 5 * std::sqrt(n * 0.02 * 0.98));
  EXPECT_NEAR(dropouts, 0.01 * n, 5 * std::sqrt(n * 0.01 * 0.99));
  const int spikes_kept = axis_count[0] + axis_count[1] + axis_count[2];
  for (int k = 0; k < 3; ++k) {
    EXPECT_NEAR(axis_count[k], spikes_kept / 3.0, 5 * std::sqrt(spikes_kept * 2.0 / 9.0));
  }
  EXPECT_NEAR(positive, spikes_kept / 2.0, 5 * std::sqrt(spikes_kept / 4.0));
}

TEST(Simulator, EnablingFaultsDoesNotChangeTheNoiseDraws) {
  ScenarioConfig clean = scenario_li2023();
  ScenarioConfig faulty = clean;
  faulty.spike_probability = 0.3;
  faulty.spike_amplitude_nT = 100;
  Simulator a(clean, 4), b(faulty, 4);
  SimSample sa, sb;
  while (a.next(&sa)) {
    ASSERT_TRUE(b.next(&sb));
    if (!(sb.flags & kFlagSpike)) {
      EXPECT_EQ(sa.m_nT, sb.m_nT);
    }
  }
}

TEST(Simulator, OffsetDriftFollowsTemperature) {
  ScenarioConfig cfg = scenario_li2023();
  cfg.mag_noise_nT = 0;
  cfg.temp_start_c = 10.0;
  cfg.temp_ref_c = 20.0;
  cfg.temp_rate_c_per_s = 0.5;  // 10 C .. 39.5 C over 60 s
  cfg.offset_drift_nT_per_c = Vec3<double>(0.5, -1.0, 2.0);
  Simulator sim(cfg, 2);
  const core::SensorModel<double>& t = cfg.truth;
  SimSample s;
  while (sim.next(&s)) {
    const double temp = 10.0 + 0.5 * s.t_s;
    EXPECT_NEAR(s.temperature_c, temp, 1e-12);
    const Vec3<double> o = t.o + cfg.offset_drift_nT_per_c * (temp - 20.0);
    EXPECT_LT((s.m_true_nT - t.predict_raw(s.r_bn_true, s.h_n_true_nT) - (o - t.o)).norm(), 1e-8);
  }
}

TEST(Simulator, FieldChangesDiurnalAndStep) {
  ScenarioConfig cfg = scenario_li2023();
  cfg.num_samples = 100;
  cfg.diurnal_nT = Vec3<double>(0, 10, -20);
  cfg.diurnal_period_s = 40.0;
  cfg.step_nT = Vec3<double>(5, 0, 0);
  cfg.step_time_s = 50.0;
  Simulator sim(cfg, 2);
  SimSample s;
  int step_flags = 0;
  while (sim.next(&s)) {
    Vec3<double> h = cfg.h_n_nT + cfg.diurnal_nT * std::sin(2 * core::kPi<double> * s.t_s / 40.0);
    if (s.t_s >= 50.0) h += cfg.step_nT;
    EXPECT_LT((s.h_n_true_nT - h).norm(), 1e-9);
    EXPECT_NEAR(s.f_nT, h.norm(), 1e-9);
    if (s.flags & kFlagFieldStep) {
      ++step_flags;
      EXPECT_EQ(s.t_s, 50.0);
    }
    // The reading follows the field.
    EXPECT_LT((s.m_true_nT - cfg.truth.predict_raw(s.r_bn_true, h)).norm(), 1e-8);
  }
  EXPECT_EQ(step_flags, 1);
}

TEST(Simulator, InsLatencyPairsSamplesWithOlderAttitudes) {
  ScenarioConfig cfg = scenario_survey();
  cfg.ins_noise_deg = 0;
  cfg.ins_latency_s = 0.05;
  cfg.num_samples = 2000;
  Simulator sim(cfg, 6);
  SimSample s;
  double max_diff = 0;
  while (sim.next(&s)) {
    EXPECT_DOUBLE_EQ(s.t_ins_s, s.t_s - 0.05);
    EXPECT_LT((s.r_bn_ins - sim.true_attitude_at(s.t_s - 0.05)).norm(), 1e-12);
    max_diff = std::max(max_diff, core::rotation_angle_between(s.r_bn_ins, s.r_bn_true));
  }
  EXPECT_GT(max_diff, 0.5 * kDeg);  // the manoeuvre turns ~18 deg/s: 50 ms is visible
  EXPECT_LT((sim.ins_attitude_at(3.0) - sim.true_attitude_at(2.95)).norm(), 1e-12);
}

TEST(Simulator, GeScenarioHasNoInsButAScalarReference) {
  Simulator sim(scenario_ge2017(), 1);
  SimSample s;
  ASSERT_TRUE(sim.next(&s));
  EXPECT_TRUE(s.flags & kFlagNoIns);
  EXPECT_TRUE(s.r_bn_ins.array().isNaN().all());
  EXPECT_TRUE(std::isnan(s.t_ins_s));
  EXPECT_TRUE(std::isnan(s.theta_deg));
  EXPECT_NEAR(s.f_nT, 45306.0, 1e-9);
  EXPECT_TRUE(sim.ins_attitude_at(0.0).array().isNaN().all());
}

TEST(Simulator, RandomAttitudesAreUniformAndHeld) {
  ScenarioConfig cfg = scenario_li2023();
  cfg.num_samples = 30000;
  cfg.samples_per_attitude = 3;
  Simulator sim(cfg, 12);
  SimSample s, prev;
  Mat3<double> sum = Mat3<double>::Zero();
  Vec3<double> dir_sum = Vec3<double>::Zero();
  int n = 0;
  while (sim.next(&s)) {
    EXPECT_LT((s.r_bn_true * s.r_bn_true.transpose() - Mat3<double>::Identity()).norm(), 1e-12);
    EXPECT_NEAR(s.r_bn_true.determinant(), 1.0, 1e-12);
    if (s.index % 3 != 0) {
      EXPECT_EQ(s.r_bn_true, prev.r_bn_true);  // held
    } else {
      if (s.index > 0) {
        EXPECT_NE(s.r_bn_true, prev.r_bn_true);
      }
      sum += s.r_bn_true;
      dir_sum += s.r_bn_true * s.h_n_true_nT.normalized();
      ++n;
    }
    prev = s;
  }
  // Haar measure: E[R] = 0, each entry has variance 1/3; the field direction is uniform on the
  // sphere.
  const double bound = 5 * std::sqrt(1.0 / 3.0 / n);
  EXPECT_LT(sum.cwiseAbs().maxCoeff() / n, bound);
  EXPECT_LT(dir_sum.cwiseAbs().maxCoeff() / n, bound);
}

TEST(Simulator, TurntableSweepsAndFixtures) {
  const core::SineParams<double> p = [] {
    core::SineParams<double> q;
    core::to_sine(scenario_sine_xy().truth, &q);
    return q;
  }();
  const Mat3<double> k = core::sine_k(p);
  const double b_up = scenario_sine_xy().h_n_nT.z();  // -34100 nT
  struct Case {
    ScenarioConfig cfg;
    double mean_z_minus_b0z;  // expected mean of the Z reading over the sweep, minus B0z
  };
  const double kz = p.k(2), sb = std::sin(p.beta_rad), sg = std::sin(p.gamma_rad),
               cg = std::cos(p.gamma_rad);
  const Case cases[] = {
      {scenario_sine_xy(), kz * cg * b_up},  // docs/equations.md E-Sine-1: about -37 uT
      {scenario_sine_xz(Fixture::kPlaneNormal), 0.0},
      {scenario_sine_xz(Fixture::kHousingY),
       kz * sb * sg * b_up},  // docs/equations.md E-Sine-4: about -379 nT
  };
  EXPECT_NEAR(cases[0].mean_z_minus_b0z, -37600, 100);
  EXPECT_NEAR(cases[2].mean_z_minus_b0z, -379, 1);
  for (const Case& c : cases) {
    SCOPED_TRACE(c.cfg.name);
    Simulator sim(c.cfg, 3);
    SimSample s;
    double z_sum = 0;
    int n = 0;
    while (sim.next(&s)) {
      EXPECT_NEAR(s.theta_deg, 10.0 * n, 1e-12);
      const Vec3<double> up_b = s.r_bn_true * Vec3<double>::UnitZ();  // the turntable axis in body
      if (std::strcmp(c.cfg.name, "sine-xy") == 0) {
        EXPECT_LT((up_b - Vec3<double>::UnitZ()).norm(), 1e-12);
      } else if (std::strcmp(c.cfg.name, "sine-xz-housing-y") == 0) {
        EXPECT_LT((up_b - Vec3<double>::UnitY()).norm(), 1e-12);
      } else {  // plane normal: the Xm and Zm sensing directions stay horizontal
        EXPECT_NEAR(k.row(0).dot(up_b), 0.0, 1e-12);
        EXPECT_NEAR(k.row(2).dot(up_b), 0.0, 1e-12);
        EXPECT_GT(up_b.y(), 0.99);
      }
      z_sum += s.m_true_nT.z() - p.b0.z();
      ++n;
    }
    EXPECT_EQ(n, 36);
    EXPECT_NEAR(z_sum / n, c.mean_z_minus_b0z, 1e-6);
  }
}

TEST(Simulator, SurveyAttitudeIsSmoothWithManoeuvreAndLines) {
  const ScenarioConfig cfg = scenario_survey();
  Simulator sim(cfg, 1);
  SimSample s, prev;
  double max_step = 0, max_tilt_man = 0, max_tilt_line = 0, heading_travel = 0;
  bool have_prev = false;
  while (sim.next(&s)) {
    const core::LiEuler<double> e = core::li_from_r_bn(s.r_bn_true);
    const double tilt = std::max(std::abs(e.beta), std::abs(e.gamma)) / kDeg;
    if (s.t_s < cfg.survey.manoeuvre_s) {
      max_tilt_man = std::max(max_tilt_man, tilt);
    } else {
      max_tilt_line = std::max(max_tilt_line, tilt);
    }
    if (have_prev) {
      max_step = std::max(max_step, core::rotation_angle_between(prev.r_bn_true, s.r_bn_true));
      heading_travel += std::abs(core::wrap_pi(e.alpha - core::li_from_r_bn(prev.r_bn_true).alpha));
    }
    prev = s;
    have_prev = true;
  }
  EXPECT_EQ(cfg.rate_hz, 200.0);
  EXPECT_NEAR(prev.t_s, survey_duration_s(cfg.survey, 4), 0.01);
  EXPECT_LT(max_step / kDeg, 0.5);  // smooth at 200 Hz, no jumps at the junctions
  EXPECT_GT(max_tilt_man, 29.0);
  EXPECT_LE(max_tilt_man, 30.0 + 1e-9);
  EXPECT_GT(max_tilt_line, 2.5);
  EXPECT_LE(max_tilt_line, 3.0 + 1e-9);
  // 3 full manoeuvre turns + 3 half turns between the lines (plus small tilt-induced wobble).
  EXPECT_NEAR(heading_travel / (2 * core::kPi<double>), 4.5, 0.1);
}

TEST(Simulator, NextDoesNotAllocate) {
  for (const ScenarioConfig& base : all_scenarios()) {
    ScenarioConfig cfg = base;
    cfg.spike_probability = 0.1;
    cfg.spike_amplitude_nT = 10;
    cfg.dropout_probability = 0.1;
    cfg.ins_latency_s = 0.01;
    Simulator sim(cfg, 1);
    SimSample s;
    std::size_t allocations = 0;
    {
      const test::AllocationScope scope;
      for (int i = 0; i < 1000 && sim.next(&s); ++i) {
        (void)sim.ins_attitude_at(s.t_s);
      }
      allocations = scope.count();
    }
    EXPECT_EQ(allocations, 0U) << cfg.name;
  }
}

}  // namespace
}  // namespace magvec::drivers::sim
