#include "magvec/drivers/serial_fluxgate.hpp"

#include <gtest/gtest.h>

#include <cstring>
#include <random>
#include <vector>

#include "support/alloc_counter.hpp"

namespace magvec::drivers {
namespace {

std::vector<hal::MagnetometerSample> feed_all(AsciiLineDecoder& d, const char* text) {
  std::vector<hal::MagnetometerSample> out;
  d.feed(
      std::span<const std::uint8_t>(reinterpret_cast<const std::uint8_t*>(text), std::strlen(text)),
      0, [&](const hal::MagnetometerSample& s) { out.push_back(s); });
  return out;
}

TEST(AsciiLine, HandWrittenLineWithChecksum) {
  AsciiLineDecoder d(AsciiLineConfig{});
  // XOR of "MAG,12345.6,-2345.1,40000.0" = 56h.
  const auto s = feed_all(d, "$MAG,12345.6,-2345.1,40000.0*56\r\n");
  ASSERT_EQ(s.size(), 1u);
  EXPECT_DOUBLE_EQ(s[0].m_nT[0], 12345.6);
  EXPECT_DOUBLE_EQ(s[0].m_nT[1], -2345.1);
  EXPECT_DOUBLE_EQ(s[0].m_nT[2], 40000.0);
  // Lower-case hex, no CR, no checksum (optional mode).
  EXPECT_EQ(feed_all(d, "$MAG,12345.6,-2345.1,40000.0*56\n").size(), 1u);
  EXPECT_EQ(feed_all(d, "$MAG,1,2,3\n").size(), 1u);
  EXPECT_EQ(d.counters().samples, 3u);
}

TEST(AsciiLine, ConfigurableOrderSeparatorScaleAndNoStartChar) {
  AsciiLineConfig c;
  c.start_char = '\0';
  c.separator = ' ';
  c.tag = {};
  c.field_of_axis = {2, 0, 1};  // line is "y z x"
  c.field_count = 3;
  c.scale = 1000.0;  // values in uT
  c.checksum = ChecksumMode::kNone;
  AsciiLineDecoder d(c);
  const auto s = feed_all(d, "-2.5 40.125 1.5e1\r\n\r\n7 8 9\n");
  ASSERT_EQ(s.size(), 2u);
  EXPECT_DOUBLE_EQ(s[0].m_nT[0], 15000.0);
  EXPECT_DOUBLE_EQ(s[0].m_nT[1], -2500.0);
  EXPECT_DOUBLE_EQ(s[0].m_nT[2], 40125.0);
  EXPECT_DOUBLE_EQ(s[1].m_nT[0], 9000.0);
  // A checksum where none is expected is malformed.
  EXPECT_TRUE(feed_all(d, "1 2 3*00\n").empty());
  EXPECT_EQ(d.counters().malformed, 1u);
}

TEST(AsciiLine, RejectsAndCountsBadLines) {
  AsciiLineConfig c;
  c.checksum = ChecksumMode::kRequired;
  AsciiLineDecoder d(c);
  EXPECT_TRUE(feed_all(d, "$MAG,12345.6,-2345.1,40000.0*57\r\n").empty());  // wrong checksum
  EXPECT_EQ(d.counters().crc_errors, 1u);
  EXPECT_TRUE(feed_all(d, "$MAG,1,2,3\n").empty());                  // checksum required
  EXPECT_TRUE(feed_all(d, "$MAG,1,2*48\n").empty());                 // 3 fields (checksum is right)
  EXPECT_TRUE(feed_all(d, "$MAX,1,2,3*48\n").empty());               // wrong tag
  EXPECT_TRUE(feed_all(d, "$MAG,1,2x,3*2F\n").empty());              // not a number
  EXPECT_TRUE(feed_all(d, "$MAG,1,,3*65\n").empty());                // empty field
  EXPECT_TRUE(feed_all(d, "$MAG,1,2,3*G1\n").empty());               // bad hex
  EXPECT_TRUE(feed_all(d, "$MAG,1,2,$MAG,1,2,3*57\n").size() == 1);  // restart on '$'
  EXPECT_EQ(d.counters().malformed, 7u);
  std::string longline = "$MAG," + std::string(200, '1') + ",2,3*00\n";
  EXPECT_TRUE(feed_all(d, longline.c_str()).empty());
  EXPECT_EQ(d.counters().overflows, 1u);
  EXPECT_EQ(feed_all(d, "$MAG,1,2,3*57\n").size(), 1u);  // recovers after the overflow
}

TEST(AsciiLine, EncodeDecodeRoundTrip) {
  AsciiLineDecoder d(AsciiLineConfig{});
  std::array<char, 128> buf{};
  const std::size_t n = d.encode({12345.678, -0.001, -49999.5}, true, buf);
  ASSERT_GT(n, 0u);
  EXPECT_EQ(std::string(buf.data(), n),
            "$MAG,12345.678,-0.001,-49999.500*" + std::string(buf.data() + n - 4, 2) + "\r\n");
  const auto s = feed_all(d, std::string(buf.data(), n).c_str());
  ASSERT_EQ(s.size(), 1u);
  EXPECT_DOUBLE_EQ(s[0].m_nT[2], -49999.5);
  std::array<char, 10> tiny{};
  EXPECT_EQ(d.encode({1, 2, 3}, true, tiny), 0u);
}

// Property: random garbage between valid lines; every valid line is recovered, in order, and the
// garbage is counted.
TEST(AsciiLine, ResynchronisesAfterRandomGarbage) {
  std::mt19937_64 rng(1234);
  std::uniform_real_distribution<double> val(-60000, 60000);
  std::uniform_int_distribution<int> glen(0, 40), byte(0, 255);
  AsciiLineDecoder d(AsciiLineConfig{});
  std::vector<std::uint8_t> stream;
  std::vector<std::array<double, 3>> truth;
  std::size_t garbage = 0;
  for (int i = 0; i < 2000; ++i) {
    const int g = glen(rng);
    for (int k = 0; k < g; ++k)
      stream.push_back(static_cast<std::uint8_t>(byte(rng)));
    garbage += static_cast<std::size_t>(g);
    std::array<double, 3> v{std::round(val(rng) * 1000) / 1000, std::round(val(rng) * 1000) / 1000,
                            std::round(val(rng) * 1000) / 1000};
    std::array<char, 96> buf{};
    const std::size_t n = d.encode(v, true, buf);
    ASSERT_GT(n, 0u);
    stream.insert(stream.end(), buf.begin(), buf.begin() + static_cast<std::ptrdiff_t>(n));
    truth.push_back(v);
  }
  std::vector<std::array<double, 3>> got;
  got.reserve(truth.size() + 10);
  magvec::test::AllocationScope scope;
  for (const std::uint8_t b : stream) {
    hal::MagnetometerSample s;
    if (d.push(b, 0, s) == hal::Status::kOk) got.push_back(s.m_nT);  // reserved: no allocation
  }
  EXPECT_EQ(scope.count(), 0u);
  ASSERT_EQ(got.size(), truth.size());
  for (std::size_t i = 0; i < truth.size(); ++i) {
    for (std::size_t a = 0; a < 3; ++a)
      ASSERT_NEAR(got[i][a], truth[i][a], 1e-9) << i;
  }
  const hal::MagCounters& c = d.counters();
  EXPECT_GT(c.garbage_bytes, garbage / 2);
  EXPECT_GT(c.malformed + c.crc_errors + c.overflows, 0u);
}

TEST(Hmr2300, DatasheetRecords) {
  // +1.0 G = 15000 = 3A98h, -0.5 G = -7500 = E2B4h, +2.0 G = 30000 = 7530h (datasheet table).
  const std::array<std::uint8_t, 14> bytes{0x3A, 0x98, 0xE2, 0xB4, 0x75, 0x30, 0x0D,
                                           0x8A, 0xD0, 0x00, 0x00, 0xC3, 0x74, 0x0D};
  Hmr2300BinaryDecoder d;
  std::vector<hal::MagnetometerSample> out;
  d.feed(bytes, 42, [&](const hal::MagnetometerSample& s) { out.push_back(s); });
  ASSERT_EQ(out.size(), 2u);
  EXPECT_EQ(out[0].raw[0], 15000);
  EXPECT_EQ(out[0].raw[1], -7500);
  EXPECT_EQ(out[0].raw[2], 30000);
  EXPECT_NEAR(out[0].m_nT[0], 100000.0, 1e-9);  // 1 G = 100000 nT
  EXPECT_NEAR(out[0].m_nT[1], -50000.0, 1e-9);
  EXPECT_NEAR(out[0].m_nT[2], 200000.0, 1e-9);
  EXPECT_EQ(out[1].raw[0], -30000);  // 8AD0h
  EXPECT_EQ(out[1].raw[2], -15500);  // C374h
  EXPECT_TRUE(d.locked());
  EXPECT_EQ(Hmr2300BinaryDecoder::encode({15000, -7500, 30000}),
            (std::array<std::uint8_t, 7>{0x3A, 0x98, 0xE2, 0xB4, 0x75, 0x30, 0x0D}));
  // While locked, a record with a wrong terminator or an out-of-range value drops lock.
  const std::array<std::uint8_t, 7> bad_term{0x00, 0x01, 0x00, 0x02, 0x00, 0x03, 0x0A};
  d.feed(bad_term, 0, [&](const hal::MagnetometerSample& s) { out.push_back(s); });
  EXPECT_FALSE(d.locked());
  EXPECT_EQ(d.counters().malformed, 1u);
  EXPECT_EQ(out.size(), 2u);
  // Two out-of-range records (7FFFh > 30000) never lock.
  Hmr2300BinaryDecoder d2;
  const std::array<std::uint8_t, 14> oor{0x7F, 0xFF, 0, 0, 0, 0, 0x0D,
                                         0x7F, 0xFF, 0, 0, 0, 0, 0x0D};
  d2.feed(oor, 0, [&](const hal::MagnetometerSample& s) { out.push_back(s); });
  EXPECT_EQ(out.size(), 2u);
}

// Property: garbage bursts between groups of >= 2 records (an isolated record after garbage cannot
// be framed without a checksum, see the header). Every record must be recovered, in order; false
// records made from garbage are possible in principle and must stay rare.
TEST(Hmr2300, ResynchronisesAfterRandomGarbage) {
  std::mt19937_64 rng(99);
  std::uniform_int_distribution<int> count(-30000, 30000), glen(1, 30), byte(0, 255), group(2, 6);
  std::vector<std::uint8_t> stream;
  std::vector<std::array<std::int32_t, 3>> truth;
  std::size_t garbage = 0;
  for (int gi = 0; gi < 500; ++gi) {
    const int g = glen(rng);
    for (int k = 0; k < g; ++k)
      stream.push_back(static_cast<std::uint8_t>(byte(rng)));
    garbage += static_cast<std::size_t>(g);
    const int n = group(rng);
    for (int r = 0; r < n; ++r) {
      const std::array<std::int16_t, 3> c{static_cast<std::int16_t>(count(rng)),
                                          static_cast<std::int16_t>(count(rng)),
                                          static_cast<std::int16_t>(count(rng))};
      const auto rec = Hmr2300BinaryDecoder::encode(c);
      stream.insert(stream.end(), rec.begin(), rec.end());
      truth.push_back({c[0], c[1], c[2]});
    }
  }
  Hmr2300BinaryDecoder d;
  std::vector<std::array<std::int32_t, 3>> got;
  got.reserve(2 * truth.size());
  magvec::test::AllocationScope scope;
  d.feed(stream, 0, [&](const hal::MagnetometerSample& s) { got.push_back(s.raw); });
  EXPECT_EQ(scope.count(), 0u);
  // Every true record appears, in order (subsequence match).
  std::size_t j = 0;
  for (const auto& g : got) {
    if (j < truth.size() && g == truth[j]) ++j;
  }
  EXPECT_EQ(j, truth.size());
  // A false record needs a random 0Dh at the one position where the decoder looks (p = 1/256 per
  // burst while locked, once more when the burst's last byte precedes a record) and plausible
  // data (p ~ 0.77): ~0.6 % of bursts. Allow 2 % of the 500 bursts.
  const std::size_t extra = got.size() - truth.size();
  EXPECT_LE(extra, 10u) << "false records from garbage";
  EXPECT_GT(d.counters().garbage_bytes, garbage / 2);
}

// Regression: after losing lock, a terminator whose older candidate record overlaps the last
// delivered record by a few bytes (here 4) re-delivered those bytes as a false sample.
TEST(Hmr2300, NoFalseSampleFromBytesOfADeliveredRecord) {
  const std::vector<std::uint8_t> stream = {
      0x00, 0x01, 0x00, 0x02, 0x00, 0x03, 0x0D,  // record (1, 2, 3), positions 0..6
      0x00, 0x00, 0x00, 0x00, 0x00, 0x00, 0x0D,  // record (0, 0, 0), 7..13: lock
      // Position 20 should hold the next terminator: lock is lost there. The 0Dh at 16 ends the
      // bytes 10..16 = 00 00 | 00 0D | 00 00 | 0D, which overlap the delivered record at 10..13.
      0x00, 0x00, 0x0D, 0x00, 0x04, 0x00, 0x05, 0x00, 0x06, 0x0D,  // 14..23: 0Dh 7 bytes later
      0x00, 0x07, 0x00, 0x08, 0x00, 0x09, 0x0D,                    // (7, 8, 9), 24..30
  };
  Hmr2300BinaryDecoder d;
  std::vector<std::array<std::int32_t, 3>> got;
  d.feed(stream, 0, [&](const hal::MagnetometerSample& s) { got.push_back(s.raw); });
  // Before the fix, (0, 13, 0) from bytes 10..16 came out third. The record (4, 5, 6) at 17..23
  // is framed by the one after it (both candidates new) and delivered with it, one record late.
  const std::vector<std::array<std::int32_t, 3>> want = {
      {1, 2, 3}, {0, 0, 0}, {4, 5, 6}, {7, 8, 9}};
  EXPECT_EQ(got, want);
  EXPECT_EQ(d.counters().samples, 4u);
  EXPECT_EQ(d.counters().malformed, 1u);  // the lock loss at position 20
  EXPECT_TRUE(d.locked());
}

class FakeSerial final : public hal::SerialPort, public hal::Clock {
 public:
  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n, std::uint32_t) noexcept override {
    n = 0;
    while (n < buf.size() && n < 5 && pos < data.size())
      buf[n++] = data[pos++];  // 5-byte chunks
    return n ? hal::Status::kOk : hal::Status::kTimeout;
  }
  hal::Status write(std::span<const std::uint8_t> d, std::size_t& n) noexcept override {
    n = d.size();
    return hal::Status::kOk;
  }
  std::uint64_t now_us() const noexcept override { return 5000; }
  std::vector<std::uint8_t> data;
  std::size_t pos{0};
};

TEST(SerialFluxgate, MagnetometerSourceOverSerialPort) {
  FakeSerial port;
  const char* text = "xx$MAG,1,2,3\r\n$MAG,4,5,6*50\r\n";
  port.data.assign(text, text + std::strlen(text));
  SerialFluxgate<AsciiLineDecoder> src(port, port, AsciiLineDecoder(AsciiLineConfig{}), 1000);
  hal::MagnetometerSample s;
  ASSERT_EQ(src.read(s, 100), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.m_nT[2], 3);
  EXPECT_EQ(s.t_us, 4000u);
  hal::Status st = hal::Status::kNoData;
  for (int i = 0; i < 10 && st != hal::Status::kOk; ++i)
    st = src.read(s, 100);
  ASSERT_EQ(st, hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.m_nT[0], 4);
  EXPECT_EQ(src.read(s, 100), hal::Status::kTimeout);
  EXPECT_EQ(src.counters().garbage_bytes, 2u);
  EXPECT_EQ(src.counters().samples, 2u);
}

// A rejected line is the caller's to know (the HAL contract, as the ADC source returns kCrcError
// for a bad frame): read() returns the rejection, and the line after it comes with the next call.
TEST(SerialFluxgate, RejectedLinesAreReturnedNotSkipped) {
  FakeSerial port;
  const char* text = "$MAG,1,2,3*00\r\n$MAG,1,x,3\r\n$MAG,4,5,6*50\r\n";
  port.data.assign(text, text + std::strlen(text));
  SerialFluxgate<AsciiLineDecoder> src(port, port, AsciiLineDecoder(AsciiLineConfig{}), 1000);
  hal::MagnetometerSample s;
  EXPECT_EQ(src.read(s, 100), hal::Status::kCrcError);
  EXPECT_EQ(src.read(s, 100), hal::Status::kMalformed);
  ASSERT_EQ(src.read(s, 100), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.m_nT[0], 4);
  EXPECT_EQ(src.read(s, 100), hal::Status::kTimeout);
  EXPECT_EQ(src.counters().crc_errors, 1u);
  EXPECT_EQ(src.counters().malformed, 1u);
  EXPECT_EQ(src.counters().samples, 1u);
}

}  // namespace
}  // namespace magvec::drivers
