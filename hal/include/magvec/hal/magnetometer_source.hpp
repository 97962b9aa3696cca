// HAL: a source of triaxial magnetometer samples (fluxgate over SPI ADC, serial, or simulated).
// Values are in the sensor's own (uncalibrated) axes, in nT; calibration happens in the core.
#pragma once

#include <array>
#include <cstdint>
#include <limits>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

// Per-sample quality bits. A sample with any kMagInvalidMask bit set must not be used for
// calibration or output; the loop counts it and emits a flagged record.
enum MagFlag : std::uint32_t {
  kMagSaturated = 1u << 0,    // at least one channel at ADC/instrument full scale
  kMagStuck = 1u << 1,        // at least one channel repeated the same code N times
  kMagNotFresh = 1u << 2,     // the device reported that this conversion was not new
  kMagDeviceReset = 1u << 3,  // the device reports that it has been reset (configuration lost)
};
inline constexpr std::uint32_t kMagInvalidMask = kMagSaturated | kMagStuck | kMagDeviceReset;

struct MagnetometerSample {
  std::uint64_t t_us{0};              // sample time on the hal::Clock time base
  std::array<double, 3> m_nT{};       // field per sensor axis, nT
  std::array<std::int32_t, 3> raw{};  // raw instrument codes/counts per axis (diagnostics)
  std::uint32_t flags{0};             // MagFlag bits
  std::uint32_t sequence{0};          // increments per delivered sample (gap => dropout)
  // Sensor temperature at the sample (a fluxgate's temperature channel), degC; NaN: none.
  double temperature_degC{std::numeric_limits<double>::quiet_NaN()};
};

// Error and health counters every magnetometer driver keeps (monotonic, wrap at 2^32).
struct MagCounters {
  std::uint32_t samples{0};        // samples delivered
  std::uint32_t crc_errors{0};     // frames rejected by CRC/checksum
  std::uint32_t malformed{0};      // frames rejected as malformed / out of range
  std::uint32_t overflows{0};      // frames dropped because a bounded buffer was full
  std::uint32_t garbage_bytes{0};  // bytes skipped while resynchronising
  std::uint32_t saturated{0};      // samples flagged kMagSaturated
  std::uint32_t stuck{0};          // samples flagged kMagStuck
  std::uint32_t device_resets{0};  // samples flagged kMagDeviceReset (the driver re-initialised)
  std::uint32_t timeouts{0};       // expected sample did not arrive in time
  std::uint32_t bus_errors{0};     // transport failures
  // Samples delivered without their temperature although the driver has a temperature channel
  // (open or shorted sensor, a value outside the plausible range, no new conversion): the field
  // values of those samples stay valid, temperature_degC is NaN.
  std::uint32_t temperature_rejected{0};
};

class MagnetometerSource {
 public:
  // Returns kOk and fills `out` when a sample is available within `timeout_us` (0 = poll);
  // kTimeout/kNoData when none; another status on a transport or integrity failure (counted).
  virtual Status read(MagnetometerSample& out, std::uint32_t timeout_us) noexcept = 0;
  virtual const MagCounters& counters() const noexcept = 0;

 protected:
  ~MagnetometerSource() = default;
};

}  // namespace magvec::hal
