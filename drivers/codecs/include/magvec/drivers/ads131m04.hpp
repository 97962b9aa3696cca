// TI ADS131M04 4-channel, simultaneous-sampling 24-bit delta-sigma ADC: SPI frame codec and the
// counts -> volts conversion. Used as the front end of a 3-axis analogue fluxgate (3 of 4
// channels).
//
// Source of the format: TI ADS131M04 datasheet (SBAS788), section "SPI Communication Frames",
// Table "Command Definitions" and the register map (STATUS 01h, MODE 02h, GAIN1 04h), as
// republished in the ADS131M0x family datasheets (same tables for M02/M03/M04/M06/M08):
//   - Words are 24 bits (WLENGTH = 01b, the reset default), MSB first. 16-bit command/response/
//     register words are left-aligned in a 24-bit word and padded with one 0x00 byte.
//   - Output frame (device -> host) of the M04: response word, 4 channel words, CRC word = 6 words
//     = 18 bytes. Channel data are 24-bit two's complement; +FS = 7FFFFFh, -FS = 800000h.
//   - Input frame (host -> device): command word, optional register data words (WREG),
//     optional input CRC word (only checked when MODE.RX_CRC_EN = 1), then zero words.
//   - Commands: NULL 0000h (response: STATUS), RESET 0011h (response FF24h on the M04),
//     STANDBY 0022h, WAKEUP 0033h, LOCK 0555h, UNLOCK 0655h,
//     RREG 101a aaaa annn nnnn (read n+1 registers at a), WREG 011a aaaa annn nnnn (write n+1),
//     WREG response 010a aaaa ammm mmmm. The response to a command appears in the NEXT frame.
//   - STATUS bits: 15 LOCK, 14 F_RESYNC, 13 REG_MAP, 12 CRC_ERR, 11 CRC_TYPE, 10 RESET,
//     9:8 WLENGTH, 3:0 DRDY3..DRDY0. Reset value 0500h.
//   - CRC: CRC-16-CCITT, polynomial 1021h, seed FFFFh (MODE.CRC_TYPE = 0, the default).
//   - Full-scale input +/-VREF/gain with VREF = 1.2 V; 1 LSB = 1.2 V / gain / 2^23.
// Not verified (no hardware or silicon-level reference available here): whether the output CRC
// covers the zero pad bytes of the 16-bit response word in 24-bit mode. We follow TI's example
// driver structure (CRC over all bytes of every word that precedes the CRC word, pad included);
// the check is symmetric in encode/parse, so a different real convention would show up as CRC
// errors on hardware and is changed in one place (output_crc()).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

namespace magvec::drivers::ads131 {

inline constexpr std::size_t kWordBytes = 3;
inline constexpr std::size_t kChannels = 4;
inline constexpr std::size_t kFrameWords = 2 + kChannels;  // response, 4 channels, CRC
inline constexpr std::size_t kFrameBytes = kFrameWords * kWordBytes;
using Frame = std::array<std::uint8_t, kFrameBytes>;

// Commands.
inline constexpr std::uint16_t kCmdNull = 0x0000;
inline constexpr std::uint16_t kCmdReset = 0x0011;
inline constexpr std::uint16_t kCmdStandby = 0x0022;
inline constexpr std::uint16_t kCmdWakeup = 0x0033;
inline constexpr std::uint16_t kCmdLock = 0x0555;
inline constexpr std::uint16_t kCmdUnlock = 0x0655;
inline constexpr std::uint16_t kResetResponse = 0xFF24;  // ADS131M04 specific (FF2xh, x = channels)

// Registers.
inline constexpr std::uint8_t kRegId = 0x00;
inline constexpr std::uint8_t kRegStatus = 0x01;
inline constexpr std::uint8_t kRegMode = 0x02;
inline constexpr std::uint8_t kRegClock = 0x03;
inline constexpr std::uint8_t kRegGain1 = 0x04;
inline constexpr std::uint8_t kRegCfg = 0x06;

// STATUS register bits.
inline constexpr std::uint16_t kStatusLock = 1u << 15;
inline constexpr std::uint16_t kStatusFResync = 1u << 14;
inline constexpr std::uint16_t kStatusRegMap = 1u << 13;
inline constexpr std::uint16_t kStatusCrcErr = 1u << 12;
inline constexpr std::uint16_t kStatusCrcType = 1u << 11;
inline constexpr std::uint16_t kStatusReset = 1u << 10;
inline constexpr std::uint16_t kStatusWlengthMask = 0x0300;
inline constexpr std::uint16_t kStatusWlength24 = 0x0100;
inline constexpr std::uint16_t kStatusDrdyMask = 0x000F;
inline constexpr std::uint16_t kStatusResetValue = 0x0500;

// MODE register: 10 RESET (set by every reset, power-on included; STATUS.RESET shows it until
// the host writes it 0: how a later, unexpected reset becomes visible), 9:8 WLENGTH, 4 TIMEOUT.
// Reset value 0510h.
inline constexpr std::uint16_t kModeReset = 1u << 10;
inline constexpr std::uint16_t kModeResetValue = 0x0510;

inline constexpr std::int32_t kCodePositiveFullScale = 0x7FFFFF;
inline constexpr std::int32_t kCodeNegativeFullScale = -0x800000;
inline constexpr double kVref = 1.2;
inline constexpr double kCountsFullScale = 8388608.0;  // 2^23

// RREG/WREG command words for `count` (1..128) registers starting at `address` (0..63).
constexpr std::uint16_t rreg(std::uint8_t address, std::uint8_t count) noexcept {
  return static_cast<std::uint16_t>(0xA000u | ((address & 0x3Fu) << 7) | ((count - 1u) & 0x7Fu));
}
constexpr std::uint16_t wreg(std::uint8_t address, std::uint8_t count) noexcept {
  return static_cast<std::uint16_t>(0x6000u | ((address & 0x3Fu) << 7) | ((count - 1u) & 0x7Fu));
}
// The response the device gives (next frame) to wreg(address, count).
constexpr std::uint16_t wreg_response(std::uint8_t address, std::uint8_t count) noexcept {
  return static_cast<std::uint16_t>(0x4000u | ((address & 0x3Fu) << 7) | ((count - 1u) & 0x7Fu));
}

// PGA gain code (GAIN1.PGAGAINn, 0..7) -> gain 1..128.
constexpr double gain_from_code(std::uint8_t code) noexcept {
  return static_cast<double>(1u << (code & 7u));
}
// GAIN1 register value from four 3-bit gain codes (channel 0 in bits 2:0, channel 3 in 14:12).
constexpr std::uint16_t gain1_register(const std::array<std::uint8_t, 4>& codes) noexcept {
  return static_cast<std::uint16_t>((codes[0] & 7u) | ((codes[1] & 7u) << 4) |
                                    ((codes[2] & 7u) << 8) | ((codes[3] & 7u) << 12));
}

// Volts at the ADC input for a code at the given PGA gain code.
constexpr double code_to_volts(std::int32_t code, std::uint8_t gain_code) noexcept {
  return static_cast<double>(code) * (kVref / gain_from_code(gain_code)) / kCountsFullScale;
}

// 24-bit big-endian two's complement <-> int32.
constexpr std::int32_t decode_word24(const std::uint8_t* p) noexcept {
  const std::uint32_t u = (std::uint32_t{p[0]} << 16) | (std::uint32_t{p[1]} << 8) | p[2];
  return (u & 0x800000u) != 0 ? static_cast<std::int32_t>(u) - 0x1000000
                              : static_cast<std::int32_t>(u);
}
constexpr void encode_word24(std::int32_t value, std::uint8_t* p) noexcept {
  const auto u = static_cast<std::uint32_t>(value) & 0xFFFFFFu;
  p[0] = static_cast<std::uint8_t>(u >> 16);
  p[1] = static_cast<std::uint8_t>(u >> 8);
  p[2] = static_cast<std::uint8_t>(u);
}
// A 16-bit word left-aligned in a 24-bit word (pad byte 0).
constexpr void encode_word16(std::uint16_t value, std::uint8_t* p) noexcept {
  p[0] = static_cast<std::uint8_t>(value >> 8);
  p[1] = static_cast<std::uint8_t>(value);
  p[2] = 0;
}
constexpr std::uint16_t decode_word16(const std::uint8_t* p) noexcept {
  return static_cast<std::uint16_t>((p[0] << 8) | p[1]);
}

// Output CRC of a frame: over all bytes preceding the CRC word.
std::uint16_t output_crc(std::span<const std::uint8_t, kFrameBytes> frame) noexcept;

// Input frame: command word, then the data words (at most kFrameWords - 2), then (optionally)
// the input CRC over the preceding words, rest zero.
bool build_command_frame(std::uint16_t command, std::span<const std::uint16_t> data_words,
                         bool with_input_crc, Frame& out) noexcept;

struct Response {
  std::uint16_t response{0};  // response/status word
  std::array<std::int32_t, kChannels> codes{};
  std::uint16_t crc_received{0};
  std::uint16_t crc_computed{0};
};
enum class ParseResult : std::uint8_t { kOk, kCrcError };

// Parses an output frame (always 18 bytes, enforced by the type). Fills `out` in both cases so
// that a caller can log what arrived; kCrcError means the content must not be used.
ParseResult parse_response_frame(std::span<const std::uint8_t, kFrameBytes> frame,
                                 Response& out) noexcept;

// Output frame as the device would send it (simulated ADC, tests).
void encode_response_frame(std::uint16_t response, const std::array<std::int32_t, kChannels>& codes,
                           Frame& out) noexcept;

}  // namespace magvec::drivers::ads131
