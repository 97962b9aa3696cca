#include "magvec/drivers/param_store.hpp"

#include <gtest/gtest.h>

#include <array>
#include <vector>

#include "magvec/drivers/sim_flash.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::drivers {
namespace {

constexpr std::size_t kSector = 64;
constexpr std::size_t kSlot = 2 * kSector;  // two sectors per slot
constexpr std::size_t kFlashSize = 8 * kSector;

std::vector<std::uint8_t> blob(std::uint8_t seed, std::size_t n) {
  std::vector<std::uint8_t> b(n);
  for (std::size_t i = 0; i < n; ++i)
    b[i] = static_cast<std::uint8_t>(seed * 31 + i * 7);
  return b;
}

struct Rig {
  std::array<std::uint8_t, kFlashSize> mem{};
  SimFlash flash{mem, kSector};
  FlashParamStore store{flash, ParamStoreLayout{kSector, kSlot}};

  std::vector<std::uint8_t> load(hal::Status& st, std::uint32_t& seq) {
    std::array<std::uint8_t, kSlot> out{};
    std::size_t len = 0;
    st = store.load(out, len, seq);
    return {out.begin(), out.begin() + static_cast<std::ptrdiff_t>(len)};
  }
};

TEST(ParamStore, StoreLoadAlternatesSlotsAndKeepsNewest) {
  Rig r;
  hal::Status st;
  std::uint32_t seq = 0;
  r.load(st, seq);
  EXPECT_EQ(st, hal::Status::kNotFound);
  ASSERT_EQ(r.store.check_layout(), hal::Status::kOk);
  for (std::uint8_t i = 1; i <= 5; ++i) {
    const auto b = blob(i, 30u + i);
    ASSERT_EQ(r.store.store(b), hal::Status::kOk);
    EXPECT_EQ(r.load(st, seq), b);
    EXPECT_EQ(st, hal::Status::kOk);
    EXPECT_EQ(seq, i);
    EXPECT_TRUE(r.store.inspect(0).valid);
    EXPECT_EQ(r.store.inspect(i % 2 == 1 ? 0 : 1).sequence, i);  // odd -> slot 0, even -> slot 1
  }
  // Empty blob and maximal blob.
  ASSERT_EQ(r.store.store({}), hal::Status::kOk);
  EXPECT_TRUE(r.load(st, seq).empty());
  EXPECT_EQ(st, hal::Status::kOk);
  const auto big = blob(9, r.store.max_blob_size());
  ASSERT_EQ(r.store.store(big), hal::Status::kOk);
  EXPECT_EQ(r.load(st, seq), big);
  const auto too_big = blob(9, r.store.max_blob_size() + 1);
  EXPECT_EQ(r.store.store(too_big), hal::Status::kOverflow);
  EXPECT_EQ(r.load(st, seq), big);
  // Output buffer too small.
  std::array<std::uint8_t, 4> small{};
  std::size_t len = 0;
  EXPECT_EQ(r.store.load(small, len, seq), hal::Status::kOverflow);
}

TEST(ParamStore, RejectsBadLayoutAndBitRot) {
  std::array<std::uint8_t, kFlashSize> mem{};
  SimFlash flash(mem, kSector);
  FlashParamStore unaligned(flash, ParamStoreLayout{10, kSlot});
  EXPECT_EQ(unaligned.check_layout(), hal::Status::kInvalidArgument);
  FlashParamStore too_big(flash, ParamStoreLayout{0, 5 * kSector});
  EXPECT_EQ(too_big.store(blob(1, 10)), hal::Status::kInvalidArgument);

  Rig r;
  ASSERT_EQ(r.store.store(blob(1, 40)), hal::Status::kOk);
  ASSERT_EQ(r.store.store(blob(2, 40)), hal::Status::kOk);
  // Flip one payload bit in the newest slot (slot 1): load falls back to the older, intact one.
  r.mem[kSector + kSlot + FlashParamStore::kHeaderSize + 5] ^= 0x08;
  hal::Status st;
  std::uint32_t seq = 0;
  EXPECT_EQ(r.load(st, seq), blob(1, 40));
  EXPECT_EQ(seq, 1u);
  // And the next store overwrites the damaged slot, not the good one.
  ASSERT_EQ(r.store.store(blob(3, 40)), hal::Status::kOk);
  EXPECT_EQ(r.load(st, seq), blob(3, 40));
  EXPECT_EQ(seq, 2u);
  EXPECT_TRUE(r.store.inspect(0).valid);
}

// Power cut at every byte of a store(): the last good calibration survives, and load() returns
// exactly the old or (only if the write completed) the new blob -- never anything else.
TEST(ParamStore, PowerCutAtEveryProgrammedByteNeverLosesOrCorrupts) {
  const auto a = blob(1, 77);
  const auto b = blob(2, 90);
  const auto c = blob(3, 101);
  // Total bytes programmed by one store of c: header 20 + payload.
  const std::size_t total = FlashParamStore::kHeaderSize + c.size();
  for (int prior = 1; prior <= 2; ++prior) {  // one or both slots already valid
    for (std::size_t cut = 0; cut <= total; ++cut) {
      Rig r;
      ASSERT_EQ(r.store.store(a), hal::Status::kOk);
      if (prior == 2) {
        ASSERT_EQ(r.store.store(b), hal::Status::kOk);
      }
      const auto& last_good = prior == 2 ? b : a;
      r.flash.cut_after_program_bytes(cut);
      const hal::Status w = r.store.store(c);
      r.flash.restore_power();
      hal::Status st;
      std::uint32_t seq = 0;
      const auto got = r.load(st, seq);
      ASSERT_EQ(st, hal::Status::kOk) << "cut " << cut;
      if (w == hal::Status::kOk) {
        EXPECT_EQ(cut, total);  // only an uninterrupted write reports success
        EXPECT_EQ(got, c);
      } else {
        EXPECT_EQ(w, hal::Status::kPowerLoss);
        EXPECT_EQ(got, last_good) << "cut " << cut;
      }
      // After the reboot the store works again and the next blob wins.
      ASSERT_EQ(r.store.store(blob(4, 33)), hal::Status::kOk);
      EXPECT_EQ(r.load(st, seq), blob(4, 33));
    }
  }
}

TEST(ParamStore, PowerCutDuringEraseNeverLosesTheLastGood) {
  const auto a = blob(1, 60);
  const auto b = blob(2, 100);  // header + payload span both sectors of a slot
  for (std::size_t erase_ok = 0; erase_ok < 2; ++erase_ok) {
    for (std::size_t bytes = 0; bytes <= kSector; ++bytes) {
      Rig r;
      ASSERT_EQ(r.store.store(a), hal::Status::kOk);
      ASSERT_EQ(r.store.store(b), hal::Status::kOk);  // slot 1 newest, slot 0 holds a
      r.flash.cut_during_erase(erase_ok, bytes);      // the next store erases slot 0
      EXPECT_EQ(r.store.store(blob(3, 20)), hal::Status::kPowerLoss);
      r.flash.restore_power();
      hal::Status st;
      std::uint32_t seq = 0;
      EXPECT_EQ(r.load(st, seq), b);
      EXPECT_EQ(seq, 2u);
    }
  }
}

TEST(ParamStore, NoHeapAllocation) {
  Rig r;
  const auto b = blob(5, 100);
  std::array<std::uint8_t, kSlot> out{};
  std::size_t len = 0;
  std::uint32_t seq = 0;
  magvec::test::AllocationScope scope;
  for (int i = 0; i < 10; ++i) {
    ASSERT_EQ(r.store.store(b), hal::Status::kOk);
    ASSERT_EQ(r.store.load(out, len, seq), hal::Status::kOk);
  }
  EXPECT_EQ(scope.count(), 0u);
}

}  // namespace
}  // namespace magvec::drivers
