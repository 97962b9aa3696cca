#include "magvec/drivers/ads131m04.hpp"

#include <gtest/gtest.h>

#include <deque>
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
