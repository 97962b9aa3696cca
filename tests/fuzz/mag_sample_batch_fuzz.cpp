// The batched raw-sample message (magvec_lcm.mag_sample_batch, lcm.raw_batch > 1) as `magvec
// replay` and any log reader decode it. Input: the encoded message.
// Invariants: decode never throws nor allocates beyond the input (the count is checked against the
// bytes left before the samples are allocated: host/lcm/harden_generated.cmake); an accepted batch
// holds exactly `count` samples of 60 bytes each and consumed exactly getEncodedSize() bytes;
// re-encoding gives the very input bytes; every sample carries its values bit-exactly through the
// HAL conversion (lcm_codec), as a per-sample message does.
#include <cstring>
#include <vector>

#include "fuzz_check.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"

using namespace magvec::host::daemon;

namespace {

constexpr std::size_t kHeaderBytes = 8 + 4;  // fingerprint, count
constexpr std::size_t kSampleBytes = 60;     // t_us, m_nT[3], raw[3], flags, sequence, f_ref_nT

template <typename Msg>
std::vector<std::uint8_t> encoded(const Msg& m) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(m.getEncodedSize()));
  FUZZ_CHECK(m.encode(out.data(), 0, static_cast<int>(out.size())) == static_cast<int>(out.size()));
  return out;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  magvec_lcm::mag_sample_batch b;
  const int n = b.decode(data, 0, static_cast<int>(size));
  if (n < 0) return 0;
  FUZZ_CHECK(b.count >= 0);
  FUZZ_CHECK(b.samples.size() == static_cast<std::size_t>(b.count));
  FUZZ_CHECK(static_cast<std::size_t>(n) == kHeaderBytes + kSampleBytes * b.samples.size());
  FUZZ_CHECK(static_cast<std::size_t>(n) <= size);
  FUZZ_CHECK(n == b.getEncodedSize());
  const std::vector<std::uint8_t> bytes = encoded(b);
  FUZZ_CHECK(std::memcmp(bytes.data(), data, bytes.size()) == 0);
  magvec_lcm::mag_sample_batch again;
  FUZZ_CHECK(again.decode(bytes.data(), 0, static_cast<int>(bytes.size())) == n);
  FUZZ_CHECK(encoded(again) == bytes);
  // Each sample as replay feeds it: through the HAL sample and back, bit for bit.
  magvec_lcm::mag_sample_batch rebuilt;
  for (const magvec_lcm::mag_sample& m : b.samples)
    rebuilt.samples.push_back(to_lcm(from_lcm(m), m.f_ref_nT));
  rebuilt.count = b.count;
  FUZZ_CHECK(encoded(rebuilt) == bytes);
  return 0;
}
