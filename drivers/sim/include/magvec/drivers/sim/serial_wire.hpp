// SerialWire: the bytes a simulated serial instrument has written and its reader has not yet read
// (the UART's receive buffer on the host side). Bounded: a byte written to a full wire is lost and
// counted, as a real receive buffer overruns when the reader falls behind. Shared by the
// simulated serial fluxgate and the simulated G-882, which differ only in what they write.
// Heap-free, noexcept, portable.
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/hal/status.hpp"

namespace magvec::drivers::sim {

template <std::size_t kBytes>
class SerialWire {
 public:
  // Returns false (the byte lost) when the wire is full.
  bool put(std::uint8_t b) noexcept {
    if (count_ == kBytes) return false;
    ring_[(head_ + count_) % kBytes] = b;
    ++count_;
    return true;
  }
  // hal::SerialPort::read semantics without waiting: kOk with at least one byte, else kTimeout.
  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n_read) noexcept {
    n_read = 0;
    while (n_read < buf.size() && count_ > 0) {
      buf[n_read++] = ring_[head_];
      head_ = (head_ + 1) % kBytes;
      --count_;
    }
    return n_read > 0 ? hal::Status::kOk : hal::Status::kTimeout;
  }
  std::size_t size() const noexcept { return count_; }

 private:
  std::array<std::uint8_t, kBytes> ring_{};
  std::size_t head_{0};
  std::size_t count_{0};
};

}  // namespace magvec::drivers::sim
