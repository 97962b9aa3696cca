// The reference total field F from the geomagnetic model at the INS position, for magvecd in real
// mode with neither a scalar magnetometer nor a configured calibration.reference_field_nT: the
// WMM2025 (host/geomag) evaluated at each valid position fix (the height above the ellipsoid is
// the INS altitude plus its geoid undulation) and at the date of the fix, as autopilots look up
// their declination and field strength from GNSS.
//
// What it is worth: the model's stated 1-sigma of F (138 nT, WMM2025's error model: core-field
// commission and crustal/external omission); a local anomaly can exceed it. The loop therefore
// validates a candidate by the scatter of |h| - F about its mean and judges the mean against this
// sigma (core/sensor_loop.hpp, LoopConfig::reference_sigma_nT), and the records carry
// kOutModelReference. A fix the INS does not declare valid is not used; a fix the model cannot
// take (date outside 2025-2030, a height outside its range) is counted and the previous F kept.
#pragma once

#include <cstdint>
#include <functional>
#include <limits>
#include <optional>
#include <string>

#include "magvec/hal/position_source.hpp"
#include "magvec/host/geomag/reference_field.hpp"

namespace magvec::host::daemon {

struct PositionReferenceCounters {
  std::uint64_t fixes{0};         // position fixes used
  std::uint64_t not_valid{0};     // fixes the INS did not declare valid (not used)
  std::uint64_t model_errors{0};  // fixes the model could not evaluate (date, height)
};

class PositionReference {
 public:
  // Decimal year of "now" (the daemon: the system clock's UTC date; tests: a fixed date).
  using YearFn = std::function<double()>;

  PositionReference(geomag::MagneticModel model, YearFn year);

  // Takes a fix; true when F changed (a new value to hand on).
  bool on_position(const hal::PositionSample& p);

  // NaN until the first usable fix.
  double total_nT() const noexcept { return field_ ? field_->total_nT : kNaN; }
  // The model's 1-sigma of F (known before the first fix: it does not depend on the place).
  static constexpr double sigma_nT() noexcept { return geomag::MagneticModel::kTotalSigma_nT; }
  const std::optional<geomag::ReferenceField>& field() const noexcept { return field_; }
  const hal::PositionSample& last_fix() const noexcept { return fix_; }
  const PositionReferenceCounters& counters() const noexcept { return counters_; }
  const std::string& model_name() const noexcept { return model_.name(); }
  // The last evaluation failure ("" when none): for the log.
  const std::string& last_error() const noexcept { return last_error_; }
  // e.g. "WMM2025 at 52.3800 N 4.9000 E 12 m, 2026.91: F 49123.4 nT (1-sigma 138 nT)".
  std::string describe() const;

  // The system clock's UTC date as a decimal year (geomag::decimal_year).
  static double utc_decimal_year_now();

 private:
  static constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();

  geomag::MagneticModel model_;
  YearFn year_;
  std::optional<geomag::ReferenceField> field_;
  hal::PositionSample fix_{};
  PositionReferenceCounters counters_{};
  std::string last_error_;
};

}  // namespace magvec::host::daemon
