// HAL: a source of INS position fixes (geodetic WGS84 latitude and longitude, altitude), for what
// depends on where the platform is rather than how it is turned: the geomagnetic model's
// reference field at the survey site. Same shape as AttitudeSource: samples already converted to
// degrees and metres, stamped on the hal::Clock time base, every rejected frame counted.
#pragma once

#include <cstdint>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

enum PositionFlag : std::uint32_t {
  kPosValid = 1u << 0,        // the INS declares its position valid
  kPosStatusKnown = 1u << 1,  // a status message has been received (else validity unknown)
};

struct PositionSample {
  std::uint64_t t_us{0};      // receive time of the frame that completed the fix (hal::Clock)
  std::uint64_t t_ins_us{0};  // INS time of the latest epoch (as reported), 0: none yet
  double lat_deg{0};          // geodetic latitude, north positive, [-90, 90]
  double lon_deg{0};          // longitude, east positive, [-180, 180]
  double altitude_m{0};       // above mean sea level (the geoid)
  double undulation_m{0};     // geoid above the WGS84 ellipsoid
  std::uint32_t flags{0};     // PositionFlag bits
  // Height above the WGS84 ellipsoid (what a geomagnetic model takes).
  double height_m() const noexcept { return altitude_m + undulation_m; }
};

struct PositionCounters {
  std::uint32_t samples{0};       // fixes delivered
  std::uint32_t malformed{0};     // frames with a wrong length
  std::uint32_t out_of_range{0};  // frames whose values cannot be a position (counted, dropped)
  std::uint32_t duplicates{0};    // frames received twice back to back, dropped
  std::uint32_t overflows{0};     // fixes dropped because the reader did not keep up
};

class PositionSource {
 public:
  // kOk and `out` filled when a fix is available within timeout_us (0 = poll); kTimeout/kNoData
  // when none; another status for a transport failure.
  virtual Status read(PositionSample& out, std::uint32_t timeout_us) noexcept = 0;
  virtual const PositionCounters& counters() const noexcept = 0;

 protected:
  ~PositionSource() = default;
};

}  // namespace magvec::hal
