// Unit tests of the calibration runners (host/calibration/{batch,ekf,sine}_runner, evaluation):
// each estimator over a simulated CSV fills a consistent CalibrationFile; dropouts are counted;
// more rows than the store holds is an error, not a truncation; the EKF trace has one row per
// sample and pass; the evaluator's figures match a direct computation.
#include <gtest/gtest.h>
#include <stdlib.h>

#include <cmath>
#include <filesystem>
#include <fstream>
#include <string>

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

TEST_F(Runners, MoreRowsThanTheStoreIsAnErrorNotATruncation) {
  write_sim(sim::scenario_li2023(), 1, file("li.csv"));  // 60 rows
  host::io::CsvReader reader(file("li.csv"));
  try {
    (void)host::run_batch_with_capacity<50>(reader, host::BatchRunOptions{});
    FAIL() << "expected CapacityError";
  } catch (const host::CapacityError& e) {
    EXPECT_NE(std::string(e.what()).find("60 usable rows"), std::string::npos) << e.what();
    EXPECT_NE(std::string(e.what()).find("10 would be dropped"), std::string::npos) << e.what();
  }
  host::io::CsvReader again(file("li.csv"));
  EXPECT_TRUE(host::run_batch_with_capacity<60>(again, host::BatchRunOptions{}).result.ok());
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

TEST_F(Runners, EkfWithoutEnoughSamplesSaysSo) {
  sim::ScenarioConfig cfg = sim::scenario_ge2017();
  cfg.num_samples = 30;
  write_sim(cfg, 2, file("ge.csv"));
  host::EkfRunOptions o;
  o.noise_nT = 200;
  const host::EkfRun run = host::run_ekf(file("ge.csv"), {}, o);
  EXPECT_EQ(run.verdict, "too_few_samples") << run.reason;
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
  ev.add(Vec3<double>(NAN, 0, 0), 100.0, &r);  // ignored
  const host::Evaluation e = ev.result();
  EXPECT_EQ(e.n_intensity, 2U);
  EXPECT_DOUBLE_EQ(e.intensity_rms_before_nT, 10.0);
  EXPECT_DOUBLE_EQ(e.intensity_rms_after_nT, 0.0);
  EXPECT_TRUE(e.has_enu);
  EXPECT_NEAR(e.enu_sd_after_nT(0), std::sqrt(2.0) * 100.0, 1e-9);  // +-100 about 0, n - 1
  EXPECT_DOUBLE_EQ(e.coverage, 2.0 / 32.0);
}

}  // namespace
