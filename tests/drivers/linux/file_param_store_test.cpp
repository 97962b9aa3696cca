// FileParamStore (drivers/linux/file_param_store.hpp): round trip, the FlashParamStore record
// format on disk, a crash simulated at every step of store() (left-over temp files, truncated and
// bit-flipped records), corrupt files preserved instead of overwritten, OS errors named.
#include "magvec/drivers/linux/file_param_store.hpp"

#include <sys/stat.h>
#include <sys/wait.h>
#include <unistd.h>

#include <gtest/gtest.h>

#include <array>
#include <cerrno>
#include <filesystem>
#include <fstream>
#include <iterator>
#include <string>
#include <vector>

#include "magvec/drivers/param_record.hpp"

namespace {

using namespace magvec;
namespace fs = std::filesystem;
using drivers::FileParamStore;
using drivers::OsError;
using Bytes = std::vector<std::uint8_t>;

constexpr std::size_t kMax = 256;

Bytes blob(std::uint8_t seed, std::size_t n) {
  Bytes b(n);
  for (std::size_t i = 0; i < n; ++i)
    b[i] = static_cast<std::uint8_t>(seed * 31u + i * 7u);
  return b;
}

Bytes read_file(const fs::path& p) {
  std::ifstream f(p, std::ios::binary);
  return Bytes(std::istreambuf_iterator<char>(f), std::istreambuf_iterator<char>());
}
void write_file(const fs::path& p, const Bytes& b) {
  std::ofstream f(p, std::ios::binary | std::ios::trunc);
  f.write(reinterpret_cast<const char*>(b.data()), static_cast<std::streamsize>(b.size()));
}

struct Loaded {
  hal::Status status{hal::Status::kBusError};
  Bytes data;
  std::uint32_t sequence{0};
};
Loaded load(FileParamStore& s, bool previous = false) {
  Loaded l;
  std::array<std::uint8_t, kMax> out{};
  std::size_t n = 0;
  l.status = previous ? s.load_previous(out, n, l.sequence) : s.load(out, n, l.sequence);
  l.data.assign(out.begin(), out.begin() + static_cast<std::ptrdiff_t>(n));
  return l;
}

class FileParamStoreTest : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string tmpl = (fs::temp_directory_path() / "magvec_ps_XXXXXX").string();
    ASSERT_NE(::mkdtemp(tmpl.data()), nullptr);
    dir_ = tmpl;
    path_ = dir_ / "cal.bin";
  }
  void TearDown() override {
    ::chmod(dir_.c_str(), 0700);
    fs::remove_all(dir_);
  }
  std::unique_ptr<FileParamStore> open() {
    OsError err;
    auto s = FileParamStore::open(path_.string(), kMax, &err);
    EXPECT_NE(s, nullptr) << err.message;
    return s;
  }

  fs::path dir_;
  fs::path path_;
};

TEST_F(FileParamStoreTest, RoundTripKeepsThePreviousVersion) {
  auto s = open();
  ASSERT_NE(s, nullptr);
  EXPECT_EQ(load(*s).status, hal::Status::kNotFound);
  EXPECT_EQ(load(*s, true).status, hal::Status::kNotFound);
  ASSERT_EQ(s->store(blob(1, 100)), hal::Status::kOk) << s->last_error().message;
  Loaded l = load(*s);
  ASSERT_EQ(l.status, hal::Status::kOk);
  EXPECT_EQ(l.data, blob(1, 100));
  EXPECT_EQ(l.sequence, 1u);
  ASSERT_EQ(s->store(blob(2, kMax)), hal::Status::kOk);
  l = load(*s);
  EXPECT_EQ(l.data, blob(2, kMax));
  EXPECT_EQ(l.sequence, 2u);
  l = load(*s, true);
  ASSERT_EQ(l.status, hal::Status::kOk);
  EXPECT_EQ(l.data, blob(1, 100));
  EXPECT_EQ(l.sequence, 1u);
  ASSERT_EQ(s->store({}), hal::Status::kOk);  // an empty blob is a valid blob
  l = load(*s);
  EXPECT_EQ(l.status, hal::Status::kOk);
  EXPECT_TRUE(l.data.empty());
  EXPECT_EQ(l.sequence, 3u);
  EXPECT_FALSE(fs::exists(path_.string() + ".tmp"));
  EXPECT_FALSE(fs::exists(path_.string() + ".prev.tmp"));

  // A new instance (a restart) sees the same.
  auto again = open();
  EXPECT_EQ(load(*again).sequence, 3u);
  EXPECT_EQ(load(*again, true).data, blob(2, kMax));
}

TEST_F(FileParamStoreTest, SizeLimitsAreEnforced) {
  auto s = open();
  EXPECT_EQ(s->max_blob_size(), kMax);
  EXPECT_EQ(s->store(blob(1, kMax + 1)), hal::Status::kOverflow);
  EXPECT_FALSE(fs::exists(path_));
  ASSERT_EQ(s->store(blob(1, 10)), hal::Status::kOk);
  std::array<std::uint8_t, 9> small{};
  std::size_t n = 7;
  std::uint32_t seq = 0;
  EXPECT_EQ(s->load(small, n, seq), hal::Status::kOverflow);
  EXPECT_EQ(n, 0u);
}

TEST_F(FileParamStoreTest, FileHoldsTheFlashParamStoreRecord) {
  auto s = open();
  ASSERT_EQ(s->store(blob(5, 40)), hal::Status::kOk);
  const Bytes file = read_file(path_);
  ASSERT_EQ(file.size(), drivers::kParamRecordHeaderSize + 40);
  EXPECT_EQ(Bytes(file.begin(), file.begin() + 4), (Bytes{'M', 'V', 'P', 'S'}));
  const auto h = drivers::check_param_record(file, kMax);
  EXPECT_TRUE(h.valid);
  EXPECT_EQ(h.sequence, 1u);
  EXPECT_EQ(h.length, 40u);
}

TEST_F(FileParamStoreTest, CrashLeavingAPartialTempFileKeepsTheOldBlob) {
  auto s = open();
  ASSERT_EQ(s->store(blob(1, 64)), hal::Status::kOk);
  // Crash during step 1 of the next store: a partial new record in cal.bin.tmp (every length).
  Bytes next(drivers::kParamRecordHeaderSize + 64);
  drivers::encode_param_record_header(std::span<std::uint8_t, drivers::kParamRecordHeaderSize>(
                                          next.data(), drivers::kParamRecordHeaderSize),
                                      2, blob(2, 64));
  const Bytes payload = blob(2, 64);
  std::copy(payload.begin(), payload.end(), next.begin() + drivers::kParamRecordHeaderSize);
  for (std::size_t len = 0; len <= next.size(); len += 7) {
    write_file(path_.string() + ".tmp",
               Bytes(next.begin(), next.begin() + static_cast<std::ptrdiff_t>(len)));
    const Loaded l = load(*s);
    ASSERT_EQ(l.status, hal::Status::kOk);
    EXPECT_EQ(l.data, blob(1, 64));
    EXPECT_EQ(l.sequence, 1u);
  }
  // The next store simply replaces the left-over temp file.
  ASSERT_EQ(s->store(blob(3, 64)), hal::Status::kOk);
  EXPECT_EQ(load(*s).data, blob(3, 64));
  EXPECT_EQ(load(*s, true).data, blob(1, 64));
}

TEST_F(FileParamStoreTest, CrashBetweenPrevAndMainRenameKeepsTheOldBlob) {
  auto s = open();
  ASSERT_EQ(s->store(blob(1, 30)), hal::Status::kOk);
  ASSERT_EQ(s->store(blob(2, 30)), hal::Status::kOk);
  // State after step 2 of a third store: .prev already holds the current record, a partial
  // .prev.tmp and the complete new .tmp are lying around, the main rename never happened.
  fs::copy_file(path_, path_.string() + ".prev", fs::copy_options::overwrite_existing);
  write_file(path_.string() + ".prev.tmp", Bytes{'M', 'V'});
  const Loaded l = load(*s);
  ASSERT_EQ(l.status, hal::Status::kOk);
  EXPECT_EQ(l.data, blob(2, 30));
  ASSERT_EQ(s->store(blob(3, 30)), hal::Status::kOk);
  EXPECT_EQ(load(*s).data, blob(3, 30));
  EXPECT_EQ(load(*s).sequence, 3u);
}

TEST_F(FileParamStoreTest, MissingMainFileFallsBackToPrevious) {
  auto s = open();
  ASSERT_EQ(s->store(blob(1, 30)), hal::Status::kOk);
  ASSERT_EQ(s->store(blob(2, 30)), hal::Status::kOk);
  fs::remove(path_);
  const Loaded l = load(*s);
  ASSERT_EQ(l.status, hal::Status::kOk);
  EXPECT_EQ(l.data, blob(1, 30));
  // The next store continues the sequence after the previous record.
  ASSERT_EQ(s->store(blob(3, 30)), hal::Status::kOk);
  EXPECT_EQ(load(*s).sequence, 2u);
}

TEST_F(FileParamStoreTest, EveryTruncationAndBitFlipIsCorruptNeverGarbage) {
  auto s = open();
  ASSERT_EQ(s->store(blob(1, 48)), hal::Status::kOk);
  ASSERT_EQ(s->store(blob(2, 48)), hal::Status::kOk);
  const Bytes good = read_file(path_);
  for (std::size_t len = 0; len < good.size(); ++len) {
    write_file(path_, Bytes(good.begin(), good.begin() + static_cast<std::ptrdiff_t>(len)));
    const Loaded l = load(*s);
    ASSERT_EQ(l.status, hal::Status::kCorrupt) << "truncated to " << len;
    EXPECT_TRUE(l.data.empty());
  }
  Bytes longer = good;
  longer.push_back(0);
  write_file(path_, longer);
  EXPECT_EQ(load(*s).status, hal::Status::kCorrupt);
  for (std::size_t i = 0; i < good.size(); ++i) {
    for (int bit = 0; bit < 8; bit += 3) {
      Bytes bad = good;
      bad[i] = static_cast<std::uint8_t>(bad[i] ^ (1u << bit));
      write_file(path_, bad);
      const Loaded l = load(*s);
      ASSERT_EQ(l.status, hal::Status::kCorrupt) << "byte " << i << " bit " << bit;
      EXPECT_TRUE(l.data.empty());
    }
  }
  // The message names the file and the reason.
  EXPECT_NE(s->last_error().message.find(path_.string()), std::string::npos);
  EXPECT_NE(s->last_error().message.find("CRC"), std::string::npos) << s->last_error().message;
  write_file(path_, Bytes(good.begin(), good.begin() + 30));
  EXPECT_EQ(load(*s).status, hal::Status::kCorrupt);
  EXPECT_NE(s->last_error().message.find("truncated"), std::string::npos)
      << s->last_error().message;
  // The previous version is still there, explicitly.
  const Loaded prev = load(*s, true);
  ASSERT_EQ(prev.status, hal::Status::kOk);
  EXPECT_EQ(prev.data, blob(1, 48));
}

TEST_F(FileParamStoreTest, CorruptFileIsPreservedNotOverwritten) {
  auto s = open();
  ASSERT_EQ(s->store(blob(1, 20)), hal::Status::kOk);
  ASSERT_EQ(s->store(blob(2, 20)), hal::Status::kOk);
  Bytes bad = read_file(path_);
  bad[25] ^= 0x10;
  write_file(path_, bad);
  ASSERT_EQ(load(*s).status, hal::Status::kCorrupt);

  ASSERT_EQ(s->store(blob(3, 20)), hal::Status::kOk) << s->last_error().message;
  const fs::path kept = path_.string() + ".corrupt-1";
  EXPECT_EQ(s->preserved_corrupt_path(), kept.string());
  EXPECT_EQ(read_file(kept), bad);
  Loaded l = load(*s);
  EXPECT_EQ(l.data, blob(3, 20));
  EXPECT_EQ(l.sequence, 2u);                    // continues after the valid .prev (sequence 1)
  EXPECT_EQ(load(*s, true).data, blob(1, 20));  // the corrupt record never became .prev

  write_file(path_, Bytes{1, 2, 3});
  ASSERT_EQ(s->store(blob(4, 20)), hal::Status::kOk);
  EXPECT_EQ(read_file(path_.string() + ".corrupt-2"), (Bytes{1, 2, 3}));
  EXPECT_EQ(read_file(kept), bad);
  EXPECT_EQ(load(*s).data, blob(4, 20));
}

TEST_F(FileParamStoreTest, ConcurrentWritersAreSerialised) {
  constexpr int kWriters = 3;
  constexpr int kStores = 10;
  std::vector<pid_t> children;
  for (int w = 0; w < kWriters; ++w) {
    const pid_t pid = ::fork();
    if (pid == 0) {
      OsError err;
      auto s = FileParamStore::open(path_.string(), kMax, &err);
      if (s == nullptr) ::_exit(1);
      for (int i = 0; i < kStores; ++i)
        if (s->store(blob(static_cast<std::uint8_t>(w), 100)) != hal::Status::kOk) ::_exit(2);
      ::_exit(0);
    }
    children.push_back(pid);
  }
  for (const pid_t pid : children) {
    int status = 0;
    ::waitpid(pid, &status, 0);
    EXPECT_TRUE(WIFEXITED(status) && WEXITSTATUS(status) == 0) << "writer status " << status;
  }
  auto s = open();
  const Loaded l = load(*s);
  ASSERT_EQ(l.status, hal::Status::kOk);
  EXPECT_EQ(l.sequence, static_cast<std::uint32_t>(kWriters * kStores));  // no store lost
  EXPECT_EQ(load(*s, true).sequence, l.sequence - 1);
}

TEST(FileParamStoreErrors, BadPathsAndSizesGiveClearErrors) {
  OsError err;
  EXPECT_EQ(FileParamStore::open("/nonexistent-magvec-dir/cal.bin", 64, &err), nullptr);
  EXPECT_EQ(err.error_number, ENOENT);
  EXPECT_NE(err.message.find("param file /nonexistent-magvec-dir/cal.bin: open directory "
                             "/nonexistent-magvec-dir: No such file or directory (errno 2)"),
            std::string::npos)
      << err.message;
  err = {};
  EXPECT_EQ(FileParamStore::open("/tmp/cal.bin", 0, &err), nullptr);
  EXPECT_EQ(err.error_number, EINVAL);
  EXPECT_NE(err.message.find("max_blob"), std::string::npos) << err.message;
}

// Runs `body` as an unprivileged user (root bypasses permission checks) in a child process;
// returns the child's exit status (0 = all checks passed, else the number of the failed check).
template <typename Body>
int run_unprivileged(Body body) {
  const pid_t pid = ::fork();
  if (pid == 0) {
    if (::getuid() == 0 && (::setgid(65534) != 0 || ::setuid(65534) != 0)) ::_exit(100);
    ::_exit(body());
  }
  int status = 0;
  ::waitpid(pid, &status, 0);
  return WIFEXITED(status) ? WEXITSTATUS(status) : 200;
}

TEST_F(FileParamStoreTest, PermissionErrorsNameFileAndErrno) {
  {
    auto s = open();
    ASSERT_EQ(s->store(blob(1, 20)), hal::Status::kOk);
  }
  // Directory readable but not writable by the user: load works, store fails with a clear error
  // and leaves the stored blob intact.
  ASSERT_EQ(::chmod(dir_.c_str(), 0755), 0);
  ASSERT_EQ(::chmod(path_.c_str(), 0644), 0);
  const std::string path = path_.string();
  int rc = run_unprivileged([&] {
    OsError err;
    auto s = FileParamStore::open(path, kMax, &err);
    if (s == nullptr) return 1;
    if (load(*s).status != hal::Status::kOk) return 2;
    if (s->store(blob(2, 20)) != hal::Status::kBusError) return 3;
    const std::string& m = s->last_error().message;
    if (m.find(path + ".tmp") == std::string::npos) return 4;
    if (m.find("Permission denied (errno 13)") == std::string::npos) return 5;
    if (s->last_error().error_number != EACCES) return 6;
    return 0;
  });
  EXPECT_EQ(rc, 0) << "check " << rc << " failed";
  // File not readable: open fails naming the file.
  ASSERT_EQ(::chmod(path_.c_str(), 0600), 0);
  rc = run_unprivileged([&] {
    OsError err;
    if (FileParamStore::open(path, kMax, &err) != nullptr) return 1;
    if (err.message != "param file " + path + ": open: Permission denied (errno 13)") return 2;
    return 0;
  });
  EXPECT_EQ(rc, 0) << "check " << rc << " failed";
  auto s = open();
  EXPECT_EQ(load(*s).data, blob(1, 20));
}

}  // namespace
