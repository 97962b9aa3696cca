// RAM-backed NOR flash (hal::Flash) with power-cut injection, for ParamStore tests and the
// host-in-the-loop harness. NOR semantics: erase -> 0xFF, program ANDs. After an injected cut every
// operation fails with kPowerLoss until restore_power() (a reboot); the medium keeps what was
// written up to the cut, including one partially programmed byte.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/hal/flash.hpp"

namespace magvec::drivers {

class SimFlash final : public hal::Flash {
 public:
  // `storage` (owned by the caller) size must be a multiple of sector_size. Starts erased.
  SimFlash(std::span<std::uint8_t> storage, std::size_t sector_size) noexcept;

  std::size_t size() const noexcept override { return storage_.size(); }
  std::size_t sector_size() const noexcept override { return sector_size_; }
  hal::Status read(std::size_t offset, std::span<std::uint8_t> out) const noexcept override;
  hal::Status erase_sector(std::size_t sector_index) noexcept override;
  hal::Status program(std::size_t offset, std::span<const std::uint8_t> data) noexcept override;

  // Power cut after `bytes` more bytes have been programmed completely; the next byte is left
  // half-programmed (old & (data | 0x55)).
  void cut_after_program_bytes(std::size_t bytes) noexcept;
  // Power cut during the (erases_ok + 1)-th erase from now, after `bytes_erased` bytes of that
  // sector were set to 0xFF.
  void cut_during_erase(std::size_t erases_ok, std::size_t bytes_erased) noexcept;
  void restore_power() noexcept;
  bool powered() const noexcept { return powered_; }
  std::size_t bytes_programmed() const noexcept { return bytes_programmed_; }
  std::size_t erases() const noexcept { return erases_; }
  std::span<std::uint8_t> raw() noexcept { return storage_; }

 private:
  std::span<std::uint8_t> storage_;
  std::size_t sector_size_;
  bool powered_{true};
  bool program_cut_armed_{false};
  std::size_t program_budget_{0};
  bool erase_cut_armed_{false};
  std::size_t erase_budget_{0};
  std::size_t erase_partial_bytes_{0};
  std::size_t bytes_programmed_{0};
  std::size_t erases_{0};
};

}  // namespace magvec::drivers
