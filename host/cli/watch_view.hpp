// The frame `magvec ctl watch` draws from magvecd's calibration state (and health): plain text,
// fixed layout, no terminal codes (the caller clears the screen), so tests render canned states.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <magvec_lcm/calibration_state.hpp>
#include <magvec_lcm/health.hpp>
#include <string>

namespace magvec::host::cli {

inline constexpr int kWatchBands = 4;    // core/coverage.hpp: bands equal in z
inline constexpr int kWatchSectors = 8;  // azimuth sectors, the first from -180 deg
inline constexpr int kWatchBarWidth = 30;

struct WatchContext {
  std::string url;
  double age_s{0};  // since the state arrived (the frame says when it is stale)
  const magvec_lcm::health* health{nullptr};
};

namespace watch_detail {

inline std::string fixed(double v, int decimals) {
  if (!std::isfinite(v)) return "-";
  char buf[64];
  std::snprintf(buf, sizeof buf, "%.*f", decimals, v);
  return buf;
}

inline int popcount(std::uint32_t x) {
  int n = 0;
  for (; x != 0U; x &= x - 1U)
    ++n;
  return n;
}

}  // namespace watch_detail

inline std::string render_watch(const magvec_lcm::calibration_state& s, const WatchContext& c) {
  using watch_detail::fixed;
  std::string f;
  f += "magvec ctl watch  " + c.url;
  if (c.age_s > 3) f += "  (no state for " + fixed(c.age_s, 0) + " s)";
  f += "\n";
  f += "calibrator " + s.calibrator + "   state " + s.state + "   cal_id " +
       std::to_string(s.cal_id) + " (persisted " + std::to_string(s.persisted_cal_id) + ")\n";

  const double p = std::isfinite(s.progress) ? std::clamp(s.progress, 0.0, 1.0) : 0.0;
  const int filled = static_cast<int>(std::floor(p * kWatchBarWidth + 1e-9));
  f += "progress [" + std::string(static_cast<std::size_t>(filled), '#') +
       std::string(static_cast<std::size_t>(kWatchBarWidth - filled), '.') + "] " +
       fixed(100 * p, 0) + " %";
  if (s.samples_needed > 0)
    f += "   samples " + std::to_string(s.samples) + "/" + std::to_string(s.samples_needed);
  const auto cells = static_cast<std::uint32_t>(s.coverage_cells);
  f += "   cells " + std::to_string(watch_detail::popcount(cells));
  if (s.coverage_needed > 0) f += "/" + std::to_string(s.coverage_needed);
  f += "\n\n";

  // The grid as coverage.hpp numbers it: cell = band * 8 + sector; the top row is the field
  // pointing up the sensor's z axis.
  f += "coverage of field directions (sensor frame; # filled, . empty)\n";
  f += "  azimuth        -180 -135  -90  -45    0   45   90  135\n";
  static constexpr const char* kBandNames[kWatchBands] = {"z -1.0..-0.5", "z -0.5.. 0.0",
                                                          "z  0.0..+0.5", "z +0.5..+1.0"};
  for (int band = kWatchBands - 1; band >= 0; --band) {
    f += "  " + std::string(kBandNames[band]) + "  ";
    for (int sector = 0; sector < kWatchSectors; ++sector) {
      const bool hit = (cells >> static_cast<unsigned>(band * kWatchSectors + sector)) & 1U;
      f += hit ? "    #" : "    .";
    }
    f += "\n";
  }
  f += "\n";

  f += "hint: " + (s.hint.empty() ? std::string("-") : s.hint) + "\n";
  f += "residual |h|-F: " +
       (std::isfinite(s.residual_nT)
            ? fixed(s.residual_nT, 2) + " nT rms (active cal_id " + std::to_string(s.cal_id) + ")"
            : std::string("- (no scalar reference)")) +
       "\n";
  std::string verdict = "-";
  if (s.state == "applied") {
    verdict = "applied: cal_id " + std::to_string(s.cal_id) + ", validation rms " +
              fixed(s.validation_rms_nT, 3) + " nT";
  } else if (s.state == "failed") {
    verdict = "failed: " + s.failure;
    if (!s.solver_reason.empty()) verdict += " (" + s.solver_reason + ")";
    verdict += ", validation rms " + fixed(s.validation_rms_nT, 3) + " nT";
  } else if (s.state == "solving" || s.state == "validating") {
    verdict = "pending (" + s.state + ")";
  }
  f += "verdict: " + verdict + "\n";
  if (c.health != nullptr) {
    const magvec_lcm::health& h = *c.health;
    f += "health: mag " + std::to_string(h.mag_samples) + " samples, ins " +
         std::to_string(h.att_samples) + ", records " + std::to_string(h.records) +
         ", no attitude " + std::to_string(h.no_attitude) + ", dropouts " +
         std::to_string(h.dropouts);
    // Shown when they happen: a reset ADC or a repeating INS is worth the operator's eye.
    if (h.mag_device_resets != 0) f += ", mag resets " + std::to_string(h.mag_device_resets);
    if (h.att_duplicates != 0) f += ", ins duplicates " + std::to_string(h.att_duplicates);
    f += "\n";
    if (h.scalar_present) {
      const std::int64_t rejected =
          h.scalar_malformed + h.scalar_crc_errors + h.scalar_out_of_range + h.scalar_overflows;
      f += "scalar: " + std::to_string(h.scalar_samples) + " readings, " +
           std::to_string(rejected) + " lines rejected, " + std::to_string(h.scalar_garbage_bytes) +
           " garbage bytes, low signal " + std::to_string(h.scalar_low_signal) + ", timeouts " +
           std::to_string(h.scalar_timeouts) + ", F fallback " +
           std::to_string(h.scalar_f_fallback) + " samples\n";
    }
  }
  return f;
}

}  // namespace magvec::host::cli
