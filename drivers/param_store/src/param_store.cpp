// Two-slot power-cut-safe parameter store; layout and protocol in param_store.hpp.
#include "magvec/drivers/param_store.hpp"

#include <array>

#include "magvec/drivers/crc.hpp"

namespace magvec::drivers {

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
  const ParamRecordHeader header = parse_param_record_header(h, max_blob_size());
  if (!header.valid) return info;
  const std::uint32_t length = header.length;
  std::uint32_t crc = param_record_crc_start(h);
  std::array<std::uint8_t, 64> chunk{};
  for (std::size_t done = 0; done < length;) {
    const std::size_t n = length - done < chunk.size() ? length - done : chunk.size();
    const std::span<std::uint8_t> part(chunk.data(), n);
    if (flash_.read(off + kHeaderSize + done, part) != hal::Status::kOk) return info;
    crc = crc32_update(crc, part);
    done += n;
  }
  if (crc32_final(crc) != header.crc) return info;
  info.valid = true;
  info.sequence = header.sequence;
  info.length = length;
  return info;
}

int FlashParamStore::newest_valid(SlotInfo (&info)[2]) const noexcept {
  info[0] = inspect(0);
  info[1] = inspect(1);
  if (info[0].valid && info[1].valid)
    return param_sequence_newer(info[1].sequence, info[0].sequence) ? 1 : 0;
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
  const ParamRecordHeader header = parse_param_record_header(h, max_blob_size());
  if (!header.valid || crc32_final(crc32_update(param_record_crc_start(h), dst)) != header.crc) {
    return hal::Status::kCorrupt;
  }
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
  encode_param_record_header(h, sequence, blob);

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
