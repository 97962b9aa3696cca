// Calibration guidance: while a calibration collects, how far it is and what is missing. One
// computation for every calibrator and every display (magvecd's calibration state, `magvec ctl
// watch`): progress is the smallest of the fractions of what the calibrator needs before a solve
// can be tried (samples, coverage cells of the grid in coverage.hpp, and a calibrator-specific
// need such as the EKF's start-up set), so 1 means "the solve can be tried"; the hint is a code
// with parameters (the host renders the text), derived from the empty cells and the current
// attitude.
//
// Where an empty cell lies. The cells are those of the calibrator's coverage rule: raw field
// directions in the sensor frame. The field's direction in the navigation frame is taken from the
// latest reading and attitude (n = R_bn^T m / |m|, ignoring the misalignment and the sensor
// errors, a few degrees at most, against 45-degree cells), and each candidate manoeuvre, a tilt
// (pitch or roll, at most kGuidanceMaxTiltDeg from level) followed by a sweep through the
// headings, predicts the cell R_bn' n would hit. The smallest tilt that reaches an empty cell
// wins; a turn alone is preferred, as it is the easiest manoeuvre. The cell of the current reading
// counts as filled: the calibrator is filling it now.
// Pure math: no heap, noexcept, Scalar-templated (float and double).
#pragma once

#include <algorithm>
#include <cmath>
#include <cstddef>
#include <cstdint>
#include <cstdlib>

#include "magvec/core/coverage.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/types.hpp"

namespace magvec::core {

enum class GuidanceHint : std::uint8_t {
  kNone = 0,         // not collecting: nothing to do
  kReady = 1,        // everything needed is in: the solve can be tried
  kNoField = 2,      // no magnetometer reading yet
  kNoReference = 3,  // samples are refused without the scalar reference field
  kNoAttitude = 4,   // no usable INS attitude: keep still while the INS (re)aligns
  kTurn = 5,         // turn to heading_deg: empty cells that way at the current tilt
  kPitch = 6,        // pitch by pitch_deg (+: nose up), then (heading_deg >= 0) turn to it
  kRoll = 7,         // roll by roll_deg (+: right wing down), then (heading_deg >= 0) turn to it
  kKeepMoving = 8,   // no reachable empty cell, or only samples/convergence missing
};

inline constexpr int kGuidanceMaxTiltDeg = 45;  // tilts beyond it are not asked for
inline constexpr int kGuidanceTiltStepDeg = 10;
inline constexpr int kGuidanceHeadingStepDeg = 15;

template <typename Scalar>
struct GuidanceInput {
  bool collecting{false};
  std::uint32_t cells{0};  // coverage cells hit (coverage.hpp grid, sensor frame)
  int cells_needed{0};     // cells the calibrator needs (0: no coverage rule)
  std::size_t samples{0};  // samples kept
  std::size_t samples_needed{0};
  Scalar other_fraction{1};   // a further need in [0, 1] (EKF start-up set, convergence)
  bool need_reference{true};  // the calibrator refuses samples without the scalar reference
  bool have_reference{true};  // the latest reading came with one
  bool need_attitude{true};   // the calibrator refuses samples without attitude
  bool have_attitude{false};  // r_bn is the platform's current attitude
  Mat3<Scalar> r_bn = Mat3<Scalar>::Identity();
  bool have_field{false};  // m_nT is the latest raw reading
  Vec3<Scalar> m_nT = Vec3<Scalar>::Zero();
};

template <typename Scalar>
struct Guidance {
  Scalar progress{0};          // min of the fractions below, [0, 1]
  Scalar samples_fraction{1};  // samples / samples_needed
  Scalar cells_fraction{1};    // cells hit / cells_needed
  Scalar other_fraction{1};
  std::uint32_t cells{0};  // the coverage mask (bit i: cell i)
  int cells_hit{0};
  int cells_needed{0};
  GuidanceHint hint{GuidanceHint::kNone};
  int heading_deg{-1};  // kTurn (and after a tilt): target heading, clockwise from north; -1: none
  int pitch_deg{0};     // kPitch: change of pitch, + nose up
  int roll_deg{0};      // kRoll: change of roll, + right wing down
  int target_cells{0};  // empty cells reachable by turning through all headings after the tilt
};

namespace guidance_detail {

inline int popcount32(std::uint32_t x) noexcept {
  int n = 0;
  for (; x != 0U; x &= x - 1U)
    ++n;
  return n;
}

template <typename Scalar>
Scalar fraction(Scalar have, Scalar need) noexcept {
  return need > Scalar(0) ? std::clamp(have / need, Scalar(0), Scalar(1)) : Scalar(1);
}

// What a sweep through the headings at one tilt reaches.
struct Sweep {
  std::uint32_t empty_reached{0};  // empty cells hit by some heading
  int best_turn_deg{0};            // smallest heading change (aerospace, clockwise +) to one
  bool found{false};
};

// Sweeps the headings at Li tilt (beta, gamma); alpha0 is the current Li heading (about Up).
template <typename Scalar>
Sweep sweep(const Vec3<Scalar>& n, Scalar alpha0, Scalar beta, Scalar gamma,
            std::uint32_t empty) noexcept {
  Sweep s;
  constexpr int kSteps = 360 / kGuidanceHeadingStepDeg;
  for (int k = 0; k < kSteps; ++k) {
    // Turn by t degrees clockwise (aerospace yaw +t): Li alpha - t.
    int t = k * kGuidanceHeadingStepDeg;
    if (t > 180) t -= 360;
    const LiEuler<Scalar> e{alpha0 - deg_to_rad(static_cast<Scalar>(t)), beta, gamma};
    const unsigned cell = coverage_cell<Scalar>(r_bn_from_li(e) * n);
    if ((empty & (1U << cell)) == 0U) continue;
    s.empty_reached |= 1U << cell;
    if (!s.found || std::abs(t) < std::abs(s.best_turn_deg)) s.best_turn_deg = t;
    s.found = true;
  }
  return s;
}

inline int wrap360(int deg) noexcept {
  deg %= 360;
  return deg < 0 ? deg + 360 : deg;
}

}  // namespace guidance_detail

// The guidance for one moment of a calibration. Cheap enough for a display rate (at most 19 tilts
// x 24 headings of one rotation and one cell lookup each, ~35 us on the host), not meant for every
// sample.
template <typename Scalar>
Guidance<Scalar> calibration_guidance(const GuidanceInput<Scalar>& in) noexcept {
  using guidance_detail::fraction;
  Guidance<Scalar> g;
  g.cells = in.cells;
  g.cells_hit = guidance_detail::popcount32(in.cells);
  g.cells_needed = in.cells_needed;
  if (!in.collecting) return g;
  g.samples_fraction =
      fraction(static_cast<Scalar>(in.samples), static_cast<Scalar>(in.samples_needed));
  g.cells_fraction =
      fraction(static_cast<Scalar>(g.cells_hit), static_cast<Scalar>(in.cells_needed));
  g.other_fraction = std::isfinite(in.other_fraction)
                         ? std::clamp(in.other_fraction, Scalar(0), Scalar(1))
                         : Scalar(0);
  g.progress = std::min({g.samples_fraction, g.cells_fraction, g.other_fraction});
  if (g.progress >= Scalar(1)) {
    g.hint = GuidanceHint::kReady;
    return g;
  }
  const Scalar len = in.m_nT.norm();
  if (!in.have_field || !in.m_nT.allFinite() || !(len > Scalar(0))) {
    g.hint = GuidanceHint::kNoField;
    return g;
  }
  if (in.need_reference && !in.have_reference) {
    g.hint = GuidanceHint::kNoReference;
    return g;
  }
  const bool attitude = in.have_attitude && in.r_bn.allFinite();
  if (in.need_attitude && !attitude) {
    g.hint = GuidanceHint::kNoAttitude;
    return g;
  }
  g.hint = GuidanceHint::kKeepMoving;
  // Only samples missing: any motion adds them. Without attitude no manoeuvre can be predicted.
  const bool want_cells = g.cells_fraction < Scalar(1) || g.other_fraction < Scalar(1);
  if (!want_cells || !attitude) return g;

  const Vec3<Scalar> b = in.m_nT / len;
  const Vec3<Scalar> n = in.r_bn.transpose() * b;
  const std::uint32_t empty = ~(in.cells | (1U << coverage_cell<Scalar>(b)));
  const LiEuler<Scalar> e = li_from_r_bn(in.r_bn);
  const int beta_deg = static_cast<int>(std::lround(rad_to_deg(e.beta)));
  const int gamma_deg = static_cast<int>(std::lround(rad_to_deg(e.gamma)));
  // Tilt changes by increasing size; at each size pitch before roll, the one reaching more cells.
  for (int size = 0; size <= 2 * kGuidanceMaxTiltDeg; size += kGuidanceTiltStepDeg) {
    guidance_detail::Sweep best;
    int best_pitch = 0, best_roll = 0;
    for (int axis = 0; axis < 2 && (size > 0 || axis == 0); ++axis) {
      for (int sign = 1; sign >= -1 && (size > 0 || sign == 1); sign -= 2) {
        const int dp = axis == 0 ? sign * size : 0;
        const int dr = axis == 1 ? sign * size : 0;
        if (std::abs(beta_deg + dp) > kGuidanceMaxTiltDeg ||
            std::abs(gamma_deg + dr) > kGuidanceMaxTiltDeg)
          continue;
        const guidance_detail::Sweep s = guidance_detail::sweep<Scalar>(
            n, e.alpha, e.beta + deg_to_rad(Scalar(dp)), e.gamma + deg_to_rad(Scalar(dr)), empty);
        if (!s.found) continue;
        if (!best.found || guidance_detail::popcount32(s.empty_reached) >
                               guidance_detail::popcount32(best.empty_reached)) {
          best = s;
          best_pitch = dp;
          best_roll = dr;
        }
      }
    }
    if (!best.found) continue;
    g.target_cells = guidance_detail::popcount32(best.empty_reached);
    // Current heading (Li alpha is counter-clockwise about Up): aerospace heading = -alpha.
    const int heading_now = static_cast<int>(std::lround(rad_to_deg(-e.alpha)));
    const int heading_target = guidance_detail::wrap360(heading_now + best.best_turn_deg);
    if (size == 0) {
      g.hint = GuidanceHint::kTurn;
      g.heading_deg = heading_target;
    } else {
      g.hint = best_pitch != 0 ? GuidanceHint::kPitch : GuidanceHint::kRoll;
      g.pitch_deg = best_pitch;
      g.roll_deg = best_roll;
      g.heading_deg = best.best_turn_deg == 0 ? -1 : heading_target;
    }
    return g;
  }
  return g;
}

}  // namespace magvec::core
