// Invariant checks for the libFuzzer targets: a violated invariant aborts with its location, which
// libFuzzer reports as a crash and saves the input (a "does not crash" target would miss wrong
// results that do not crash).
#pragma once

#include <cstddef>
#include <cstdint>
#include <cstdio>
#include <cstdlib>

#define FUZZ_CHECK(cond)                                                                  \
  do {                                                                                    \
    if (!(cond)) {                                                                        \
      std::fprintf(stderr, "%s:%d: invariant violated: %s\n", __FILE__, __LINE__, #cond); \
      std::abort();                                                                       \
    }                                                                                     \
  } while (false)

namespace magvec::fuzz {

// Consumes bytes from the front of the input (configuration choices), zero when exhausted.
class Bytes {
 public:
  Bytes(const std::uint8_t* data, std::size_t size) noexcept : p_(data), n_(size) {}
  std::uint8_t u8() noexcept {
    if (n_ == 0) return 0;
    --n_;
    return *p_++;
  }
  std::uint16_t u16() noexcept { return static_cast<std::uint16_t>(u8() | (u8() << 8)); }
  std::uint32_t u32() noexcept {
    return static_cast<std::uint32_t>(u16()) | (static_cast<std::uint32_t>(u16()) << 16);
  }
  const std::uint8_t* data() const noexcept { return p_; }
  std::size_t size() const noexcept { return n_; }

 private:
  const std::uint8_t* p_;
  std::size_t n_;
};

}  // namespace magvec::fuzz
