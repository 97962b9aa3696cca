#include "magvec/drivers/ads131m04.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <deque>
#include <limits>
#include <vector>

#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/crc.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::drivers {
namespace {

using namespace ads131;

// Hand-assembled output frame: STATUS 010Fh (24-bit words, DRDY0..3), ch0 123456h = +1193046,
// ch1 FFFFFEh = -2, ch2 000001h = +1, ch3 800000h = -FS. CRC-16-CCITT(FFFFh) over the 15 bytes
// = 3957h (worked out with an independent bitwise implementation).
constexpr Frame kNormalFrame{0x01, 0x0F, 0x00, 0x12, 0x34, 0x56, 0xFF, 0xFF, 0xFE,
                             0x00, 0x00, 0x01, 0x80, 0x00, 0x00, 0x39, 0x57, 0x00};
// ch0 = +FS (7FFFFFh), ch1 = 16, ch2 = -FS, ch3 = 0; CRC DB55h.
constexpr Frame kSaturatedFrame{0x01, 0x0F, 0x00, 0x7F, 0xFF, 0xFF, 0x00, 0x00, 0x10,
                                0x80, 0x00, 0x00, 0x00, 0x00, 0x00, 0xDB, 0x55, 0x00};

// Temperature channel frames: the axes as in kNormalFrame, ch3 the PT1000 amplifier of the
// documented example (100 degC/V, 0 V at 0 degC, gain 1). CRCs worked out independently
// (CRC-16-CCITT, seed FFFFh, over the 15 bytes before the CRC word).
// ch3 191111h = 1642769 = 0.2350000 V = 23.5 degC (within one code, 1.4e-5 degC).
constexpr Frame kTemperatureFrame{0x01, 0x0F, 0x00, 0x12, 0x34, 0x56, 0xFF, 0xFF, 0xFE,
                                  0x00, 0x00, 0x01, 0x19, 0x11, 0x11, 0xED, 0xAD, 0x00};
// ch3 7FFFFFh = +FS: the open sensor railed the amplifier.
constexpr Frame kOpenSensorFrame{0x01, 0x0F, 0x00, 0x12, 0x34, 0x56, 0xFF, 0xFF, 0xFE,
                                 0x00, 0x00, 0x01, 0x7F, 0xFF, 0xFF, 0xEB, 0x3B, 0x00};
// As kTemperatureFrame but STATUS 0107h: DRDY3 clear, channel 3 has no new conversion.
constexpr Frame kStaleTemperatureFrame{0x01, 0x07, 0x00, 0x12, 0x34, 0x56, 0xFF, 0xFF, 0xFE,
                                       0x00, 0x00, 0x01, 0x19, 0x11, 0x11, 0x06, 0xC6, 0x00};
// ch3 CAAAABh = -3495253 = -0.5 V = -50 degC: below the default plausible range (-40 degC).
constexpr Frame kColdFrame{0x01, 0x0F, 0x00, 0x12, 0x34, 0x56, 0xFF, 0xFF, 0xFE,
                           0x00, 0x00, 0x01, 0xCA, 0xAA, 0xAB, 0x15, 0x0F, 0x00};
constexpr double kTemperature23_5 = 1642769.0 * 1.2 / 8388608.0 * 100.0;

Ads131FluxgateConfig temperature_config() {
  Ads131FluxgateConfig cfg;
  cfg.temperature.enabled = true;  // the defaults are the PT1000 example
  return cfg;
}

TEST(Ads131m04, CommandWords) {
  EXPECT_EQ(rreg(kRegStatus, 1), 0xA080);  // 101 000001 0000000
  EXPECT_EQ(wreg(kRegGain1, 1), 0x6200);   // 011 000100 0000000
  EXPECT_EQ(wreg_response(kRegGain1, 1), 0x4200);
  EXPECT_EQ(wreg(kRegMode, 3), 0x6102);  // 3 registers from 02h: n = 2
  EXPECT_EQ(gain1_register({1, 2, 3, 7}), 0x7321);
  EXPECT_EQ(gain_from_code(0), 1.0);
  EXPECT_EQ(gain_from_code(7), 128.0);
}

TEST(Ads131m04, BuildCommandFrames) {
  Frame f{};
  ASSERT_TRUE(build_command_frame(kCmdReset, {}, false, f));
  const Frame reset{0x00, 0x11, 0x00, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
  EXPECT_EQ(f, reset);
  const std::array<std::uint16_t, 1> gain{0x0021};
  ASSERT_TRUE(build_command_frame(wreg(kRegGain1, 1), gain, false, f));
  const Frame wr{0x62, 0x00, 0x00, 0x00, 0x21, 0x00, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0};
  EXPECT_EQ(f, wr);
  // Input CRC (RX_CRC_EN): over the command and data words, pads included.
  ASSERT_TRUE(build_command_frame(wreg(kRegGain1, 1), gain, true, f));
  const std::uint16_t crc = crc16_ccitt(std::span<const std::uint8_t>(f.data(), 6));
  EXPECT_EQ(f[6], crc >> 8);
  EXPECT_EQ(f[7], crc & 0xFF);
  // Too many data words for one frame.
  const std::array<std::uint16_t, 6> too_many{};
  EXPECT_FALSE(build_command_frame(wreg(kRegMode, 6), too_many, false, f));
}

TEST(Ads131m04, ParseHandAssembledFrame) {
  Response r;
  ASSERT_EQ(parse_response_frame(kNormalFrame, r), ParseResult::kOk);
  EXPECT_EQ(r.response, 0x010F);
  EXPECT_EQ(r.codes[0], 1193046);
  EXPECT_EQ(r.codes[1], -2);
  EXPECT_EQ(r.codes[2], 1);
  EXPECT_EQ(r.codes[3], -8388608);
  EXPECT_EQ(r.crc_received, 0x3957);
  Frame again{};
  encode_response_frame(0x010F, r.codes, again);
  EXPECT_EQ(again, kNormalFrame);
}

TEST(Ads131m04, EveryBitFlipIsACrcError) {
  for (std::size_t byte = 0; byte < kFrameBytes - 1; ++byte) {  // last byte is the CRC word's pad
    for (int bit = 0; bit < 8; ++bit) {
      Frame f = kNormalFrame;
      f[byte] ^= static_cast<std::uint8_t>(1u << bit);
      Response r;
      EXPECT_EQ(parse_response_frame(f, r), ParseResult::kCrcError) << byte << ":" << bit;
    }
  }
}

TEST(Ads131m04, CountsToVolts) {
  // 1 LSB = 1.2 V / gain / 2^23.
  EXPECT_DOUBLE_EQ(code_to_volts(kCodePositiveFullScale, 0), 1.2 * 8388607.0 / 8388608.0);
  EXPECT_DOUBLE_EQ(code_to_volts(kCodeNegativeFullScale, 0), -1.2);
  EXPECT_DOUBLE_EQ(code_to_volts(1193046, 0), 1193046.0 * 1.2 / 8388608.0);
  EXPECT_DOUBLE_EQ(code_to_volts(1000, 3), 1000.0 * 0.15 / 8388608.0);
}

TEST(Ads131FrameDecoder, ConvertsAxesThroughChannelMapAndTransferCoefficients) {
  Ads131FluxgateConfig cfg;
  cfg.channel_of_axis = {0, 1, 2};
  cfg.nT_per_volt = {1e4, 2e4, 5e3};
  cfg.gain_code = {0, 1, 0, 0};
  Ads131FrameDecoder dec(cfg);
  hal::MagnetometerSample s;
  ASSERT_EQ(dec.decode(kNormalFrame, 1234, s), hal::Status::kOk);
  EXPECT_EQ(s.t_us, 1234u);
  EXPECT_NEAR(s.m_nT[0], 1706.6659927368164, 1e-9);           // 1193046 * 1.2/2^23 * 1e4
  EXPECT_NEAR(s.m_nT[1], -2 * 0.6 / 8388608.0 * 2e4, 1e-15);  // gain 2
  EXPECT_NEAR(s.m_nT[2], 1 * 1.2 / 8388608.0 * 5e3, 1e-15);
  EXPECT_EQ(s.raw[0], 1193046);
  EXPECT_EQ(s.flags, 0u);
  // Channel 3 (at -FS) is not used: no saturation flag. Map z to it and the flag appears.
  cfg.channel_of_axis = {0, 1, 3};
  Ads131FrameDecoder dec3(cfg);
  ASSERT_EQ(dec3.decode(kNormalFrame, 0, s), hal::Status::kOk);
  EXPECT_TRUE(s.flags & hal::kMagSaturated);
  EXPECT_EQ(dec3.counters().saturated, 1u);
}

TEST(Ads131FrameDecoder, SaturationCrcStatusAndStuckDetection) {
  Ads131FluxgateConfig cfg;
  cfg.stuck_count = 5;
  Ads131FrameDecoder dec(cfg);
  hal::MagnetometerSample s;
  ASSERT_EQ(dec.decode(kSaturatedFrame, 0, s), hal::Status::kOk);
  EXPECT_TRUE(s.flags & hal::kMagSaturated);

  Frame bad = kNormalFrame;
  bad[16] ^= 0x01;  // CRC word corrupted
  EXPECT_EQ(dec.decode(bad, 0, s), hal::Status::kCrcError);
  EXPECT_EQ(dec.counters().crc_errors, 1u);

  // 16-bit word length reported in STATUS: not our frame layout.
  Frame f{};
  encode_response_frame(0x000F, {1, 2, 3, 4}, f);
  EXPECT_EQ(dec.decode(f, 0, s), hal::Status::kMalformed);
  EXPECT_EQ(dec.counters().malformed, 1u);

  // RESET bit and a missing DRDY bit on a used channel.
  encode_response_frame(0x0500 | 0x0D, {10, 20, 30, 0}, f);  // DRDY1 clear
  ASSERT_EQ(dec.decode(f, 0, s), hal::Status::kOk);
  EXPECT_TRUE(s.flags & hal::kMagDeviceReset);
  EXPECT_TRUE(s.flags & hal::kMagNotFresh);
  EXPECT_EQ(dec.counters().device_resets, 1u);

  // Stuck: the same code 5 times on axis y while x changes.
  for (int i = 0; i < 5; ++i) {
    encode_response_frame(0x010F, {100 + i, 777, 200 + i, 0}, f);
    ASSERT_EQ(dec.decode(f, 0, s), hal::Status::kOk);
    EXPECT_EQ((s.flags & hal::kMagStuck) != 0, i == 4) << i;
  }
  encode_response_frame(0x010F, {100, 778, 200, 0}, f);
  ASSERT_EQ(dec.decode(f, 0, s), hal::Status::kOk);
  EXPECT_FALSE(s.flags & hal::kMagStuck);
  EXPECT_EQ(dec.counters().stuck, 1u);
}

TEST(Ads131FrameDecoder, TemperatureChannelConvertsChannel3) {
  Ads131FrameDecoder dec(temperature_config());
  hal::MagnetometerSample s;
  ASSERT_EQ(dec.decode(kTemperatureFrame, 10, s), hal::Status::kOk);
  EXPECT_NEAR(s.temperature_degC, 23.5, 2e-5);
  EXPECT_DOUBLE_EQ(s.temperature_degC, kTemperature23_5);
  EXPECT_EQ(s.flags, 0u);
  EXPECT_NEAR(s.m_nT[0], 1706.6659927368164, 1e-9);  // the field is as without the channel
  EXPECT_EQ(dec.counters().temperature_rejected, 0u);

  // Another scale, offset and PGA gain: a thermistor bridge of -50 degC/V around 25 degC at gain
  // 4 (the code then means a quarter of the volts).
  Ads131FluxgateConfig cfg = temperature_config();
  cfg.temperature.degC_per_volt = -50.0;
  cfg.temperature.offset_degC = 25.0;
  cfg.gain_code[3] = 2;
  Ads131FrameDecoder thermistor(cfg);
  ASSERT_EQ(thermistor.decode(kTemperatureFrame, 10, s), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.temperature_degC, 25.0 - 50.0 * 1642769.0 * 0.3 / 8388608.0);
  EXPECT_EQ(thermistor.counters().temperature_rejected, 0u);
}

TEST(Ads131FrameDecoder, DisabledTemperatureChannelGivesNaNUncounted) {
  Ads131FrameDecoder dec(Ads131FluxgateConfig{});
  hal::MagnetometerSample s;
  s.temperature_degC = 1.0;  // a reused sample must not keep an old temperature
  ASSERT_EQ(dec.decode(kTemperatureFrame, 0, s), hal::Status::kOk);
  EXPECT_TRUE(std::isnan(s.temperature_degC));
  ASSERT_EQ(dec.decode(kOpenSensorFrame, 0, s), hal::Status::kOk);
  EXPECT_TRUE(std::isnan(s.temperature_degC));
  EXPECT_EQ(s.flags, 0u);  // channel 3 is not an axis: its full scale is not a saturation
  EXPECT_EQ(dec.counters().temperature_rejected, 0u);
  EXPECT_EQ(dec.counters().samples, 2u);
}

TEST(Ads131FrameDecoder, OpenStaleOrImplausibleTemperatureIsRejectedAndCountedFieldStaysValid) {
  Ads131FrameDecoder dec(temperature_config());
  hal::MagnetometerSample s;
  const Frame* rejected[] = {&kOpenSensorFrame, &kStaleTemperatureFrame, &kColdFrame};
  std::uint32_t n = 0;
  for (const Frame* f : rejected) {
    s.temperature_degC = 20.0;
    ASSERT_EQ(dec.decode(*f, 0, s), hal::Status::kOk);
    ++n;
    EXPECT_TRUE(std::isnan(s.temperature_degC)) << n;
    EXPECT_EQ(s.flags, 0u) << n;  // the field sample itself stays valid
    EXPECT_NEAR(s.m_nT[0], 1706.6659927368164, 1e-9);
    EXPECT_EQ(dec.counters().temperature_rejected, n);
  }
  EXPECT_EQ(dec.counters().saturated, 0u);
  // A good conversion again after the faults.
  ASSERT_EQ(dec.decode(kTemperatureFrame, 0, s), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.temperature_degC, kTemperature23_5);
  EXPECT_EQ(dec.counters().temperature_rejected, 3u);
  EXPECT_EQ(dec.counters().samples, 4u);
  // -50 degC is fine for a sensor specified down to -55 degC.
  Ads131FluxgateConfig wide = temperature_config();
  wide.temperature.min_degC = -55.0;
  Ads131FrameDecoder cold(wide);
  ASSERT_EQ(cold.decode(kColdFrame, 0, s), hal::Status::kOk);
  EXPECT_NEAR(s.temperature_degC, -50.0, 2e-5);
  EXPECT_EQ(cold.counters().temperature_rejected, 0u);
}

TEST(Ads131FrameDecoder, CorruptTemperatureFramesAreCrcErrorsWithoutATemperatureCount) {
  Ads131FrameDecoder dec(temperature_config());
  hal::MagnetometerSample s;
  // Every single-bit error in the channel-3 word or the CRC word is caught by the CRC: a
  // corrupted temperature never reaches a sample.
  std::uint32_t errors = 0;
  for (std::size_t byte = 12; byte < 17; ++byte) {
    for (int bit = 0; bit < 8; ++bit) {
      Frame f = kTemperatureFrame;
      f[byte] ^= static_cast<std::uint8_t>(1u << bit);
      EXPECT_EQ(dec.decode(f, 0, s), hal::Status::kCrcError) << byte << ":" << bit;
      ++errors;
    }
  }
  // A frame with a plausible-looking temperature whose CRC word was not updated.
  Frame forged = kTemperatureFrame;
  forged[13] = 0x22;
  EXPECT_EQ(dec.decode(forged, 0, s), hal::Status::kCrcError);
  ++errors;
  EXPECT_EQ(dec.counters().crc_errors, errors);
  EXPECT_EQ(dec.counters().temperature_rejected, 0u);
  EXPECT_EQ(dec.counters().samples, 0u);
  // A malformed frame (16-bit word length) with a temperature: no sample, no temperature count.
  Frame f16{};
  encode_response_frame(0x000F, {1, 2, 3, 1642769}, f16);
  EXPECT_EQ(dec.decode(f16, 0, s), hal::Status::kMalformed);
  EXPECT_EQ(dec.counters().temperature_rejected, 0u);
}

TEST(Ads131FluxgateConfig, CheckConfigNamesTheProblem) {
  EXPECT_EQ(check_config(Ads131FluxgateConfig{}), Ads131ConfigError::kNone);
  EXPECT_EQ(check_config(temperature_config()), Ads131ConfigError::kNone);
  Ads131FluxgateConfig c = temperature_config();
  c.channel_of_axis = {0, 1, 3};
  EXPECT_EQ(check_config(c), Ads131ConfigError::kAxisOnTemperatureChannel);
  c.temperature.enabled = false;  // channel 3 as an axis is fine without the temperature
  EXPECT_EQ(check_config(c), Ads131ConfigError::kNone);
  c.channel_of_axis = {0, 4, 2};
  EXPECT_EQ(check_config(c), Ads131ConfigError::kAxisChannelOutOfRange);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const double inf = std::numeric_limits<double>::infinity();
  for (const double bad : {0.0, nan, inf, -inf}) {
    c = temperature_config();
    c.temperature.degC_per_volt = bad;
    EXPECT_EQ(check_config(c), Ads131ConfigError::kTemperatureScale) << bad;
  }
  c = temperature_config();
  c.temperature.offset_degC = nan;
  EXPECT_EQ(check_config(c), Ads131ConfigError::kTemperatureScale);
  c = temperature_config();
  c.temperature.min_degC = 85.0;
  EXPECT_EQ(check_config(c), Ads131ConfigError::kTemperatureRange);
  c = temperature_config();
  c.temperature.max_degC = nan;
  EXPECT_EQ(check_config(c), Ads131ConfigError::kTemperatureRange);
  EXPECT_STREQ(to_string(Ads131ConfigError::kAxisOnTemperatureChannel),
               "an axis uses channel 3, the temperature channel");
}

// A minimal register-level model of the ADC on the other side of the SPI bus.
class FakeAdc final : public hal::SpiBus, public hal::DataReadyLine {
 public:
  hal::Status transfer(std::span<const std::uint8_t> tx,
                       std::span<std::uint8_t> rx) noexcept override {
    if (tx.size() != kFrameBytes || rx.size() != kFrameBytes) return hal::Status::kInvalidArgument;
    if (fail_next) {
      fail_next = false;
      return hal::Status::kBusError;
    }
    Frame out{};
    // STATUS shows MODE.RESET (set by a reset, cleared by the host).
    const std::uint16_t response = next_response == status
                                       ? static_cast<std::uint16_t>(status | (mode & kModeReset))
                                       : next_response;
    encode_response_frame(response, codes, out);
    if (corrupt_next) {
      out[4] ^= 0x10;
      corrupt_next = false;
    }
    for (std::size_t i = 0; i < kFrameBytes; ++i)
      rx[i] = out[i];
    const std::uint16_t cmd = decode_word16(tx.data());
    commands.push_back(cmd);
    if (cmd == kCmdReset) {
      device_reset();
      next_response = mute_reset ? status : kResetResponse;
    } else if ((cmd & 0xE000) == 0x6000) {
      const auto addr = static_cast<std::uint8_t>((cmd >> 7) & 0x3F);
      if (addr == kRegGain1) gain1 = decode_word16(tx.data() + 3);
      if (addr == kRegMode) mode = decode_word16(tx.data() + 3);
      next_response = static_cast<std::uint16_t>(0x4000 | (cmd & 0x1FFF));
    } else {
      next_response = status;
    }
    return hal::Status::kOk;
  }
  hal::Status wait_edge(hal::EdgeEvent& ev, std::uint32_t) noexcept override {
    if (edges.empty()) return hal::Status::kTimeout;
    ev = edges.front();
    edges.pop_front();
    return hal::Status::kOk;
  }
  std::uint32_t missed_edges() const noexcept override { return 0; }
  // Registers back to their defaults (the RESET command, or a reset the host did not ask for).
  void device_reset() {
    gain1 = 0;
    mode = kModeResetValue;
  }

  std::uint16_t status{0x010F};  // without MODE.RESET
  std::uint16_t mode{kModeResetValue};
  std::vector<std::uint16_t> commands;
  bool mute_reset{false};  // answer RESET with STATUS instead of the acknowledge
  std::uint16_t next_response{0x0500 | 0x0F};
  std::array<std::int32_t, 4> codes{1000, -2000, 3000, 0};
  std::uint16_t gain1{0};
  bool fail_next{false};
  bool corrupt_next{false};
  std::deque<hal::EdgeEvent> edges;
};

TEST(Ads131Fluxgate, InitWritesGainAndReadsSamplesOnFallingEdges) {
  FakeAdc adc;
  Ads131FluxgateConfig cfg;
  cfg.gain_code = {2, 2, 2, 0};
  Ads131Fluxgate drv(adc, adc, cfg);
  hal::MagnetometerSample s;
  EXPECT_EQ(drv.read(s, 0), hal::Status::kNotReady);
  ASSERT_EQ(drv.init(), hal::Status::kOk);
  EXPECT_EQ(adc.gain1, 0x0222);
  EXPECT_EQ(drv.read(s, 1000), hal::Status::kTimeout);
  EXPECT_EQ(drv.counters().timeouts, 1u);
  adc.edges.push_back({500, hal::Edge::kRising});
  adc.edges.push_back({1000, hal::Edge::kFalling});
  ASSERT_EQ(drv.read(s, 1000), hal::Status::kOk);
  EXPECT_EQ(s.t_us, 1000u);  // DRDY edge time, not the read time
  EXPECT_NEAR(s.m_nT[0], 1000 * 0.3 / 8388608.0 * 1e4, 1e-12);
  EXPECT_NEAR(s.m_nT[1], -2000 * 0.3 / 8388608.0 * 1e4, 1e-12);

  adc.corrupt_next = true;
  adc.edges.push_back({2000, hal::Edge::kFalling});
  EXPECT_EQ(drv.read(s, 1000), hal::Status::kCrcError);
  adc.fail_next = true;
  adc.edges.push_back({3000, hal::Edge::kFalling});
  EXPECT_EQ(drv.read(s, 1000), hal::Status::kBusError);
  EXPECT_EQ(drv.counters().crc_errors, 1u);
  EXPECT_EQ(drv.counters().bus_errors, 1u);
  EXPECT_EQ(drv.counters().samples, 1u);

  // Zero heap allocations in the per-sample path.
  magvec::test::AllocationScope scope;
  for (int i = 0; i < 100; ++i) {
    adc.codes[0] = i;
    adc.edges.push_back({4000u + static_cast<std::uint64_t>(i), hal::Edge::kFalling});
  }
  adc.commands.reserve(adc.commands.size() + 100);
  const std::size_t before = scope.count();  // deque growth above is the test's, not the driver's
  for (int i = 0; i < 100; ++i)
    ASSERT_EQ(drv.read(s, 1000), hal::Status::kOk);
  EXPECT_EQ(scope.count(), before);
}

// The ADC resets mid-stream (registers back to their defaults, STATUS.RESET set): the sample is
// flagged and counted, the driver configures the device again in the same read, and the next
// sample is good. A re-initialisation that fails is retried by the next reads (kNotReady).
TEST(Ads131Fluxgate, DeviceResetMidStreamIsFlaggedCountedAndReinitialised) {
  FakeAdc adc;
  Ads131FluxgateConfig cfg;
  cfg.gain_code = {1, 1, 1, 0};
  Ads131Fluxgate drv(adc, adc, cfg);
  ASSERT_EQ(drv.init(), hal::Status::kOk);
  EXPECT_EQ(adc.gain1, 0x0111);
  EXPECT_EQ(adc.mode, 0x0110);  // MODE.RESET cleared, the rest at its default
  const std::vector<std::uint16_t> init_commands = {
      kCmdReset, kCmdNull, wreg(kRegGain1, 1), kCmdNull, wreg(kRegMode, 1), kCmdNull};
  EXPECT_EQ(adc.commands, init_commands);
  const double nT_per_code = 1.2 / 2 / 8388608.0 * 1e4;  // gain 2
  hal::MagnetometerSample s;
  adc.edges.push_back({1000, hal::Edge::kFalling});
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);
  EXPECT_EQ(s.flags, 0u);
  EXPECT_DOUBLE_EQ(s.m_nT[0], 1000 * nT_per_code);

  adc.device_reset();
  adc.commands.clear();
  adc.edges.push_back({2000, hal::Edge::kFalling});
  adc.edges.push_back({3000, hal::Edge::kFalling});
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);
  EXPECT_EQ(s.t_us, 2000u);
  EXPECT_EQ(s.flags, hal::kMagDeviceReset);  // converted at the default gain: not valid
  EXPECT_EQ(drv.counters().device_resets, 1u);
  std::vector<std::uint16_t> reinit = {kCmdNull};  // the data read, then init()
  reinit.insert(reinit.end(), init_commands.begin(), init_commands.end());
  EXPECT_EQ(adc.commands, reinit);
  EXPECT_EQ(adc.gain1, 0x0111);
  EXPECT_EQ(adc.mode, 0x0110);
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);
  EXPECT_EQ(s.flags, 0u);
  EXPECT_DOUBLE_EQ(s.m_nT[0], 1000 * nT_per_code);

  // Another reset, and the device does not acknowledge the RESET command this time.
  adc.device_reset();
  adc.mute_reset = true;
  adc.edges.push_back({4000, hal::Edge::kFalling});
  adc.edges.push_back({5000, hal::Edge::kFalling});
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);
  EXPECT_EQ(s.flags, hal::kMagDeviceReset);
  EXPECT_FALSE(drv.initialised());
  EXPECT_EQ(drv.read(s, 0), hal::Status::kNotReady);  // tried again, failed again
  EXPECT_EQ(drv.read(s, 0), hal::Status::kNotReady);
  adc.mute_reset = false;
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);  // configured again, then the pending conversion
  EXPECT_EQ(s.t_us, 5000u);
  EXPECT_EQ(s.flags, 0u);
  EXPECT_DOUBLE_EQ(s.m_nT[0], 1000 * nT_per_code);
  EXPECT_EQ(drv.counters().device_resets, 2u);
  EXPECT_EQ(drv.counters().samples, 5u);
}

TEST(Ads131Fluxgate, ReadsTheTemperatureChannelAndRefusesABadConfiguration) {
  FakeAdc adc;
  Ads131Fluxgate drv(adc, adc, temperature_config());
  ASSERT_EQ(drv.init(), hal::Status::kOk);
  adc.codes[3] = 1642769;  // 23.5 degC
  adc.edges.push_back({1000, hal::Edge::kFalling});
  hal::MagnetometerSample s;
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.temperature_degC, kTemperature23_5);
  adc.codes[3] = kCodePositiveFullScale;  // the sensor opens
  adc.edges.push_back({2000, hal::Edge::kFalling});
  ASSERT_EQ(drv.read(s, 0), hal::Status::kOk);
  EXPECT_TRUE(std::isnan(s.temperature_degC));
  EXPECT_EQ(s.flags, 0u);
  EXPECT_EQ(drv.counters().temperature_rejected, 1u);

  Ads131FluxgateConfig bad = temperature_config();
  bad.channel_of_axis = {3, 1, 2};
  FakeAdc adc2;
  Ads131Fluxgate refused(adc2, adc2, bad);
  EXPECT_EQ(refused.init(), hal::Status::kInvalidArgument);
  EXPECT_TRUE(adc2.commands.empty());  // nothing sent to the device
  EXPECT_FALSE(refused.initialised());
}

TEST(Ads131Fluxgate, InitFailsOnWrongResetAcknowledge) {
  FakeAdc adc;
  Ads131Fluxgate drv(adc, adc, Ads131FluxgateConfig{});
  adc.fail_next = true;
  EXPECT_EQ(drv.init(), hal::Status::kBusError);
  // A device that answers STATUS to everything (e.g. ADS131M08 would answer FF28h): not ready.
  class Mute final : public hal::SpiBus {
   public:
    hal::Status transfer(std::span<const std::uint8_t>,
                         std::span<std::uint8_t> rx) noexcept override {
      Frame f{};
      encode_response_frame(0x0500, {0, 0, 0, 0}, f);
      for (std::size_t i = 0; i < kFrameBytes; ++i)
        rx[i] = f[i];
      return hal::Status::kOk;
    }
  } mute;
  Ads131Fluxgate drv2(mute, adc, Ads131FluxgateConfig{});
  EXPECT_EQ(drv2.init(), hal::Status::kNotReady);
  EXPECT_FALSE(drv2.initialised());
}

}  // namespace
}  // namespace magvec::drivers
