// HAL: one SPI device (chip select handled by the implementation). Full duplex: tx.size() bytes
// are clocked out while the same number of bytes is clocked in, CS asserted for the whole transfer.
#pragma once

#include <cstdint>
#include <span>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

class SpiBus {
 public:
  // tx and rx must have the same size (else kInvalidArgument); rx may alias nothing in tx.
  // The caller owns both buffers; the implementation does not keep references after return.
  virtual Status transfer(std::span<const std::uint8_t> tx,
                          std::span<std::uint8_t> rx) noexcept = 0;

 protected:
  ~SpiBus() = default;
};

}  // namespace magvec::hal
