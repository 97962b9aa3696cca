// Direction coverage: the one grid every calibrator, the loop and the reports use to say how much
// of the sphere of field directions a data set spans (docs/equations.md "Acceptance"). 32 cells of
// equal area: 4 bands equal in z (Archimedes: equal z-intervals have equal area) times 8 sectors in
// azimuth. A 30-degree cap hits 2 to 4 cells, a full rotation all 32.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>

#include "magvec/core/types.hpp"

namespace magvec::core {

inline constexpr int kCoverageBands = 4;
inline constexpr int kCoverageSectors = 8;
inline constexpr int kCoverageCells = kCoverageBands * kCoverageSectors;

// Azimuth sector (0..7) of (x, y): floor((atan2(y, x) + pi) / (pi / 4)), 8 taken as 7, decided by
// comparisons instead of an arctangent (every sample calls it: 330 instructions on the M4F).
// Exact on the sector boundaries (|y| = |x|, an axis), signed zeros as atan2 takes them.
template <typename Scalar>
int coverage_sector(Scalar x, Scalar y) noexcept {
  const Scalar ax = std::abs(x), ay = std::abs(y);
  if (ay == Scalar(0)) {
    // atan2(+-0, x): +-0 for x > 0 or +0; +-pi for x < 0 or -0.
    const bool negative_x = x < Scalar(0) || (x == Scalar(0) && std::signbit(x));
    if (!negative_x) return 4;
    return std::signbit(y) ? 0 : 7;
  }
  if (y > Scalar(0)) {                          // atan2 in (0, pi)
    if (x > Scalar(0)) return ay < ax ? 4 : 5;  // [0, pi/4), [pi/4, pi/2)
    return ay > ax ? 6 : 7;                     // [pi/2, 3pi/4), [3pi/4, pi)
  }
  if (x < Scalar(0)) return ay < ax ? 0 : 1;  // (-pi, -3pi/4), [-3pi/4, -pi/2)
  return ay > ax ? 2 : 3;                     // [-pi/2, -pi/4), [-pi/4, 0)
}

// Cell index (0..31) of a direction; d need not be unit length but must be non-zero.
template <typename Scalar>
unsigned coverage_cell(const Vec3<Scalar>& d) noexcept {
  const Scalar len = d.norm();
  const Scalar z = len > Scalar(0) ? d(2) / len : Scalar(0);
  int band = static_cast<int>((z + Scalar(1)) * Scalar(0.5) * Scalar(kCoverageBands));
  band = std::clamp(band, 0, kCoverageBands - 1);
  return static_cast<unsigned>(band * kCoverageSectors + coverage_sector(d(0), d(1)));
}

// The set of cells hit so far.
class CoverageGrid {
 public:
  void clear() noexcept { cells_ = 0; }
  template <typename Scalar>
  void add(const Vec3<Scalar>& d) noexcept {
    if (d.allFinite() && d.squaredNorm() > Scalar(0)) cells_ |= 1U << coverage_cell(d);
  }
  int hit() const noexcept {
    int n = 0;
    for (std::uint32_t x = cells_; x != 0U; x &= x - 1U)
      ++n;
    return n;
  }
  // Fraction of the sphere's cells hit, [0, 1].
  template <typename Scalar>
  Scalar fraction() const noexcept {
    return static_cast<Scalar>(hit()) / Scalar(kCoverageCells);
  }
  std::uint32_t cells() const noexcept { return cells_; }

 private:
  std::uint32_t cells_{0};
};

}  // namespace magvec::core
