#include "magvec/drivers/crc.hpp"

#include <gtest/gtest.h>

#include <array>
#include <cstring>

namespace magvec::drivers {
namespace {

std::span<const std::uint8_t> bytes(const char* s) {
  return {reinterpret_cast<const std::uint8_t*>(s), std::strlen(s)};
}

// Catalogued check values ("123456789"): CRC-16/CCITT-FALSE = 0x29B1, CRC-32/ISO-HDLC = 0xCBF43926.
TEST(Crc, CheckValues) {
  EXPECT_EQ(crc16_ccitt(bytes("123456789")), 0x29B1);
  EXPECT_EQ(crc32(bytes("123456789")), 0xCBF43926u);
  EXPECT_EQ(crc32(bytes("")), 0u);
  EXPECT_EQ(crc16_ccitt(bytes("")), 0xFFFF);
}

TEST(Crc, Crc16AppendedGivesZeroRemainder) {
  std::array<std::uint8_t, 6> d{0x01, 0x02, 0x03, 0x04, 0, 0};
  const std::uint16_t c = crc16_ccitt(std::span<const std::uint8_t>(d.data(), 4));
  d[4] = static_cast<std::uint8_t>(c >> 8);
  d[5] = static_cast<std::uint8_t>(c);
  EXPECT_EQ(crc16_ccitt(d), 0);
}

TEST(Crc, Crc32IsIncremental) {
  const auto all = bytes("hello, fluxgate");
  const std::uint32_t one = crc32(all);
  std::uint32_t s = crc32_update(kCrc32Init, all.first(5));
  s = crc32_update(s, all.subspan(5));
  EXPECT_EQ(crc32_final(s), one);
}

TEST(Crc, NmeaXor) {
  // "$GPGLL,5300.97914,N,00259.98174,E,125926,A*28" is a widely quoted NMEA sentence.
  EXPECT_EQ(xor_checksum(bytes("GPGLL,5300.97914,N,00259.98174,E,125926,A")), 0x28);
}

}  // namespace
}  // namespace magvec::drivers
