// Every LCM message type of host/lcm as decoded by magvecd (command channel), magvec ctl (reply)
// and magvec replay (log events). Input: 1 byte selecting the type, then the encoded message.
// Invariants: decode never throws and never reads outside the buffer; an accepted message consumed
// exactly getEncodedSize() bytes; re-encoding it and decoding that again is a fixed point; types
// without strings re-encode to the very input bytes; the HAL conversions (lcm_codec) carry every
// value bit-exactly (the basis of exact replay).
#include <cstring>
#include <vector>

#include "fuzz_check.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"

using namespace magvec::host::daemon;

namespace {

template <typename Msg>
std::vector<std::uint8_t> encoded(const Msg& m) {
  std::vector<std::uint8_t> out(static_cast<std::size_t>(m.getEncodedSize()));
  FUZZ_CHECK(m.encode(out.data(), 0, static_cast<int>(out.size())) == static_cast<int>(out.size()));
  return out;
}

// Returns the decoded message's encoding, or empty when the input was rejected.
template <typename Msg>
std::vector<std::uint8_t> check_type(const std::uint8_t* data, std::size_t size, bool no_strings,
                                     Msg* out) {
  Msg m;
  const int n = m.decode(data, 0, static_cast<int>(size));
  if (n < 0) return {};
  FUZZ_CHECK(static_cast<std::size_t>(n) <= size);
  FUZZ_CHECK(n == m.getEncodedSize());
  const std::vector<std::uint8_t> first = encoded(m);
  if (no_strings) FUZZ_CHECK(std::memcmp(first.data(), data, first.size()) == 0);
  Msg again;
  FUZZ_CHECK(again.decode(first.data(), 0, static_cast<int>(first.size())) == n);
  FUZZ_CHECK(encoded(again) == first);
  *out = m;
  return first;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  if (size == 0) return 0;
  const std::uint8_t type = data[0];
  ++data;
  --size;
  switch (type % 8) {
    case 0: {
      magvec_lcm::mag_sample m;
      const auto bytes = check_type(data, size, true, &m);
      if (!bytes.empty()) FUZZ_CHECK(encoded(to_lcm(from_lcm(m), m.f_ref_nT)) == bytes);
      break;
    }
    case 1: {
      magvec_lcm::attitude m;
      const auto bytes = check_type(data, size, true, &m);
      if (!bytes.empty()) FUZZ_CHECK(encoded(to_lcm(from_lcm(m))) == bytes);
      break;
    }
    case 2: {
      magvec_lcm::calibrated_vector m;
      const auto bytes = check_type(data, size, true, &m);
      if (!bytes.empty()) {
        const magvec::hal::OutputRecord r = from_lcm(m);
        FUZZ_CHECK(bit_identical(r, r));
        FUZZ_CHECK(encoded(to_lcm(r)) == bytes);
      }
      break;
    }
    case 3: {
      magvec_lcm::calibration_state m;
      (void)check_type(data, size, false, &m);
      break;
    }
    case 4: {
      magvec_lcm::health m;
      (void)check_type(data, size, true, &m);
      break;
    }
    case 5: {
      magvec_lcm::pipeline_event m;
      const auto bytes = check_type(data, size, false, &m);
      if (!bytes.empty()) {
        // SET_ACTIVE carries the model bit-exactly.
        const magvec::core::SensorModel<double> model = model_from_arrays(m.w, m.o_nT, m.rm_quat);
        double w[9], o[3], q[4];
        model_to_arrays(model, w, o, q);
        FUZZ_CHECK(std::memcmp(w, m.w, sizeof w) == 0 && std::memcmp(o, m.o_nT, sizeof o) == 0 &&
                   std::memcmp(q, m.rm_quat, sizeof q) == 0);
      }
      break;
    }
    case 6: {
      magvec_lcm::command m;
      (void)check_type(data, size, false, &m);
      break;
    }
    case 7: {
      magvec_lcm::command_reply m;
      (void)check_type(data, size, false, &m);
      break;
    }
  }
  return 0;
}
