// magvecd's TOML configuration (also the SESSION_START event of a replayed log). Invariants: the
// only exception is ConfigError naming the source; an accepted configuration has every number
// within its documented range (finite rates and periods, non-zero bounded transfer factors,
// 11-bit CAN ids) and is accepted identically when parsed again.
#include <cmath>
#include <string>

#include "fuzz_check.hpp"
#include "magvec/host/daemon/config.hpp"

using namespace magvec::host::daemon;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  Config c;
  try {
    c = parse_config(text, "fuzz.toml");
  } catch (const ConfigError& e) {
    FUZZ_CHECK(std::string(e.what()).rfind("fuzz.toml", 0) == 0);
    return 0;
  }
  FUZZ_CHECK(!c.daemon.state_dir.empty());
  FUZZ_CHECK(c.daemon.health_period_s >= 0.01 && c.daemon.health_period_s <= 3600);
  FUZZ_CHECK(c.magnetometer.rate_hz >= 0.1 && c.magnetometer.rate_hz <= 10000);
  for (const double k : c.magnetometer.adc.nT_per_volt)
    FUZZ_CHECK(std::isfinite(k) && k != 0 && std::abs(k) <= 1e9);
  for (const auto ch : c.magnetometer.adc.channel_of_axis)
    FUZZ_CHECK(ch <= 3);
  for (const auto g : c.magnetometer.adc.gain_code)
    FUZZ_CHECK(g <= 7);
  FUZZ_CHECK(c.ins.rate_hz >= 1 && c.ins.rate_hz <= 1000);
  for (const std::uint32_t id :
       {c.ins.ids.status_01, c.ins.ids.status_03, c.ins.ids.ekf_info, c.ins.ids.ekf_quat,
        c.ins.ids.ekf_euler, c.ins.ids.ekf_orientation_acc})
    FUZZ_CHECK(id <= 0x7FF);
  // nan: not known (estimated from the data); anything else within range.
  FUZZ_CHECK(std::isnan(c.calibration.noise_nT) ||
             (c.calibration.noise_nT >= 1e-6 && c.calibration.noise_nT <= 1e5));
  FUZZ_CHECK(std::isnan(c.calibration.attitude_noise_deg) ||
             (c.calibration.attitude_noise_deg >= 1e-6 && c.calibration.attitude_noise_deg <= 10));
  FUZZ_CHECK(
      std::isnan(c.calibration.reference_field_nT) ||
      (c.calibration.reference_field_nT >= 1000 && c.calibration.reference_field_nT <= 200000));
  const ScalarConfig& sc = c.scalar;
  FUZZ_CHECK(sc.format == "g882" && !sc.device.empty() && sc.baud >= 300 && sc.baud <= 4'000'000);
  FUZZ_CHECK(sc.line.preamble > ' ' && sc.line.preamble <= '~' &&
             (sc.line.preamble < '0' || sc.line.preamble > '9'));
  FUZZ_CHECK(sc.line.analog_channels <= 8 && sc.line.min_signal <= 9999);
  FUZZ_CHECK(sc.line.min_field_nT >= 0 && sc.line.min_field_nT < sc.line.max_field_nT &&
             sc.line.max_field_nT < 200000);
  FUZZ_CHECK(!sc.enabled || sc.align.horizon_us * c.magnetometer.rate_hz * 1e-6 <=
                                static_cast<double>(kScalarQueueSamples));
  FUZZ_CHECK(std::isnan(sc.align.fallback_nT) ||
             sc.align.fallback_nT == c.calibration.reference_field_nT);
  const Config again = parse_config(text, "fuzz.toml");
  FUZZ_CHECK(again.lcm.url == c.lcm.url && again.daemon.state_dir == c.daemon.state_dir);
  FUZZ_CHECK(again.magnetometer.adc.nT_per_volt == c.magnetometer.adc.nT_per_volt);
  return 0;
}
