// Turntable calibration by sine fitting (Jia et al. 2019, eq. 1-17), with the corrections of
// docs/equations.md E-Sine:
//  * each axis of each sweep is fitted by linear least squares as a sin(theta) + b cos(theta) + D
//    = A sin(theta + phi) + D (streaming 3x3 normal equations, O(1) memory, no iteration);
//  * signed, turn-direction independent angles (001-3):
//      alpha = 90deg - |wrap(phi_y - phi_x)|,  beta = sign(wrap(phi_y - phi_x)) wrap(phi_z -
//      phi_x);
//  * ratio direction A_x / A_y = kx / ky (001-2);
//  * the Z offset from the XZ sweep (001-1), with both fixture geometries of 001-4:
//      kPlaneNormal: the XZ sweep turns about the normal of the actual Xm-Zm sensing plane:
//        gamma = asin(cos(phi) / cos(beta)), kz / kx = A'_z / A'_x, B0z = D'_z;
//      kHousingY: it turns about the housing y axis:
//        tan(gamma) = 1 / (cos(beta) tan(phi)), A'_z = kz Bh sqrt(cos^2 b sin^2 g + cos^2 g),
//        D'_z = B0z + kz sin(beta) sin(gamma) B_vertical;
//  * the inclination estimated from the Z offsets (001-5), signed: the vertical field follows from
//    D_z - D'_z and the horizontal one from A'_z; with |B| this fixes kx = A_x / (|B| cos I).
// Frames: the fixture frame of the XY sweep is the sensor model's frame (m = K B + B0, K lower
// triangular). up_sign_xy = +1 when fixture +Z points Up during the XY sweep; up_sign_xz = +1 when
// the turntable axis (housing +Y, or the plane normal Xm x Zm) points Up during the XZ sweep.
#pragma once

#include <Eigen/Cholesky>
#include <cmath>
#include <cstddef>
#include <cstdint>

#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

// Per-axis fit A sin(theta + phi) + D of one sweep.
template <typename Scalar>
struct SweepFit {
  bool ok = false;
  Vec3<Scalar> amplitude = Vec3<Scalar>::Zero();  // A >= 0
  Vec3<Scalar> phase_rad = Vec3<Scalar>::Zero();  // phi in (-pi, pi]
  Vec3<Scalar> offset = Vec3<Scalar>::Zero();     // D
  Vec3<Scalar> rms = Vec3<Scalar>::Zero();        // residual RMS per axis
  std::size_t samples{0};
};

// Streaming accumulator of one turntable sweep.
template <typename Scalar>
class SineSweep {
 public:
  static constexpr std::size_t kMinSamples = 4;

  void reset() noexcept {
    n_.setZero();
    rhs_.setZero();
    yy_.setZero();
    count_ = 0;
    skipped_ = 0;
  }
  // theta: turntable angle [rad]; m: raw reading [nT]. Non-finite rows are skipped and counted.
  bool add(Scalar theta_rad, const Vec3<Scalar>& m) noexcept {
    if (!std::isfinite(theta_rad) || !m.allFinite()) {
      ++skipped_;
      return false;
    }
    const Vec3<Scalar> phi(std::sin(theta_rad), std::cos(theta_rad), Scalar(1));
    n_ += phi * phi.transpose();
    rhs_ += phi * m.transpose();
    yy_ += m.cwiseProduct(m);
    ++count_;
    return true;
  }
  std::size_t count() const noexcept { return count_; }
  std::size_t skipped() const noexcept { return skipped_; }

  SweepFit<Scalar> fit() const noexcept {
    SweepFit<Scalar> out;
    out.samples = count_;
    if (count_ < kMinSamples) return out;
    const Eigen::LDLT<Mat3<Scalar>> ldlt(n_);
    if (ldlt.info() != Eigen::Success || !ldlt.isPositive()) return out;
    const Mat3<Scalar> coef = ldlt.solve(rhs_);  // column k: [a, b, D] of axis k
    if (!coef.allFinite() || ldlt.rcond() < Scalar(1e-6)) return out;
    for (int k = 0; k < 3; ++k) {
      const Scalar a = coef(0, k), b = coef(1, k);
      out.amplitude(k) = std::hypot(a, b);
      out.phase_rad(k) = std::atan2(b, a);
      out.offset(k) = coef(2, k);
      // sum (y - phi^T c)^2 = y^T y - c^T rhs (normal equations hold).
      const Scalar sse = yy_(k) - coef.col(k).dot(rhs_.col(k));
      out.rms(k) = std::sqrt(std::max(sse, Scalar(0)) / static_cast<Scalar>(count_));
    }
    out.ok = true;
    return out;
  }

 private:
  Mat3<Scalar> n_ = Mat3<Scalar>::Zero();
  Mat3<Scalar> rhs_ = Mat3<Scalar>::Zero();
  Vec3<Scalar> yy_ = Vec3<Scalar>::Zero();
  std::size_t count_{0};
  std::size_t skipped_{0};
};

enum class SineFixture : std::uint8_t {
  kPlaneNormal,  // XZ sweep turns about the normal of the actual Xm-Zm sensing plane
  kHousingY,     // XZ sweep turns about the housing (fixture) y axis
};

template <typename Scalar>
struct SineFitOptions {
  SineFixture xz_fixture = SineFixture::kHousingY;
  Scalar field_nT{0};    // |B|, required
  Scalar up_sign_xy{1};  // +1: fixture +Z points Up in the XY sweep
  Scalar up_sign_xz{1};  // +1: the XZ turntable axis (housing +Y / Xm x Zm) points Up
  bool inclination_known = false;
  Scalar inclination_rad{0};  // used when inclination_known (positive downward)
};

enum class SineStatus : std::uint8_t {
  kOk,
  kTooFewSamples,    // a sweep has fewer than 4 usable samples
  kDegenerateSweep,  // the sweep does not span enough turntable angles (singular fit)
  kNoField,          // |B| missing or not positive
  kInconsistent,     // formulas out of range (e.g. |cos(phi) / cos(beta)| > 1)
};

template <typename Scalar>
struct SineSolution {
  SineStatus status = SineStatus::kTooFewSamples;
  SineParams<Scalar> params{};
  Scalar inclination_rad{0};  // estimated (001-5) unless given
  SweepFit<Scalar> xy{}, xz{};

  SensorModel<Scalar> model() const noexcept { return from_sine(params); }
};

template <typename Scalar>
SineSolution<Scalar> solve_sine(const SineSweep<Scalar>& xy_sweep,
                                const SineSweep<Scalar>& xz_sweep,
                                const SineFitOptions<Scalar>& opt) noexcept {
  using std::abs;
  using std::cos;
  using std::sin;
  constexpr Scalar kHalfPi = kPi<Scalar> / Scalar(2);
  SineSolution<Scalar> out;
  if (xy_sweep.count() < SineSweep<Scalar>::kMinSamples ||
      xz_sweep.count() < SineSweep<Scalar>::kMinSamples) {
    return out;
  }
  out.xy = xy_sweep.fit();
  out.xz = xz_sweep.fit();
  if (!out.xy.ok || !out.xz.ok) {
    out.status = SineStatus::kDegenerateSweep;
    return out;
  }
  if (!(opt.field_nT > Scalar(0)) || !std::isfinite(opt.field_nT)) {
    out.status = SineStatus::kNoField;
    return out;
  }
  const SweepFit<Scalar>& a = out.xy;
  const SweepFit<Scalar>& b = out.xz;
  SineParams<Scalar> p;
  // XY sweep: alpha, beta (docs/equations.md E-Sine-3).
  const Scalar dyx = wrap_pi(a.phase_rad(1) - a.phase_rad(0));
  p.alpha_rad = kHalfPi - abs(dyx);
  p.beta_rad =
      (dyx < Scalar(0) ? Scalar(-1) : Scalar(1)) * wrap_pi(a.phase_rad(2) - a.phase_rad(0));
  const Scalar ky_kx = a.amplitude(1) / a.amplitude(0);  // docs/equations.md E-Sine-2
  // XZ sweep: gamma, kz / kx.
  const Scalar phi = abs(wrap_pi(b.phase_rad(2) - b.phase_rad(0)));
  const Scalar cb = cos(p.beta_rad), sb = sin(p.beta_rad);
  Scalar kz_kx{0}, r2{1};
  if (opt.xz_fixture == SineFixture::kPlaneNormal) {
    const Scalar sg = cos(phi) / cb;
    if (!(abs(sg) <= Scalar(1))) {
      out.status = SineStatus::kInconsistent;
      return out;
    }
    p.gamma_rad = std::asin(sg);
    kz_kx = b.amplitude(2) / b.amplitude(0);
  } else {
    p.gamma_rad = std::atan2(cos(phi) * cb, cb * cb * sin(phi));
    const Scalar sg = sin(p.gamma_rad), cg = cos(p.gamma_rad);
    r2 = std::sqrt(cb * cb * sg * sg + cg * cg);
    kz_kx = b.amplitude(2) / (b.amplitude(0) * r2);
  }
  const Scalar sg = sin(p.gamma_rad), cg = cos(p.gamma_rad);
  // Inclination (001-5): U / Bh from the two Z offsets and the XZ amplitude of Z.
  const Scalar dz = a.offset(2) - b.offset(2);
  const Scalar denom = opt.xz_fixture == SineFixture::kPlaneNormal
                           ? opt.up_sign_xy * cg
                           : (opt.up_sign_xy * cg - opt.up_sign_xz * sb * sg) / r2;
  const Scalar u_over_h = dz / (b.amplitude(2) * denom);
  out.inclination_rad = opt.inclination_known ? opt.inclination_rad : std::atan(-u_over_h);
  const Scalar bh = opt.field_nT * cos(out.inclination_rad);
  const Scalar up = -opt.field_nT * sin(out.inclination_rad);
  // Scale factors: both sweeps see kx * Bh on the x axis.
  p.k(0) = Scalar(0.5) * (a.amplitude(0) + b.amplitude(0)) / bh;
  p.k(1) = p.k(0) * ky_kx;
  p.k(2) = p.k(0) * kz_kx;
  // Offsets: x and y carry no vertical field in either sweep; z from the XZ sweep (001-1).
  p.b0(0) = Scalar(0.5) * (a.offset(0) + b.offset(0));
  p.b0(1) = a.offset(1);
  p.b0(2) = opt.xz_fixture == SineFixture::kPlaneNormal
                ? b.offset(2)
                : b.offset(2) - p.k(2) * sb * sg * opt.up_sign_xz * up;
  if (!p.k.allFinite() || !p.b0.allFinite() || !std::isfinite(p.gamma_rad)) {
    out.status = SineStatus::kInconsistent;
    return out;
  }
  out.params = p;
  out.status = SineStatus::kOk;
  return out;
}

}  // namespace magvec::core
