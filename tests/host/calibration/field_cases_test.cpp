// Field-ready calibration: simulated recordings with the character of real ones, calibrated with
// DEFAULT options (no noise figures, no time offset given), scored against the simulator's truth:
//   (a) MEMS magnetometer + optical attitude: 285 Hz, 700 nT per axis, 0.04 deg attitude noise,
//       the magnetometer 14 ms late; slow (<= 60 deg/s) and fast (<= 200 deg/s) rotations;
//   (b) an airborne calibration cap: 10 Hz, 30 deg of direction spread, caesium-like reference;
//   (c) a compass capture: no attitude, no reference field, 20 uT offsets.
// Floors are computed by the test from the truth on the same data: the E/N/U error of the TRUE
// calibration with the attitude taken at the TRUE time (the test's own slerp of the recorded
// attitudes), and for (c) the relative intensity spread of the true calibration.
#include <gtest/gtest.h>
#include <stdlib.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>
#include <vector>

#include "calibration/batch_runner.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/host/io/csv.hpp"

namespace {

namespace fs = std::filesystem;
namespace core = magvec::core;
namespace host = magvec::host;
using core::Mat3;
using core::Quat;
using core::Vec3;

constexpr double kDeg = core::kPi<double> / 180.0;

// A fluxgate/MEMS sensor with visible errors and a misalignment to the attitude reference.
core::LiParams<double> sensor() {
  core::LiParams<double> p;
  p.ks = {1.03, 0.97, 1.015};
  p.o_rad = Vec3<double>(0.8, -1.2, 0.6) * kDeg;
  p.kof = {350, -420, 180};
  p.rm_rad = Vec3<double>(2.5, -1.5, 1.0) * kDeg;
  return p;
}
const Vec3<double> kHn(1500.0, 19500.0, -45000.0);  // E, N, U [nT]

// Smooth tumbling: heading turning, pitch and roll swinging, rates scaled to max_rate_dps.
Mat3<double> tumble(double t, double max_rate_dps) {
  const double w = max_rate_dps / 60.0;  // 1 at 60 deg/s
  const double a = 30.0 * w * t;
  const double b = 55.0 * std::sin(0.55 * w * t);
  const double g = 80.0 * std::sin(0.43 * w * t + 1.0);
  return core::r_bn_from_li(core::LiEuler<double>{a * kDeg, b * kDeg, g * kDeg});
}

Mat3<double> small_rotation(const Vec3<double>& v) {
  const double a = v.norm();
  if (!(a > 0)) return Mat3<double>::Identity();
  return Eigen::AngleAxisd(a, v / a).toRotationMatrix();
}

struct Recording {
  std::vector<double> t;
  std::vector<Vec3<double>> m;
  std::vector<Mat3<double>> r_meas;  // recorded attitude (noisy), at t
  std::vector<Mat3<double>> r_mag;   // true attitude when the magnetometer sampled
};

// MEMS-like: the reading stamped t was taken at t - lag.
Recording mems(double max_rate_dps, double duration_s, unsigned seed) {
  Recording rec;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0, 1);
  const core::SensorModel<double> model = core::from_li(sensor());
  const double dt = 1.0 / 285.714;
  const double lag = 0.014, sa = 0.04 * kDeg;
  const double sm = 700;
  for (double t = 0; t < duration_s; t += dt) {
    const Mat3<double> r_true = tumble(t, max_rate_dps);
    const Mat3<double> r_mag = tumble(t - lag, max_rate_dps);
    rec.t.push_back(t);
    rec.r_mag.push_back(r_mag);
    rec.m.push_back(model.predict_raw(r_mag, kHn) + sm * Vec3<double>(g(rng), g(rng), g(rng)));
    rec.r_meas.push_back(small_rotation(sa * Vec3<double>(g(rng), g(rng), g(rng))) * r_true);
  }
  return rec;
}

void write(const Recording& rec, const std::string& path, bool with_f) {
  std::vector<std::string> cols = {"t_s", "hx_nT", "hy_nT", "hz_nT"};
  if (with_f) cols.push_back("F_nT");
  for (const char* c : {"qw", "qx", "qy", "qz"})
    cols.push_back(c);
  host::io::CsvWriter w(path, cols);
  for (std::size_t i = 0; i < rec.t.size(); ++i) {
    const Quat<double> q(Mat3<double>(rec.r_meas[i].transpose()));  // body -> ENU
    std::vector<double> row = {rec.t[i], rec.m[i](0), rec.m[i](1), rec.m[i](2)};
    if (with_f) row.push_back(kHn.norm());
    for (double v : {q.w(), q.x(), q.y(), q.z()})
      row.push_back(v);
    w.write_row(row);
  }
  w.commit();
}

// The test's own attitude interpolation (slerp of the recorded attitudes at t - tau).
bool attitude_at(const Recording& rec, double t, Mat3<double>* r) {
  const double dt = rec.t[1] - rec.t[0];
  const double x = (t - rec.t[0]) / dt;
  if (x < 0 || x >= static_cast<double>(rec.t.size() - 1)) return false;
  const std::size_t i = static_cast<std::size_t>(x);
  const Quat<double> q0(rec.r_meas[i]), q1(rec.r_meas[i + 1]);
  *r = q0.slerp(x - static_cast<double>(i), q1).toRotationMatrix();
  return true;
}

// RMS per E/N/U component of R(t - tau)^T Rm^T W (m - o) - h_n (true field), over the middle
// of the recording.
Vec3<double> enu_rms(const Recording& rec, const core::SensorModel<double>& model, double tau) {
  const Mat3<double> rmt = model.rm_matrix().transpose();
  Vec3<double> ss = Vec3<double>::Zero();
  int n = 0;
  for (std::size_t i = 100; i + 100 < rec.t.size(); ++i) {
    Mat3<double> r;
    if (!attitude_at(rec, rec.t[i] - tau, &r)) continue;
    const Vec3<double> e = r.transpose() * (rmt * (model.w * (rec.m[i] - model.o))) - kHn;
    ss += e.cwiseProduct(e);
    ++n;
  }
  return (ss / n).cwiseSqrt();
}

class FieldCases : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "magvec_field_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string file(const char* name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

void check_mems(const std::string& path, const Recording& rec, const char* label) {
  host::io::CsvReader reader(path);
  const host::BatchRun run = host::run_batch(reader, host::BatchRunOptions{});  // defaults
  ASSERT_TRUE(run.result.ok()) << label << ": " << run.reason;
  const host::TimeOffsetEstimate& to = run.time_offset;
  ASSERT_TRUE(to.estimated) << to.note;
  const Vec3<double> floor = enu_rms(rec, core::from_li(sensor()), 0.014);
  const Vec3<double> ours = enu_rms(rec, run.result.model, to.offset_s);
  const Vec3<double> unaligned = enu_rms(rec, run.result.model, 0.0);
  std::printf(
      "%s: verdict %s, noise %.1f +- %.1f nT (truth 700), INS %.4f +- %.4f deg (truth 0.04), "
      "offset %.2f +- %.2f ms (truth 14)\n  E/N/U RMS vs truth %.1f/%.1f/%.1f nT, floor "
      "%.1f/%.1f/%.1f nT, without the offset %.1f/%.1f/%.1f nT\n",
      label, core::verdict_name(run.result.verdict), run.result.noise.mag_nT,
      run.result.noise.mag_sigma_nT, run.result.noise.attitude_deg,
      run.result.noise.attitude_sigma_deg, to.offset_s * 1e3, to.sigma_s * 1e3, ours(0), ours(1),
      ours(2), floor(0), floor(1), floor(2), unaligned(0), unaligned(1), unaligned(2));
  EXPECT_NEAR(to.offset_s, 0.014, 0.001);
  EXPECT_LT(std::abs(to.offset_s - 0.014), 4 * to.sigma_s + 1e-4) << "the 1-sigma is honest";
  EXPECT_NEAR(run.result.noise.mag_nT, 700, 4 * run.result.noise.mag_sigma_nT + 14);
  for (int k = 0; k < 3; ++k)
    EXPECT_LT(ours(k), 1.1 * floor(k)) << label << " component " << k;
}

TEST_F(FieldCases, MemsSlowRotationWithA14msLagIsAcceptedAtTheFloor) {
  const Recording rec = mems(60, 60, 11);
  write(rec, file("mems_slow.csv"), true);
  check_mems(file("mems_slow.csv"), rec, "MEMS slow (60 deg/s)");
}

TEST_F(FieldCases, MemsFastRotationWithA14msLagIsAcceptedAtTheFloor) {
  const Recording rec = mems(200, 40, 12);
  write(rec, file("mems_fast.csv"), true);
  check_mems(file("mems_fast.csv"), rec, "MEMS fast (200 deg/s)");
}

// (b) A cap: 10 Hz, directions within 15 deg of one attitude, fluxgate 0.5 nT, INS 0.01 deg,
// caesium reference 0.02 nT.
struct Cap {
  std::vector<Vec3<double>> m;
  std::vector<Mat3<double>> r;
  std::vector<double> f;
};
Cap cap(const core::LiParams<double>& truth, int n, unsigned seed) {
  Cap c;
  std::mt19937_64 rng(seed);
  std::normal_distribution<double> g(0, 1);
  std::uniform_real_distribution<double> u(0, 1);
  const core::SensorModel<double> model = core::from_li(truth);
  const Mat3<double> base = core::r_bn_from_li(core::LiEuler<double>{0.7, 0.05, -0.03});
  for (int i = 0; i < n; ++i) {
    const Vec3<double> axis = Vec3<double>(g(rng), g(rng), g(rng)).normalized();
    const Mat3<double> r = small_rotation(axis * 15.0 * kDeg * std::sqrt(u(rng))) * base;
    c.r.push_back(small_rotation(0.01 * kDeg * Vec3<double>(g(rng), g(rng), g(rng))) * r);
    c.m.push_back(model.predict_raw(r, kHn) + 0.5 * Vec3<double>(g(rng), g(rng), g(rng)));
    c.f.push_back(kHn.norm() + 0.02 * g(rng));
  }
  return c;
}
void write_cap(const Cap& c, const std::string& path, int keep_mod, int keep_rem) {
  host::io::CsvWriter w(path, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT", "qw", "qx", "qy", "qz"});
  for (std::size_t i = 0; i < c.m.size(); ++i) {
    if (static_cast<int>(i % static_cast<std::size_t>(keep_mod)) == keep_rem) continue;
    const Quat<double> q(Mat3<double>(c.r[i].transpose()));
    const double row[9] = {0.1 * static_cast<double>(i),
                           c.m[i](0),
                           c.m[i](1),
                           c.m[i](2),
                           c.f[i],
                           q.w(),
                           q.x(),
                           q.y(),
                           q.z()};
    w.write_row(row);
  }
  w.commit();
}

TEST_F(FieldCases, AirborneCapIsRefusedWithoutAPriorAndAcceptedWithOne) {
  const core::LiParams<double> truth = sensor();
  const Cap c = cap(truth, 3000, 21);
  write_cap(c, file("cap_fit.csv"), 5, 0);  // every 5th row held out
  {
    host::io::CsvReader reader(file("cap_fit.csv"));
    const host::BatchRun run = host::run_batch(reader, host::BatchRunOptions{});
    EXPECT_EQ(run.result.verdict, core::Verdict::kInsufficientCoverage) << run.reason;
    EXPECT_NE(run.reason.find("--prior"), std::string::npos) << run.reason;
  }
  // The prior: last season's full calibration of the same sensor, whose offsets have drifted by
  // a few nT since, with the 1-sigmas it was delivered with.
  core::OneStepPrior<double> prior;
  prior.mean = truth;
  prior.mean.kof += Vec3<double>(4, -3, 5);
  prior.mean.ks += Vec3<double>(2e-4, -1e-4, 1e-4);
  prior.sigma.ks = Vec3<double>::Constant(3e-4);
  prior.sigma.o_rad = Vec3<double>::Constant(0.01 * kDeg);
  prior.sigma.kof = Vec3<double>::Constant(5.0);
  prior.sigma.rm_rad = Vec3<double>::Constant(0.02 * kDeg);
  host::BatchRunOptions o;
  o.config.prior = &prior;
  host::io::CsvReader reader(file("cap_fit.csv"));
  const host::BatchRun run = host::run_batch(reader, o);
  ASSERT_TRUE(run.result.ok()) << run.reason;
  std::printf("cap with prior: the data determine %s; moved: %s\n",
              host::parameter_names(run.result.quality.updated).c_str(),
              host::parameter_names(run.result.quality.moved).c_str());
  // Hold-out |h| - F on the rows the fit never saw.
  double ss = 0, ss_prior = 0;
  int n = 0;
  const core::SensorModel<double> pm = core::from_li(prior.mean);
  for (std::size_t i = 0; i < c.m.size(); i += 5) {
    const double e = (run.result.model.w * (c.m[i] - run.result.model.o)).norm() - c.f[i];
    const double ep = (pm.w * (c.m[i] - pm.o)).norm() - c.f[i];
    ss += e * e;
    ss_prior += ep * ep;
    ++n;
  }
  const double rms = std::sqrt(ss / n), rms_prior = std::sqrt(ss_prior / n);
  const double noise = std::hypot(0.5, 0.02);  // intensity noise: one axis' worth + reference
  std::printf(
      "cap hold-out |h|-F RMS %.3f nT (prior alone %.3f nT), noise %.3f nT, estimated "
      "%.3f +- %.3f nT\n",
      rms, rms_prior, noise, run.result.noise.mag_nT, run.result.noise.mag_sigma_nT);
  EXPECT_LT(rms, 1.2 * noise);
  EXPECT_GT(rms_prior, 1.5 * noise) << "the prior alone is not good enough: the data matter";
}

// (c) A compass: no attitude, no F, 20 uT offsets, MEMS noise.
TEST_F(FieldCases, CompassWithoutAttitudeOrReferenceIsAcceptedAtTheFloor) {
  core::LiParams<double> truth = sensor();
  truth.kof = {20000, -15000, 8000};
  truth.rm_rad.setZero();
  const core::SensorModel<double> model = core::from_li(truth);
  std::mt19937_64 rng(31);
  std::normal_distribution<double> g(0, 1);
  std::vector<Vec3<double>> m;
  {
    host::io::CsvWriter w(file("compass.csv"), {"t_s", "hx_nT", "hy_nT", "hz_nT"});
    for (int i = 0; i < 2000; ++i) {
      const Mat3<double> r = tumble(0.05 * i, 60);
      m.push_back(model.predict_raw(r, kHn) + 150.0 * Vec3<double>(g(rng), g(rng), g(rng)));
      const double row[4] = {0.05 * i, m.back()(0), m.back()(1), m.back()(2)};
      w.write_row(row);
    }
    w.commit();
  }
  host::io::CsvReader reader(file("compass.csv"));
  host::BatchRunOptions o;
  o.method = core::BatchMethod::kEllipsoidOnly;  // what `calibrate` picks without attitude
  const host::BatchRun run = host::run_batch(reader, o);
  ASSERT_TRUE(run.result.ok()) << run.reason;
  EXPECT_TRUE(run.field_from_data);
  // Relative intensity spread (the scale is relative without a reference).
  auto rel_sd = [&](const core::SensorModel<double>& mdl) {
    double s = 0, s2 = 0;
    for (const Vec3<double>& x : m) {
      const double h = (mdl.w * (x - mdl.o)).norm();
      s += h;
      s2 += h * h;
    }
    const double n = static_cast<double>(m.size()), mean = s / n;
    return std::sqrt(s2 / n - mean * mean) / mean;
  };
  const double ours = rel_sd(run.result.model), floor = rel_sd(model);
  std::printf(
      "compass: noise %.1f +- %.1f nT (truth 150), relative |h| spread %.3e, floor %.3e, "
      "offset error %.1f nT\n",
      run.result.noise.mag_nT, run.result.noise.mag_sigma_nT, ours, floor,
      (run.result.model.o - model.o).norm());
  EXPECT_LT(ours, 1.1 * floor);
  EXPECT_LT((run.result.model.o - model.o).norm(), 200.0);  // offsets recovered to ~1 % of 20 uT
}

}  // namespace
