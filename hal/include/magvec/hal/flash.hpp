// HAL: byte-addressable NOR-like flash, the medium under ParamStore. Semantics follow NOR flash:
// erase sets a whole sector to 0xFF; program can only clear bits (new = old & data). A power cut
// during either operation leaves the affected bytes in an undefined mix of old and new values.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/hal/status.hpp"

namespace magvec::hal {

class Flash {
 public:
  virtual std::size_t size() const noexcept = 0;         // bytes
  virtual std::size_t sector_size() const noexcept = 0;  // bytes, divides size()
  // All offsets are absolute; out-of-range requests return kInvalidArgument and change nothing.
  virtual Status read(std::size_t offset, std::span<std::uint8_t> out) const noexcept = 0;
  virtual Status erase_sector(std::size_t sector_index) noexcept = 0;
  virtual Status program(std::size_t offset, std::span<const std::uint8_t> data) noexcept = 0;

 protected:
  ~Flash() = default;
};

}  // namespace magvec::hal
