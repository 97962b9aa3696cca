// Unit tests of the calibration runners (host/calibration/{batch,ekf,sine}_runner, evaluation):
// each estimator over a simulated CSV fills a consistent CalibrationFile; dropouts are counted;
// more rows than the store holds is an error, not a truncation; the EKF trace has one row per
// sample and pass; the evaluator's figures match a direct computation.
#include <gtest/gtest.h>
#include <stdlib.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>
#include <string>
#include <vector>

#include "calibration/batch_runner.hpp"
#include "calibration/ekf_runner.hpp"
#include "calibration/evaluation.hpp"
#include "calibration/sine_runner.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/io/csv.hpp"

namespace {

namespace fs = std::filesystem;
namespace sim = magvec::drivers::sim;
namespace host = magvec::host;
using magvec::core::Vec3;

// Simulated recording with the columns the reader needs (t, raw, F, Li attitude, theta).
void write_sim(const sim::ScenarioConfig& cfg, std::uint64_t seed, const std::string& path) {
  sim::Simulator s(cfg, seed);
  host::io::CsvWriter w(path, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT", "alpha_deg", "beta_deg",
                               "gamma_deg", "theta_deg"});
  sim::SimSample x;
  while (s.next(&x)) {
    const magvec::core::LiEuler<double> e = magvec::core::li_from_r_bn(x.r_bn_ins);
    const double row[9] = {x.t_s,
                           x.m_nT(0),
                           x.m_nT(1),
                           x.m_nT(2),
                           x.f_nT,
                           magvec::core::rad_to_deg(e.alpha),
                           magvec::core::rad_to_deg(e.beta),
                           magvec::core::rad_to_deg(e.gamma),
                           x.theta_deg};
    w.write_row(row);
  }
  w.commit();
}

class Runners : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "magvec_runners_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string file(const char* name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

TEST_F(Runners, BatchFillsTheCalibrationFileAndCountsDropouts) {
  sim::ScenarioConfig cfg = sim::scenario_li2023();
  cfg.num_samples = 200;
  cfg.dropout_probability = 0.05;
  write_sim(cfg, 4, file("li.csv"));
  host::io::CsvReader reader(file("li.csv"));
  const host::BatchRun run = host::run_batch(reader, host::BatchRunOptions{});
  ASSERT_TRUE(run.result.ok()) << run.reason;
  EXPECT_EQ(run.rows, 200U);
  const host::CalibrationFile& c = run.cal;
  EXPECT_EQ(c.quality.verdict, "ok");
  EXPECT_GT(c.counts.skipped_nonfinite, 0U);  // the dropouts
  EXPECT_EQ(c.counts.used + c.counts.skipped_nonfinite + c.counts.rejected_outliers, 200U);
  EXPECT_EQ(c.provenance.method, "li-ml");
  for (const char* k : {"ks", "O_deg", "Kof_nT", "Rm_deg", "h_n_nT"})
    EXPECT_EQ(c.sigma.count(k), 1U) << k;
  ASSERT_TRUE(run.eval.has_enu);
  // After calibration the E/N/U spread is the INS-noise floor (0.015 deg of 53.7 uT: ~14 nT per
  // tilt axis), far below the raw spread.
  for (int i = 0; i < 3; ++i) {
    EXPECT_LT(run.eval.enu_sd_after_nT(i), 30.0) << i;
    EXPECT_GT(run.eval.enu_sd_before_nT(i), 1000.0) << i;
  }
  EXPECT_LT(run.eval.intensity_rms_after_nT, 0.45);
  EXPECT_DOUBLE_EQ(c.quality.residual_rms_after_nT, run.eval.intensity_rms_after_nT);
}

TEST_F(Runners, LongRecordingsAreThinnedNotRefused) {
  sim::ScenarioConfig cfg = sim::scenario_li2023();
  cfg.num_samples = 1000;
  write_sim(cfg, 1, file("li.csv"));
  host::io::CsvReader reader(file("li.csv"));
  host::BatchRunOptions o;
  o.max_rows_kept = 100;  // memory bound: the kept set is thinned to every 2nd, 4th, ... row
  const host::BatchRun run = host::run_batch(reader, o);
  EXPECT_EQ(run.rows, 1000U);
  EXPECT_GE(run.keep_stride, 8U);
  EXPECT_LT(run.rows_kept, 200U);
  EXPECT_GE(run.rows_kept, 100U);
  EXPECT_EQ(run.result.counts.offered, run.rows_kept);
  EXPECT_TRUE(run.result.ok()) << run.reason;
  EXPECT_DOUBLE_EQ(run.cal.quality.extra.at("keep_stride"), static_cast<double>(run.keep_stride));
}

TEST_F(Runners, EkfPassesAndTraceRows) {
  sim::ScenarioConfig cfg = sim::scenario_ge2017();
  cfg.num_samples = 400;
  write_sim(cfg, 2, file("ge.csv"));
  host::EkfRunOptions o;
  o.noise_nT = 200;
  o.passes = 3;
  o.trace_path = file("trace.csv");
  const host::EkfRun run = host::run_ekf(file("ge.csv"), {}, o);
  EXPECT_EQ(run.verdict, "ok") << run.reason;
  EXPECT_EQ(run.rows, 400U);
  EXPECT_EQ(run.trace_rows, 1200U);
  EXPECT_TRUE(run.initialised);
  // Three passes: every sample of the last pass is an accepted update (no gating at 200 nT).
  EXPECT_EQ(run.cal.counts.used, 400U);
  EXPECT_EQ(run.cal.sigma.at("b_nT").size(), 3U);
  EXPECT_EQ(run.cal.sigma.at("Cinv").size(), 9U);
  // cal.json W/o are the filter's C^-1/b with Rm identity.
  EXPECT_TRUE(run.cal.model.rm.isApprox(magvec::core::Quat<double>::Identity()));
  EXPECT_LT((run.cal.model.o - cfg.truth.o).norm(), 100.0);
  EXPECT_LT((run.cal.model.g() - cfg.truth.g()).cwiseAbs().maxCoeff(), 5e-3);
}

// ---- EKF with default options: noise from the data, one acceptance policy, every verdict ------

// Readings (t, m, F) without attitude.
void write_rows(const std::string& path, const std::vector<Vec3<double>>& m,
                const std::vector<double>& f) {
  host::io::CsvWriter w(path, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT"});
  for (std::size_t i = 0; i < m.size(); ++i) {
    const double row[5] = {0.1 * static_cast<double>(i), m[i](0), m[i](1), m[i](2), f[i]};
    w.write_row(row);
  }
  w.commit();
}

struct GeData {
  std::vector<Vec3<double>> m, m_true;
  std::vector<double> f;
};
GeData ge_data(std::uint32_t n, double noise_nT, std::uint64_t seed) {
  sim::ScenarioConfig cfg = sim::scenario_ge2017();
  cfg.num_samples = n;
  cfg.mag_noise_nT = noise_nT;
  sim::Simulator s(cfg, seed);
  sim::SimSample x;
  GeData d;
  while (s.next(&x)) {
    d.m.push_back(x.m_nT);
    d.m_true.push_back(x.m_true_nT);
    d.f.push_back(x.f_nT);
  }
  return d;
}

// RMS over the noise-free readings (simulator truth) of the calibrated intensity error.
double truth_rmse(const magvec::core::SensorModel<double>& model, const GeData& d) {
  double se = 0;
  for (std::size_t i = 0; i < d.m_true.size(); ++i) {
    const double e = (model.w * (d.m_true[i] - model.o)).norm() - d.f[i];
    se += e * e;
  }
  return std::sqrt(se / static_cast<double>(d.m_true.size()));
}

TEST_F(Runners, EkfAcceptsNoisyFullCoverageDataWithDefaults) {
  // 200 nT per axis (the Ge setup), no --noise-nT: the noise comes from the data.
  const GeData d = ge_data(1000, 200, 2);
  write_rows(file("ge.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("ge.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "ok") << run.reason;
  EXPECT_TRUE(run.noise_estimated);
  EXPECT_TRUE(run.cal.noise.mag_estimated);
  EXPECT_GT(run.cal.noise.mag_sigma_nT, 0.0);
  EXPECT_LT(run.cal.noise.mag_sigma_nT, 10.0);
  EXPECT_NEAR(run.cal.noise.mag_nT, 200.0, 4 * run.cal.noise.mag_sigma_nT);
  EXPECT_TRUE(run.warnings.empty());
  // docs/equations.md E-Ge-6: the floor of 1000 samples at 200 nT is an intensity RMSE of 18.1 nT.
  const double rmse = truth_rmse(run.model, d);
  std::printf("[ekf-runner] 200 nT: noise %.1f +- %.1f nT, intensity RMSE %.1f nT (floor 18.1)\n",
              run.cal.noise.mag_nT, run.cal.noise.mag_sigma_nT, rmse);
  EXPECT_LT(rmse, 1.3 * 18.1);
  EXPECT_EQ(run.cal.quality.extra.at("init_attempts"), 1.0);
}

TEST_F(Runners, EkfWarnsWhenTheGivenNoiseDisagreesWithTheData) {
  const GeData d = ge_data(1000, 200, 3);
  write_rows(file("ge.csv"), d.m, d.f);
  host::EkfRunOptions o;
  o.noise_nT = 60;  // 3.3x too small
  const host::EkfRun run = host::run_ekf(file("ge.csv"), {}, o);
  std::printf("[ekf-runner] given 60 nT on 200 nT data: %s: %s\n", run.verdict.c_str(),
              run.reason.c_str());
  ASSERT_EQ(run.warnings.size(), 1U) << run.reason;
  EXPECT_NE(run.warnings[0].find("--noise-nT 60.000 nT disagrees with the data's own estimate of "
                                 "the magnetometer noise ("),
            std::string::npos)
      << run.warnings[0];
  EXPECT_NEAR(run.noise_estimate_nT, 200.0, 30.0);
  EXPECT_NE(run.verdict, "ok");
  EXPECT_FALSE(run.cal.noise.mag_estimated);
  EXPECT_DOUBLE_EQ(run.cal.noise.mag_nT, 60.0);
}

TEST_F(Runners, EkfShortRecordingStartsAtTheEnd) {
  // 30 samples: fewer than the start-up set, enough for a determined fit.
  const GeData d = ge_data(30, 200, 2);
  write_rows(file("ge.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("ge.csv"), {}, host::EkfRunOptions{});
  EXPECT_TRUE(run.initialised);
  EXPECT_EQ(run.counters.init_attempts, 1U);
  EXPECT_EQ(run.counters.updates, 0U);
  EXPECT_EQ(run.verdict, "ok") << run.reason;
}

TEST_F(Runners, EkfVerdictNoData) {
  std::ofstream(file("empty.csv")) << "t_s,hx_nT,hy_nT,hz_nT,F_nT\n";
  const host::EkfRun run = host::run_ekf(file("empty.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "no_data") << run.reason;
}

TEST_F(Runners, EkfVerdictTooFewSamples) {
  const GeData d = ge_data(12, 200, 2);
  write_rows(file("ge.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("ge.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "too_few_samples") << run.reason;
  EXPECT_NE(run.reason.find("12 usable samples"), std::string::npos) << run.reason;
}

TEST_F(Runners, EkfVerdictUnitMismatch) {
  GeData d = ge_data(500, 200, 4);
  for (auto& m : d.m)
    m /= 1000;  // uT values under an nT header
  write_rows(file("ut.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("ut.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "unit_mismatch") << run.reason;
  EXPECT_NE(run.reason.find("uT under an nT header"), std::string::npos) << run.reason;
}

TEST_F(Runners, EkfVerdictInsufficientCoverageOnANarrowCap) {
  // Airborne-like: 10 Hz for 10 min, directions within a 30 deg cap (half-angle 15 deg), 1 nT
  // noise, a caesium-like reference (0.01 nT).
  const sim::ScenarioConfig ge = sim::scenario_ge2017();
  std::mt19937_64 rng(9);
  std::normal_distribution<double> nd(0.0, 1.0);
  const Vec3<double> axis = ge.h_n_nT.normalized();
  const Vec3<double> e1 = axis.cross(Vec3<double>(1, 0, 0)).normalized();
  const Vec3<double> e2 = axis.cross(e1);
  const double f = ge.h_n_nT.norm();
  std::vector<Vec3<double>> m;
  std::vector<double> fs;
  for (int i = 0; i < 6000; ++i) {
    const double t = 0.1 * i;
    const double th = magvec::core::deg_to_rad(15.0) * std::abs(std::sin(0.05 * t));
    const double ph = 0.21 * t;
    const Vec3<double> u =
        std::cos(th) * axis + std::sin(th) * (std::cos(ph) * e1 + std::sin(ph) * e2);
    const Vec3<double> h = f * u;
    m.push_back(ge.truth.w.inverse() * h + ge.truth.o + Vec3<double>(nd(rng), nd(rng), nd(rng)));
    fs.push_back(f + 0.01 * nd(rng));
  }
  write_rows(file("cap.csv"), m, fs);
  const host::EkfRun run = host::run_ekf(file("cap.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "insufficient_coverage") << run.reason;
  EXPECT_FALSE(run.initialised);
  EXPECT_NE(run.reason.find("% of the sphere"), std::string::npos) << run.reason;
  EXPECT_NE(run.reason.find("do not determine"), std::string::npos) << run.reason;
  EXPECT_NE(run.reason.find("b_"), std::string::npos) << run.reason;
  // Truthful counts: the tries made, no updates.
  EXPECT_NE(run.reason.find(std::to_string(run.counters.init_attempts) + " initial fit"),
            std::string::npos)
      << run.reason;
  EXPECT_GT(run.counters.init_attempts, 0U);
  EXPECT_EQ(run.counters.updates, 0U);
}

TEST_F(Runners, EkfVerdictNotAnEllipsoid) {
  // Directions everywhere, |m| as on a hyperboloid x^2 + y^2 - z^2 = F^2.
  std::mt19937_64 rng(5);
  std::normal_distribution<double> nd(0.0, 1.0);
  std::vector<Vec3<double>> m;
  std::vector<double> fs;
  const double f = 45306;
  for (int i = 0; i < 600; ++i) {
    const double a = 2 * magvec::core::kPi<double> * (i * 0.618034 - std::floor(i * 0.618034));
    const double z = 0.9 * std::sin(0.37 * i);
    m.push_back(Vec3<double>(f * std::cosh(z) * std::cos(a), f * std::cosh(z) * std::sin(a),
                             f * std::sinh(z)) +
                50 * Vec3<double>(nd(rng), nd(rng), nd(rng)));
    fs.push_back(f);
  }
  write_rows(file("hyp.csv"), m, fs);
  const host::EkfRun run = host::run_ekf(file("hyp.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "not_an_ellipsoid") << run.reason;
  EXPECT_NE(run.reason.find("never started"), std::string::npos) << run.reason;
}

TEST_F(Runners, EkfVerdictNotConvergedWhenTheFilterDivergedAtTheEnd) {
  // 1000 good samples, then the offset jumps by 13 uT for the last 80: the filter restarts after
  // the window in which most samples were gated and has too few samples left to start again.
  GeData d = ge_data(1080, 200, 6);
  for (std::size_t i = 1000; i < d.m.size(); ++i)
    d.m[i] += Vec3<double>(9000, -7000, 6000);
  write_rows(file("jump.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("jump.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "not_converged") << run.reason;
  EXPECT_GT(run.counters.updates, 800U);
  EXPECT_GE(run.counters.reinitialisations, 1U);
  EXPECT_NE(run.reason.find("the filter made " + std::to_string(run.counters.updates) + " updates"),
            std::string::npos)
      << run.reason;
  EXPECT_EQ(run.reason.find("never started"), std::string::npos) << run.reason;
}

TEST_F(Runners, EkfVerdictResidualTooLarge) {
  // 3 uT noise on a 45 uT field: the estimated noise is over 5 % of the field.
  const GeData d = ge_data(3000, 3000, 7);
  write_rows(file("noisy.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("noisy.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "residual_too_large") << run.reason;
  EXPECT_NEAR(run.noise_estimate_nT, 3000, 300);
}

TEST_F(Runners, EkfVerdictFieldMismatch) {
  // The reference is a third of the field the sensor saw: scale factors of ~3.
  GeData d = ge_data(1000, 200, 8);
  for (double& f : d.f)
    f /= 3;
  write_rows(file("wrongf.csv"), d.m, d.f);
  const host::EkfRun run = host::run_ekf(file("wrongf.csv"), {}, host::EkfRunOptions{});
  EXPECT_EQ(run.verdict, "field_mismatch") << run.reason;
}

TEST_F(Runners, SineNeedsATheta) {
  write_sim(sim::scenario_li2023(), 1, file("li.csv"));  // theta all nan, but the column exists
  {
    std::ofstream out(file("notheta.csv"));
    out << "t_s,hx_nT,hy_nT,hz_nT\n0,1,2,3\n";
  }
  host::io::CsvReader a(file("notheta.csv")), b(file("notheta.csv"));
  EXPECT_THROW((void)host::run_sine(a, b, host::SineRunOptions{}), std::invalid_argument);
  host::io::CsvReader c(file("li.csv")), d(file("li.csv"));
  const host::SineRun run = host::run_sine(c, d, host::SineRunOptions{});
  EXPECT_EQ(run.verdict, "too_few_samples");
  EXPECT_EQ(run.cal.counts.skipped_nonfinite, 120U);
}

TEST(Evaluation, MatchesADirectComputation) {
  magvec::core::SensorModel<double> m;
  m.o = Vec3<double>(10, 0, 0);
  host::Evaluator ev(m, true);
  const magvec::core::Mat3<double> r = magvec::core::Mat3<double>::Identity();
  ev.add(Vec3<double>(110, 0, 0), 100.0, &r);  // before 10, after 0
  ev.add(Vec3<double>(-90, 0, 0), 100.0, &r);  // before -10, after 0
  ev.add(Vec3<double>(std::numeric_limits<double>::quiet_NaN(), 0, 0), 100.0, &r);  // ignored
  const host::Evaluation e = ev.result();
  EXPECT_EQ(e.n_intensity, 2U);
  EXPECT_DOUBLE_EQ(e.intensity_rms_before_nT, 10.0);
  EXPECT_DOUBLE_EQ(e.intensity_rms_after_nT, 0.0);
  EXPECT_TRUE(e.has_enu);
  EXPECT_NEAR(e.enu_sd_after_nT(0), std::sqrt(2.0) * 100.0, 1e-9);  // +-100 about 0, n - 1
  EXPECT_DOUBLE_EQ(e.coverage, 2.0 / 32.0);
}

}  // namespace
