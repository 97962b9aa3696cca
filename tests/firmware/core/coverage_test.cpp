// Direction coverage cells (coverage.hpp): the azimuth sector by comparisons is the sector of
// atan2(y, x) + pi, also on the boundaries and for signed zeros.
#include "magvec/core/coverage.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>

namespace magvec::core {
namespace {

int sector_by_atan2(double x, double y) {
  const double az = std::atan2(y, x) + kPi<double>;
  return std::clamp(static_cast<int>(std::floor(az / (kPi<double> / 4))), 0, 7);
}

TEST(Coverage, SectorIsTheArctangentsAwayFromBoundaries) {
  std::mt19937_64 rng(1);
  std::normal_distribution<double> g(0.0, 1.0);
  int checked = 0;
  for (int i = 0; i < 100000; ++i) {
    const double x = g(rng), y = g(rng);
    const double az = std::atan2(y, x) + kPi<double>;
    const double to_boundary = std::abs(std::remainder(az, kPi<double> / 4));
    if (to_boundary < 1e-12) continue;  // the arctangent's rounding decides there
    ASSERT_EQ(coverage_sector(x, y), sector_by_atan2(x, y)) << x << " " << y;
    ASSERT_EQ(coverage_sector(static_cast<float>(x), static_cast<float>(y)),
              sector_by_atan2(static_cast<float>(x), static_cast<float>(y)))
        << x << " " << y;
    ++checked;
  }
  EXPECT_GT(checked, 99000);
}

TEST(Coverage, SectorOnBoundariesAxesAndSignedZeros) {
  // Each boundary direction belongs to the sector that starts there (floor).
  EXPECT_EQ(coverage_sector(1.0, 1.0), 5);    // pi/4
  EXPECT_EQ(coverage_sector(0.0, 1.0), 6);    // pi/2
  EXPECT_EQ(coverage_sector(-1.0, 1.0), 7);   // 3 pi/4
  EXPECT_EQ(coverage_sector(-1.0, -1.0), 1);  // -3 pi/4
  EXPECT_EQ(coverage_sector(0.0, -1.0), 2);   // -pi/2
  EXPECT_EQ(coverage_sector(1.0, -1.0), 3);   // -pi/4
  EXPECT_EQ(coverage_sector(1.0, 0.0), 4);    // 0
  EXPECT_EQ(coverage_sector(1.0, -0.0), 4);   // -0
  EXPECT_EQ(coverage_sector(-1.0, 0.0), 7);   // pi (2 pi: the last sector)
  EXPECT_EQ(coverage_sector(-1.0, -0.0), 0);  // -pi
  EXPECT_EQ(coverage_sector(0.0, 0.0), 4);    // vertical: atan2(0, 0) = 0
  EXPECT_EQ(coverage_sector(-0.0, 0.0), 7);   // atan2(0, -0) = pi
  EXPECT_EQ(coverage_sector(-0.0, -0.0), 0);  // atan2(-0, -0) = -pi
  for (double x : {1.0, -1.0, 0.0, -0.0})
    for (double y : {1.0, -1.0, 0.0, -0.0})
      EXPECT_EQ(coverage_sector(x, y), sector_by_atan2(x, y)) << x << " " << y;
  // Cells: bands in z, sectors in azimuth; straight up is the top band's sector 4.
  EXPECT_EQ(coverage_cell(Vec3<double>(0, 0, 1)), 3U * kCoverageSectors + 4U);
  EXPECT_EQ(coverage_cell(Vec3<double>(0, 0, -1)), 4U);
  EXPECT_EQ(coverage_cell(Vec3<float>(-1, -1, 0)), 2U * kCoverageSectors + 1U);
}

}  // namespace
}  // namespace magvec::core
