#include "magvec/core/vector_calibration_filter.hpp"

#include <gtest/gtest.h>

#include <array>
#include <cmath>
#include <cstdio>
#include <memory>
#include <random>
#include <utility>
#include <vector>

#include "li_setup.hpp"
#include "magvec/core/batch_calibrator.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::core {
namespace {

using namespace test_setup;

// ---- simulator ------------------------------------------------------------------------------
// Truth of one run; every figure a test checks is scored against it.
struct Truth {
  LiParams<double> li = paper_li();
  Vec3<double> h_n = paper_h_n();
  double tau_s = 0;                        // magnetometer lag
  Vec3<double> tc = Vec3<double>::Zero();  // offset temperature coefficients [nT/degC]
  double t0_degC = 20;
};

struct SimSample {
  VfSample<double> in;  // what the filter sees (attitude with INS noise, reading with noise)
  Vec3<double> m_true;  // noise-free reading
  Mat3<double> r_true;  // attitude at the time the field was sensed
  Vec3<double> h_n;     // field at that time
  double temp_degC;
};

// Smooth calibration manoeuvre (Li Euler angles): turning at ~1 rad/s while pitching and rolling
// by up to 40/35 deg with periods of 5-6 s, so the field directions are covered within a few
// seconds; rates up to ~2.5 rad/s.
Mat3<double> manoeuvre(double t) {
  return r_bn_from_li(LiEuler<double>{1.0 * t + 0.8 * std::sin(0.37 * t), 0.7 * std::sin(1.3 * t),
                                      0.6 * std::sin(1.1 * t + 1.0)});
}
Vec3<double> manoeuvre_rate_n(double t) {
  const double h = 1e-5;
  return rate_n_from_attitudes(manoeuvre(t - h), manoeuvre(t + h), 2 * h);
}

struct SimOptions {
  double duration_s = 30;
  double rate_hz = 100;
  double mag_sigma_nT = 0;
  double att_sigma_rad = 0;
  bool with_reference = true;
  bool with_temperature = false;
  double temp_start_degC = 20, temp_end_degC = 20;
  // Lag kinematics: exact (the attitude at t - tau from the trajectory) or the filter's model
  // (constant rate over tau), which makes noise-free data exactly consistent.
  bool exact_lag_kinematics = true;
  // Offset drift [nT over the run] and a field step at a time.
  Vec3<double> drift_nT = Vec3<double>::Zero();
  double step_time_s = -1;
  Vec3<double> step_nT = Vec3<double>::Zero();
};

std::vector<SimSample> simulate_manoeuvre(const Truth& tr, const SimOptions& o,
                                          std::mt19937_64& rng) {
  std::normal_distribution<double> n(0, 1);
  const SensorModel<double> model = from_li(tr.li);
  const int count = static_cast<int>(o.duration_s * o.rate_hz);
  std::vector<SimSample> out;
  out.reserve(static_cast<std::size_t>(count));
  for (int i = 0; i < count; ++i) {
    const double t = i / o.rate_hz;
    SimSample s;
    const Mat3<double> r = manoeuvre(t);
    const Vec3<double> omega = manoeuvre_rate_n(t);
    if (o.exact_lag_kinematics) {
      s.r_true = manoeuvre(t - tr.tau_s);
    } else {
      // C(t - tau) = Exp(-tau [Omega x]) C(t)  ->  R(t - tau) = R(t) Exp(-tau [Omega x])^T
      const double a = omega.norm() * tr.tau_s;
      const Mat3<double> e =
          a > 0 ? Eigen::AngleAxis<double>(-a, omega.normalized()).toRotationMatrix()
                : Mat3<double>::Identity();
      s.r_true = r * e.transpose();
    }
    s.h_n = tr.h_n;
    if (o.step_time_s >= 0 && t >= o.step_time_s) s.h_n += o.step_nT;
    s.temp_degC = o.temp_start_degC + (o.temp_end_degC - o.temp_start_degC) * t / o.duration_s;
    SensorModel<double> m = model;
    m.o += tr.tc * (s.temp_degC - tr.t0_degC) + o.drift_nT * (t / o.duration_s);
    s.m_true = m.predict_raw(s.r_true, s.h_n);
    s.in.m_nT = s.m_true + o.mag_sigma_nT * Vec3<double>(n(rng), n(rng), n(rng));
    s.in.r_bn = with_ins_noise(r, o.att_sigma_rad, rng);
    s.in.omega_n_rad_s = omega;
    s.in.f_nT = o.with_reference ? s.h_n.norm() : std::numeric_limits<double>::quiet_NaN();
    s.in.temperature_degC =
        o.with_temperature ? s.temp_degC : std::numeric_limits<double>::quiet_NaN();
    s.in.interval_s = 1.0 / o.rate_hz;
    out.push_back(s);
  }
  return out;
}

template <typename Scalar>
VfSample<Scalar> cast_sample(const VfSample<double>& s) {
  VfSample<Scalar> o;
  o.m_nT = s.m_nT.cast<Scalar>();
  o.r_bn = s.r_bn.cast<Scalar>();
  o.omega_n_rad_s = s.omega_n_rad_s.cast<Scalar>();
  o.attitude_offset_s = static_cast<Scalar>(s.attitude_offset_s);
  o.f_nT = static_cast<Scalar>(s.f_nT);
  o.temperature_degC = static_cast<Scalar>(s.temperature_degC);
  o.interval_s = static_cast<Scalar>(s.interval_s);
  return o;
}

template <typename Scalar>
using Filter = VectorCalibrationFilter<Scalar>;

template <typename Scalar>
void print_counters(const Filter<Scalar>& f) {
  const VfCounters& c = f.counters();
  std::printf(
      "init %u/%u failed (verdict %s), resets %u (%s), field reopens %u, updates %u, gated %u, "
      "gated ref %u, heading held %u, folds %u\n",
      c.init_failures, c.init_attempts, verdict_name(f.last_init_verdict()), c.resets,
      vf_reset_reason_name(f.last_reset_reason()), c.field_reopens, c.updates, c.gated,
      c.gated_reference, c.heading_held, c.fold_rm);
}

template <typename Scalar>
std::unique_ptr<Filter<Scalar>> run(const std::vector<SimSample>& data, const VfConfig<Scalar>& cfg,
                                    int* initialised_at = nullptr) {
  auto f = std::make_unique<Filter<Scalar>>(cfg);
  for (std::size_t i = 0; i < data.size(); ++i) {
    const VfStatus st = f->update(cast_sample<Scalar>(data[i].in));
    if (st == VfStatus::kInitialised && initialised_at != nullptr)
      *initialised_at = static_cast<int>(i);
  }
  f->flush();  // fold_samples > 1: the last samples' information too
  return f;
}

// The filter configuration of a test run in information folds of `fold` samples (E-VF-B; 1: the
// sequential per-sample updates). The microcontroller image folds every kMcuFold samples.
constexpr int kMcuFold = 16;
template <typename Scalar>
VfConfig<Scalar> fold_cfg(int fold) {
  VfConfig<Scalar> c;
  c.fold_samples = fold;
  return c;
}

// Body-frame rotation error phi of an estimate: Rm_est = Rm_true (I - [phi x]) to first order.
Vec3<double> rm_error_body(const Quat<double>& est, const Quat<double>& truth) {
  const Mat3<double> e = truth.toRotationMatrix().transpose() * est.toRotationMatrix();
  return -Vec3<double>(e(2, 1) - e(1, 2), e(0, 2) - e(2, 0), e(1, 0) - e(0, 1)) * 0.5;
}

// Filter state errors against the truth, in the filter's parameterisation (interface units).
template <typename Scalar>
Vec<double, 19> state_errors(const Filter<Scalar>& f, const Truth& tr, const Vec3<double>& h_n) {
  using F = Filter<Scalar>;
  const SensorModel<double> t = from_li(tr.li);
  Vec<double, 19> e;
  const Mat3<double> w = f.w().template cast<double>();
  for (int k = 0; k < F::kWEntries; ++k) {
    const int r = F::kWRow[static_cast<std::size_t>(k)], c = F::kWCol[static_cast<std::size_t>(k)];
    e(F::kW0 + k) = w(r, c) - t.w(r, c);
  }
  e.segment<3>(F::kO0) = f.offset_ref_nT().template cast<double>() - t.o;
  e.segment<3>(F::kRm0) = rm_error_body(f.rm().template cast<double>(), t.rm);
  e.segment<3>(F::kHn0) = f.h_n_nT().template cast<double>() - h_n;
  e(F::kDt) = static_cast<double>(f.time_offset_s()) - tr.tau_s;
  e.segment<3>(F::kTc0) = f.temperature_coefficients_nT_per_degC().template cast<double>() - tr.tc;
  return e;
}

template <typename Scalar>
Vec<double, 19> state_sigmas(const Filter<Scalar>& f) {
  Vec<double, 19> s;
  const auto p = f.covariance();
  for (int k = 0; k < 19; ++k)
    s(k) = std::sqrt(std::max(static_cast<double>(p(k, k)), 0.0));
  return s;
}

const char* kStateNames[19] = {"W00", "W10", "W11",  "W12",  "W20",  "W22", "o_x",
                               "o_y", "o_z", "rm_x", "rm_y", "rm_z", "h_E", "h_N",
                               "h_U", "dt",  "c_x",  "c_y",  "c_z"};

// ---- 1. noise-free data ---------------------------------------------------------------------
Truth full_truth() {
  Truth tr;
  tr.li.kof = {-350, 820, 120};
  tr.tau_s = 0.010;
  tr.tc = {0.3, -0.2, 0.25};
  return tr;
}

void noise_free_recovers_every_parameter_double(int fold) {
  std::mt19937_64 rng(1);
  const Truth tr = full_truth();
  SimOptions o;
  o.duration_s = 60;
  o.with_temperature = true;
  o.temp_start_degC = 15;
  o.temp_end_degC = 35;
  o.exact_lag_kinematics = false;  // the filter's kinematics: noise-free data are consistent
  const auto data = simulate_manoeuvre(tr, o, rng);
  VfConfig<double> cfg = fold_cfg<double>(fold);
  cfg.mag_noise_nT = 1e-4;
  cfg.attitude_noise_rad = 1e-9;
  cfg.reference_sigma_nT = 1e-6;
  cfg.temperature_ref_degC = tr.t0_degC;
  cfg.init_min_rotation_deg = 5;
  int at = -1;
  auto f = run<double>(data, cfg, &at);
  print_counters(*f);
  ASSERT_TRUE(f->initialised());
  std::printf("initialised at sample %d\n", at);
  const Vec<double, 19> e = state_errors(*f, tr, tr.h_n);
  const double fmag = tr.h_n.norm();
  for (int k = 0; k < 19; ++k)
    std::printf("%s err %.3e\n", kStateNames[k], e(k));
  for (int k = 0; k < 6; ++k)
    EXPECT_LT(std::abs(e(k)), 1e-8) << kStateNames[k];
  for (int k = 6; k < 9; ++k)
    EXPECT_LT(std::abs(e(k)), 1e-8 * fmag) << kStateNames[k];
  for (int k = 9; k < 12; ++k)
    EXPECT_LT(std::abs(e(k)), 1e-8) << kStateNames[k];
  for (int k = 12; k < 15; ++k)
    EXPECT_LT(std::abs(e(k)), 1e-8 * fmag) << kStateNames[k];
  EXPECT_LT(std::abs(e(15)), 1e-8 * tr.tau_s);
  for (int k = 16; k < 19; ++k)
    EXPECT_LT(std::abs(e(k)), 1e-8 * tr.tc.cwiseAbs().maxCoeff()) << kStateNames[k];
}
TEST(VectorCalibrationFilter, NoiseFreeRecoversEveryParameterDouble) {
  noise_free_recovers_every_parameter_double(1);
}
TEST(VectorCalibrationFilter, NoiseFreeRecoversEveryParameterDoubleInFolds) {
  noise_free_recovers_every_parameter_double(kMcuFold);
}

// float32: the same data with realistic noise settings (float cannot resolve 1e-4 nT in 50 uT).
TEST(VectorCalibrationFilter, NoiseFreeFloatReachesFloatResolution) {
  std::mt19937_64 rng(1);
  const Truth tr = full_truth();
  SimOptions o;
  o.duration_s = 60;
  o.with_temperature = true;
  o.temp_start_degC = 15;
  o.temp_end_degC = 35;
  o.exact_lag_kinematics = false;
  const auto data = simulate_manoeuvre(tr, o, rng);
  VfConfig<float> cfg;
  cfg.temperature_ref_degC = static_cast<float>(tr.t0_degC);
  cfg.init_min_rotation_deg = 5;
  auto f = run<float>(data, cfg);
  print_counters(*f);
  ASSERT_TRUE(f->initialised());
  EXPECT_EQ(f->counters().resets, 0U);
  const Vec<double, 19> e = state_errors(*f, tr, tr.h_n);
  const double fmag = tr.h_n.norm();
  double worst[6] = {0, 0, 0, 0, 0, 0};  // W, o/F, rm, h/F, dt/tau, c/|c|
  for (int k = 0; k < 6; ++k)
    worst[0] = std::max(worst[0], std::abs(e(k)));
  for (int k = 6; k < 9; ++k)
    worst[1] = std::max(worst[1], std::abs(e(k)) / fmag);
  for (int k = 9; k < 12; ++k)
    worst[2] = std::max(worst[2], std::abs(e(k)));
  for (int k = 12; k < 15; ++k)
    worst[3] = std::max(worst[3], std::abs(e(k)) / fmag);
  worst[4] = std::abs(e(15)) / tr.tau_s;
  for (int k = 16; k < 19; ++k)
    worst[5] = std::max(worst[5], std::abs(e(k)) / tr.tc.cwiseAbs().maxCoeff());
  std::printf(
      "float noise-free relative errors: W %.2e, o/F %.2e, Rm %.2e rad, h_n/F %.2e, dt %.2e, c "
      "%.2e\n",
      worst[0], worst[1], worst[2], worst[3], worst[4], worst[5]);
  EXPECT_LT(worst[0], 1e-6);
  EXPECT_LT(worst[1], 1e-6);
  EXPECT_LT(worst[2], 1e-6);
  EXPECT_LT(worst[3], 1e-6);
  EXPECT_LT(worst[4], 1e-3);
  EXPECT_LT(worst[5], 5e-3);  // measured 1.9e-3: 0.01 nT over the 20 degC ramp
}

// ---- 2. one pass against the batch one-step fit ----------------------------------------------
// Monte Carlo accumulators: RMS errors of the filter and of the batch fit on the same data, and
// the filter's reported 1-sigma against its own scatter.
struct Comparison {
  static constexpr int kLi = 12;  // ks 3, O 3, Kof 3, Rm angles 3
  std::array<double, kLi> ss_filter{}, ss_batch{};
  Vec3<double> enu_ss_filter = Vec3<double>::Zero(), enu_ss_batch = Vec3<double>::Zero();
  double f_ss_filter = 0, f_ss_batch = 0;
  long enu_n = 0;
  std::vector<Vec<double, 19>> state_err, state_sd;
  int runs = 0;

  static std::array<double, kLi> li_vector(const LiParams<double>& p) {
    std::array<double, kLi> v{};
    for (int k = 0; k < 3; ++k) {
      v[static_cast<std::size_t>(k)] = p.ks(k);
      v[static_cast<std::size_t>(3 + k)] = p.o_rad(k);
      v[static_cast<std::size_t>(6 + k)] = p.kof(k);
      v[static_cast<std::size_t>(9 + k)] = p.rm_rad(k);
    }
    return v;
  }
  // Parameter-induced errors: the estimated model applied to the noise-free samples.
  static void induced(const SensorModel<double>& m, const std::vector<SimSample>& data,
                      Vec3<double>* enu_ss, double* f_ss) {
    const Mat3<double> rmt = m.rm_matrix().transpose();
    for (const SimSample& s : data) {
      const Vec3<double> hs = m.w * (s.m_true - m.o);
      const Vec3<double> e = s.r_true.transpose() * (rmt * hs) - s.h_n;
      *enu_ss += e.cwiseProduct(e);
      const double ef = hs.norm() - s.h_n.norm();
      *f_ss += ef * ef;
    }
  }
  void add(const Truth& tr, const std::vector<SimSample>& data, const Filter<double>& f,
           const BatchResult<double>& b) {
    LiParams<double> lf;
    ASSERT_EQ(to_li(f.model(), &lf), ConversionStatus::kOk);
    const auto t = li_vector(tr.li), vf = li_vector(lf), vb = li_vector(b.li);
    for (std::size_t k = 0; k < static_cast<std::size_t>(kLi); ++k) {
      ss_filter[k] += (vf[k] - t[k]) * (vf[k] - t[k]);
      ss_batch[k] += (vb[k] - t[k]) * (vb[k] - t[k]);
    }
    induced(f.model(), data, &enu_ss_filter, &f_ss_filter);
    induced(b.model, data, &enu_ss_batch, &f_ss_batch);
    enu_n += static_cast<long>(data.size());
    state_err.push_back(state_errors(f, tr, data.back().h_n));
    state_sd.push_back(state_sigmas(f));
    ++runs;
  }
  // Filter RMS over batch RMS for every Li parameter, E/N/U and |h|; the worst is returned.
  double report_and_check(double limit) const {
    static const char* names[kLi] = {"ks_x",  "ks_y",  "ks_z",  "O1", "O2", "O3",
                                     "Kof_x", "Kof_y", "Kof_z", "am", "bm", "gm"};
    double worst = 0;
    for (std::size_t k = 0; k < static_cast<std::size_t>(kLi); ++k) {
      const double rf = std::sqrt(ss_filter[k] / runs), rb = std::sqrt(ss_batch[k] / runs);
      const double unit = k < 3 ? 1e-2 : (k < 6 || k >= 9 ? kDeg : 1.0);
      std::printf("  %-6s RMS error filter %.3e batch %.3e %s  ratio %.3f\n", names[k], rf / unit,
                  rb / unit, k < 3 ? "%" : (k < 6 || k >= 9 ? "deg" : "nT"), rf / rb);
      EXPECT_LT(rf, limit * rb) << names[k];
      worst = std::max(worst, rf / rb);
    }
    for (int c = 0; c < 3; ++c) {
      const double rf = std::sqrt(enu_ss_filter(c) / static_cast<double>(enu_n));
      const double rb = std::sqrt(enu_ss_batch(c) / static_cast<double>(enu_n));
      std::printf("  %c      induced RMS filter %.3f nT batch %.3f nT  ratio %.3f\n", "ENU"[c], rf,
                  rb, rf / rb);
      EXPECT_LT(rf, limit * rb) << "ENU " << c;
      worst = std::max(worst, rf / rb);
    }
    const double rf = std::sqrt(f_ss_filter / static_cast<double>(enu_n));
    const double rb = std::sqrt(f_ss_batch / static_cast<double>(enu_n));
    std::printf("  |h|    induced RMS filter %.4f nT batch %.4f nT  ratio %.3f\n", rf, rb, rf / rb);
    EXPECT_LT(rf, limit * rb) << "|h|";
    return std::max(worst, rf / rb);
  }
  // Reported 1-sigma (RMS over runs) against the RMS error over runs, per state.
  double check_sigmas(const std::vector<int>& states, double tolerance) const {
    double worst = 0;
    for (int k : states) {
      double se = 0, ss = 0;
      for (int r = 0; r < runs; ++r) {
        se += state_err[static_cast<std::size_t>(r)](k) * state_err[static_cast<std::size_t>(r)](k);
        ss += state_sd[static_cast<std::size_t>(r)](k) * state_sd[static_cast<std::size_t>(r)](k);
      }
      const double ratio = std::sqrt(ss / se);
      std::printf("  %-5s reported 1-sigma %.3e, Monte Carlo RMS error %.3e, ratio %.3f\n",
                  kStateNames[k], std::sqrt(ss / runs), std::sqrt(se / runs), ratio);
      EXPECT_NEAR(ratio, 1.0, tolerance) << kStateNames[k];
      worst = std::max(worst, std::abs(ratio - 1));
    }
    return worst;
  }
};

std::vector<SimSample> li_samples(const Truth& tr, std::mt19937_64& rng) {
  const auto raw =
      simulate(from_li(tr.li), tr.h_n, random_attitudes(60, rng), 0.3, 0.015 * kDeg, rng);
  std::vector<SimSample> out;
  for (const Sample& s : raw) {
    SimSample o;
    o.in.m_nT = s.m;
    o.in.r_bn = s.r_meas;
    o.in.f_nT = s.f;
    o.m_true = s.m_true;
    o.r_true = s.r_true;
    o.h_n = tr.h_n;
    o.temp_degC = 20;
    out.push_back(o);
  }
  return out;
}

template <std::size_t Capacity>
BatchResult<double> batch_fit(const std::vector<SimSample>& data) {
  auto cal = std::make_unique<BatchCalibrator<double, Capacity>>();
  for (const SimSample& s : data)
    cal->add_sample(s.in.m_nT, s.in.f_nT, s.in.r_bn);
  return cal->solve(BatchMethod::kOneStep);
}

TEST(VectorCalibrationFilter, LiSetupMatchesTheBatchOneStepFit) {
  constexpr int kRuns = 100;
  const Truth tr;
  Comparison cmp;
  for (int run_i = 0; run_i < kRuns; ++run_i) {
    std::mt19937_64 rng(5000 + static_cast<unsigned>(run_i));
    const auto data = li_samples(tr, rng);
    const BatchResult<double> b = batch_fit<1024>(data);
    ASSERT_EQ(b.verdict, Verdict::kOk) << verdict_name(b.verdict);
    auto f = run<double>(data, VfConfig<double>{});
    ASSERT_TRUE(f->initialised()) << "run " << run_i;
    ASSERT_EQ(f->counters().resets, 0U);
    cmp.add(tr, data, *f, b);
  }
  std::printf("Li 2023 setup, %d runs (60 random attitudes, 0.3 nT, 0.015 deg):\n", kRuns);
  cmp.report_and_check(1.2);
  cmp.check_sigmas({0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14}, 0.25);
}

// Measured (50 runs): filter/batch RMS ratios 0.98-1.07 (am 1.07, the filter also estimates the
// time offset), reported 1-sigma over scatter 0.88-1.24. Before the start replayed every sample
// seen while collecting (docs/equations.md E-VF-1) the ratios reached 1.87 (Kof_x): the first
// 2.9 s, passed over while collecting, carry much of the x-axis information (the batch fit without
// them: Kof_x 0.159 nT instead of 0.099 nT).
void manoeuvre_matches_the_batch_one_step_fit(int fold) {
  constexpr int kRuns = 50;
  const Truth tr;
  SimOptions o;
  o.duration_s = 20;
  o.mag_sigma_nT = 0.3;
  o.att_sigma_rad = 0.015 * kDeg;
  Comparison cmp;
  for (int run_i = 0; run_i < kRuns; ++run_i) {
    std::mt19937_64 rng(7000 + static_cast<unsigned>(run_i));
    const auto data = simulate_manoeuvre(tr, o, rng);
    const BatchResult<double> b = batch_fit<kDynamicCapacity>(data);
    ASSERT_EQ(b.verdict, Verdict::kOk) << verdict_name(b.verdict);
    auto f = run<double>(data, fold_cfg<double>(fold));
    if (run_i == 0) print_counters(*f);
    ASSERT_TRUE(f->initialised()) << "run " << run_i;
    ASSERT_EQ(f->counters().resets, 0U);
    cmp.add(tr, data, *f, b);
  }
  std::printf(
      "100 Hz manoeuvre, %d runs of 20 s (0.3 nT, 0.015 deg, F given, time offset estimated):\n",
      kRuns);
  cmp.report_and_check(1.2);
  cmp.check_sigmas({0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15}, 0.25);
}
TEST(VectorCalibrationFilter, ManoeuvreMatchesTheBatchOneStepFit) {
  manoeuvre_matches_the_batch_one_step_fit(1);
}
TEST(VectorCalibrationFilter, ManoeuvreMatchesTheBatchOneStepFitInFolds) {
  manoeuvre_matches_the_batch_one_step_fit(kMcuFold);
}
}  // namespace
}  // namespace magvec::core
namespace magvec::core {
namespace {

// ---- 3. temperature, drift, field step ----------------------------------------------------------
SimOptions noisy_manoeuvre(double duration_s) {
  SimOptions o;
  o.duration_s = duration_s;
  o.mag_sigma_nT = 0.3;
  o.att_sigma_rad = 0.015 * kDeg;
  return o;
}

// A 20 degC temperature ramp over the run, with 0.3 nT/degC offset coefficients.
Truth ramp_truth() {
  Truth tr;
  tr.tc = {0.3, -0.3, 0.3};
  return tr;
}
SimOptions ramp_manoeuvre(double duration_s) {
  SimOptions o = noisy_manoeuvre(duration_s);
  o.with_temperature = true;
  o.temp_start_degC = 15;
  o.temp_end_degC = 35;
  return o;
}

// One ramp run from a seed: its data and the filter (temperatures referred to the truth's T0).
struct RampRun {
  std::vector<SimSample> data;
  std::unique_ptr<Filter<double>> f;
};
RampRun run_ramp(const Truth& tr, const SimOptions& o, unsigned seed, int fold) {
  std::mt19937_64 rng(seed);
  RampRun r;
  r.data = simulate_manoeuvre(tr, o, rng);
  VfConfig<double> cfg = fold_cfg<double>(fold);
  cfg.temperature_ref_degC = tr.t0_degC;
  r.f = run<double>(r.data, cfg);
  return r;
}

void temperature_ramp_recovers_the_coefficients(int fold) {
  const Truth tr = ramp_truth();
  const SimOptions o = ramp_manoeuvre(60);
  for (unsigned seed : {11U, 12U, 13U}) {
    const RampRun rr = run_ramp(tr, o, seed, fold);
    const Filter<double>* f = rr.f.get();
    ASSERT_TRUE(f->initialised());
    EXPECT_EQ(f->counters().resets, 0U);
    const VfSigmas<double> sg = f->sigmas();
    const Vec3<double> c = f->temperature_coefficients_nT_per_degC();
    const Vec3<double> o_end = f->offset_nT(o.temp_end_degC);
    const Vec3<double> o_true = tr.li.kof + tr.tc * (o.temp_end_degC - tr.t0_degC);
    std::printf(
        "seed %u: c = (%.4f %.4f %.4f) +- (%.4f %.4f %.4f) nT/degC, offset error at 35 degC "
        "(%.3f %.3f %.3f) nT\n",
        seed, c(0), c(1), c(2), sg.tc_nT_per_degC(0), sg.tc_nT_per_degC(1), sg.tc_nT_per_degC(2),
        o_end(0) - o_true(0), o_end(1) - o_true(1), o_end(2) - o_true(2));
    for (int k = 0; k < 3; ++k) {
      EXPECT_LT(std::abs(c(k) - tr.tc(k)), 3 * sg.tc_nT_per_degC(k)) << k;
      EXPECT_LT(std::abs(o_end(k) - o_true(k)), 1.0) << k;
    }
  }
}
// E-VF-10's output envelope against the same figure formed independently: the outputs (|h| and
// E/N/U) of the filter's model at each envelope attitude, for the reading that model predicts
// there, differentiated numerically in the 15 calibration parameters (W's entries, o, Rm's error
// as Rm (I - [phi x]) per E-VF-3, c_T), with the filter's covariance: (1/n) sum J P J^T. A run with
// a temperature ramp, so that the c_T columns (dT times o's) count.
void output_uncertainty_is_the_envelopes_linearised_error(int fold) {
  const RampRun rr = run_ramp(ramp_truth(), ramp_manoeuvre(20), 31, fold);
  const std::vector<SimSample>& data = rr.data;
  const Filter<double>* f = rr.f.get();
  ASSERT_TRUE(f->initialised());
  ASSERT_EQ(f->counters().resets, 0U);
  const VfOutputUncertainty<double> ou = f->output_uncertainty();
  ASSERT_EQ(ou.attitudes, static_cast<std::uint32_t>(kEnvelopeAttitudes));
  // The filter's tilt moments: every sample it was given (no reset).
  TiltMoments<double> tilts;
  for (const SimSample& s : data)
    tilts.add(s.in.r_bn);
  const SensorModel<double> m = f->model();
  const Mat3<double> w0 = f->w();
  const Mat3<double> rm0 = f->rm().toRotationMatrix();
  const Vec3<double> o0 = f->offset_ref_nT();
  const Vec3<double> c0 = f->temperature_coefficients_nT_per_degC();
  const double dt = data.back().in.temperature_degC - f->temperature_ref_degC();
  const Vec3<double> h_n = f->h_n_nT();
  // The calibration parameters' covariance (state order W, o, Rm, c_T).
  const std::array<int, 15> cal = {0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 16, 17, 18};
  const auto p_full = f->covariance();
  Mat<double, 15, 15> p;
  for (int i = 0; i < 15; ++i)
    for (int j = 0; j < 15; ++j)
      p(i, j) = p_full(cal[static_cast<std::size_t>(i)], cal[static_cast<std::size_t>(j)]);
  const std::array<std::pair<int, int>, 6> w_entry = {
      {{0, 0}, {1, 0}, {1, 1}, {1, 2}, {2, 0}, {2, 2}}};
  double sum_i = 0, sum_v = 0;
  int n = 0;
  for_each_envelope_attitude(tilts, [&](const Mat3<double>& r) {
    const Vec3<double> reading = m.predict_raw(r, h_n);
    // Outputs (|h|, E, N, U) at parameters moved by d along parameter k.
    auto outputs = [&](int k, double d) {
      Mat3<double> w = w0;
      Vec3<double> off = o0, c = c0;
      Mat3<double> rm = rm0;
      if (k < 6)
        w(w_entry[static_cast<std::size_t>(k)].first,
          w_entry[static_cast<std::size_t>(k)].second) += d;
      else if (k < 9)
        off(k - 6) += d;
      else if (k < 12)
        rm = rm0 * exp_so3(Vec3<double>(-d * Vec3<double>::Unit(k - 9)));
      else
        c(k - 12) += d;
      const Vec3<double> hs = w * (reading - off - c * dt);
      const Vec3<double> enu = r.transpose() * rm.transpose() * hs;
      return Vec<double, 4>(hs.norm(), enu(0), enu(1), enu(2));
    };
    Mat<double, 4, 15> j;
    for (int k = 0; k < 15; ++k) {
      const double step = k < 6 ? 1e-6 : (k < 9 ? 1e-3 : (k < 12 ? 1e-7 : 1e-3));
      j.col(k) = (outputs(k, step) - outputs(k, -step)) / (2 * step);
    }
    sum_i += (j.row(0) * p * j.row(0).transpose())(0, 0);
    const Mat<double, 3, 15> jv = j.bottomRows<3>();
    sum_v += (jv * p * jv.transpose()).trace();
    ++n;
  });
  ASSERT_EQ(n, kEnvelopeAttitudes);
  const double sigma_i = std::sqrt(sum_i / n);
  const double sigma_v = std::sqrt(sum_v / (3 * n));
  std::printf("fold %d: envelope |h| %.6f nT (independent %.6f), E/N/U %.6f nT (%.6f)\n", fold,
              ou.intensity_nT, sigma_i, ou.vector_nT, sigma_v);
  EXPECT_NEAR(ou.intensity_nT, sigma_i, 1e-4 * sigma_i);
  EXPECT_NEAR(ou.vector_nT, sigma_v, 1e-4 * sigma_v);
}
TEST(VectorCalibrationFilter, OutputUncertaintyIsTheEnvelopesLinearisedError) {
  output_uncertainty_is_the_envelopes_linearised_error(1);
}
TEST(VectorCalibrationFilter, OutputUncertaintyIsTheEnvelopesLinearisedErrorInFolds) {
  output_uncertainty_is_the_envelopes_linearised_error(kMcuFold);
}

TEST(VectorCalibrationFilter, TemperatureRampRecoversTheCoefficients) {
  temperature_ramp_recovers_the_coefficients(1);
}
TEST(VectorCalibrationFilter, TemperatureRampRecoversTheCoefficientsInFolds) {
  temperature_ramp_recovers_the_coefficients(kMcuFold);
}

// 300 nT over 10 minutes (0.5 nT/s), with a 1 nT/sqrt(s) random walk on the offset.
void tracks_a_300_nt_offset_drift(int fold) {
  const Truth tr;
  SimOptions o = noisy_manoeuvre(600);
  o.drift_nT = {300, -300, 300};
  std::mt19937_64 rng(21);
  const auto data = simulate_manoeuvre(tr, o, rng);
  VfConfig<double> cfg = fold_cfg<double>(fold);
  cfg.offset_q_nT2_per_s = 1.0;
  Filter<double> f(cfg);
  double ss = 0, worst = 0, worst_sigma = 0;
  int n = 0;
  for (std::size_t i = 0; i < data.size(); ++i) {
    f.update(data[i].in);
    const double t = static_cast<double>(i) / o.rate_hz;
    if (t < 300 || !f.initialised()) continue;
    const Vec3<double> truth_o = tr.li.kof + o.drift_nT * (t / o.duration_s);
    const Vec3<double> e = f.offset_ref_nT() - truth_o;
    ss += e.squaredNorm() / 3;
    worst = std::max(worst, e.cwiseAbs().maxCoeff());
    worst_sigma =
        std::max(worst_sigma, (e.cwiseQuotient(f.sigmas().o_ref_nT)).cwiseAbs().maxCoeff());
    ++n;
  }
  print_counters(f);
  const double rms = std::sqrt(ss / n);
  std::printf(
      "offset drift 300 nT/600 s: offset error over the last 300 s RMS %.3f nT, worst %.3f nT "
      "(%.2f sigma), final 1-sigma %.3f nT\n",
      rms, worst, worst_sigma, f.sigmas().o_ref_nT.maxCoeff());
  EXPECT_EQ(f.counters().resets, 0U);
  EXPECT_LT(rms, 1.0);          // measured 0.73 nT
  EXPECT_LT(worst_sigma, 4.0);  // measured 2.98 sigma (3.02 nT against a 1.14 nT 1-sigma)
}
TEST(VectorCalibrationFilter, TracksA300nTOffsetDrift) {
  tracks_a_300_nt_offset_drift(1);
}
TEST(VectorCalibrationFilter, TracksA300nTOffsetDriftInFolds) {
  tracks_a_300_nt_offset_drift(kMcuFold);
}

void follows_a_20_nt_field_step(int fold) {
  const Truth tr;
  SimOptions o = noisy_manoeuvre(60);
  SimOptions o_step = o;
  o_step.step_time_s = 30;
  o_step.step_nT = {0, 12, -16};
  std::mt19937_64 rng_a(31), rng_b(31);
  const auto data = simulate_manoeuvre(tr, o, rng_a);
  const auto data_step = simulate_manoeuvre(tr, o_step, rng_b);
  VfConfig<double> cfg = fold_cfg<double>(fold);
  cfg.field_q_nT2_per_s = 0.01;
  auto f = run<double>(data, cfg);
  auto g = run<double>(data_step, cfg);
  print_counters(*g);
  EXPECT_GE(g->counters().field_reopens, 1U);
  EXPECT_EQ(g->counters().resets, 0U);
  const Vec<double, 19> e = state_errors(*f, tr, data.back().h_n);
  const Vec<double, 19> es = state_errors(*g, tr, data_step.back().h_n);
  const Vec<double, 19> sig = state_sigmas(*g);
  for (int k = 12; k < 15; ++k) {
    std::printf("%s error after the step %.3f nT (1-sigma %.3f)\n", kStateNames[k], es(k), sig(k));
    EXPECT_LT(std::abs(es(k)), 3 * sig(k) + 0.5) << kStateNames[k];
  }
  double worst = 0;
  for (int k = 0; k < 12; ++k) {
    if (k >= 6 && k < 9) continue;  // offsets: reported with W below
    worst = std::max(worst, std::abs(es(k) - e(k)) / sig(k));
    EXPECT_LT(std::abs(es(k)), 3 * sig(k)) << kStateNames[k];
  }
  std::printf("W and Rm with and without the step differ by at most %.3f sigma\n", worst);
  EXPECT_LT(worst, 1.0);
}
TEST(VectorCalibrationFilter, FollowsA20nTFieldStepWithoutCorruptingWAndRm) {
  follows_a_20_nt_field_step(1);
}
TEST(VectorCalibrationFilter, FollowsA20nTFieldStepWithoutCorruptingWAndRmInFolds) {
  follows_a_20_nt_field_step(kMcuFold);
}

// Spikes on 2 % of the live samples (+-400 nT on one axis, 1 300 whitened sigmas): each one gated,
// none applied (the state ends where the same data without those samples take it, within a tenth
// of a sigma), no reset. In folds the gate first takes the NIS at R alone (a bound), the exact one
// only when that fails: the same decisions.
void gates_spikes(int fold) {
  const Truth tr;
  const SimOptions o = noisy_manoeuvre(30);
  std::mt19937_64 rng(71);
  const auto clean = simulate_manoeuvre(tr, o, rng);
  std::vector<SimSample> spiked = clean, without;
  std::mt19937_64 pick(72);
  std::uniform_int_distribution<int> axis(0, 2);
  int spikes = 0;
  // Past the start (the first 10 s): live samples only, every 50th.
  for (std::size_t i = 0; i < clean.size(); ++i) {
    if (i < 1000 || i % 50 != 0) {
      without.push_back(clean[i]);
      continue;
    }
    spiked[i].in.m_nT(axis(pick)) += (spikes % 2 == 0 ? 400.0 : -400.0);
    ++spikes;
  }
  auto f = run<double>(without, fold_cfg<double>(fold));
  auto g = run<double>(spiked, fold_cfg<double>(fold));
  print_counters(*g);
  ASSERT_TRUE(g->initialised());
  EXPECT_EQ(g->counters().resets, 0U);
  EXPECT_EQ(g->counters().gated, static_cast<std::uint32_t>(spikes));
  EXPECT_EQ(f->counters().gated, 0U);
  const Vec<double, 19> e = state_errors(*f, tr, tr.h_n), eg = state_errors(*g, tr, tr.h_n);
  const Vec<double, 19> sig = state_sigmas(*g);
  double worst = 0;
  for (int k = 0; k < 16; ++k)  // no temperature: the coefficients stay at their prior
    worst = std::max(worst, std::abs(eg(k) - e(k)) / sig(k));
  std::printf(
      "%d spikes gated of %d; states with them and without those samples differ by at most "
      "%.3f sigma\n",
      static_cast<int>(g->counters().gated), spikes, worst);
  EXPECT_LT(worst, 0.1);
}
TEST(VectorCalibrationFilter, GatesSpikes) {
  gates_spikes(1);
}
TEST(VectorCalibrationFilter, GatesSpikesInFolds) {
  gates_spikes(kMcuFold);
}

// A finite reading so large that the whitened residual and rows overflow float32 (3e38 nT): the
// sample is refused (gated, or a restart with the non-finite reason; in folds the rows are checked
// in the block's sums at the fold), and whatever happens no non-finite value reaches the outputs.
void overflowing_reading_never_corrupts_the_state(int fold) {
  const Truth tr;
  const SimOptions o = noisy_manoeuvre(20);
  std::mt19937_64 rng(73);
  const auto data = simulate_manoeuvre(tr, o, rng);
  auto f = std::make_unique<Filter<float>>(fold_cfg<float>(fold));
  const std::size_t bad_at = data.size() / 2;
  VfStatus bad_status = VfStatus::kAccepted;
  for (std::size_t i = 0; i < data.size(); ++i) {
    VfSample<float> in = cast_sample<float>(data[i].in);
    if (i == bad_at) {
      ASSERT_TRUE(f->initialised());
      in.m_nT = Vec3<float>(3e38f, -3e38f, 3e38f);
      ASSERT_TRUE(in.m_nT.allFinite());
    }
    const VfStatus st = f->update(in);
    if (i == bad_at) bad_status = st;
    if (i >= bad_at && f->initialised()) {
      ASSERT_TRUE(f->w().allFinite()) << i;
      ASSERT_TRUE(f->offset_nT().allFinite()) << i;
      ASSERT_TRUE(f->h_n_nT().allFinite()) << i;
      ASSERT_TRUE(f->covariance().allFinite()) << i;
    }
  }
  (void)f->flush();
  std::printf("fold %d: the 3e38 nT reading gave status %d (kGated %d, kReset %d), resets %u\n",
              fold, static_cast<int>(bad_status), static_cast<int>(VfStatus::kGated),
              static_cast<int>(VfStatus::kReset), static_cast<unsigned>(f->counters().resets));
  EXPECT_TRUE(bad_status == VfStatus::kGated || bad_status == VfStatus::kReset)
      << static_cast<int>(bad_status);
  if (f->counters().resets > 0) {
    EXPECT_EQ(f->last_reset_reason(), VfResetReason::kNonFiniteState);
  }
  // It runs again by the end (a restart collects and starts from data), at the truth.
  ASSERT_TRUE(f->initialised());
  EXPECT_LT((f->w().cast<double>() - from_li(tr.li).w).cwiseAbs().maxCoeff(), 1e-3);
}
TEST(VectorCalibrationFilter, OverflowingReadingNeverCorruptsTheState) {
  overflowing_reading_never_corrupts_the_state(1);
}
TEST(VectorCalibrationFilter, OverflowingReadingNeverCorruptsTheStateInFolds) {
  overflowing_reading_never_corrupts_the_state(kMcuFold);
}

// ---- 4. time offset -------------------------------------------------------------------------
void recovers_10ms_magnetometer_lag(int fold) {
  Truth tr;
  tr.tau_s = 0.010;
  const SimOptions o = noisy_manoeuvre(30);  // exact kinematics: attitude at t - tau
  for (unsigned seed : {41U, 42U, 43U}) {
    std::mt19937_64 rng(seed);
    const auto data = simulate_manoeuvre(tr, o, rng);
    auto f = run<double>(data, fold_cfg<double>(fold));
    ASSERT_TRUE(f->initialised());
    EXPECT_EQ(f->counters().resets, 0U);
    std::printf("seed %u: time offset %.4f ms +- %.4f ms (truth 10 ms)\n", seed,
                f->time_offset_s() * 1e3, f->sigmas().dt_s * 1e3);
    EXPECT_LT(std::abs(f->time_offset_s() - tr.tau_s), 1e-3);
  }
}
TEST(VectorCalibrationFilter, Recovers10msMagnetometerLag) {
  recovers_10ms_magnetometer_lag(1);
}
TEST(VectorCalibrationFilter, Recovers10msMagnetometerLagInFolds) {
  recovers_10ms_magnetometer_lag(kMcuFold);
}

// The caller may hand over the attitude already taken at t - a (interpolated from the INS samples,
// as the CLI runner does with the filter's current offset): VfSample::attitude_offset_s = a, and
// the filter rotates only by dt - a. A 20 ms lag with a = 15 ms applied must still come out at 20
// ms (5 ms if the filter ignored a, and 15 ms if it rotated by its whole dt on top).
TEST(VectorCalibrationFilter, AttitudeAlreadyMovedByTheCallerLeavesOnlyTheRestToTheRate) {
  Truth tr;
  tr.tau_s = 0.020;
  const double applied_s = 0.015;
  const SimOptions o = noisy_manoeuvre(30);
  std::mt19937_64 rng(61);
  std::vector<SimSample> data = simulate_manoeuvre(tr, o, rng);
  std::mt19937_64 noise(62);
  for (std::size_t i = 0; i < data.size(); ++i) {
    const double t = static_cast<double>(i) / o.rate_hz;
    data[i].in.r_bn = with_ins_noise(manoeuvre(t - applied_s), o.att_sigma_rad, noise);
    data[i].in.omega_n_rad_s = manoeuvre_rate_n(t - applied_s);
    data[i].in.attitude_offset_s = applied_s;
  }
  auto f = run<double>(data, VfConfig<double>{});
  ASSERT_TRUE(f->initialised());
  std::printf("time offset %.4f ms +- %.4f ms (truth 20 ms, 15 ms applied by the caller)\n",
              f->time_offset_s() * 1e3, f->sigmas().dt_s * 1e3);
  EXPECT_LT(std::abs(f->time_offset_s() - tr.tau_s), 4 * f->sigmas().dt_s);
  EXPECT_LT(std::abs(f->time_offset_s() - tr.tau_s), 1e-4);
  // A non-finite offset is bad input, counted, the state untouched.
  VfSample<double> bad = data.back().in;
  bad.attitude_offset_s = std::numeric_limits<double>::quiet_NaN();
  const double before = f->time_offset_s();
  EXPECT_EQ(f->update(bad), VfStatus::kRejectedNonFinite);
  EXPECT_EQ(f->time_offset_s(), before);
}

// ---- 5. float32 against double --------------------------------------------------------------
// Both precisions from the same stored start (a start from data may keep different samples when a
// batch verdict differs in the last digit, which would compare data sets, not arithmetic).
template <typename Scalar>
VfStart<Scalar> stored_start(const Truth& tr) {
  LiParams<double> li = tr.li;
  // A previous calibration, off by about its stated 1-sigmas.
  li.ks += Vec3<double>(2e-5, -1e-5, 1.5e-5);
  li.o_rad += Vec3<double>(1e-5, -2e-5, 1e-5);
  li.kof += Vec3<double>(1, -0.7, 1.2);
  li.rm_rad += Vec3<double>(0.01, -0.008, 0.012) * kDeg;
  VfStart<Scalar> st;
  st.model = from_li(li).template cast<Scalar>();
  st.sigma.ks.setConstant(Scalar(3e-5));
  st.sigma.o_rad.setConstant(Scalar(3e-5));
  st.sigma.kof.setConstant(Scalar(1.5));
  st.sigma.rm_rad.setConstant(static_cast<Scalar>(0.02 * kDeg));
  st.temperature_ref_degC = static_cast<Scalar>(tr.t0_degC);
  return st;
}

// Measured: largest difference 0.054 sigma (seed 51; 0.024-0.054 over seeds 51-56). It was 3.2
// sigma while float32 floored the reference sigma at 16 eps (0.1 nT instead of the configured
// 0.01 nT), deferred the misalignment fold, and the first samples after the stored start were
// taken at their first linearisation (E-VF-1, E-VF-A).
void float_matches_double(int fold) {
  Truth tr;
  tr.tau_s = 0.005;
  tr.tc = {0.3, -0.3, 0.3};
  SimOptions o = noisy_manoeuvre(30);
  o.with_temperature = true;
  o.temp_start_degC = 15;
  o.temp_end_degC = 35;
  std::mt19937_64 rng(51);
  const auto data = simulate_manoeuvre(tr, o, rng);
  Filter<double> fd(fold_cfg<double>(fold));
  Filter<float> ff(fold_cfg<float>(fold));
  fd.start(stored_start<double>(tr));
  ff.start(stored_start<float>(tr));
  for (const SimSample& s : data) {
    fd.update(s.in);
    ff.update(cast_sample<float>(s.in));
  }
  fd.flush();
  ff.flush();
  ASSERT_TRUE(fd.initialised());
  ASSERT_TRUE(ff.initialised());
  print_counters(fd);
  print_counters(ff);
  const Vec<double, 19> ed = state_errors(fd, tr, tr.h_n), ef = state_errors(ff, tr, tr.h_n);
  const Vec<double, 19> sig = state_sigmas(fd);
  double worst = 0, worst_truth = 0;
  int worst_k = 0;
  for (int k = 0; k < 19; ++k) {
    const double d = std::abs(ef(k) - ed(k)) / sig(k);
    worst_truth = std::max(worst_truth, std::abs(ed(k)) / sig(k));
    if (d > worst) {
      worst = d;
      worst_k = k;
    }
  }
  std::printf(
      "float32 vs double: largest difference %.3f sigma (%s); double's largest error %.2f sigma\n",
      worst, kStateNames[worst_k], worst_truth);
  EXPECT_LT(worst, 0.1);
  EXPECT_LT(worst_truth, 4.0);
}
TEST(VectorCalibrationFilter, FloatMatchesDoubleWithinATenthSigma) {
  float_matches_double(1);
}
TEST(VectorCalibrationFilter, FloatMatchesDoubleWithinATenthSigmaInFolds) {
  float_matches_double(kMcuFold);
}

// ---- 6. no heap per sample ------------------------------------------------------------------
template <typename Scalar>
std::size_t allocations_over_a_run(const std::vector<SimSample>& data, int fold) {
  std::vector<VfSample<Scalar>> in;
  for (const SimSample& s : data)
    in.push_back(cast_sample<Scalar>(s.in));
  auto f = std::make_unique<Filter<Scalar>>(fold_cfg<Scalar>(fold));
  test::AllocationScope scope;
  for (const VfSample<Scalar>& s : in)
    f->update(s);
  f->flush();
  const std::size_t n = scope.count();
  EXPECT_TRUE(f->initialised());
  return n;
}

TEST(VectorCalibrationFilter, NoHeapAllocationPerSample) {
  Truth tr;
  tr.tau_s = 0.005;
  SimOptions o = noisy_manoeuvre(20);
  o.with_temperature = true;
  o.temp_end_degC = 30;
  std::mt19937_64 rng(61);
  const auto data = simulate_manoeuvre(tr, o, rng);
  // The whole run, the start from data (batch fit and replays) included.
  for (int fold : {1, kMcuFold}) {
    EXPECT_EQ(allocations_over_a_run<double>(data, fold), 0U) << fold;
    EXPECT_EQ(allocations_over_a_run<float>(data, fold), 0U) << fold;
  }
}

}  // namespace
}  // namespace magvec::core
