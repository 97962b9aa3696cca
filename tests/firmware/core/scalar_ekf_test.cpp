// Tests of the Ge et al. 2017 scalar EKF (docs/equations.md E-Ge): exact recovery, Monte Carlo
// against the statistical floors, the paper's printed settings, float32, spikes, bad input,
// divergence, drift, allocation-free update path.
#include "magvec/core/scalar_ekf.hpp"

#include <gtest/gtest.h>

#include <Eigen/Eigenvalues>

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <limits>
#include <random>
#include <vector>

#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

constexpr double kF = 45306.0;  // paper total field [nT]

Mat3<double> paper_c() {
  Mat3<double> c;
  c << 1.362, 0.002, 0.001, 0.001, 0.861, 0.002, 0.002, 0.001, 1.046;
  return c;
}

struct Scenario {
  Mat3<double> c = paper_c();
  Vec3<double> b{600, 700, 750};
  double f = kF;
  double sigma = 200;
  int n = 1000;
  double spike_fraction = 0;
  double spike_nT = 5000;
};

struct Data {
  std::vector<Vec3<double>> clean;  // noise-free readings
  std::vector<Vec3<double>> noisy;  // what the filter sees
  int spikes = 0;
};

// Ge model (eq. 13): m = C h + b + noise, h uniformly distributed over directions with |h| = F.
Data simulate(const Scenario& s, std::uint64_t seed) {
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> nd(0.0, 1.0);
  std::uniform_real_distribution<double> ud(0.0, 1.0);
  std::uniform_int_distribution<int> axis(0, 2);
  Data d;
  for (int i = 0; i < s.n; ++i) {
    Vec3<double> u(nd(rng), nd(rng), nd(rng));
    u.normalize();
    const Vec3<double> m0 = s.c * (s.f * u) + s.b;
    Vec3<double> m = m0 + s.sigma * Vec3<double>(nd(rng), nd(rng), nd(rng));
    if (s.spike_fraction > 0 && ud(rng) < s.spike_fraction) {
      m(axis(rng)) += (ud(rng) < 0.5 ? -1.0 : 1.0) * s.spike_nT;
      ++d.spikes;
    }
    d.clean.push_back(m0);
    d.noisy.push_back(m);
  }
  return d;
}

struct RunResult {
  double rmse = 0;         // parameter-induced intensity RMSE (estimate applied to clean readings)
  Vec3<double> b_err;      // estimated minus true offset [nT]
  double g_rel_err = 0;    // |G_est - G| / |G|
  bool reflected = false;  // det(C^-1) < 0
  Vec3<double> b_sigma;    // predicted 1-sigma of b
  double intensity_sigma_rms = 0;
  EkfCounters counters;
};

template <typename Scalar>
RunResult run(const Scenario& s, const Data& d, const EkfConfig<Scalar>& cfg) {
  ScalarEkf<Scalar> ekf(cfg);
  for (const Vec3<double>& m : d.noisy)
    ekf.update(m.cast<Scalar>(), static_cast<Scalar>(s.f));
  RunResult r;
  const Mat3<double> w = ekf.c_inv().template cast<double>();
  const Vec3<double> b = ekf.offset_nT().template cast<double>();
  double se = 0, sv = 0;
  for (const Vec3<double>& m0 : d.clean) {
    const double e = (w * (m0 - b)).norm() - s.f;
    se += e * e;
    const double sig = static_cast<double>(ekf.intensity_sigma_nT(m0.cast<Scalar>()));
    sv += sig * sig;
  }
  r.rmse = std::sqrt(se / static_cast<double>(d.clean.size()));
  r.intensity_sigma_rms = std::sqrt(sv / static_cast<double>(d.clean.size()));
  r.b_err = b - s.b;
  const Mat3<double> w_true = s.c.inverse();
  const Mat3<double> g_true = w_true.transpose() * w_true;
  r.g_rel_err = (w.transpose() * w - g_true).norm() / g_true.norm();
  r.reflected = w.determinant() < 0;
  r.b_sigma = ekf.sigma().template tail<3>().template cast<double>();
  r.counters = ekf.counters();
  return r;
}

struct McSummary {
  double median_rmse = 0, max_rmse = 0;
  Vec3<double> b_sd = Vec3<double>::Zero();  // RMS of b error (about the truth)
  Vec3<double> b_sigma_mean = Vec3<double>::Zero();
  double intensity_sigma_mean = 0;
  int reflected = 0;
  std::vector<double> rmse;
};

template <typename Scalar>
McSummary monte_carlo(const Scenario& s, const EkfConfig<Scalar>& cfg, int seeds,
                      std::uint64_t first_seed = 1000) {
  McSummary mc;
  for (int k = 0; k < seeds; ++k) {
    const Data d = simulate(s, first_seed + static_cast<std::uint64_t>(k));
    const RunResult r = run<Scalar>(s, d, cfg);
    mc.rmse.push_back(r.rmse);
    mc.b_sd += r.b_err.cwiseProduct(r.b_err);
    mc.b_sigma_mean += r.b_sigma;
    mc.intensity_sigma_mean += r.intensity_sigma_rms;
    mc.reflected += r.reflected ? 1 : 0;
  }
  const double n = static_cast<double>(seeds);
  mc.b_sd = (mc.b_sd / n).cwiseSqrt();
  mc.b_sigma_mean /= n;
  mc.intensity_sigma_mean /= n;
  std::vector<double> sorted = mc.rmse;
  std::sort(sorted.begin(), sorted.end());
  mc.median_rmse = 0.5 * (sorted[sorted.size() / 2] + sorted[(sorted.size() - 1) / 2]);
  mc.max_rmse = sorted.back();
  return mc;
}

void print(const char* name, const McSummary& mc) {
  std::printf(
      "[ekf-mc] %-34s median RMSE %7.2f nT  max %8.2f nT  b SD %7.2f %7.2f %7.2f nT  reflected "
      "%d\n",
      name, mc.median_rmse, mc.max_rmse, mc.b_sd(0), mc.b_sd(1), mc.b_sd(2), mc.reflected);
}

template <typename Scalar>
EkfConfig<Scalar> default_config(double sigma) {
  EkfConfig<Scalar> c;
  c.noise_sigma_nT = static_cast<Scalar>(sigma);
  return c;
}

Vec3<double> mean_of(const std::vector<Vec3<double>>& v) {
  Vec3<double> m = Vec3<double>::Zero();
  for (const auto& x : v)
    m += x;
  return m / static_cast<double>(v.size());
}

// ---------------------------------------------------------------------------------------------

TEST(ScalarEkf, NoiseFreeConvergesToTruth) {
  Scenario s;
  s.sigma = 0;
  const Data d = simulate(s, 7);
  EkfConfig<double> cfg = default_config<double>(1.0);  // sigma only weights the samples here
  cfg.debias = false;
  ScalarEkf<double> ekf(cfg);
  int accepted = 0;
  for (const auto& m : d.noisy)
    accepted += ekf.update(m, kF) == EkfStatus::kAccepted ? 1 : 0;
  EXPECT_EQ(accepted, s.n - cfg.init_samples);
  const Mat3<double> w = ekf.c_inv();
  const Mat3<double> w_true = s.c.inverse();
  const Mat3<double> g_true = w_true.transpose() * w_true;
  EXPECT_LT((w.transpose() * w - g_true).norm() / g_true.norm(), 1e-8);
  EXPECT_LT((ekf.offset_nT() - s.b).norm() / s.b.norm(), 1e-8);
  // The canonical model compensates the clean readings to F.
  const SensorModel<double> model = ekf.model();
  for (int i = 0; i < 50; ++i)
    EXPECT_NEAR((model.w * (d.clean[static_cast<std::size_t>(i)] - model.o)).norm(), kF, 1e-6);
  EXPECT_EQ(ekf.counters().gated, 0u);
}

// The start-up set lives in the derived class and the filter reaches it by pointer: a copy (or an
// assignment) taken during start-up must carry its own set. The copy continues exactly as the
// uncopied filter does, however the original goes on.
TEST(ScalarEkf, ACopyDuringStartUpOwnsItsStartUpSet) {
  Scenario s;
  const Data d = simulate(s, 11);
  const EkfConfig<double> cfg = default_config<double>(s.sigma);
  ScalarEkf<double> reference(cfg);
  ScalarEkf<double> original(cfg);
  const std::size_t half = 40;  // fewer than init_samples (64): still collecting
  for (std::size_t i = 0; i < half; ++i) {
    reference.update(d.noisy[i], kF);
    original.update(d.noisy[i], kF);
  }
  ASSERT_FALSE(original.initialised());
  ScalarEkf<double> copy(original);
  ScalarEkf<double> assigned(cfg);
  assigned = original;
  // The original now sees other data (a wrong field): its start-up set changes.
  for (std::size_t i = half; i < d.noisy.size(); ++i)
    original.update(d.noisy[i], 2 * kF);
  for (std::size_t i = half; i < d.noisy.size(); ++i) {
    const EkfStatus r = reference.update(d.noisy[i], kF);
    EXPECT_EQ(copy.update(d.noisy[i], kF), r) << i;
    EXPECT_EQ(assigned.update(d.noisy[i], kF), r) << i;
  }
  ASSERT_TRUE(reference.initialised());
  EXPECT_EQ(copy.state(), reference.state());
  EXPECT_EQ(assigned.state(), reference.state());
  EXPECT_EQ(copy.covariance(), reference.covariance());
  EXPECT_NE(original.state(), reference.state());
}

TEST(ScalarEkf, NoiseFreeLargeOffsetsConvergeInFloatAndDouble) {
  Scenario s;
  s.sigma = 0;
  s.b = {20000, -20000, 20000};
  const Data d = simulate(s, 11);
  const Mat3<double> w_true = s.c.inverse();
  const Mat3<double> g_true = w_true.transpose() * w_true;
  EkfConfig<double> cfg = default_config<double>(1.0);
  cfg.debias = false;
  ScalarEkf<double> ekf(cfg);
  EkfConfig<float> cfg_f = default_config<float>(1.0);
  cfg_f.debias = false;
  ScalarEkf<float> ekf_f(cfg_f);
  for (const auto& m : d.noisy) {
    ekf.update(m, kF);
    ekf_f.update(m.cast<float>(), static_cast<float>(kF));
  }
  const Mat3<double> w = ekf.c_inv();
  EXPECT_LT((w.transpose() * w - g_true).norm() / g_true.norm(), 1e-8);
  EXPECT_LT((ekf.offset_nT() - s.b).norm() / s.b.norm(), 1e-8);
  // float32: limited by its resolution (~1e-7 relative), not by the filter.
  const Mat3<double> wf = ekf_f.c_inv().cast<double>();
  EXPECT_LT((wf.transpose() * wf - g_true).norm() / g_true.norm(), 2e-6);
  EXPECT_LT((ekf_f.offset_nT().cast<double>() - s.b).norm(), 0.1);
  EXPECT_EQ(ekf_f.counters().reinitialisations, 0u);
}

TEST(ScalarEkf, PaperSetupReachesTheStatisticalFloorInOnePass) {
  const Scenario s;
  const McSummary mc = monte_carlo<double>(s, default_config<double>(s.sigma), 60);
  print("default (quadric start), double", mc);
  std::printf("[ekf-mc]   predicted b sigma %.1f %.1f %.1f nT, predicted intensity sigma %.1f nT\n",
              mc.b_sigma_mean(0), mc.b_sigma_mean(1), mc.b_sigma_mean(2), mc.intensity_sigma_mean);
  // docs/equations.md E-Ge-6 floors: intensity RMSE 18.1 nT, b SD 13/10/11 nT.
  EXPECT_LT(mc.median_rmse, 1.2 * 18.1);
  EXPECT_LT(mc.max_rmse, 3.0 * 18.1);
  EXPECT_LT(mc.b_sd(0), 1.3 * 13.0);
  EXPECT_LT(mc.b_sd(1), 1.3 * 10.0);
  EXPECT_LT(mc.b_sd(2), 1.3 * 11.0);
  EXPECT_EQ(mc.reflected, 0);
  // The filter's own covariance is consistent with the Monte Carlo scatter.
  for (int k = 0; k < 3; ++k) {
    EXPECT_GT(mc.b_sigma_mean(k) / mc.b_sd(k), 0.75) << k;
    EXPECT_LT(mc.b_sigma_mean(k) / mc.b_sd(k), 1.33) << k;
  }
  EXPECT_GT(mc.intensity_sigma_mean / mc.median_rmse, 0.7);
  EXPECT_LT(mc.intensity_sigma_mean / mc.median_rmse, 1.5);
}

TEST(ScalarEkf, PaperPrintedSettingsFailAsDocumentedInErrata) {
  // EkfConfig::paper(): x0, P0, Q, R exactly as printed. Not tuned: this documents the failure.
  const Scenario s;
  const McSummary mc = monte_carlo<double>(s, EkfConfig<double>::paper(), 60);
  print("paper() printed settings", mc);
  // docs/equations.md E-Ge-3: bias SD 85-101 nT (vs the floor of 13/10/11) and some runs reflected.
  EXPECT_GT(mc.b_sd.minCoeff(), 3.0 * 13.0);
  EXPECT_GT(mc.median_rmse, 2.0 * 18.1);
  EXPECT_GT(mc.reflected, 0);
}

TEST(ScalarEkf, OnePassStrategyComparison) {
  // The measurement behind the default: sound settings from "identity + mean" are heavy-tailed in
  // one pass; iterating helps; the quadric start reaches the floor.
  const Scenario s;
  constexpr int kSeeds = 60;
  std::vector<McSummary> results;
  {
    McSummary acc;
    std::vector<double> rmse;
    for (int iters : {1, 3}) {
      McSummary mc;
      Vec3<double> b2 = Vec3<double>::Zero();
      for (int k = 0; k < kSeeds; ++k) {
        const Data d = simulate(s, 1000 + static_cast<std::uint64_t>(k));
        EkfConfig<double> cfg = EkfConfig<double>::given_start(mean_of(d.noisy), kF, s.sigma);
        cfg.iterations = iters;
        const RunResult r = run<double>(s, d, cfg);
        mc.rmse.push_back(r.rmse);
        b2 += r.b_err.cwiseProduct(r.b_err);
        mc.reflected += r.reflected ? 1 : 0;
      }
      mc.b_sd = (b2 / kSeeds).cwiseSqrt();
      std::vector<double> sorted = mc.rmse;
      std::sort(sorted.begin(), sorted.end());
      mc.median_rmse = 0.5 * (sorted[kSeeds / 2] + sorted[kSeeds / 2 - 1]);
      mc.max_rmse = sorted.back();
      print(iters == 1 ? "identity+mean start, EKF" : "identity+mean start, IEKF x3", mc);
      results.push_back(mc);
    }
  }
  EkfConfig<double> iter_cfg = default_config<double>(s.sigma);
  iter_cfg.iterations = 2;
  const McSummary quad = monte_carlo<double>(s, default_config<double>(s.sigma), kSeeds);
  const McSummary quad_it = monte_carlo<double>(s, iter_cfg, kSeeds);
  print("quadric start, EKF (default)", quad);
  print("quadric start, IEKF x2", quad_it);
  // The default has the lighter tail than the plain sound filter and is no worse than iterating it.
  EXPECT_LT(quad.max_rmse, results[0].max_rmse);
  EXPECT_LT(quad.median_rmse, 1.05 * quad_it.median_rmse);
}

TEST(ScalarEkf, Float32WithNormalisationMatchesFloat64) {
  // Large offsets, low noise: the case that breaks raw-nT float32 (docs/equations.md E-Ge-5).
  Scenario s;
  s.b = {20000, -20000, 20000};
  s.sigma = 2;
  constexpr int kSeeds = 20;
  const McSummary d64 = monte_carlo<double>(s, default_config<double>(s.sigma), kSeeds, 500);
  const McSummary f32 = monte_carlo<float>(s, default_config<float>(s.sigma), kSeeds, 500);
  EkfConfig<float> raw = default_config<float>(s.sigma);
  raw.field_scale_nT = 1.0f;  // no normalisation: for comparison only
  const McSummary f32_raw = monte_carlo<float>(s, raw, kSeeds, 500);
  print("20 uT offsets, 2 nT: double", d64);
  print("20 uT offsets, 2 nT: float", f32);
  print("20 uT offsets, 2 nT: float raw nT", f32_raw);
  EXPECT_LT(f32.median_rmse, 2.0 * d64.median_rmse);
  for (int k = 0; k < 3; ++k)
    EXPECT_LT(f32.b_sd(k), 2.0 * d64.b_sd(k)) << k;

  // Paper setup: within 1.1x.
  const Scenario p;
  const McSummary p64 = monte_carlo<double>(p, default_config<double>(p.sigma), 50);
  const McSummary p32 = monte_carlo<float>(p, default_config<float>(p.sigma), 50);
  print("paper setup: double", p64);
  print("paper setup: float", p32);
  EXPECT_LT(p32.median_rmse, 1.1 * p64.median_rmse);
  for (int k = 0; k < 3; ++k)
    EXPECT_LT(p32.b_sd(k), 1.1 * p64.b_sd(k)) << k;
}

TEST(ScalarEkf, SpikesAreGatedAndCounted) {
  Scenario clean;
  Scenario spiky;
  spiky.spike_fraction = 0.01;
  constexpr int kSeeds = 50;
  std::vector<double> r_clean, r_spiky;
  Vec3<double> b2_clean = Vec3<double>::Zero(), b2_spiky = Vec3<double>::Zero();
  int spikes = 0;
  std::uint32_t rejected = 0;
  for (int k = 0; k < kSeeds; ++k) {
    const std::uint64_t seed = 3000 + static_cast<std::uint64_t>(k);
    // Same noise stream for both: the spike draws come after the noise draws of each sample, so use
    // independent data sets and compare the distributions.
    const Data dc = simulate(clean, seed);
    const Data ds = simulate(spiky, seed);
    const RunResult rc = run<double>(clean, dc, default_config<double>(clean.sigma));
    const RunResult rs = run<double>(spiky, ds, default_config<double>(spiky.sigma));
    r_clean.push_back(rc.rmse);
    r_spiky.push_back(rs.rmse);
    b2_clean += rc.b_err.cwiseProduct(rc.b_err);
    b2_spiky += rs.b_err.cwiseProduct(rs.b_err);
    spikes += ds.spikes;
    rejected += rs.counters.gated + rs.counters.init_outliers;
    EXPECT_EQ(rs.counters.reinitialisations, 0u);
  }
  std::sort(r_clean.begin(), r_clean.end());
  std::sort(r_spiky.begin(), r_spiky.end());
  const double med_clean = r_clean[kSeeds / 2], med_spiky = r_spiky[kSeeds / 2];
  std::printf(
      "[ekf-mc] spikes: %d injected, %u rejected; median RMSE %.2f (clean %.2f), max %.2f (clean "
      "%.2f)\n",
      spikes, rejected, med_spiky, med_clean, r_spiky.back(), r_clean.back());
  EXPECT_GT(spikes, 300);
  // A 5000 nT spike on one axis changes |m| by 5000 |cos|: those within ~5 sigma of the noise are
  // harmless and pass; most are rejected, and hardly any clean sample is.
  EXPECT_GT(static_cast<double>(rejected), 0.6 * spikes);
  EXPECT_LT(static_cast<double>(rejected), 1.05 * spikes + 5);
  EXPECT_LT(med_spiky, 1.3 * med_clean);
  for (int k = 0; k < 3; ++k)
    EXPECT_LT(std::sqrt(b2_spiky(k)), 1.3 * std::sqrt(b2_clean(k))) << k;
}

TEST(ScalarEkf, NonFiniteInputsAreRejectedAndStateUntouched) {
  const Scenario s;
  const Data d = simulate(s, 5);
  ScalarEkf<double> ekf(default_config<double>(s.sigma));
  for (int i = 0; i < 200; ++i)
    ekf.update(d.noisy[static_cast<std::size_t>(i)], kF);
  ASSERT_TRUE(ekf.initialised());
  const auto x = ekf.state();
  const auto p = ekf.covariance();
  const auto c = ekf.counters();
  constexpr double kNan = std::numeric_limits<double>::quiet_NaN();
  constexpr double kInf = std::numeric_limits<double>::infinity();
  EXPECT_EQ(ekf.update(Vec3<double>(kNan, 1, 2), kF), EkfStatus::kRejectedNonFinite);
  EXPECT_EQ(ekf.update(Vec3<double>(1, kInf, 2), kF), EkfStatus::kRejectedNonFinite);
  EXPECT_EQ(ekf.update(Vec3<double>(1e308, 1e308, 2), kF),
            EkfStatus::kRejectedNonFinite);  // overflows
  EXPECT_EQ(ekf.update(d.noisy[300], kNan), EkfStatus::kRejectedBadReference);
  EXPECT_EQ(ekf.update(d.noisy[300], -1.0), EkfStatus::kRejectedBadReference);
  EXPECT_EQ(ekf.update(d.noisy[300], 0.0), EkfStatus::kRejectedBadReference);
  EXPECT_EQ(ekf.counters().rejected_nonfinite, c.rejected_nonfinite + 3);
  EXPECT_EQ(ekf.counters().rejected_reference, c.rejected_reference + 3);
  EXPECT_EQ(ekf.counters().updates, c.updates);
  EXPECT_EQ(ekf.counters().reinitialisations, 0u);
  EXPECT_TRUE(ekf.state() == x);
  EXPECT_TRUE(ekf.covariance() == p);
  // Also during the initial collection.
  ScalarEkf<float> f(default_config<float>(s.sigma));
  EXPECT_EQ(f.update(Vec3<float>(std::nanf(""), 0, 0), 45306.f), EkfStatus::kRejectedNonFinite);
  EXPECT_EQ(f.field_scale_nT(), 0.0f);
  EXPECT_EQ(f.update(d.noisy[0].cast<float>(), 45306.f), EkfStatus::kCollecting);
}

TEST(ScalarEkf, HugeFiniteSampleIsGatedNotAccepted) {
  const Scenario s;
  const Data d = simulate(s, 6);
  ScalarEkf<double> ekf(default_config<double>(s.sigma));
  for (int i = 0; i < 200; ++i)
    ekf.update(d.noisy[static_cast<std::size_t>(i)], kF);
  const auto x = ekf.state();
  EXPECT_EQ(ekf.update(Vec3<double>(1e12, -1e12, 3e11), kF), EkfStatus::kGated);
  EXPECT_EQ(ekf.counters().gated, 1u);
  EXPECT_TRUE(ekf.state() == x);
}

// Readings along a path of directions u(a), a = step * i (a slowly turning platform).
template <typename Path>
std::vector<Vec3<double>> path_readings(int n, double step, Path u_of, std::uint64_t seed) {
  const Scenario s;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> nd(0.0, 1.0);
  std::vector<Vec3<double>> out;
  for (int i = 0; i < n; ++i) {
    const Vec3<double> u = u_of(step * i).normalized();
    out.push_back(s.c * (s.f * u) + s.b + s.sigma * Vec3<double>(nd(rng), nd(rng), nd(rng)));
  }
  return out;
}

TEST(ScalarEkf, PoorCoverageIsRefusedAndCounted) {
  // Level turns only (a plane of directions), or a cone: the ellipsoid is not determined.
  const auto plane = path_readings(
      3000, 0.01, [](double a) { return Vec3<double>(std::cos(a), std::sin(a), 0); }, 1);
  const auto cone = path_readings(
      3000, 0.01, [](double a) { return Vec3<double>(std::cos(a), std::sin(a), 0.3); }, 2);
  for (const auto* data : {&plane, &cone}) {
    ScalarEkf<double> ekf(default_config<double>(200));
    int accepted = 0;
    for (const auto& m : *data)
      accepted += ekf.update(m, kF) == EkfStatus::kAccepted ? 1 : 0;
    EXPECT_EQ(accepted, 0);
    EXPECT_FALSE(ekf.initialised());
    EXPECT_GT(ekf.counters().init_failures, 0u);
    EXPECT_EQ(ekf.init_report().failure, EkfInitFailure::kUndetermined);
    EXPECT_NE(ekf.init_report().undetermined & (1U << kEkfBz), 0u);  // nothing along z
    EXPECT_TRUE(ekf.state().allFinite());
    EXPECT_TRUE(ekf.covariance().allFinite());
  }
}

TEST(ScalarEkf, SlowlyTurningPlatformInitialisesFromSpreadSamples) {
  // 6000 samples, 2 mrad per sample in heading with a pitching motion: consecutive samples are
  // close, so the start-up set keeps only the samples that add direction information.
  const auto data = path_readings(
      6000, 0.002,
      [](double a) { return Vec3<double>(std::cos(a), std::sin(a), 0.6 * std::sin(3 * a)); }, 3);
  ScalarEkf<double> ekf(default_config<double>(200));
  int accepted = 0;
  for (const auto& m : data)
    accepted += ekf.update(m, kF) == EkfStatus::kAccepted ? 1 : 0;
  EXPECT_TRUE(ekf.initialised());
  EXPECT_GT(accepted, 1000);
  EXPECT_EQ(ekf.counters().reinitialisations, 0u);
  const Scenario s;
  const Vec3<double> err = ekf.offset_nT() - s.b;
  const Vec3<double> sd = ekf.sigma().tail<3>();
  for (int k = 0; k < 3; ++k)
    EXPECT_LT(std::abs(err(k)), 4 * sd(k)) << k;  // consistent with its sigma
  EXPECT_LT(sd.maxCoeff(), 60.0);
}

TEST(ScalarEkf, GivenStartDivergesOnLargeOffsetsLowNoiseAndRecoversByRefit) {
  // The sound start of docs/equations.md E-Ge-3 (identity + mean of the measurements) with 20 uT
  // offsets and 2 nT noise: without protection the plain EKF ends 30-500x above the floor or
  // diverges; with divergence detection it restarts from a fit of new samples and ends at the
  // floor.
  Scenario s;
  s.b = {20000, -20000, 20000};
  s.sigma = 2;
  for (int k = 0; k < 8; ++k) {
    const Data d = simulate(s, 700 + static_cast<std::uint64_t>(k));
    EkfConfig<float> cfg =
        EkfConfig<float>::given_start(mean_of(d.noisy).cast<float>(), static_cast<float>(kF), 2.0f);
    EkfConfig<float> bare = cfg;
    bare.gate_nis = 0;
    bare.divergence_detection = false;
    const RunResult r_bare = run<float>(s, d, bare);
    const RunResult r = run<float>(s, d, cfg);
    EXPECT_GT(r_bare.b_err.norm(), 5.0) << k;  // the floor is ~0.2 nT; some runs diverge entirely
    EXPECT_GE(r.counters.reinitialisations, 1u) << k;
    EXPECT_LT(r.b_err.norm(), 1.0) << k;
  }
}

TEST(ScalarEkf, DivergenceIsDetectedAndTheFilterReinitialises) {
  // The offset jumps by 3000 nT (e.g. a magnetised part): every sample is gated, the window check
  // restarts the filter, which then converges to the new offset.
  Scenario s;
  const Data before = simulate(s, 21);
  Scenario after = s;
  after.b = s.b + Vec3<double>(3000, -2000, 1000);
  const Data later = simulate(after, 22);
  ScalarEkf<double> ekf(default_config<double>(s.sigma));
  for (const auto& m : before.noisy)
    ekf.update(m, kF);
  EXPECT_EQ(ekf.counters().reinitialisations, 0u);
  bool saw_reinit = false;
  for (const auto& m : later.noisy)
    saw_reinit |= ekf.update(m, kF) == EkfStatus::kReinitialised;
  EXPECT_TRUE(saw_reinit);
  EXPECT_EQ(ekf.counters().reinitialisations, 1u);
  EXPECT_TRUE(ekf.last_reset_reason() == EkfResetReason::kTooManyGated ||
              ekf.last_reset_reason() == EkfResetReason::kNisTooHigh);
  EXPECT_TRUE(ekf.initialised());
  EXPECT_LT((ekf.offset_nT() - after.b).norm(), 100.0);
}

TEST(ScalarEkf, ProcessNoiseOnOffsetTracksSlowDrift) {
  // b drifts by 300 nT (x) over 6000 samples; 2 nT noise.
  Scenario s;
  s.sigma = 2;
  s.n = 6000;
  const Data d = simulate(s, 31);
  auto drift = [&](int i) { return Vec3<double>(300.0 * i / s.n, 0, 0); };
  auto final_error = [&](double q_b, bool detect, std::uint32_t* reinits) {
    EkfConfig<double> cfg = default_config<double>(s.sigma);
    cfg.q.tail<3>().setConstant(q_b);
    cfg.divergence_detection = detect;
    ScalarEkf<double> ekf(cfg);
    for (int i = 0; i < s.n; ++i)
      ekf.update(d.noisy[static_cast<std::size_t>(i)] + drift(i), kF);
    *reinits = ekf.counters().reinitialisations;
    return (ekf.offset_nT() - (s.b + drift(s.n - 1))).norm();
  };
  std::uint32_t r0 = 0, r0d = 0, r1 = 0;
  const double e0 = final_error(0.0, false, &r0);
  const double e0d = final_error(0.0, true, &r0d);
  const double e1 = final_error(1e-2, true, &r1);  // (0.1 nT)^2 per sample
  std::printf(
      "[ekf] drift 300 nT: final offset error %.2f nT with Q = 0, %.2f nT with Q = 0 and "
      "divergence detection (%u restarts), %.2f nT with Q_b = 0.01 nT^2 (%u restarts)\n",
      e0, e0d, r0d, e1, r1);
  EXPECT_GT(e0, 50.0);
  EXPECT_GT(r0d, 0u);  // a model that cannot follow the drift is detected
  EXPECT_LT(e1, 5.0);
  EXPECT_EQ(r1, 0u);
}

TEST(ScalarEkf, BiermanAndAgeeTurnerMatchDenseJosephForm) {
  // Reference: dense EKF with Joseph-form covariance update, same model, paper-style Q.
  const Scenario s;
  const Data d = simulate(s, 41);
  EkfConfig<double> cfg = EkfConfig<double>::given_start(mean_of(d.noisy), kF, s.sigma);
  cfg.gate_nis = 0;
  cfg.divergence_detection = false;
  cfg.q.setConstant(1e-9);
  cfg.q.tail<3>().setConstant(1.0);
  ScalarEkf<double> ekf(cfg);
  using SV = Vec<double, 12>;
  using SM = Mat<double, 12, 12>;
  SV x;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      x(3 * r + c) = r == c ? 1.0 : 0.0;
  x.tail<3>() = cfg.b0_nT / kF;
  SM p = cfg.p0.asDiagonal();
  p.bottomRightCorner<3, 3>() /= kF * kF;
  SV q = cfg.q;
  q.tail<3>() /= kF * kF;
  const double sig = s.sigma / kF;
  for (int i = 0; i < 200; ++i) {
    const Vec3<double> m = d.noisy[static_cast<std::size_t>(i)] / kF;
    ASSERT_EQ(ekf.update(d.noisy[static_cast<std::size_t>(i)], kF), EkfStatus::kAccepted);
    p += q.asDiagonal();
    Mat3<double> w;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        w(r, c) = x(3 * r + c);
    const Vec3<double> v = m - x.tail<3>();
    const Vec3<double> y = w * v;
    SV h;
    for (int r = 0; r < 3; ++r)
      for (int c = 0; c < 3; ++c)
        h(3 * r + c) = 2 * y(r) * v(c) - 2 * sig * sig * w(r, c);
    h.tail<3>() = -2 * w.transpose() * y;
    const Mat3<double> g = w.transpose() * w;
    const double r = 4 * sig * sig * (w.transpose() * y).squaredNorm() +
                     2 * sig * sig * sig * sig * g.squaredNorm();
    // E|W (m - b)|^2 = |y_true|^2 + sig^2 tr(W^T W): the prediction of F^2 removes the term.
    const double pred = y.squaredNorm() - sig * sig * w.squaredNorm();
    const double sv = h.dot(p * h) + r;
    const SV k = p * h / sv;
    x += k * (1.0 - pred);
    const SM a = SM::Identity() - k * h.transpose();
    p = a * p * a.transpose() + r * k * k.transpose();
  }
  EXPECT_LT((ekf.state().head<9>() - x.head<9>()).norm(), 1e-9);
  EXPECT_LT((ekf.state().tail<3>() - x.tail<3>() * kF).norm(), 1e-6);
  SM p_iface = p;
  p_iface.bottomRows<3>() *= kF;
  p_iface.rightCols<3>() *= kF;
  const SM pe = ekf.covariance();
  EXPECT_LT((pe - p_iface).norm() / p_iface.norm(), 1e-8);
  EXPECT_LT((pe - pe.transpose()).norm(), 1e-12 * pe.norm());
  EXPECT_GT(Eigen::SelfAdjointEigenSolver<SM>(pe).eigenvalues().minCoeff(), 0.0);
}

TEST(ScalarEkf, PaperConfigReproducesThePrintedValues) {
  const auto c = EkfConfig<double>::paper();
  Vec<double, 12> x0, p0, q;
  x0 << 1.5, 0.05, 0.05, 0.05, 0.5, 0.05, 0.05, 0.05, 1, 0, 0, 0;
  p0 << 1, 1e-4, 1e-4, 1e-4, 1, 1e-4, 1e-4, 1e-4, 1, 1e4, 1e4, 1e4;
  q << 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e-4, 1e4, 1e4, 1e4;
  EXPECT_EQ(c.init_mode, EkfInitMode::kGiven);
  Vec<double, 12> x;
  for (int r = 0; r < 3; ++r)
    for (int k = 0; k < 3; ++k)
      x(ekf_w_index(r, k)) = c.w0(r, k);
  x.tail<3>() = c.b0_nT;
  EXPECT_TRUE(x == x0);
  EXPECT_TRUE(c.p0 == p0);
  EXPECT_TRUE(c.q == q);
  EXPECT_EQ(c.r_fixed_nT4, 1e4);
  // The start is applied once the first reference field fixes the normalisation.
  ScalarEkf<double> ekf(c);
  EXPECT_FALSE(ekf.initialised());
  ekf.update(Vec3<double>(kF, 0, 0), kF);
  EXPECT_TRUE(ekf.initialised());
  EXPECT_EQ(ekf.field_scale_nT(), kF);
}

template <typename Scalar>
std::size_t allocations_during_updates() {
  const Scenario s;
  const Data d = simulate(s, 9);
  std::vector<Vec3<Scalar>> samples;
  for (const auto& m : d.noisy)
    samples.push_back(m.cast<Scalar>());
  samples[500](1) = std::numeric_limits<Scalar>::quiet_NaN();
  EkfConfig<Scalar> cfg = default_config<Scalar>(s.sigma);
  cfg.iterations = 2;
  ScalarEkf<Scalar> ekf(cfg);
  Scalar sink{0};
  Eigen::internal::set_is_malloc_allowed(false);
  const test::AllocationScope scope;
  for (const auto& m : samples) {
    ekf.update(m, static_cast<Scalar>(kF));
    sink += ekf.intensity_sigma_nT(samples[0]);
  }
  const auto model = ekf.model();
  const auto p = ekf.covariance();
  const auto sd = ekf.sigma();
  const std::size_t n = scope.count();
  Eigen::internal::set_is_malloc_allowed(true);
  EXPECT_TRUE(ekf.initialised());
  EXPECT_TRUE(std::isfinite(static_cast<double>(sink + model.w(0, 0) + p(0, 0) + sd(0))));
  return n;
}

TEST(ScalarEkf, UpdatePathDoesNotAllocate) {
  EXPECT_EQ(allocations_during_updates<double>(), 0u);
  EXPECT_EQ(allocations_during_updates<float>(), 0u);
}

// ---- debias, noise estimate, start-up by information ----------------------------------------

// Mean over seeds of the calibrated intensity error on the noise-free readings (the simulator's
// truth), with its standard error. `f_used` is the reference the filter is given.
struct BiasStat {
  double mean = 0, se = 0;
};
BiasStat intensity_bias(const EkfConfig<double>& cfg, double f_used, int seeds) {
  const Scenario s;
  double sum = 0, sum2 = 0;
  for (int k = 0; k < seeds; ++k) {
    const Data d = simulate(s, 9000 + static_cast<std::uint64_t>(k));
    ScalarEkf<double> ekf(cfg);
    for (const auto& m : d.noisy)
      ekf.update(m, f_used);
    double e = 0;
    for (const auto& m0 : d.clean)
      e += ekf.intensity_nT(m0) - s.f;
    e /= static_cast<double>(d.clean.size());
    sum += e;
    sum2 += e * e;
  }
  const double n = static_cast<double>(seeds);
  const double mean = sum / n;
  return {mean, std::sqrt((sum2 / n - mean * mean) / (n - 1))};
}

TEST(ScalarEkf, DebiasedPredictionLeavesNoMeanIntensityError) {
  // Ge setup, 200 nT: the noise power sigma^2 tr(W^T W) biases |y|^2 up by sigma^2 tr(G); its
  // effect on the intensity is sigma^2 tr(G) / (2F) = 1.24 nT.
  const Scenario s;
  const Mat3<double> w = s.c.inverse();
  const double tr_g = (w.transpose() * w).trace();
  const double bias_nT = s.sigma * s.sigma * tr_g / (2 * s.f);
  // 400 seeds: a standard error of 0.3 nT, a quarter of the noise-power bias and an eighth of the
  // opposite sign's. Known limit: at 1600 seeds (SE 0.15 nT) a residual of +0.5 nT shows; it is
  // the imperfect cancellation of two other O(sigma^2 / F) terms of the scalar model (the weight
  // 1 / R uses the noisy y: +1.6 nT; the Jacobian at the noisy reading: -1.1 nT), not the debias.
  constexpr int kSeeds = 400;
  EkfConfig<double> cfg = default_config<double>(s.sigma);
  const BiasStat right = intensity_bias(cfg, s.f, kSeeds);
  EkfConfig<double> est = cfg;
  est.estimate_noise = true;
  const BiasStat estimated = intensity_bias(est, s.f, kSeeds);
  EkfConfig<double> none = cfg;
  none.debias = false;
  const BiasStat undebiased = intensity_bias(none, s.f, kSeeds);
  // The opposite sign (adding the term) solves |y|^2 = F^2 - sigma^2 tr(G); the debiased filter
  // solves the same equation when given F'^2 = F^2 - 2 sigma^2 tr(G) (G true; the estimate differs
  // by 1e-3 relative, 0.003 nT here).
  const BiasStat wrong = intensity_bias(cfg, std::sqrt(s.f * s.f - 2 * bias_nT * 2 * s.f), kSeeds);
  std::printf(
      "[ekf-mc] mean intensity error over %d seeds: debiased %.3f +- %.3f nT, noise estimated %.3f "
      "+- %.3f, no debias %.3f +- %.3f, opposite sign %.3f +- %.3f (expected 0, 0, %.2f, %.2f)\n",
      kSeeds, right.mean, right.se, estimated.mean, estimated.se, undebiased.mean, undebiased.se,
      wrong.mean, wrong.se, -bias_nT, -2 * bias_nT);
  EXPECT_LT(std::abs(right.mean), 3 * right.se);
  EXPECT_LT(std::abs(estimated.mean), 3 * estimated.se);
  // The statistic sees the sign error it is meant to catch (the missing term alone, -1.24 nT, is
  // about 4 standard errors: printed, not asserted).
  EXPECT_GT(std::abs(wrong.mean), 3 * wrong.se);
  EXPECT_LT(undebiased.mean, right.mean);
  EXPECT_NEAR(wrong.mean, -2 * bias_nT, 3 * wrong.se);
}

TEST(ScalarEkf, NoiseIsEstimatedFromTheData) {
  // Started with a guess 20x off; the estimate comes from the start-up residuals and innovations.
  for (const double sigma : {2.0, 200.0}) {
    Scenario s;
    s.sigma = sigma;
    s.n = 3000;
    int within = 0;
    for (int k = 0; k < 10; ++k) {
      const Data d = simulate(s, 4100 + static_cast<std::uint64_t>(k));
      EkfConfig<double> cfg = default_config<double>(sigma / 20);
      cfg.estimate_noise = true;
      ScalarEkf<double> ekf(cfg);
      for (const auto& m : d.noisy)
        ekf.update(m, s.f);
      ASSERT_TRUE(ekf.initialised());
      const double est = ekf.noise_estimate_nT(), sd = ekf.noise_estimate_sigma_nT();
      EXPECT_NEAR(ekf.noise_nT(), est, 1e-9 * sigma);  // in use
      EXPECT_LT(sd, 0.03 * sigma);
      EXPECT_GT(sd, 0.005 * sigma);
      EXPECT_LT(std::abs(est - sigma), 4 * sd) << sigma << " seed " << k;
      within += std::abs(est - sigma) < 2 * sd ? 1 : 0;
      // The filter is as good as with the noise given.
      EXPECT_LT(run<double>(s, d, cfg).rmse,
                1.2 * run<double>(s, d, default_config<double>(sigma)).rmse);
    }
    EXPECT_GE(within, 7) << sigma;  // 95 % expected within 2 sigma
  }
  // Given noise: used as given, the estimate still reported.
  Scenario s;
  const Data d = simulate(s, 4200);
  ScalarEkf<float> ekf(default_config<float>(10));
  for (const auto& m : d.noisy)
    ekf.update(m.cast<float>(), static_cast<float>(s.f));
  EXPECT_FLOAT_EQ(ekf.noise_nT(), 10.0f);
  EXPECT_NEAR(ekf.noise_estimate_nT(), s.sigma, 4 * ekf.noise_estimate_sigma_nT());
}

TEST(ScalarEkf, SpikesDoNotInflateTheNoiseEstimate) {
  Scenario s;
  s.spike_fraction = 0.02;
  s.n = 3000;
  const Data d = simulate(s, 4300);
  EkfConfig<double> cfg = default_config<double>(10);
  cfg.estimate_noise = true;
  ScalarEkf<double> ekf(cfg);
  for (const auto& m : d.noisy)
    ekf.update(m, s.f);
  ASSERT_TRUE(ekf.initialised());
  EXPECT_LT(std::abs(ekf.noise_estimate_nT() / s.sigma - 1), 0.06) << ekf.noise_estimate_nT();
}

// Readings whose direction sweeps a cap of half-angle half_deg about an axis, slowly (100 Hz,
// the tilt oscillating at 0.06 Hz and the azimuth turning at 0.2 Hz).
std::vector<Vec3<double>> cap_readings(double half_deg, double sigma, int n, std::uint64_t seed) {
  const Scenario s;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> nd(0.0, 1.0);
  const Vec3<double> axis = Vec3<double>(0.3, 0.5, 0.8).normalized();
  const Vec3<double> e1 = axis.cross(Vec3<double>(1, 0, 0)).normalized();
  const Vec3<double> e2 = axis.cross(e1);
  std::vector<Vec3<double>> out;
  for (int i = 0; i < n; ++i) {
    const double t = 0.01 * i;
    const double th = deg_to_rad(half_deg) * std::abs(std::sin(0.37 * t)), ph = 1.3 * t;
    const Vec3<double> u =
        std::cos(th) * axis + std::sin(th) * (std::cos(ph) * e1 + std::sin(ph) * e2);
    out.push_back(s.c * (s.f * u) + s.b + sigma * Vec3<double>(nd(rng), nd(rng), nd(rng)));
  }
  return out;
}

TEST(ScalarEkf, StartUpSetIsChosenByInformation) {
  // A slowly swept hemisphere: consecutive samples are nearly equal; the start-up set keeps the
  // informative ones (exchanging members as the sweep goes on) and the filter starts once the fit
  // is determined.
  const Scenario s;
  const auto data = cap_readings(90, s.sigma, 20000, 11);
  EkfConfig<double> cfg = default_config<double>(s.sigma);
  ScalarEkf<double> ekf(cfg);
  int accepted = 0, tried = 0;
  for (const auto& m : data) {
    const EkfStatus st = ekf.update(m, kF);
    accepted += st == EkfStatus::kAccepted ? 1 : 0;
    tried += st == EkfStatus::kInitFailed || st == EkfStatus::kInitialised ? 1 : 0;
  }
  ASSERT_TRUE(ekf.initialised());
  const EkfCounters& c = ekf.counters();
  EXPECT_GT(c.init_exchanges, 0u);
  EXPECT_EQ(c.init_attempts, static_cast<std::uint32_t>(tried));
  EXPECT_EQ(c.init_failures + 1, c.init_attempts);
  EXPECT_EQ(c.updates, static_cast<std::uint32_t>(accepted));
  EXPECT_GT(accepted, 10000);
  const Vec3<double> err = ekf.offset_nT() - s.b;
  const Vec3<double> sd = ekf.sigma().tail<3>();
  for (int k = 0; k < 3; ++k)
    EXPECT_LT(std::abs(err(k)), 4 * sd(k)) << k;
}

TEST(ScalarEkf, NarrowCapNamesTheUndeterminedParameters) {
  // 30 deg of direction spread (half-angle 15 deg), even at 1 nT: the offset along the cap and
  // the scales are not determined. The filter does not start and says which states lack
  // information; every try is counted.
  for (const double sigma : {1.0, 200.0}) {
    const auto data = cap_readings(15, sigma, 20000, 12);
    EkfConfig<double> cfg = default_config<double>(10);
    cfg.estimate_noise = true;
    ScalarEkf<double> ekf(cfg);
    int failed = 0;
    for (const auto& m : data)
      failed += ekf.update(m, kF) == EkfStatus::kInitFailed ? 1 : 0;
    EXPECT_GT(failed, 0);
    EXPECT_EQ(ekf.counters().init_failures, static_cast<std::uint32_t>(failed));
    // At the end of the data: one more try if the set changed since the last.
    EXPECT_FALSE(ekf.try_start());
    EXPECT_FALSE(ekf.initialised());
    EXPECT_LE(ekf.counters().init_failures, static_cast<std::uint32_t>(failed) + 1);
    EXPECT_EQ(ekf.counters().init_attempts, ekf.counters().init_failures);
    const auto& r = ekf.init_report();
    EXPECT_EQ(r.failure, EkfInitFailure::kUndetermined) << sigma;
    EXPECT_EQ(r.samples, cfg.init_samples);
    EXPECT_EQ(ekf.counters().updates, 0u);
    // Offsets are among the undetermined states, and their bits agree with the sigmas.
    EXPECT_NE(r.undetermined & (7U << kEkfBx), 0u) << std::hex << r.undetermined;
    for (int k = 0; k < kEkfStateDim; ++k)
      EXPECT_EQ((r.undetermined >> k) & 1U, r.relative_sigma(k) > r.limit ? 1U : 0U);
    EXPECT_LE(r.limit, cfg.init_max_sigma);
  }
}

TEST(ScalarEkf, TryStartFitsAShortRecording) {
  const Scenario s;
  const Data d = simulate(s, 77);
  ScalarEkf<double> few(default_config<double>(s.sigma));
  for (int i = 0; i < 12; ++i)
    few.update(d.noisy[static_cast<std::size_t>(i)], kF);
  EXPECT_FALSE(few.try_start());
  EXPECT_EQ(few.init_report().failure, EkfInitFailure::kTooFewSamples);
  EXPECT_EQ(few.counters().init_attempts, 0u);
  ScalarEkf<double> ekf(default_config<double>(s.sigma));
  for (int i = 0; i < 40; ++i)
    EXPECT_EQ(ekf.update(d.noisy[static_cast<std::size_t>(i)], kF), EkfStatus::kCollecting);
  EXPECT_TRUE(ekf.try_start());
  EXPECT_EQ(ekf.counters().init_attempts, 1u);
  EXPECT_LT((ekf.offset_nT() - s.b).norm(), 5 * ekf.sigma().tail<3>().norm());
}

TEST(ScalarEkf, ReadingsOffAnEllipsoidAreNamedSo) {
  // Directions spread over the sphere but |m| varying as on a hyperboloid x^2 + y^2 - z^2 = F^2:
  // the set determines every parameter, and the quadric is not an ellipsoid.
  std::mt19937_64 rng(5);
  std::normal_distribution<double> nd(0.0, 1.0);
  ScalarEkf<double> ekf(default_config<double>(200));
  for (int i = 0; i < 400; ++i) {
    const double a = 2 * kPi<double> * (i * 0.618034 - std::floor(i * 0.618034));
    const double zt = 0.9 * std::sin(0.37 * i);
    const Vec3<double> m(kF * std::cosh(zt) * std::cos(a), kF * std::cosh(zt) * std::sin(a),
                         kF * std::sinh(zt));
    ekf.update(m + 200 * Vec3<double>(nd(rng), nd(rng), nd(rng)), kF);
  }
  EXPECT_FALSE(ekf.initialised());
  EXPECT_GT(ekf.counters().init_failures, 0u);
  EXPECT_EQ(ekf.init_report().failure, EkfInitFailure::kNotAnEllipsoid)
      << std::hex << ekf.init_report().undetermined;
}

}  // namespace
}  // namespace magvec::core
