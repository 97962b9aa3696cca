// ADS131M04 frame codec; format documented in ads131m04.hpp.
#include "magvec/drivers/ads131m04.hpp"

#include "magvec/drivers/crc.hpp"

namespace magvec::drivers::ads131 {

std::uint16_t output_crc(std::span<const std::uint8_t, kFrameBytes> frame) noexcept {
  return crc16_ccitt(frame.first(kFrameBytes - kWordBytes));
}

bool build_command_frame(std::uint16_t command, std::span<const std::uint16_t> data_words,
                         bool with_input_crc, Frame& out) noexcept {
  const std::size_t max_data = kFrameWords - 1 - (with_input_crc ? 1 : 0);
  if (data_words.size() > max_data) return false;
  out.fill(0);
  encode_word16(command, out.data());
  std::size_t word = 1;
  for (const std::uint16_t d : data_words)
    encode_word16(d, out.data() + kWordBytes * word++);
  if (with_input_crc) {
    const std::uint16_t crc =
        crc16_ccitt(std::span<const std::uint8_t>(out.data(), kWordBytes * word));
    encode_word16(crc, out.data() + kWordBytes * word);
  }
  return true;
}

ParseResult parse_response_frame(std::span<const std::uint8_t, kFrameBytes> frame,
                                 Response& out) noexcept {
  out.response = decode_word16(frame.data());
  for (std::size_t ch = 0; ch < kChannels; ++ch) {
    out.codes[ch] = decode_word24(frame.data() + kWordBytes * (1 + ch));
  }
  out.crc_received = decode_word16(frame.data() + kWordBytes * (kFrameWords - 1));
  out.crc_computed = output_crc(frame);
  return out.crc_received == out.crc_computed ? ParseResult::kOk : ParseResult::kCrcError;
}

void encode_response_frame(std::uint16_t response, const std::array<std::int32_t, kChannels>& codes,
                           Frame& out) noexcept {
  out.fill(0);
  encode_word16(response, out.data());
  for (std::size_t ch = 0; ch < kChannels; ++ch) {
    encode_word24(codes[ch], out.data() + kWordBytes * (1 + ch));
  }
  encode_word16(output_crc(out), out.data() + kWordBytes * (kFrameWords - 1));
}

}  // namespace magvec::drivers::ads131
