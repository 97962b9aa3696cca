// The geomagnetic reference field at a site and date: the World Magnetic Model 2025 evaluated with
// GeographicLib's MagneticModel over the coefficients shipped in data/geomag (provenance there).
//
// A calibration needs the total field F (and can check its field direction) where no scalar
// magnetometer recorded one; the model gives both, with the model's own stated 1-sigma, which
// bounds how well the absolute scale can be known from it.
//
// Uncertainty: the WMM2025 error model, "one standard deviation difference between a
// hypothetical measurement and the calculator result" (NOAA NCEI, The US/UK World Magnetic
// Model for 2025-2030 technical report and the WMM page's accuracy table, Table 3): X (north)
// 137 nT, Y (east) 89 nT, Z (down) 141 nT, H 133 nT, F 138 nT, I 0.20 deg,
// D sqrt(0.26^2 + (5417 / H[nT])^2) deg. It covers the core-field model's commission and
// omission (crustal, external) errors; a local anomaly near the site can exceed it.
#pragma once

#include <memory>
#include <stdexcept>
#include <string>
#include <string_view>

#include "magvec/core/types.hpp"

namespace GeographicLib {
class MagneticModel;
}

namespace magvec::host::geomag {

// Bad input (position, date, model file): the message names the value and the valid range.
class GeomagError : public std::invalid_argument {
 public:
  using std::invalid_argument::invalid_argument;
};

struct Site {
  double lat_deg = 0;   // geodetic (WGS84) latitude, [-90, 90]
  double lon_deg = 0;   // longitude, east positive, [-180, 360]
  double height_m = 0;  // height above the WGS84 ellipsoid (not above sea level)
};

struct Date {
  int year = 0;
  int month = 0;
  int day = 0;
};

// "LAT,LON,ALT" (deg, deg, m above the ellipsoid); throws GeomagError naming what is wrong.
Site parse_site(std::string_view text);
// "YYYY-MM-DD" (a real calendar date); throws GeomagError.
Date parse_date(std::string_view text);
// Decimal year as the WMM software counts it: year + (day of year - 1) / days in the year.
double decimal_year(const Date& date);

// 1-sigma of the model's values (WMM2025 error model, above).
struct FieldUncertainty {
  core::Vec3<double> enu_nT = core::Vec3<double>::Zero();  // east (Y), north (X), up (Z)
  double horizontal_nT = 0;
  double total_nT = 0;
  double inclination_deg = 0;
  double declination_deg = 0;  // grows near the magnetic poles (small H)
};

struct ReferenceField {
  core::Vec3<double> enu_nT = core::Vec3<double>::Zero();  // East, North, Up [nT]
  double total_nT = 0;                                     // F = |enu_nT|
  double horizontal_nT = 0;
  double declination_deg = 0;  // east of true north
  double inclination_deg = 0;  // positive down
  FieldUncertainty sigma;
  std::string model;  // e.g. "WMM2025"
  double decimal_year = 0;
};

class MagneticModel {
 public:
  // 1-sigma of F in the error model above: the same everywhere, so known before any position.
  static constexpr double kTotalSigma_nT = 138.0;

  // Loads `name`.wmm and `name`.wmm.cof (GeographicLib's format) from `dir`. Only WMM2025 is
  // accepted: the error model above belongs to it. Throws GeomagError when the files are missing
  // or invalid.
  explicit MagneticModel(const std::string& dir, const std::string& name = "wmm2025");
  ~MagneticModel();
  MagneticModel(MagneticModel&&) noexcept;
  MagneticModel& operator=(MagneticModel&&) noexcept;
  MagneticModel(const MagneticModel&) = delete;
  MagneticModel& operator=(const MagneticModel&) = delete;

  // The shipped WMM2025: $MAGVEC_GEOMAG_DIR if set, else ../share/magvec/geomag from the
  // executable (installed), else the source tree's data/geomag, else the configured install path.
  static MagneticModel wmm2025();
  static std::string default_dir();

  // Field at `site` and decimal year `year`. Throws GeomagError for a non-finite input, a latitude
  // outside [-90, 90], a longitude outside [-180, 360], a height outside the model's range
  // (-1 km to 850 km) or a date outside its validity [2025.0, 2030.0): never returns NaN.
  ReferenceField field(const Site& site, double year) const;
  ReferenceField field(const Site& site, const Date& date) const;

  double min_year() const noexcept { return min_year_; }
  double max_year() const noexcept { return max_year_; }
  const std::string& name() const noexcept { return name_; }

 private:
  std::unique_ptr<GeographicLib::MagneticModel> model_;
  std::string name_;
  double min_year_ = 0;
  double max_year_ = 0;
  double min_height_m_ = 0;
  double max_height_m_ = 0;
};

}  // namespace magvec::host::geomag
