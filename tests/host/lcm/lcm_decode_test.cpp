// Decoding hostile bytes with the generated LCM types (host/lcm/harden_generated.cmake). Found by
// tests/fuzz/lcm_decode_fuzz: a string length below 1 made decode() throw std::length_error, or
// overflow for INT32_MIN, instead of rejecting the message (through a subscription that would
// terminate magvecd on one malformed packet on its command channel); a string with an embedded NUL
// was accepted and re-encoded inconsistently. The array count check of mag_sample_batch (fuzzed by
// tests/fuzz/mag_sample_batch_fuzz) came with the type.
#include <gtest/gtest.h>

#include <cstdint>
#include <cstring>
#include <lcm/lcm-cpp.hpp>
#include <limits>
#include <vector>

#include "magvec/host/daemon/lcm_codec.hpp"

namespace magvec::host::daemon {
namespace {

template <typename Msg>
std::vector<std::uint8_t> encode(const Msg& m) {
  std::vector<std::uint8_t> b(static_cast<std::size_t>(m.getEncodedSize()));
  EXPECT_EQ(m.encode(b.data(), 0, static_cast<int>(b.size())), static_cast<int>(b.size()));
  return b;
}

void put_be32(std::vector<std::uint8_t>& b, std::size_t at, std::int32_t v) {
  const auto u = static_cast<std::uint32_t>(v);
  for (std::size_t i = 0; i < 4; ++i)
    b[at + i] = static_cast<std::uint8_t>(u >> (24 - 8 * i));
}

constexpr std::int32_t kBadLengths[] = {
    0,   -1, -2, std::numeric_limits<std::int32_t>::min(), std::numeric_limits<std::int32_t>::max(),
    1000};

TEST(LcmDecode, StringLengthsBelowOneOrBeyondTheBufferAreRejected) {
  magvec_lcm::command c{};
  c.request_id = 7;
  c.command = "status";
  const std::vector<std::uint8_t> good = encode(c);
  magvec_lcm::command back{};
  ASSERT_EQ(back.decode(good.data(), 0, static_cast<int>(good.size())),
            static_cast<int>(good.size()));
  EXPECT_EQ(back.command, "status");
  for (const std::int32_t len : kBadLengths) {
    SCOPED_TRACE(len);
    std::vector<std::uint8_t> bad = good;
    put_be32(bad, 16, len);  // after the fingerprint and request_id
    magvec_lcm::command m{};
    int n = 0;
    EXPECT_NO_THROW(n = m.decode(bad.data(), 0, static_cast<int>(bad.size())));
    EXPECT_LT(n, 0);
  }
  // One C string: NUL last and nowhere before (found by fuzzing: an embedded NUL decoded into a
  // std::string that re-encoded to fewer bytes than getEncodedSize() announced).
  for (const std::size_t at : {std::size_t{20}, std::size_t{22}, good.size() - 1}) {
    SCOPED_TRACE(at);
    std::vector<std::uint8_t> bad = good;
    bad[at] = at == good.size() - 1 ? 'x' : 0;
    magvec_lcm::command m{};
    EXPECT_LT(m.decode(bad.data(), 0, static_cast<int>(bad.size())), 0);
  }
  // An empty string is length 1 (its NUL) and fine.
  c.command.clear();
  const std::vector<std::uint8_t> empty = encode(c);
  EXPECT_EQ(back.decode(empty.data(), 0, static_cast<int>(empty.size())),
            static_cast<int>(empty.size()));
  EXPECT_EQ(back.command, "");
}

// Every string of every type: the length word of the k-th string set to each bad value.
TEST(LcmDecode, EveryStringFieldOfEveryTypeIsChecked) {
  magvec_lcm::calibration_state s{};
  s.calibrator = "li";
  s.state = "idle";
  s.failure = "none";
  s.solver_reason = "";
  magvec_lcm::command_reply r{};
  r.message = "ok";
  magvec_lcm::pipeline_event e = session_start_event(1, "[lcm]\n");
  // Offsets of the length words: after the fingerprint (8) and the fields before each string.
  constexpr std::size_t kCalStateHintCode =
      8 + 8 + 4 + 3 + 4 + 5 + 4 + 5 + 4 + 1 + 8 + 8 + 4 + 4 + 9 * 8 + 3 * 8 + 4 * 8 + 4 * 4;
  struct Case {
    std::vector<std::uint8_t> bytes;
    std::vector<std::size_t> length_offsets;
    int (*decode)(const std::vector<std::uint8_t>&);
  };
  const std::vector<Case> cases = {
      {encode(s),
       {8 + 8, 8 + 8 + 4 + 3, 8 + 8 + 4 + 3 + 4 + 5, 8 + 8 + 4 + 3 + 4 + 5 + 4 + 5,
        // hint_code and hint: after solver_reason (""), 2 doubles, 2 int32, w, o, rm, 4 int32
        kCalStateHintCode, kCalStateHintCode + 4 + 1},
       [](const std::vector<std::uint8_t>& b) {
         magvec_lcm::calibration_state m{};
         return m.decode(b.data(), 0, static_cast<int>(b.size()));
       }},
      {encode(r),
       {8 + 8 + 1},
       [](const std::vector<std::uint8_t>& b) {
         magvec_lcm::command_reply m{};
         return m.decode(b.data(), 0, static_cast<int>(b.size()));
       }},
      {encode(e),
       {8 + 1 + 8},
       [](const std::vector<std::uint8_t>& b) {
         magvec_lcm::pipeline_event m{};
         return m.decode(b.data(), 0, static_cast<int>(b.size()));
       }},
  };
  for (const Case& c : cases) {
    ASSERT_EQ(c.decode(c.bytes), static_cast<int>(c.bytes.size()));
    for (const std::size_t at : c.length_offsets) {
      for (const std::int32_t len : kBadLengths) {
        SCOPED_TRACE(testing::Message() << "offset " << at << " length " << len);
        std::vector<std::uint8_t> bad = c.bytes;
        put_be32(bad, at, len);
        int n = 0;
        EXPECT_NO_THROW(n = c.decode(bad));
        EXPECT_LT(n, 0);
      }
    }
  }
}

magvec_lcm::mag_sample_batch sample_batch(int n) {
  magvec_lcm::mag_sample_batch b{};
  for (int i = 0; i < n; ++i) {
    hal::MagnetometerSample s;
    s.t_us = 1'000'000 + 1000 * static_cast<std::uint64_t>(i);
    s.m_nT = {1.5 * i, -2.25, 4e4 + i};
    s.raw = {i, -i, 7};
    s.flags = static_cast<std::uint32_t>(i % 3);
    s.sequence = static_cast<std::uint32_t>(100 + i);
    b.samples.push_back(to_lcm(s, i == 1 ? std::numeric_limits<double>::quiet_NaN() : 5e4));
  }
  b.count = n;
  return b;
}

// The batched raw message (lcm.raw_batch > 1) carries every field of each sample bit-exactly.
TEST(LcmDecode, MagSampleBatchRoundTrips) {
  for (const int n : {0, 1, 10, 1000}) {
    SCOPED_TRACE(n);
    const magvec_lcm::mag_sample_batch b = sample_batch(n);
    const std::vector<std::uint8_t> bytes = encode(b);
    EXPECT_EQ(bytes.size(), 8u + 4u + 60u * static_cast<std::size_t>(n));
    magvec_lcm::mag_sample_batch back{};
    ASSERT_EQ(back.decode(bytes.data(), 0, static_cast<int>(bytes.size())),
              static_cast<int>(bytes.size()));
    ASSERT_EQ(back.count, n);
    ASSERT_EQ(back.samples.size(), static_cast<std::size_t>(n));
    for (int i = 0; i < n; ++i)
      EXPECT_EQ(encode(back.samples[static_cast<std::size_t>(i)]),
                encode(b.samples[static_cast<std::size_t>(i)]));
    EXPECT_EQ(encode(back), bytes);
  }
}

// The count of a variable-length array is checked before the decoder allocates: a negative count
// made resize() throw std::length_error and INT32_MAX allocated 2^31 samples before the buffer
// ran out (host/lcm/harden_generated.cmake). Counts beyond the bytes, truncations and a wrong
// fingerprint are rejected without throwing.
TEST(LcmDecode, MagSampleBatchBadCountsAndTruncationsAreRejected) {
  const std::vector<std::uint8_t> good = encode(sample_batch(3));
  for (const std::int32_t count : {-1, std::numeric_limits<std::int32_t>::min(), 4, 100, 181,
                                   std::numeric_limits<std::int32_t>::max()}) {
    SCOPED_TRACE(count);
    std::vector<std::uint8_t> bad = good;
    put_be32(bad, 8, count);  // after the fingerprint
    magvec_lcm::mag_sample_batch m{};
    int n = 0;
    EXPECT_NO_THROW(n = m.decode(bad.data(), 0, static_cast<int>(bad.size())));
    EXPECT_LT(n, 0);
  }
  for (std::size_t len = 0; len < good.size(); ++len) {
    magvec_lcm::mag_sample_batch m{};
    EXPECT_LT(m.decode(good.data(), 0, static_cast<int>(len)), 0) << len;
  }
  std::vector<std::uint8_t> other = good;
  other[0] ^= 1;
  magvec_lcm::mag_sample_batch m{};
  EXPECT_LT(m.decode(other.data(), 0, static_cast<int>(other.size())), 0);
  // A per-sample message is not a batch (and the other way round): the fingerprints differ.
  const std::vector<std::uint8_t> single = encode(sample_batch(1).samples[0]);
  EXPECT_LT(m.decode(single.data(), 0, static_cast<int>(single.size())), 0);
  magvec_lcm::mag_sample s{};
  EXPECT_LT(s.decode(good.data(), 0, static_cast<int>(good.size())), 0);
}

// What magvecd does: a typed subscription on the command channel. The malformed packet is dropped
// (LCM reports the decode error) and the next good one is delivered.
TEST(LcmDecode, MalformedCommandPacketDoesNotStopTheSubscriber) {
  lcm::LCM l("memq://");
  ASSERT_TRUE(l.good());
  struct Handler {
    int count{0};
    std::string last;
    void on(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::command* m) {
      ++count;
      last = m->command;
    }
  } h;
  l.subscribe("MAGVEC_COMMAND", &Handler::on, &h);
  magvec_lcm::command c{};
  c.command = "status";
  std::vector<std::uint8_t> bad = encode(c);
  put_be32(bad, 16, 0);
  ASSERT_EQ(l.publish("MAGVEC_COMMAND", bad.data(), static_cast<unsigned>(bad.size())), 0);
  EXPECT_NO_THROW(l.handleTimeout(1000));
  EXPECT_EQ(h.count, 0);
  ASSERT_EQ(l.publish("MAGVEC_COMMAND", &c), 0);
  EXPECT_GE(l.handleTimeout(1000), 1);
  EXPECT_EQ(h.count, 1);
  EXPECT_EQ(h.last, "status");
}

}  // namespace
}  // namespace magvec::host::daemon
