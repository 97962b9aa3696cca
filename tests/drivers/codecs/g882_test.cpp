// G882LineDecoder and SerialScalarSource (drivers/codecs g882.hpp): the manual's example lines,
// garbage, truncated and restarted lines, out-of-range readings, overflow, and the encoder.
#include "magvec/drivers/g882.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <string>
#include <vector>

namespace magvec::drivers {
namespace {

struct Fed {
  std::vector<hal::ScalarSample> samples;
  std::vector<hal::Status> rejections;
};

Fed feed(G882LineDecoder& d, const std::string& text, std::uint64_t t_us = 0) {
  Fed f;
  hal::ScalarSample s;
  for (const char c : text) {
    const hal::Status st = d.push(static_cast<std::uint8_t>(c), t_us, s);
    if (st == hal::Status::kOk) {
      f.samples.push_back(s);
    } else if (st != hal::Status::kNoData) {
      f.rejections.push_back(st);
    }
  }
  return f;
}

TEST(G882Line, DefaultOutputLineOfTheManual) {
  G882LineDecoder d(G882LineConfig{});
  // Page 37 layout: '$', blank, 5 digits, '.', 3 digits, ',', 4-digit signal level, CR LF.
  const Fed f = feed(d, "$ 48123.456,0721\r\n", 1234);
  ASSERT_EQ(f.samples.size(), 1u);
  EXPECT_DOUBLE_EQ(f.samples[0].f_nT, 48123.456);
  EXPECT_DOUBLE_EQ(f.samples[0].quality, 721.0 / 9999.0);
  EXPECT_EQ(f.samples[0].t_us, 1234u);
  EXPECT_EQ(f.samples[0].flags, 0u);
  EXPECT_EQ(d.counters().samples, 1u);
  EXPECT_EQ(d.counters().garbage_bytes, 0u);
}

TEST(G882Line, ManualExampleWithThreeAnalogChannels) {
  G882LineConfig c;
  c.analog_channels = 3;
  G882LineDecoder d(c);
  // Page 47's example line. Its diagram numbers the three fields 1..3; page 37 calls the first
  // field after the reading channel 0, the signal level, which is how it is read here.
  const Fed f = feed(d, "$ 54369.127,1234,5678,0000\r\n");
  ASSERT_EQ(f.samples.size(), 1u);
  EXPECT_DOUBLE_EQ(f.samples[0].f_nT, 54369.127);
  EXPECT_DOUBLE_EQ(f.samples[0].quality, 1234.0 / 9999.0);
  // With the default one channel the same line has fields left over: malformed.
  G882LineDecoder one(G882LineConfig{});
  EXPECT_TRUE(feed(one, "$ 54369.127,1234,5678,0000\r\n").samples.empty());
  EXPECT_EQ(one.counters().malformed, 1u);
}

TEST(G882Line, HundredThousandsDigitAndLoneLineFeed) {
  G882LineConfig c;
  c.max_field_nT = 150000;
  G882LineDecoder d(c);
  const Fed f = feed(d, "$100001.250,9999\n$ 17000.000,0000\r\n");
  ASSERT_EQ(f.samples.size(), 2u);
  EXPECT_DOUBLE_EQ(f.samples[0].f_nT, 100001.25);
  EXPECT_DOUBLE_EQ(f.samples[0].quality, 1.0);
  EXPECT_DOUBLE_EQ(f.samples[1].f_nT, 17000.0);
  EXPECT_EQ(f.samples[1].sequence, f.samples[0].sequence + 1);
}

TEST(G882Line, JulianClockFieldOnlyWhenConfigured) {
  const std::string line = "$ 48123.456,0721,D123H04M05S06_78\r\n";
  G882LineDecoder plain(G882LineConfig{});
  EXPECT_TRUE(feed(plain, line).samples.empty());
  EXPECT_EQ(plain.counters().malformed, 1u);
  G882LineConfig c;
  c.julian_time = true;
  G882LineDecoder d(c);
  EXPECT_EQ(feed(d, line).samples.size(), 1u);
  EXPECT_EQ(feed(d, "$ 48123.456,0721,H04M05S06\r\n").samples.size(), 1u);  // a subset
  // Out of order, wrong digit count, unknown letter, empty: malformed.
  for (const char* bad : {"$ 48123.456,0721,M05H04\r\n", "$ 48123.456,0721,D12H04\r\n",
                          "$ 48123.456,0721,X12\r\n", "$ 48123.456,0721,\r\n"}) {
    const std::uint32_t before = d.counters().malformed;
    EXPECT_TRUE(feed(d, bad).samples.empty()) << bad;
    EXPECT_EQ(d.counters().malformed, before + 1) << bad;
  }
}

TEST(G882Line, MalformedLinesAreCountedAndRejected) {
  G882LineDecoder d(G882LineConfig{});
  const char* const bad[] = {
      "$ 48123.456\r\n",         // signal channel missing
      "$ 48123.45,0721\r\n",     // two decimals
      "$48123.456,0721\r\n",     // hundred-thousands character missing
      "$248123.456,0721\r\n",    // only '1' or blank allowed there
      "$ 4812a.456,0721\r\n",    // not a digit
      "$ 48123,456,0721\r\n",    // no decimal point
      "$ 48123.456;0721\r\n",    // wrong separator
      "$ 48123.456,721\r\n",     // three-digit channel
      "$ 48123.456,07210\r\n",   // five-digit channel
      "$ -8123.456,0721\r\n",    // sign
      "$\r\n",                   // empty
      "$ 48123.456,0721 \r\n",   // trailing blank
      "$ 48123.456,0721\r\r\n",  // two CRs
  };
  std::uint32_t n = 0;
  for (const char* line : bad) {
    const Fed f = feed(d, line);
    EXPECT_TRUE(f.samples.empty()) << line;
    ASSERT_EQ(f.rejections.size(), 1u) << line;
    EXPECT_EQ(f.rejections[0], hal::Status::kMalformed) << line;
    EXPECT_EQ(d.counters().malformed, ++n) << line;
  }
  EXPECT_EQ(d.counters().samples, 0u);
  EXPECT_EQ(d.counters().crc_errors, 0u);  // the format has no checksum
  // The decoder is not stuck: a good line still decodes.
  EXPECT_EQ(feed(d, "$ 48123.456,0721\r\n").samples.size(), 1u);
}

TEST(G882Line, OutOfRangeReadingsAreCountedSeparately) {
  G882LineDecoder d(G882LineConfig{});  // 17,000..100,000 nT (the G-882 operating range)
  const Fed f = feed(d, "$ 16999.999,0721\r\n$100000.001,0721\r\n$ 00000.000,0000\r\n");
  EXPECT_TRUE(f.samples.empty());
  EXPECT_EQ(f.rejections.size(), 3u);
  EXPECT_EQ(d.counters().out_of_range, 3u);
  EXPECT_EQ(d.counters().malformed, 0u);
  const Fed edge = feed(d, "$ 17000.000,0721\r\n$100000.000,0721\r\n");
  EXPECT_EQ(edge.samples.size(), 2u);
}

TEST(G882Line, GarbageIsSkippedAndTheNextLineRecovered) {
  G882LineDecoder d(G882LineConfig{});
  const Fed f = feed(d, std::string("xyz\x01\xff 1.0\r\n") + "$ 48123.456,0721\r\n");
  ASSERT_EQ(f.samples.size(), 1u);
  EXPECT_EQ(d.counters().garbage_bytes, 11u);
  EXPECT_EQ(d.counters().malformed, 0u);
}

TEST(G882Line, TruncatedLineRestartedByThePreambleIsLost) {
  G882LineDecoder d(G882LineConfig{});
  // A line cut after "$ 4812" (e.g. a dropped byte run), then a complete one.
  const Fed f = feed(d, "$ 4812$ 48123.456,0721\r\n", 7);
  ASSERT_EQ(f.samples.size(), 1u);
  EXPECT_DOUBLE_EQ(f.samples[0].f_nT, 48123.456);
  ASSERT_EQ(f.rejections.size(), 1u);
  EXPECT_EQ(f.rejections[0], hal::Status::kMalformed);
  EXPECT_EQ(d.counters().malformed, 1u);
  EXPECT_EQ(d.counters().garbage_bytes, 6u);  // "$ 4812"
  // A line cut before its end with a line feed in the middle: malformed.
  EXPECT_TRUE(feed(d, "$ 48123.4\n56,0721\r\n").samples.empty());
  EXPECT_EQ(d.counters().malformed, 2u);
}

TEST(G882Line, OverlongLineIsAnOverflowAndSkippedToItsEnd) {
  G882LineDecoder d(G882LineConfig{});
  const std::string longline = "$ 48123.456" + std::string(100, '0') + "\r\n";
  const Fed f = feed(d, longline + "$ 48123.456,0721\r\n");
  EXPECT_EQ(f.samples.size(), 1u);
  EXPECT_EQ(d.counters().overflows, 1u);
  EXPECT_EQ(d.counters().garbage_bytes, longline.size() - 1);  // every byte after the preamble
}

TEST(G882Line, LowSignalIsFlaggedNotRejected) {
  G882LineConfig c;
  c.min_signal = 500;
  G882LineDecoder d(c);
  const Fed f = feed(d, "$ 48123.456,0499\r\n$ 48123.456,0500\r\n");
  ASSERT_EQ(f.samples.size(), 2u);
  EXPECT_EQ(f.samples[0].flags, hal::kScalarLowSignal);
  EXPECT_EQ(f.samples[1].flags, 0u);
  EXPECT_EQ(d.counters().low_signal, 1u);
  EXPECT_EQ(d.counters().samples, 2u);
}

TEST(G882Line, OtherPreambleAndNoAnalogChannels) {
  G882LineConfig c;
  c.preamble = '#';
  c.analog_channels = 0;
  G882LineDecoder d(c);
  const Fed f = feed(d, "$ 48123.456\r\n# 48123.456\r\n");
  ASSERT_EQ(f.samples.size(), 1u);
  EXPECT_TRUE(std::isnan(f.samples[0].quality));
  EXPECT_EQ(d.counters().garbage_bytes, 13u);  // the '$' line is not a line
}

TEST(G882Line, EncoderRoundTripsAndRefusesWhatTheFormatCannotHold) {
  G882LineConfig c;
  c.analog_channels = 3;
  c.max_field_nT = 199999.999;
  c.min_field_nT = 0;
  G882LineDecoder d(c);
  std::array<char, 64> buf{};
  const std::size_t n = d.encode(54369.1274, 1234, buf);
  EXPECT_EQ(std::string(buf.data(), n), "$ 54369.127,1234,0000,0000\r\n");
  for (const double f : {0.0, 9.999, 48123.4565, 99999.9996, 123456.789, 199999.999}) {
    const std::size_t k = d.encode(f, 721, buf);
    ASSERT_GT(k, 0u) << f;
    const Fed got = feed(d, std::string(buf.data(), k));
    ASSERT_EQ(got.samples.size(), 1u) << std::string(buf.data(), k);
    EXPECT_NEAR(got.samples[0].f_nT, f, 0.0005 + 1e-9);
  }
  EXPECT_EQ(d.encode(200000.0, 0, buf), 0u);
  EXPECT_EQ(d.encode(-1.0, 0, buf), 0u);
  EXPECT_EQ(d.encode(std::nan(""), 0, buf), 0u);
  EXPECT_EQ(d.encode(48000.0, 0, std::span<char>(buf.data(), 10)), 0u);
  EXPECT_EQ(d.encode(48000.0, 65535, buf), 28u);  // signal clamped to 9999
}

// A serial port fake: hands out its bytes in chunks of at most `chunk`.
struct ScriptedPort final : hal::SerialPort {
  std::string data;
  std::size_t pos{0};
  std::size_t chunk{5};
  bool fail{false};
  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n, std::uint32_t) noexcept override {
    n = 0;
    if (fail) return hal::Status::kBusError;
    while (n < buf.size() && n < chunk && pos < data.size())
      buf[n++] = static_cast<std::uint8_t>(data[pos++]);
    return n > 0 ? hal::Status::kOk : hal::Status::kTimeout;
  }
  hal::Status write(std::span<const std::uint8_t> d, std::size_t& n) noexcept override {
    n = d.size();
    return hal::Status::kOk;
  }
};

struct StepClock final : hal::Clock {
  std::uint64_t t{1'000'000};
  std::uint64_t now_us() const noexcept override { return t; }
};

TEST(SerialScalarSource, ReadsLinesReportsRejectionsAndBusErrors) {
  ScriptedPort port;
  port.data = "$ 48123.456,0721\r\n$ 4812x.456,0721\r\n$ 48124.000,0722\r\n";
  StepClock clock;
  SerialScalarSource src(port, clock, G882LineDecoder(G882LineConfig{}), 250);
  hal::ScalarSample s;
  ASSERT_EQ(src.read(s, 0), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.f_nT, 48123.456);
  EXPECT_EQ(s.t_us, 1'000'000u - 250u);
  EXPECT_EQ(src.read(s, 0), hal::Status::kMalformed);
  ASSERT_EQ(src.read(s, 0), hal::Status::kOk);
  EXPECT_DOUBLE_EQ(s.f_nT, 48124.0);
  EXPECT_EQ(src.read(s, 0), hal::Status::kTimeout);
  port.fail = true;
  EXPECT_EQ(src.read(s, 0), hal::Status::kBusError);
  EXPECT_EQ(src.counters().bus_errors, 1u);
  EXPECT_EQ(src.counters().samples, 2u);
  EXPECT_EQ(src.counters().malformed, 1u);
}

}  // namespace
}  // namespace magvec::drivers
