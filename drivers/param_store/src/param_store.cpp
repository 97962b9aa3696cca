// Two-slot power-cut-safe parameter store; layout and protocol in param_store.hpp.
#include "magvec/drivers/param_store.hpp"

#include <array>

#include "magvec/drivers/crc.hpp"

namespace magvec::drivers {
namespace {

std::uint32_t le32(const std::uint8_t* p) noexcept {
  return static_cast<std::uint32_t>(p[0]) | (static_cast<std::uint32_t>(p[1]) << 8) |
         (static_cast<std::uint32_t>(p[2]) << 16) | (static_cast<std::uint32_t>(p[3]) << 24);
}
std::uint16_t le16(const std::uint8_t* p) noexcept {
  return static_cast<std::uint16_t>(p[0] | (p[1] << 8));
}
void put32(std::uint8_t* p, std::uint32_t v) noexcept {
  for (int i = 0; i < 4; ++i)
    p[i] = static_cast<std::uint8_t>(v >> (8 * i));
}
void put16(std::uint8_t* p, std::uint16_t v) noexcept {
  p[0] = static_cast<std::uint8_t>(v);
  p[1] = static_cast<std::uint8_t>(v >> 8);
}
bool newer(std::uint32_t a, std::uint32_t b) noexcept {
  return static_cast<std::int32_t>(a - b) > 0;
}

}  // namespace

hal::Status FlashParamStore::check_layout() const noexcept {
  const std::size_t sector = flash_.sector_size();
  if (sector == 0 || layout_.slot_size <= kHeaderSize || layout_.slot_size % sector != 0 ||
      layout_.base % sector != 0 || layout_.base > flash_.size() ||
      2 * layout_.slot_size > flash_.size() - layout_.base) {
    return hal::Status::kInvalidArgument;
  }
  return hal::Status::kOk;
}

FlashParamStore::SlotInfo FlashParamStore::inspect(std::size_t slot) const noexcept {
  SlotInfo info;
  std::array<std::uint8_t, kHeaderSize> h{};
  const std::size_t off = slot_offset(slot);
  if (flash_.read(off, h) != hal::Status::kOk) return info;
  if (le32(h.data()) != kMagic || le16(h.data() + 4) != kVersion ||
      le16(h.data() + 6) != kHeaderSize) {
    return info;
  }
  const std::uint32_t length = le32(h.data() + 12);
  if (length > max_blob_size()) return info;
  std::uint32_t crc = crc32_update(kCrc32Init, std::span<const std::uint8_t>(h.data() + 4, 12));
  std::array<std::uint8_t, 64> chunk{};
  for (std::size_t done = 0; done < length;) {
    const std::size_t n = length - done < chunk.size() ? length - done : chunk.size();
    const std::span<std::uint8_t> part(chunk.data(), n);
    if (flash_.read(off + kHeaderSize + done, part) != hal::Status::kOk) return info;
    crc = crc32_update(crc, part);
    done += n;
  }
  if (crc32_final(crc) != le32(h.data() + 16)) return info;
  info.valid = true;
  info.sequence = le32(h.data() + 8);
  info.length = length;
  return info;
}

int FlashParamStore::newest_valid(SlotInfo (&info)[2]) const noexcept {
  info[0] = inspect(0);
  info[1] = inspect(1);
  if (info[0].valid && info[1].valid) return newer(info[1].sequence, info[0].sequence) ? 1 : 0;
  if (info[0].valid) return 0;
  if (info[1].valid) return 1;
  return -1;
}

hal::Status FlashParamStore::load(std::span<std::uint8_t> out, std::size_t& length,
                                  std::uint32_t& sequence) noexcept {
  length = 0;
  if (check_layout() != hal::Status::kOk) return hal::Status::kInvalidArgument;
  SlotInfo info[2];
  const int best = newest_valid(info);
  if (best < 0) return hal::Status::kNotFound;
  const SlotInfo& b = info[best];
  if (b.length > out.size()) return hal::Status::kOverflow;
  const std::span<std::uint8_t> dst = out.first(b.length);
  if (flash_.read(slot_offset(static_cast<std::size_t>(best)) + kHeaderSize, dst) !=
      hal::Status::kOk) {
    return hal::Status::kBusError;
  }
  // Re-check the bytes actually copied (the medium could change between inspect and read).
  std::array<std::uint8_t, kHeaderSize> h{};
  if (flash_.read(slot_offset(static_cast<std::size_t>(best)), h) != hal::Status::kOk) {
    return hal::Status::kBusError;
  }
  std::uint32_t crc = crc32_update(kCrc32Init, std::span<const std::uint8_t>(h.data() + 4, 12));
  crc = crc32_final(crc32_update(crc, dst));
  if (crc != le32(h.data() + 16)) return hal::Status::kCorrupt;
  length = b.length;
  sequence = b.sequence;
  return hal::Status::kOk;
}

hal::Status FlashParamStore::store(std::span<const std::uint8_t> blob) noexcept {
  if (check_layout() != hal::Status::kOk) return hal::Status::kInvalidArgument;
  if (blob.size() > max_blob_size()) return hal::Status::kOverflow;
  SlotInfo info[2];
  const int best = newest_valid(info);
  const std::size_t target = best == 0 ? 1 : 0;
  const std::uint32_t sequence = best < 0 ? 1u : info[best].sequence + 1u;
  const std::size_t off = slot_offset(target);

  const std::size_t sector = flash_.sector_size();
  for (std::size_t s = 0; s < layout_.slot_size / sector; ++s) {
    if (auto st = flash_.erase_sector(off / sector + s); st != hal::Status::kOk) return st;
  }
  std::array<std::uint8_t, kHeaderSize> h{};
  put32(h.data(), kMagic);
  put16(h.data() + 4, kVersion);
  put16(h.data() + 6, static_cast<std::uint16_t>(kHeaderSize));
  put32(h.data() + 8, sequence);
  put32(h.data() + 12, static_cast<std::uint32_t>(blob.size()));
  std::uint32_t crc = crc32_update(kCrc32Init, std::span<const std::uint8_t>(h.data() + 4, 12));
  put32(h.data() + 16, crc32_final(crc32_update(crc, blob)));

  // Header body, payload, and only then the magic that makes the slot visible to load().
  if (auto st =
          flash_.program(off + 4, std::span<const std::uint8_t>(h.data() + 4, kHeaderSize - 4));
      st != hal::Status::kOk) {
    return st;
  }
  if (!blob.empty()) {
    if (auto st = flash_.program(off + kHeaderSize, blob); st != hal::Status::kOk) return st;
  }
  if (auto st = flash_.program(off, std::span<const std::uint8_t>(h.data(), 4));
      st != hal::Status::kOk) {
    return st;
  }
  const SlotInfo check = inspect(target);
  if (!check.valid || check.sequence != sequence || check.length != blob.size()) {
    return hal::Status::kCorrupt;
  }
  return hal::Status::kOk;
}

}  // namespace magvec::drivers
