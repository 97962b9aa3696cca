// ADS131M04 output frames through the fluxgate frame decoder (the SPI path of magvecd's ADC).
// Input: 4 configuration bytes (channel map, gain codes, stuck count), then 18-byte frames.
// Invariants: every frame is counted exactly once (samples + crc_errors + malformed); a frame is
// accepted only when its CRC word matches, and then its channel words re-encode to the same bytes;
// a sample's field is finite, within the configured full scale, and its raw codes are 24-bit;
// the sequence increments by one per sample; saturation and stuck flags agree with the codes;
// the temperature (channel 3, enabled by the stuck-count byte's top bit when no axis uses channel
// 3) is finite and within its plausible range or NaN, NaN exactly when the channel is disabled, not
// fresh, at full scale or out of range, and counters().temperature_rejected counts the NaNs of an
// enabled channel (none when disabled).
#include <array>
#include <cmath>
#include <cstring>

#include "fuzz_check.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"

using namespace magvec;
using namespace magvec::drivers;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::Bytes in(data, size);
  Ads131FluxgateConfig cfg;
  const std::uint8_t map = in.u8();
  for (std::size_t a = 0; a < 3; ++a)
    cfg.channel_of_axis[a] = static_cast<std::uint8_t>((map >> (2 * a)) & 3u);
  const std::uint16_t gains = in.u16();
  for (std::size_t c = 0; c < 4; ++c)
    cfg.gain_code[c] = static_cast<std::uint8_t>((gains >> (3 * c)) & 7u);
  const std::uint8_t stuck_byte = in.u8();
  cfg.stuck_count = stuck_byte % 8;  // small, so that the detector is reached
  cfg.nT_per_volt = {1e4, -2e4, 5e3};
  // Bits of the configuration bytes the layout above leaves unused: the temperature channel on or
  // off, the sign of its scale (a thermistor bridge falls with temperature) and a narrow range.
  const bool axis_on_3 =
      cfg.channel_of_axis[0] == 3 || cfg.channel_of_axis[1] == 3 || cfg.channel_of_axis[2] == 3;
  cfg.temperature.enabled = (stuck_byte & 0x80u) != 0 && !axis_on_3;
  cfg.temperature.degC_per_volt = (gains & 0x1000u) != 0 ? -50.0 : 100.0;
  cfg.temperature.offset_degC = (gains & 0x2000u) != 0 ? 25.0 : 0.0;
  if ((gains & 0x4000u) != 0) {
    cfg.temperature.min_degC = 10.0;
    cfg.temperature.max_degC = 40.0;
  }
  FUZZ_CHECK(check_config(cfg) == Ads131ConfigError::kNone);
  std::uint64_t temperature_nans = 0;
  Ads131FrameDecoder dec(cfg);

  std::uint64_t frames = 0, oks = 0, resets = 0;
  std::uint32_t last_sequence = 0;
  // Independent model of the stuck detector: the same code stuck_count times in a row among the
  // accepted frames.
  std::array<std::int32_t, 3> last_code{};
  std::array<std::uint32_t, 3> repeat{};
  while (in.size() >= ads131::kFrameBytes) {
    ads131::Frame f;
    std::memcpy(f.data(), in.data(), f.size());
    for (std::size_t i = 0; i < f.size(); ++i)
      (void)in.u8();
    ++frames;
    hal::MagnetometerSample s;
    const hal::Status st = dec.decode(f, 1000 * frames, s);

    ads131::Response r;
    const ads131::ParseResult pr = ads131::parse_response_frame(f, r);
    FUZZ_CHECK((pr == ads131::ParseResult::kOk) == (r.crc_received == r.crc_computed));
    if (st == hal::Status::kOk || st == hal::Status::kMalformed)
      FUZZ_CHECK(pr == ads131::ParseResult::kOk);
    if (st == hal::Status::kCrcError) FUZZ_CHECK(pr == ads131::ParseResult::kCrcError);
    if (pr == ads131::ParseResult::kOk) {
      ads131::Frame again;
      ads131::encode_response_frame(r.response, r.codes, again);
      // The response word's pad byte is not carried by Response: compare everything else.
      FUZZ_CHECK(std::memcmp(again.data(), f.data(), 2) == 0);
      FUZZ_CHECK(std::memcmp(again.data() + 3, f.data() + 3, 12) == 0);
    }
    if (st != hal::Status::kOk) continue;
    ++oks;
    if (oks > 1) FUZZ_CHECK(s.sequence == last_sequence + 1);
    last_sequence = s.sequence;
    FUZZ_CHECK(s.t_us == 1000 * frames);
    for (std::size_t a = 0; a < 3; ++a) {
      const std::int32_t code = r.codes[cfg.channel_of_axis[a]];
      FUZZ_CHECK(s.raw[a] == code);
      FUZZ_CHECK(code >= ads131::kCodeNegativeFullScale && code <= ads131::kCodePositiveFullScale);
      FUZZ_CHECK(std::isfinite(s.m_nT[a]));
      const double full_scale_nT = ads131::kVref /
                                   ads131::gain_from_code(cfg.gain_code[cfg.channel_of_axis[a]]) *
                                   std::abs(cfg.nT_per_volt[a]);
      FUZZ_CHECK(std::abs(s.m_nT[a]) <= full_scale_nT * (1 + 1e-12));
      const bool at_full_scale =
          code == ads131::kCodePositiveFullScale || code == ads131::kCodeNegativeFullScale;
      if (at_full_scale) FUZZ_CHECK((s.flags & hal::kMagSaturated) != 0);
      repeat[a] = code == last_code[a] ? repeat[a] + 1 : 1;
      last_code[a] = code;
    }
    bool stuck = false, not_fresh = false;
    for (std::size_t a = 0; a < 3; ++a) {
      stuck = stuck || (cfg.stuck_count != 0 && repeat[a] >= cfg.stuck_count);
      not_fresh = not_fresh || (r.response & (1u << cfg.channel_of_axis[a])) == 0;
    }
    FUZZ_CHECK(((s.flags & hal::kMagStuck) != 0) == stuck);
    FUZZ_CHECK(((s.flags & hal::kMagNotFresh) != 0) == not_fresh);
    FUZZ_CHECK(((s.flags & hal::kMagDeviceReset) != 0) ==
               ((r.response & ads131::kStatusReset) != 0));
    if ((s.flags & hal::kMagDeviceReset) != 0) ++resets;

    const double temp = s.temperature_degC;
    FUZZ_CHECK(std::isnan(temp) || std::isfinite(temp));
    if (!cfg.temperature.enabled) {
      FUZZ_CHECK(std::isnan(temp));
    } else {
      const std::int32_t code = r.codes[kAds131TemperatureChannel];
      const bool usable = (r.response & 0x8u) != 0 && code != ads131::kCodePositiveFullScale &&
                          code != ads131::kCodeNegativeFullScale;
      const double expected =
          cfg.temperature.offset_degC +
          ads131::code_to_volts(code, cfg.gain_code[kAds131TemperatureChannel]) *
              cfg.temperature.degC_per_volt;
      const bool in_range =
          expected >= cfg.temperature.min_degC && expected <= cfg.temperature.max_degC;
      if (usable && in_range) {
        FUZZ_CHECK(temp == expected);
      } else {
        FUZZ_CHECK(std::isnan(temp));
        ++temperature_nans;
      }
    }
  }
  const hal::MagCounters& c = dec.counters();
  FUZZ_CHECK(c.samples == oks);
  FUZZ_CHECK(std::uint64_t{c.samples} + c.crc_errors + c.malformed == frames);
  FUZZ_CHECK(c.saturated <= c.samples && c.stuck <= c.samples);
  FUZZ_CHECK(c.device_resets == resets);
  FUZZ_CHECK(c.overflows == 0 && c.garbage_bytes == 0 && c.timeouts == 0 && c.bus_errors == 0);
  FUZZ_CHECK(c.temperature_rejected == temperature_nans);
  FUZZ_CHECK(c.temperature_rejected <= c.samples);
  return 0;
}
