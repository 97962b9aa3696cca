// The ParamStore record (the persisted calibration on the MCU's flash). Input: a flash image of
// two 256-byte slots (sector 64 bytes), then a blob to store. Invariants: load() returns a record
// only if the slot's bytes pass the record check (magic, version, length, CRC) independently of the
// store, and it is the newest valid one; it reports kNotFound only if neither slot passes; store()
// of any blob that fits succeeds, the next load() returns exactly that blob with the next sequence
// number, and the slot that held the newest record before the store is byte-identical afterwards
// (the last good calibration).
#include <array>
#include <cstring>
#include <vector>

#include "fuzz_check.hpp"
#include "magvec/drivers/param_record.hpp"
#include "magvec/drivers/param_store.hpp"
#include "magvec/drivers/sim_flash.hpp"

using namespace magvec;
using namespace magvec::drivers;

namespace {

constexpr std::size_t kSector = 64;
constexpr std::size_t kSlot = 256;

// The record in a slot by the format alone: header + length bytes, checked as one record.
ParamRecordHeader slot_record(const std::vector<std::uint8_t>& image, std::size_t slot) {
  const std::uint8_t* p = image.data() + slot * kSlot;
  const std::size_t max_payload = kSlot - kParamRecordHeaderSize;
  const ParamRecordHeader h = parse_param_record_header(
      std::span<const std::uint8_t, kParamRecordHeaderSize>(p, kParamRecordHeaderSize),
      max_payload);
  if (!h.valid) return h;
  return check_param_record(std::span<const std::uint8_t>(p, kParamRecordHeaderSize + h.length),
                            max_payload);
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  std::vector<std::uint8_t> image(2 * kSlot, 0xFF);
  std::memcpy(image.data(), data, size < image.size() ? size : image.size());
  const std::vector<std::uint8_t> blob(data + (size < image.size() ? size : image.size()),
                                       data + size);

  // The record check itself: a valid record re-encodes to the same header.
  for (std::size_t slot = 0; slot < 2; ++slot) {
    const ParamRecordHeader h = slot_record(image, slot);
    if (!h.valid) continue;
    std::array<std::uint8_t, kParamRecordHeaderSize> again{};
    encode_param_record_header(again, h.sequence,
                               std::span<const std::uint8_t>(
                                   image.data() + slot * kSlot + kParamRecordHeaderSize, h.length));
    FUZZ_CHECK(std::memcmp(again.data(), image.data() + slot * kSlot, again.size()) == 0);
  }

  std::vector<std::uint8_t> storage(image.size());
  SimFlash flash(storage, kSector);  // starts erased: the image is the medium's content
  std::memcpy(flash.raw().data(), image.data(), image.size());
  FlashParamStore store(flash, ParamStoreLayout{0, kSlot});
  FUZZ_CHECK(store.check_layout() == hal::Status::kOk);
  const ParamRecordHeader r0 = slot_record(image, 0), r1 = slot_record(image, 1);
  std::array<std::uint8_t, kSlot> out{};
  std::size_t length = 0;
  std::uint32_t sequence = 0;
  const hal::Status st = store.load(out, length, sequence);
  int newest = -1;
  if (r0.valid && r1.valid)
    newest = param_sequence_newer(r1.sequence, r0.sequence) ? 1 : 0;
  else if (r0.valid)
    newest = 0;
  else if (r1.valid)
    newest = 1;
  if (newest < 0) {
    FUZZ_CHECK(st == hal::Status::kNotFound);
  } else {
    FUZZ_CHECK(st == hal::Status::kOk);
    const ParamRecordHeader& h = newest == 0 ? r0 : r1;
    FUZZ_CHECK(sequence == h.sequence && length == h.length);
    FUZZ_CHECK(std::memcmp(
                   out.data(),
                   image.data() + static_cast<std::size_t>(newest) * kSlot + kParamRecordHeaderSize,
                   length) == 0);
  }

  const hal::Status put = store.store(blob);
  if (blob.size() > store.max_blob_size()) {
    FUZZ_CHECK(put == hal::Status::kOverflow);
    FUZZ_CHECK(storage == image);
    return 0;
  }
  FUZZ_CHECK(put == hal::Status::kOk);
  if (newest >= 0) {
    const std::size_t off = static_cast<std::size_t>(newest) * kSlot;
    FUZZ_CHECK(std::memcmp(storage.data() + off, image.data() + off, kSlot) == 0);
  }
  std::uint32_t sequence2 = 0;
  FUZZ_CHECK(store.load(out, length, sequence2) == hal::Status::kOk);
  FUZZ_CHECK(length == blob.size());
  FUZZ_CHECK(blob.empty() || std::memcmp(out.data(), blob.data(), blob.size()) == 0);
  FUZZ_CHECK(sequence2 == (newest < 0 ? 1u : sequence + 1u));
  return 0;
}
