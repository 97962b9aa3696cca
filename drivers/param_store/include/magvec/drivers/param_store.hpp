// Power-cut-safe two-slot parameter store over a hal::Flash (docs/architecture.md#hal: ParamStore).
//
// Slot layout: one record of param_record.hpp at the start of each slot (each slot a whole
// number of sectors); its magic 'MVPS' at offset 0 is programmed LAST: the commit marker.
// store(): target = the slot that does NOT hold the newest valid record; erase it, program
// header (without magic) and payload, then the magic, then read back and verify. A cut at any
// point leaves the other slot (the last good calibration) untouched; the interrupted slot fails
// the magic or the CRC check and is ignored by load(). CRC-32 also catches bit rot.
// Residual risk (documented, not hidden): a torn write that happens to produce a valid CRC-32
// (probability ~2^-32 per torn slot) would be accepted.
#pragma once

#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/drivers/param_record.hpp"
#include "magvec/hal/flash.hpp"
#include "magvec/hal/param_store.hpp"

namespace magvec::drivers {

struct ParamStoreLayout {
  std::size_t base{0};       // offset of slot 0 (sector aligned)
  std::size_t slot_size{0};  // bytes per slot (multiple of the sector size); slot 1 follows slot 0
};

class FlashParamStore final : public hal::ParamStore {
 public:
  static constexpr std::uint32_t kMagic = kParamRecordMagic;
  static constexpr std::uint16_t kVersion = kParamRecordVersion;
  static constexpr std::size_t kHeaderSize = kParamRecordHeaderSize;

  FlashParamStore(hal::Flash& flash, const ParamStoreLayout& layout) noexcept
      : flash_(flash), layout_(layout) {}

  // kInvalidArgument if the layout does not fit the flash or is not sector aligned.
  hal::Status check_layout() const noexcept;

  hal::Status load(std::span<std::uint8_t> out, std::size_t& length,
                   std::uint32_t& sequence) noexcept override;
  hal::Status store(std::span<const std::uint8_t> blob) noexcept override;
  std::size_t max_blob_size() const noexcept override {
    return layout_.slot_size > kHeaderSize ? layout_.slot_size - kHeaderSize : 0;
  }

  struct SlotInfo {
    bool valid{false};
    std::uint32_t sequence{0};
    std::uint32_t length{0};
  };
  // Validates slot 0 or 1 (magic, version, length, CRC).
  SlotInfo inspect(std::size_t slot) const noexcept;

 private:
  std::size_t slot_offset(std::size_t slot) const noexcept {
    return layout_.base + slot * layout_.slot_size;
  }
  int newest_valid(SlotInfo (&info)[2]) const noexcept;

  hal::Flash& flash_;
  ParamStoreLayout layout_;
};

}  // namespace magvec::drivers
