// The survey envelope of a calibration's outputs (docs/equations.md E-VF-10, E-Acc-3): what the
// remaining uncertainty of a calibration does to the E/N/U and |h| outputs at every heading, at the
// tilts the calibration data had. Shared by the online vector filter (its covariance in U-D form)
// and the one-step batch fit (its inverse normal matrix).
//   TiltMoments: running mean and covariance of the body-frame vertical u = R_bn e3 (Welford).
//   for_each_envelope_attitude: six body verticals reproducing that mean and covariance
//     (mean +- sqrt(3 lambda_k) e_k), each at kEnvelopeHeadings headings (exact for the heading
//     average of the quartic terms of the |h| error).
//   EnvelopeGram: G_v = sum J^T J and G_i = sum (J^T g)(J^T g)^T over the envelope, J the output's
//     Jacobian with respect to the calibration parameters and g the output's direction; with the
//     parameters' covariance P the per-axis RMS of the E/N/U error is sqrt(tr(P G_v) / (3 n)) and
//     the RMS of the |h| error sqrt(tr(P G_i) / n).
// Fixed-size, heap-free, noexcept, float and double.
#pragma once

#include <algorithm>
#include <array>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <limits>

#include "magvec/core/frames.hpp"
#include "magvec/core/symmetric_eigen.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

inline constexpr int kEnvelopeTilts = 6;
inline constexpr int kEnvelopeHeadings = 8;
inline constexpr int kEnvelopeAttitudes = kEnvelopeTilts * kEnvelopeHeadings;

template <typename Scalar>
class TiltMoments {
 public:
  void reset() noexcept {
    n_ = 0;
    mean_.setZero();
    m2_.setZero();
  }
  void add(const Mat3<Scalar>& r_bn) noexcept {
    const Vec3<Scalar> u = r_bn.col(2);  // Up in body axes: R_bn e3
    ++n_;
    const Vec3<Scalar> delta = u - mean_;
    mean_ += delta / static_cast<Scalar>(n_);
    m2_ += delta * (u - mean_).transpose();
  }
  std::uint32_t count() const noexcept { return n_; }
  const Vec3<Scalar>& mean() const noexcept { return mean_; }
  Mat3<Scalar> covariance() const noexcept {
    return n_ > 1 ? Mat3<Scalar>(m2_ / static_cast<Scalar>(n_)) : Mat3<Scalar>::Zero();
  }
  // RMS spread of the vertical (rad, small angles): the batch methods' heading observability.
  Scalar spread_rad() const noexcept {
    if (n_ < 2) return Scalar(0);
    return std::sqrt(std::max(m2_.trace() / static_cast<Scalar>(n_), Scalar(0)));
  }

 private:
  std::uint32_t n_{0};
  Vec3<Scalar> mean_ = Vec3<Scalar>::Zero();
  Mat3<Scalar> m2_ = Mat3<Scalar>::Zero();
};

// Calls f(R_bn) for the kEnvelopeAttitudes attitudes of the envelope. False (f not called) when
// there is no tilt yet or the covariance's eigen decomposition fails.
template <typename Scalar, typename F>
bool for_each_envelope_attitude(const TiltMoments<Scalar>& m, F&& f) noexcept {
  if (m.count() < 1) return false;
  Vec3<Scalar> ev;
  Mat3<Scalar> evec;
  if (!symmetric_eigen_jacobi<Scalar, 3>(m.covariance(), &ev, &evec)) return false;
  std::array<Vec3<Scalar>, kEnvelopeTilts> tilts;
  for (std::size_t k = 0; k < 3; ++k) {
    const int c = static_cast<int>(k);
    const Vec3<Scalar> d = std::sqrt(Scalar(3) * std::max(ev(c), Scalar(0))) * evec.col(c);
    tilts[2 * k] = m.mean() + d;
    tilts[2 * k + 1] = m.mean() - d;
  }
  for (const Vec3<Scalar>& t_raw : tilts) {
    const Scalar tn = t_raw.norm();
    const Vec3<Scalar> u = tn > Scalar(0) ? Vec3<Scalar>(t_raw / tn) : Vec3<Scalar>::UnitZ();
    // T: the rotation taking the n-frame vertical e3 to u (R_bn = T Rz(psi) has R_bn e3 = u).
    const Vec3<Scalar> ax = Vec3<Scalar>::UnitZ().cross(u);
    const Scalar sa = ax.norm();
    const Scalar angle = std::atan2(sa, u(2));
    Mat3<Scalar> t = Mat3<Scalar>::Identity();
    if (sa > Scalar(0)) {
      t = exp_so3(Vec3<Scalar>(ax * (angle / sa)));
    } else if (u(2) < Scalar(0)) {
      t = exp_so3(Vec3<Scalar>(kPi<Scalar>, Scalar(0), Scalar(0)));
    }
    // R_bn = T Rz(psi_k): Rz mixes T's first two columns by cos and sin of the eight headings,
    // 45 degrees apart (a table: no sin, cos or 3x3 product per attitude).
    static_assert(kEnvelopeHeadings == 8);
    constexpr double kH = 0.70710678118654752440;  // cos 45 deg
    constexpr std::array<double, 8> kCos{1, kH, 0, -kH, -1, -kH, 0, kH};
    constexpr std::array<double, 8> kSin{0, kH, 1, kH, 0, -kH, -1, -kH};
    Mat3<Scalar> r;
    r.col(2) = t.col(2);
    for (std::size_t k = 0; k < kCos.size(); ++k) {
      const auto c = static_cast<Scalar>(kCos[k]);
      const auto s = static_cast<Scalar>(kSin[k]);
      r.col(0) = c * t.col(0) + s * t.col(1);
      r.col(1) = c * t.col(1) - s * t.col(0);
      f(static_cast<const Mat3<Scalar>&>(r));
    }
  }
  return true;
}

template <typename Scalar, int N>
struct EnvelopeGram {
  Mat<Scalar, N, N> gv = Mat<Scalar, N, N>::Zero();
  Mat<Scalar, N, N> gi = Mat<Scalar, N, N>::Zero();
  int n{0};
  // j: d(output)/d(parameters) at one envelope attitude; g_dir: the output's unit direction.
  // Upper triangles only, in plain loops over the column-major storage (Eigen's products took
  // ~5 300 instructions per attitude on the M4F for N = 15); finish() mirrors them.
  void add(const Mat<Scalar, 3, N>& j, const Vec3<Scalar>& g_dir) noexcept {
    const Scalar* a = j.data();  // column k at a + 3k
    Vec<Scalar, N> hi;
    for (Eigen::Index c = 0; c < N; ++c)
      hi(c) = a[3 * c] * g_dir(0) + a[3 * c + 1] * g_dir(1) + a[3 * c + 2] * g_dir(2);
    Scalar* v = gv.data();
    Scalar* w = gi.data();
    for (Eigen::Index c = 0; c < N; ++c) {
      const Scalar* jc = a + 3 * c;
      for (Eigen::Index r = 0; r <= c; ++r) {
        const Scalar* jr = a + 3 * r;
        v[N * c + r] += jr[0] * jc[0] + jr[1] * jc[1] + jr[2] * jc[2];
        w[N * c + r] += hi(r) * hi(c);
      }
    }
    ++n;
  }
  // After the last add(): the lower triangles from the upper.
  void finish() noexcept {
    gv.template triangularView<Eigen::StrictlyLower>() = gv.transpose();
    gi.template triangularView<Eigen::StrictlyLower>() = gi.transpose();
  }
  // Per-axis RMS of the E/N/U error and RMS of the |h| error from tr(P G_v), tr(P G_i) (in the
  // units of the Jacobian's output). NaN without an attitude.
  Scalar vector_rms(Scalar trace_p_gv) const noexcept {
    if (n == 0) return std::numeric_limits<Scalar>::quiet_NaN();
    return std::sqrt(std::max(trace_p_gv / static_cast<Scalar>(n), Scalar(0)) / Scalar(3));
  }
  Scalar intensity_rms(Scalar trace_p_gi) const noexcept {
    if (n == 0) return std::numeric_limits<Scalar>::quiet_NaN();
    return std::sqrt(std::max(trace_p_gi / static_cast<Scalar>(n), Scalar(0)));
  }
};

}  // namespace magvec::core
