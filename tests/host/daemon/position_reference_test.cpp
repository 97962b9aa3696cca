// PositionReference: F from the WMM2025 at each valid INS position fix, at the height above the
// ellipsoid (altitude + undulation), against the model evaluated directly; invalid fixes and
// fixes the model cannot take are counted and change nothing.
#include "magvec/host/daemon/position_reference.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <string>

namespace magvec::host::daemon {
namespace {

hal::PositionSample fix_at(double lat_deg, double lon_deg, double altitude_m, double undulation_m) {
  hal::PositionSample p;
  p.lat_deg = lat_deg;
  p.lon_deg = lon_deg;
  p.altitude_m = altitude_m;
  p.undulation_m = undulation_m;
  p.flags = hal::kPosValid | hal::kPosStatusKnown;
  return p;
}

double model_f(double lat_deg, double lon_deg, double height_m, double year) {
  geomag::Site s;
  s.lat_deg = lat_deg;
  s.lon_deg = lon_deg;
  s.height_m = height_m;
  return geomag::MagneticModel::wmm2025().field(s, year).total_nT;
}

TEST(PositionReference, ValidFixGivesTheModelFieldAtTheHeightAboveTheEllipsoid) {
  PositionReference ref(geomag::MagneticModel::wmm2025(), [] { return 2026.5; });
  EXPECT_TRUE(std::isnan(ref.total_nT()));
  EXPECT_DOUBLE_EQ(ref.sigma_nT(), 138.0);  // known before any fix
  EXPECT_NE(ref.describe().find("no valid INS position yet"), std::string::npos);

  EXPECT_TRUE(ref.on_position(fix_at(-33.9, 18.4, 1500, 30)));
  const double f = model_f(-33.9, 18.4, 1530, 2026.5);
  EXPECT_DOUBLE_EQ(ref.total_nT(), f);
  // Not the altitude above the geoid (30 m lower: 0.4 nT here).
  EXPECT_GT(std::fabs(model_f(-33.9, 18.4, 1500, 2026.5) - f), 0.1);
  EXPECT_EQ(ref.field()->model, "WMM2025");
  EXPECT_NE(ref.describe().find("33.9000 S 18.4000 E 1530 m"), std::string::npos) << ref.describe();

  // The same place again: no change to hand on. Another place: a new F.
  EXPECT_FALSE(ref.on_position(fix_at(-33.9, 18.4, 1500, 30)));
  EXPECT_TRUE(ref.on_position(fix_at(64.1, -21.9, 0, 65)));
  EXPECT_DOUBLE_EQ(ref.total_nT(), model_f(64.1, -21.9, 65, 2026.5));
  EXPECT_EQ(ref.counters().fixes, 3u);
}

TEST(PositionReference, InvalidFixesAndDatesOutsideTheModelChangeNothing) {
  double year = 2026.0;
  PositionReference ref(geomag::MagneticModel::wmm2025(), [&year] { return year; });
  hal::PositionSample p = fix_at(10, 20, 0, 0);
  p.flags = hal::kPosStatusKnown;  // the INS does not declare it valid
  EXPECT_FALSE(ref.on_position(p));
  EXPECT_TRUE(std::isnan(ref.total_nT()));
  EXPECT_EQ(ref.counters().not_valid, 1u);

  EXPECT_TRUE(ref.on_position(fix_at(10, 20, 0, 0)));
  const double f = ref.total_nT();
  year = 2031.0;  // past the WMM2025's validity
  EXPECT_FALSE(ref.on_position(fix_at(40, 20, 0, 0)));
  EXPECT_DOUBLE_EQ(ref.total_nT(), f);  // the last good F stays
  EXPECT_EQ(ref.counters().model_errors, 1u);
  EXPECT_NE(ref.last_error().find("2031"), std::string::npos) << ref.last_error();
  EXPECT_DOUBLE_EQ(ref.last_fix().lat_deg, 10.0);
}

TEST(PositionReference, TheSystemDateIsADecimalYear) {
  const double y = PositionReference::utc_decimal_year_now();
  EXPECT_GE(y, 2024.0);
  EXPECT_LT(y, 2100.0);
}

}  // namespace
}  // namespace magvec::host::daemon
