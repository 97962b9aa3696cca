// Simulated NOR flash with power-cut injection; see sim_flash.hpp.
#include "magvec/drivers/sim_flash.hpp"

namespace magvec::drivers {

SimFlash::SimFlash(std::span<std::uint8_t> storage, std::size_t sector_size) noexcept
    : storage_(storage), sector_size_(sector_size == 0 ? 1 : sector_size) {
  for (auto& b : storage_)
    b = 0xFF;
}

hal::Status SimFlash::read(std::size_t offset, std::span<std::uint8_t> out) const noexcept {
  if (!powered_) return hal::Status::kPowerLoss;
  if (offset > storage_.size() || out.size() > storage_.size() - offset) {
    return hal::Status::kInvalidArgument;
  }
  for (std::size_t i = 0; i < out.size(); ++i)
    out[i] = storage_[offset + i];
  return hal::Status::kOk;
}

hal::Status SimFlash::erase_sector(std::size_t sector_index) noexcept {
  if (!powered_) return hal::Status::kPowerLoss;
  const std::size_t n_sectors = storage_.size() / sector_size_;
  if (sector_index >= n_sectors) return hal::Status::kInvalidArgument;
  std::size_t bytes = sector_size_;
  bool cut = false;
  if (erase_cut_armed_) {
    if (erase_budget_ == 0) {
      bytes = erase_partial_bytes_ < sector_size_ ? erase_partial_bytes_ : sector_size_;
      cut = true;
      erase_cut_armed_ = false;
    } else {
      --erase_budget_;
    }
  }
  for (std::size_t i = 0; i < bytes; ++i)
    storage_[sector_index * sector_size_ + i] = 0xFF;
  ++erases_;
  if (cut) {
    powered_ = false;
    return hal::Status::kPowerLoss;
  }
  return hal::Status::kOk;
}

hal::Status SimFlash::program(std::size_t offset, std::span<const std::uint8_t> data) noexcept {
  if (!powered_) return hal::Status::kPowerLoss;
  if (offset > storage_.size() || data.size() > storage_.size() - offset) {
    return hal::Status::kInvalidArgument;
  }
  for (std::size_t i = 0; i < data.size(); ++i) {
    if (program_cut_armed_ && program_budget_ == 0) {
      storage_[offset + i] &= static_cast<std::uint8_t>(data[i] | 0x55u);
      program_cut_armed_ = false;
      powered_ = false;
      return hal::Status::kPowerLoss;
    }
    storage_[offset + i] &= data[i];
    ++bytes_programmed_;
    if (program_cut_armed_) --program_budget_;
  }
  return hal::Status::kOk;
}

void SimFlash::cut_after_program_bytes(std::size_t bytes) noexcept {
  program_cut_armed_ = true;
  program_budget_ = bytes;
}

void SimFlash::cut_during_erase(std::size_t erases_ok, std::size_t bytes_erased) noexcept {
  erase_cut_armed_ = true;
  erase_budget_ = erases_ok;
  erase_partial_bytes_ = bytes_erased;
}

void SimFlash::restore_power() noexcept {
  powered_ = true;
  program_cut_armed_ = false;
  erase_cut_armed_ = false;
}

}  // namespace magvec::drivers
