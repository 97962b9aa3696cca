// Test helpers: the simulation setups of Li et al. 2023 (docs/equations.md E-Li-8) built from the
// core's own forward model (SensorModel::predict_raw, r_bn_from_li), deterministic from a seed.
#pragma once

#include <cmath>
#include <limits>
#include <random>
#include <vector>

#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"

namespace magvec::core::test_setup {

// Double constants: <cmath>'s NAN and INFINITY are floats (clang: -Wdouble-promotion).
inline constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
inline constexpr double kInf = std::numeric_limits<double>::infinity();

inline constexpr double kDeg = kPi<double> / 180.0;

struct Sample {
  Vec3<double> m;       // raw reading (noisy)
  Vec3<double> m_true;  // noise-free reading
  Mat3<double> r_true;
  Mat3<double> r_meas;  // with INS noise
  double f;
};

inline LiParams<double> paper_li() {
  LiParams<double> p;
  p.ks = {1.08, 1.02, 1.033};
  p.o_rad = Vec3<double>(1.7, 3.5, 2.1) * kDeg;
  p.kof = {4.9, 3.4, 0.7};
  p.rm_rad = Vec3<double>(5.7, 2.1, 3.5) * kDeg;
  return p;
}
inline Vec3<double> paper_h_n() {
  return {-4053.0, 25022.0, -47374.0};
}

// Uniformly distributed random rotation (Haar), as R_bn.
inline Mat3<double> random_rotation(std::mt19937_64& rng) {
  std::normal_distribution<double> n(0, 1);
  Quat<double> q(n(rng), n(rng), n(rng), n(rng));
  q.normalize();
  return q.toRotationMatrix();
}

// Li Euler angles of the true attitudes with independent noise on each angle.
inline Mat3<double> with_ins_noise(const Mat3<double>& r, double sigma_rad, std::mt19937_64& rng) {
  if (sigma_rad == 0) return r;
  std::normal_distribution<double> n(0, sigma_rad);
  LiEuler<double> e = li_from_r_bn(r);
  e.alpha += n(rng);
  e.beta += n(rng);
  e.gamma += n(rng);
  return r_bn_from_li(e);
}

inline std::vector<Sample> simulate(const SensorModel<double>& model, const Vec3<double>& h_n,
                                    const std::vector<Mat3<double>>& attitudes, double mag_sigma,
                                    double att_sigma_rad, std::mt19937_64& rng) {
  std::normal_distribution<double> n(0, 1);
  std::vector<Sample> out;
  for (const Mat3<double>& r : attitudes) {
    Sample s;
    s.r_true = r;
    s.m_true = model.predict_raw(r, h_n);
    s.m = s.m_true + mag_sigma * Vec3<double>(n(rng), n(rng), n(rng));
    s.r_meas = with_ins_noise(r, att_sigma_rad, rng);
    s.f = h_n.norm();
    out.push_back(s);
  }
  return out;
}

inline std::vector<Mat3<double>> random_attitudes(int n, std::mt19937_64& rng) {
  std::vector<Mat3<double>> a;
  for (int i = 0; i < n; ++i)
    a.push_back(random_rotation(rng));
  return a;
}

// A calibration box on a table: 6 faces (tilts) x 3 headings = 18 structured attitudes.
inline std::vector<Mat3<double>> box_attitudes() {
  const double tilts[6][2] = {{0, 0}, {0, 180}, {70, 0}, {-70, 0}, {0, 90}, {0, -90}};
  std::vector<Mat3<double>> a;
  for (double heading : {10.0, 130.0, 250.0}) {
    for (const auto& t : tilts) {
      a.push_back(r_bn_from_li(LiEuler<double>{heading * kDeg, t[0] * kDeg, t[1] * kDeg}));
    }
  }
  return a;
}

// Level platform turning through headings only.
inline std::vector<Mat3<double>> level_attitudes(int n) {
  std::vector<Mat3<double>> a;
  for (int i = 0; i < n; ++i)
    a.push_back(r_bn_from_li(LiEuler<double>{(360.0 * i / n) * kDeg, 0, 0}));
  return a;
}

inline double sd(const std::vector<double>& v) {
  double mean = 0;
  for (double x : v)
    mean += x;
  mean /= static_cast<double>(v.size());
  double ss = 0;
  for (double x : v)
    ss += (x - mean) * (x - mean);
  return std::sqrt(ss / static_cast<double>(v.size() - 1));
}

}  // namespace magvec::core::test_setup
