// Triaxial analogue fluxgate read through a TI ADS131M04 (frame format: ads131m04.hpp), with the
// ADC's DRDY output on a GPIO line. Implements hal::MagnetometerSource.
// Conversion (docs/architecture.md#drivers): B_axis[nT] = code / 2^23 * (VREF / gain) *
// k_axis[nT/V], with k_axis the fluxgate electronics' transfer coefficient (e.g. 10 uT/V = 1e4
// nT/V). Health checks per sample: output CRC, WLENGTH, device RESET bit, DRDY bits of the used
// channels, saturation (code at +/- full scale), stuck channel (the same code N times in a row).
// A device reset mid-stream (brown-out, a glitch on SYNC/RESET) puts every register back to its
// default: the gains are lost and the codes no longer mean what the transfer says. init() clears
// MODE.RESET, so STATUS.RESET in a data frame means exactly that: the sample is flagged
// kMagDeviceReset (an invalid sample, counted in device_resets) and read() re-initialises the
// device before returning it. A failed re-initialisation is retried by every following read(),
// which returns kNotReady until it succeeds.
//
// Temperature channel: the fourth input (channel 3) of the M04 is an ordinary differential input
// (SBAS788, "Input Multiplexer" and "Channel Configuration": every channel converts the same way)
// and can carry the fluxgate's temperature: T[degC] = offset_degC + volts * degC_per_volt. The
// example used for the defaults, magvecd's example configuration and the MCU image is a PT1000 in
// a bridge with an instrumentation amplifier giving 10 mV/degC and 0 V at 0 degC: 100 degC/V,
// offset 0; at gain 1 the ADC's +-1.2 V span +-120 degC. An open PT1000 (or a broken wire) drives
// the amplifier into its rail and the ADC to full scale; a conversion at full scale, outside the
// plausible range [min_degC, max_degC], or without its DRDY3 bit (not a new conversion) gives no
// temperature: temperature_degC is NaN and counters().temperature_rejected counts it. The field
// values of that sample are unaffected (a broken temperature sensor does not invalidate the
// fluxgate). Disabled (the default): every sample's temperature_degC is NaN and nothing is counted.
#pragma once

#include <array>
#include <cstdint>

#include "magvec/drivers/ads131m04.hpp"
#include "magvec/hal/data_ready_line.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/spi_bus.hpp"

namespace magvec::drivers {

inline constexpr std::uint8_t kAds131TemperatureChannel = 3;

struct Ads131TemperatureConfig {
  bool enabled{false};
  double degC_per_volt{100.0};  // PT1000 bridge + amplifier, 10 mV/degC (see above)
  double offset_degC{0.0};      // temperature at 0 V
  double min_degC{-40.0};       // plausible range of the sensor where it is used; outside: rejected
  double max_degC{85.0};
};

struct Ads131FluxgateConfig {
  std::array<std::uint8_t, 3> channel_of_axis{0, 1, 2};  // ADC channel (0..3) of sensor x, y, z
  std::array<double, 3> nT_per_volt{1e4, 1e4, 1e4};      // fluxgate transfer coefficient per axis
  std::array<std::uint8_t, 4> gain_code{0, 0, 0, 0};     // PGAGAINn codes (gain = 2^code)
  std::uint32_t stuck_count{64};  // identical consecutive codes that flag a stuck channel; 0 = off
  Ads131TemperatureConfig temperature{};  // channel 3 (kAds131TemperatureChannel)
};

enum class Ads131ConfigError : std::uint8_t {
  kNone,
  kAxisChannelOutOfRange,     // channel_of_axis > 3
  kAxisOnTemperatureChannel,  // an axis on channel 3 while it is the temperature channel
  kTemperatureScale,          // degC_per_volt zero or not finite, offset_degC not finite
  kTemperatureRange,          // min_degC/max_degC not finite or min_degC >= max_degC
};
// The first problem of a configuration (kNone: usable). Ads131Fluxgate::init() refuses a
// configuration with a problem (kInvalidArgument); hosts check it when they read their settings.
Ads131ConfigError check_config(const Ads131FluxgateConfig& config) noexcept;
const char* to_string(Ads131ConfigError error) noexcept;

// Stateless-per-frame conversion plus the per-channel stuck detector, separated from the transport
// so that it is testable byte by byte.
class Ads131FrameDecoder {
 public:
  explicit Ads131FrameDecoder(const Ads131FluxgateConfig& config) noexcept : config_(config) {}

  // Decodes one output frame taken after a NULL command. Returns kOk (sample filled, flags may be
  // set, temperature_degC NaN when there is none), kCrcError or kMalformed (WLENGTH is not 24
  // bit). Counters updated either way.
  hal::Status decode(std::span<const std::uint8_t, ads131::kFrameBytes> frame, std::uint64_t t_us,
                     hal::MagnetometerSample& out) noexcept;

  const hal::MagCounters& counters() const noexcept { return counters_; }
  hal::MagCounters& counters() noexcept { return counters_; }
  const Ads131FluxgateConfig& config() const noexcept { return config_; }
  void reset_stuck_detector() noexcept;

 private:
  // Channel 3 as a temperature (NaN and counted when there is none; NaN uncounted when disabled).
  double temperature_of(const ads131::Response& r) noexcept;

  Ads131FluxgateConfig config_;
  hal::MagCounters counters_{};
  std::array<std::int32_t, 3> last_code_{};
  std::array<std::uint32_t, 3> repeat_{};
  std::uint32_t sequence_{0};
};

class Ads131Fluxgate final : public hal::MagnetometerSource {
 public:
  Ads131Fluxgate(hal::SpiBus& spi, hal::DataReadyLine& drdy,
                 const Ads131FluxgateConfig& config) noexcept
      : spi_(spi), drdy_(drdy), decoder_(config) {}

  // RESET, check the reset acknowledge (FF24h), write GAIN1 and MODE (RESET bit cleared), check
  // each WREG acknowledge. kNotReady if the device does not answer as expected, kBusError on an
  // SPI failure, kInvalidArgument (nothing sent) if check_config() finds a problem.
  hal::Status init() noexcept;

  // Waits for a falling DRDY edge (up to timeout_us), clocks one NULL frame and decodes it.
  // The sample time is the DRDY edge time (the conversion instant, not the SPI read time).
  // A sample flagged kMagDeviceReset is returned after the device was re-initialised.
  hal::Status read(hal::MagnetometerSample& out, std::uint32_t timeout_us) noexcept override;
  const hal::MagCounters& counters() const noexcept override { return decoder_.counters(); }
  bool initialised() const noexcept { return initialised_; }

 private:
  hal::Status exchange(std::uint16_t command, std::span<const std::uint16_t> data,
                       ads131::Response& response, bool& crc_ok) noexcept;
  // WREG of one register, then a NULL that must return its acknowledge.
  hal::Status write_register(std::uint8_t address, std::uint16_t value) noexcept;

  hal::SpiBus& spi_;
  hal::DataReadyLine& drdy_;
  Ads131FrameDecoder decoder_;
  bool initialised_{false};
  bool reinit_pending_{false};  // a device reset was seen and re-initialising it failed
};

}  // namespace magvec::drivers
