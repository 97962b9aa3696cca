// PositionReference; see position_reference.hpp.
#include "magvec/host/daemon/position_reference.hpp"

#include <cmath>
#include <cstdio>
#include <ctime>
#include <utility>

namespace magvec::host::daemon {

PositionReference::PositionReference(geomag::MagneticModel model, YearFn year)
    : model_(std::move(model)), year_(std::move(year)) {}

bool PositionReference::on_position(const hal::PositionSample& p) {
  if ((p.flags & hal::kPosValid) == 0) {
    ++counters_.not_valid;
    return false;
  }
  geomag::Site site;
  site.lat_deg = p.lat_deg;
  site.lon_deg = p.lon_deg;
  site.height_m = p.height_m();
  try {
    const geomag::ReferenceField f = model_.field(site, year_());
    const bool changed = !field_ || f.total_nT != field_->total_nT;
    field_ = f;
    fix_ = p;
    ++counters_.fixes;
    return changed;
  } catch (const geomag::GeomagError& e) {
    ++counters_.model_errors;
    last_error_ = e.what();
    return false;
  }
}

std::string PositionReference::describe() const {
  if (!field_) return model_.name() + ": no valid INS position yet";
  char buf[200];
  std::snprintf(buf, sizeof buf, "%s at %.4f %c %.4f %c %.0f m, %.2f: F %.1f nT (1-sigma %.0f nT)",
                field_->model.c_str(), std::fabs(fix_.lat_deg), fix_.lat_deg < 0 ? 'S' : 'N',
                std::fabs(fix_.lon_deg), fix_.lon_deg < 0 ? 'W' : 'E', fix_.height_m(),
                field_->decimal_year, field_->total_nT, sigma_nT());
  return buf;
}

double PositionReference::utc_decimal_year_now() {
  const std::time_t now = std::time(nullptr);
  std::tm utc{};
  ::gmtime_r(&now, &utc);
  geomag::Date d;
  d.year = utc.tm_year + 1900;
  d.month = utc.tm_mon + 1;
  d.day = utc.tm_mday;
  return geomag::decimal_year(d);
}

}  // namespace magvec::host::daemon
