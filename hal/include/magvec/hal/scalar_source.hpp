// HAL: a source of total-field (scalar) magnetometer readings, e.g. an optically pumped cesium or
// potassium magnetometer on a serial line. Unlike the vector magnetometer it measures |B| without
// axes, so it needs no calibration and serves as the reference F of the vector calibration.
#pragma once

#include <cstdint>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

// Per-reading quality bits. A reading with any kScalarInvalidMask bit set must not be used as F.
enum ScalarFlag : std::uint32_t {
  kScalarLowSignal = 1u << 0,  // the instrument's signal level is below the configured minimum
};
inline constexpr std::uint32_t kScalarInvalidMask = kScalarLowSignal;

struct ScalarSample {
  std::uint64_t t_us{0};      // reading time on the hal::Clock time base
  double f_nT{0};             // total field, nT
  double quality{0};          // instrument signal level as a fraction of its full scale, 0..1
  std::uint32_t flags{0};     // ScalarFlag bits
  std::uint32_t sequence{0};  // increments per delivered reading
};

// Error and health counters every scalar driver keeps (monotonic, wrap at 2^32).
struct ScalarCounters {
  std::uint32_t samples{0};        // readings delivered (including flagged ones)
  std::uint32_t malformed{0};      // lines rejected as not matching the format
  std::uint32_t crc_errors{0};     // lines rejected by a checksum (formats that have one)
  std::uint32_t out_of_range{0};   // well-formed readings outside the instrument's range
  std::uint32_t overflows{0};      // lines longer than the decoder's bound
  std::uint32_t garbage_bytes{0};  // bytes skipped while resynchronising
  std::uint32_t low_signal{0};     // readings flagged kScalarLowSignal
  std::uint32_t bus_errors{0};     // transport failures
};

class ScalarSource {
 public:
  // Returns kOk and fills `out` when a reading is available within `timeout_us` (0 = poll);
  // kTimeout/kNoData when none; another status for a rejected line or a transport failure
  // (counted).
  virtual Status read(ScalarSample& out, std::uint32_t timeout_us) noexcept = 0;
  virtual const ScalarCounters& counters() const noexcept = 0;

 protected:
  ~ScalarSource() = default;
};

}  // namespace magvec::hal
