#include "magvec/host/geomag/reference_field.hpp"

#include <GeographicLib/Constants.hpp>
#include <GeographicLib/MagneticModel.hpp>
#include <algorithm>
#include <charconv>
#include <cmath>
#include <cstdlib>
#include <filesystem>
#include <sstream>
#include <system_error>
#include <utility>

namespace magvec::host::geomag {
namespace {

// WMM2025 error model (see the header for the source).
constexpr double kSigmaNorth_nT = 137.0;
constexpr double kSigmaEast_nT = 89.0;
constexpr double kSigmaDown_nT = 141.0;
constexpr double kSigmaHorizontal_nT = 133.0;
constexpr double kSigmaInclination_deg = 0.20;
constexpr double kSigmaDeclinationConst_deg = 0.26;
constexpr double kSigmaDeclinationH_nTdeg = 5417.0;

std::string num(double v) {
  std::ostringstream s;
  s << v;
  return s.str();
}

// One number from the whole of `part` (no trailing characters, finite).
double parse_number(std::string_view part, const char* what, std::string_view whole) {
  double v = 0;
  while (!part.empty() && part.front() == ' ')
    part.remove_prefix(1);
  while (!part.empty() && part.back() == ' ')
    part.remove_suffix(1);
  const char* end = part.data() + part.size();
  const auto [ptr, ec] = std::from_chars(part.data(), end, v);
  if (part.empty() || ec != std::errc() || ptr != end || !std::isfinite(v)) {
    throw GeomagError("site '" + std::string(whole) + "': " + what + " '" + std::string(part) +
                      "' is not a finite number (expected LAT,LON,ALT: degrees, degrees, metres "
                      "above the WGS84 ellipsoid)");
  }
  return v;
}

void check_site(const Site& s) {
  if (!std::isfinite(s.lat_deg) || s.lat_deg < -90.0 || s.lat_deg > 90.0)
    throw GeomagError("latitude " + num(s.lat_deg) + " deg is outside [-90, 90]");
  if (!std::isfinite(s.lon_deg) || s.lon_deg < -180.0 || s.lon_deg > 360.0)
    throw GeomagError("longitude " + num(s.lon_deg) + " deg is outside [-180, 360]");
  if (!std::isfinite(s.height_m)) throw GeomagError("height is not a finite number");
}

bool leap(int y) {
  return (y % 4 == 0 && y % 100 != 0) || y % 400 == 0;
}
int days_in_month(int y, int m) {
  static constexpr int kDays[12] = {31, 28, 31, 30, 31, 30, 31, 31, 30, 31, 30, 31};
  return m == 2 && leap(y) ? 29 : kDays[m - 1];
}

}  // namespace

Site parse_site(std::string_view text) {
  const std::size_t c1 = text.find(',');
  const std::size_t c2 = c1 == std::string_view::npos ? c1 : text.find(',', c1 + 1);
  if (c2 == std::string_view::npos || text.find(',', c2 + 1) != std::string_view::npos) {
    throw GeomagError("site '" + std::string(text) +
                      "': expected three comma-separated numbers LAT,LON,ALT (degrees, degrees, "
                      "metres above the WGS84 ellipsoid)");
  }
  Site s;
  s.lat_deg = parse_number(text.substr(0, c1), "latitude", text);
  s.lon_deg = parse_number(text.substr(c1 + 1, c2 - c1 - 1), "longitude", text);
  s.height_m = parse_number(text.substr(c2 + 1), "height", text);
  try {
    check_site(s);
  } catch (const GeomagError& e) {
    throw GeomagError("site '" + std::string(text) + "': " + e.what());
  }
  return s;
}

Date parse_date(std::string_view text) {
  const auto bad = [&](const std::string& why) {
    return GeomagError("date '" + std::string(text) + "': " + why);
  };
  if (text.size() != 10 || text[4] != '-' || text[7] != '-') throw bad("expected YYYY-MM-DD");
  for (std::size_t i : {0u, 1u, 2u, 3u, 5u, 6u, 8u, 9u}) {
    if (text[i] < '0' || text[i] > '9') throw bad("expected YYYY-MM-DD");
  }
  const auto field = [&](std::size_t at, std::size_t n) {
    int v = 0;
    std::from_chars(text.data() + at, text.data() + at + n, v);
    return v;
  };
  Date d{field(0, 4), field(5, 2), field(8, 2)};
  if (d.month < 1 || d.month > 12) throw bad("month " + std::to_string(d.month) + " is not 1-12");
  if (d.day < 1 || d.day > days_in_month(d.year, d.month)) {
    throw bad("day " + std::to_string(d.day) + " does not exist in " + std::to_string(d.year) +
              "-" + (d.month < 10 ? "0" : "") + std::to_string(d.month));
  }
  return d;
}

double decimal_year(const Date& date) {
  int day_of_year = date.day;
  for (int m = 1; m < date.month; ++m)
    day_of_year += days_in_month(date.year, m);
  return date.year + (day_of_year - 1) / (leap(date.year) ? 366.0 : 365.0);
}

MagneticModel::MagneticModel(const std::string& dir, const std::string& name) {
  try {
    model_ = std::make_unique<GeographicLib::MagneticModel>(name, dir);
  } catch (const GeographicLib::GeographicErr& e) {
    throw GeomagError("magnetic model '" + name + "' in " + dir + ": " + e.what());
  }
  name_ = model_->MagneticModelName();
  if (name_ != "wmm2025") {
    throw GeomagError("magnetic model " + dir + "/" + name + ".wmm is '" + name_ +
                      "': only wmm2025 is supported (its error model is the one stated)");
  }
  min_year_ = model_->MinTime();
  max_year_ = model_->MaxTime();
  min_height_m_ = model_->MinHeight();
  max_height_m_ = model_->MaxHeight();
}

MagneticModel::~MagneticModel() = default;
MagneticModel::MagneticModel(MagneticModel&&) noexcept = default;
MagneticModel& MagneticModel::operator=(MagneticModel&&) noexcept = default;

std::string MagneticModel::default_dir() {
  if (const char* env = std::getenv("MAGVEC_GEOMAG_DIR"); env != nullptr && *env != '\0')
    return env;
  // Installed: <prefix>/share/magvec/geomag next to <prefix>/bin, whatever the prefix was at
  // build time (the Debian package installs a /usr/local-configured tree under /usr).
  std::error_code ec;
  const std::filesystem::path exe = std::filesystem::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    const auto installed = exe.parent_path().parent_path() / "share" / "magvec" / "geomag";
    if (std::filesystem::exists(installed / "wmm2025.wmm", ec)) return installed.string();
  }
  if (std::filesystem::exists(std::filesystem::path(MAGVEC_GEOMAG_SOURCE_DIR) / "wmm2025.wmm", ec))
    return MAGVEC_GEOMAG_SOURCE_DIR;
  return MAGVEC_GEOMAG_INSTALL_DIR;
}

MagneticModel MagneticModel::wmm2025() {
  return MagneticModel(default_dir(), "wmm2025");
}

ReferenceField MagneticModel::field(const Site& site, double year) const {
  check_site(site);
  if (!std::isfinite(year) || year < min_year_ || year >= max_year_) {
    throw GeomagError("date " + num(year) + " (decimal year) is outside the validity of " + name_ +
                      ": [" + num(min_year_) + ", " + num(max_year_) + ")");
  }
  if (site.height_m < min_height_m_ || site.height_m > max_height_m_) {
    throw GeomagError("height " + num(site.height_m) + " m is outside the range of " + name_ +
                      ": [" + num(min_height_m_) + ", " + num(max_height_m_) +
                      "] m above the WGS84 ellipsoid");
  }
  double be = 0, bn = 0, bu = 0;
  (*model_)(year, site.lat_deg, site.lon_deg, site.height_m, be, bn, bu);
  ReferenceField r;
  r.enu_nT = core::Vec3<double>(be, bn, bu);
  r.horizontal_nT = std::hypot(be, bn);
  r.total_nT = r.enu_nT.norm();
  r.declination_deg = std::atan2(be, bn) * 180.0 / core::kPi<double>;
  r.inclination_deg = std::atan2(-bu, r.horizontal_nT) * 180.0 / core::kPi<double>;
  r.sigma.enu_nT = core::Vec3<double>(kSigmaEast_nT, kSigmaNorth_nT, kSigmaDown_nT);
  r.sigma.horizontal_nT = kSigmaHorizontal_nT;
  r.sigma.total_nT = MagneticModel::kTotalSigma_nT;
  r.sigma.inclination_deg = kSigmaInclination_deg;
  const double dh = kSigmaDeclinationH_nTdeg / r.horizontal_nT;
  r.sigma.declination_deg = std::min(180.0, std::hypot(kSigmaDeclinationConst_deg, dh));
  r.model = "WMM2025";
  r.decimal_year = year;
  if (!r.enu_nT.allFinite()) {
    throw GeomagError("the model gave a non-finite field at " + num(site.lat_deg) + ", " +
                      num(site.lon_deg) + ", " + num(site.height_m) + " m");
  }
  return r;
}

ReferenceField MagneticModel::field(const Site& site, const Date& date) const {
  return field(site, decimal_year(date));
}

}  // namespace magvec::host::geomag
