// HAL: persistent storage of one calibration blob (opaque bytes; the core serialises its
// parameters). Implementations are two-slot, CRC-protected and power-cut safe: after a power cut
// at any point of store(), load() returns either the previous or the new blob, never a corrupt one.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

class ParamStore {
 public:
  // Copies the newest valid blob into `out`, sets `length` and its `sequence` number.
  // kNotFound if no valid blob exists, kOverflow if `out` is too small (nothing copied).
  virtual Status load(std::span<std::uint8_t> out, std::size_t& length,
                      std::uint32_t& sequence) noexcept = 0;
  // Stores a new blob; the previously stored one stays loadable until this one is complete.
  virtual Status store(std::span<const std::uint8_t> blob) noexcept = 0;
  virtual std::size_t max_blob_size() const noexcept = 0;

 protected:
  ~ParamStore() = default;
};

}  // namespace magvec::hal
