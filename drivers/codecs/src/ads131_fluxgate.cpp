// ADS131M04 fluxgate front end; see ads131_fluxgate.hpp.
#include "magvec/drivers/ads131_fluxgate.hpp"

#include <limits>

namespace magvec::drivers {

using namespace ads131;

Ads131ConfigError check_config(const Ads131FluxgateConfig& config) noexcept {
  for (const std::uint8_t ch : config.channel_of_axis) {
    if (ch >= kChannels) return Ads131ConfigError::kAxisChannelOutOfRange;
  }
  const Ads131TemperatureConfig& t = config.temperature;
  if (!t.enabled) return Ads131ConfigError::kNone;
  for (const std::uint8_t ch : config.channel_of_axis) {
    if (ch == kAds131TemperatureChannel) return Ads131ConfigError::kAxisOnTemperatureChannel;
  }
  // Written as comparisons that are false for NaN: no <cmath> classification needed.
  constexpr double kHuge = 1e300;
  const bool scale_ok = t.degC_per_volt != 0.0 && t.degC_per_volt > -kHuge &&
                        t.degC_per_volt < kHuge && t.offset_degC > -kHuge && t.offset_degC < kHuge;
  if (!scale_ok) return Ads131ConfigError::kTemperatureScale;
  if (!(t.min_degC > -kHuge && t.max_degC < kHuge && t.min_degC < t.max_degC)) {
    return Ads131ConfigError::kTemperatureRange;
  }
  return Ads131ConfigError::kNone;
}

const char* to_string(Ads131ConfigError error) noexcept {
  switch (error) {
    case Ads131ConfigError::kNone:
      return "ok";
    case Ads131ConfigError::kAxisChannelOutOfRange:
      return "an axis channel is not 0..3";
    case Ads131ConfigError::kAxisOnTemperatureChannel:
      return "an axis uses channel 3, the temperature channel";
    case Ads131ConfigError::kTemperatureScale:
      return "temperature scale (degC per volt) must be finite and non-zero, offset finite";
    case Ads131ConfigError::kTemperatureRange:
      return "temperature range must be finite with min < max";
  }
  return "unknown";
}

void Ads131FrameDecoder::reset_stuck_detector() noexcept {
  last_code_.fill(0);
  repeat_.fill(0);
}

hal::Status Ads131FrameDecoder::decode(std::span<const std::uint8_t, kFrameBytes> frame,
                                       std::uint64_t t_us, hal::MagnetometerSample& out) noexcept {
  Response r;
  if (parse_response_frame(frame, r) != ParseResult::kOk) {
    ++counters_.crc_errors;
    return hal::Status::kCrcError;
  }
  // The response to NULL is the STATUS register: a frame in another word length is garbage to us.
  if ((r.response & kStatusWlengthMask) != kStatusWlength24) {
    ++counters_.malformed;
    return hal::Status::kMalformed;
  }
  std::uint32_t flags = 0;
  if ((r.response & kStatusReset) != 0) flags |= hal::kMagDeviceReset;
  for (std::size_t axis = 0; axis < 3; ++axis) {
    const std::uint8_t ch = config_.channel_of_axis[axis] & 3u;
    const std::int32_t code = r.codes[ch];
    if ((r.response & (1u << ch)) == 0) flags |= hal::kMagNotFresh;
    if (code == kCodePositiveFullScale || code == kCodeNegativeFullScale) {
      flags |= hal::kMagSaturated;
    }
    if (code == last_code_[axis]) {
      if (repeat_[axis] < 0xFFFFFFFFu) ++repeat_[axis];
    } else {
      last_code_[axis] = code;
      repeat_[axis] = 1;
    }
    if (config_.stuck_count != 0 && repeat_[axis] >= config_.stuck_count) {
      flags |= hal::kMagStuck;
    }
    out.raw[axis] = code;
    out.m_nT[axis] = code_to_volts(code, config_.gain_code[ch]) * config_.nT_per_volt[axis];
  }
  out.temperature_degC = temperature_of(r);
  out.t_us = t_us;
  out.flags = flags;
  out.sequence = sequence_++;
  ++counters_.samples;
  if ((flags & hal::kMagSaturated) != 0) ++counters_.saturated;
  if ((flags & hal::kMagStuck) != 0) ++counters_.stuck;
  if ((flags & hal::kMagDeviceReset) != 0) ++counters_.device_resets;
  return hal::Status::kOk;
}

double Ads131FrameDecoder::temperature_of(const Response& r) noexcept {
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  const Ads131TemperatureConfig& t = config_.temperature;
  if (!t.enabled) return kNaN;
  const std::int32_t code = r.codes[kAds131TemperatureChannel];
  const bool fresh = (r.response & (1u << kAds131TemperatureChannel)) != 0;
  // Full scale: the sensor is open or shorted (or the amplifier railed): no temperature at all,
  // whatever the conversion would say.
  const bool full_scale = code == kCodePositiveFullScale || code == kCodeNegativeFullScale;
  if (fresh && !full_scale) {
    const double degC =
        t.offset_degC +
        code_to_volts(code, config_.gain_code[kAds131TemperatureChannel]) * t.degC_per_volt;
    if (degC >= t.min_degC && degC <= t.max_degC) return degC;
  }
  ++counters_.temperature_rejected;
  return kNaN;
}

hal::Status Ads131Fluxgate::exchange(std::uint16_t command, std::span<const std::uint16_t> data,
                                     Response& response, bool& crc_ok) noexcept {
  Frame tx{};
  Frame rx{};
  if (!build_command_frame(command, data, false, tx)) return hal::Status::kInvalidArgument;
  if (spi_.transfer(tx, rx) != hal::Status::kOk) {
    ++decoder_.counters().bus_errors;
    return hal::Status::kBusError;
  }
  crc_ok = parse_response_frame(rx, response) == ParseResult::kOk;
  return hal::Status::kOk;
}

hal::Status Ads131Fluxgate::init() noexcept {
  initialised_ = false;
  if (check_config(decoder_.config()) != Ads131ConfigError::kNone) {
    return hal::Status::kInvalidArgument;
  }
  Response r;
  bool crc_ok = false;
  // A command's response appears in the next frame, so each command is followed by a NULL.
  if (auto s = exchange(kCmdReset, {}, r, crc_ok); s != hal::Status::kOk) return s;
  if (auto s = exchange(kCmdNull, {}, r, crc_ok); s != hal::Status::kOk) return s;
  if (!crc_ok || r.response != kResetResponse) return hal::Status::kNotReady;
  if (auto s = write_register(kRegGain1, gain1_register(decoder_.config().gain_code));
      s != hal::Status::kOk) {
    return s;
  }
  // Cleared last: a data frame with STATUS.RESET is then a reset after this configuration.
  const auto mode = static_cast<std::uint16_t>(kModeResetValue & ~kModeReset);
  if (auto s = write_register(kRegMode, mode); s != hal::Status::kOk) return s;
  decoder_.reset_stuck_detector();
  initialised_ = true;
  reinit_pending_ = false;
  return hal::Status::kOk;
}

hal::Status Ads131Fluxgate::write_register(std::uint8_t address, std::uint16_t value) noexcept {
  Response r;
  bool crc_ok = false;
  const std::array<std::uint16_t, 1> data{value};
  if (auto s = exchange(wreg(address, 1), data, r, crc_ok); s != hal::Status::kOk) return s;
  if (auto s = exchange(kCmdNull, {}, r, crc_ok); s != hal::Status::kOk) return s;
  if (!crc_ok || r.response != wreg_response(address, 1)) return hal::Status::kNotReady;
  return hal::Status::kOk;
}

hal::Status Ads131Fluxgate::read(hal::MagnetometerSample& out, std::uint32_t timeout_us) noexcept {
  if (!initialised_ && (!reinit_pending_ || init() != hal::Status::kOk)) {
    return hal::Status::kNotReady;
  }
  hal::EdgeEvent ev;
  // Only a falling edge (DRDY is active low) announces a conversion; rising edges are skipped.
  do {
    const hal::Status s = drdy_.wait_edge(ev, timeout_us);
    if (s == hal::Status::kTimeout || s == hal::Status::kNoData) {
      if (timeout_us > 0) ++decoder_.counters().timeouts;
      return hal::Status::kTimeout;
    }
    if (s != hal::Status::kOk) {
      ++decoder_.counters().bus_errors;
      return s;
    }
  } while (ev.edge != hal::Edge::kFalling);
  Frame tx{};
  Frame rx{};
  build_command_frame(kCmdNull, {}, false, tx);
  if (spi_.transfer(tx, rx) != hal::Status::kOk) {
    ++decoder_.counters().bus_errors;
    return hal::Status::kBusError;
  }
  const hal::Status s = decoder_.decode(rx, ev.t_us, out);
  if (s == hal::Status::kOk && (out.flags & hal::kMagDeviceReset) != 0) {
    // The registers are back at their defaults: configure the device again before the next
    // conversion is read. This sample stays flagged (converted with the default gains).
    if (init() != hal::Status::kOk) reinit_pending_ = true;
  }
  return s;
}

}  // namespace magvec::drivers
