// Linux transports: hal::ParamStore in a file, power-cut safe.
//
// Record format: exactly the FlashParamStore slot record (param_record.hpp: magic 'MVPS',
// version, header size, sequence, length, CRC-32 over header fields and payload), one record per
// file. Files next to `path`:
//   path            the current record
//   path.prev       the record before it (kept for revert and as a fallback when path is missing)
//   path.tmp        a new record being written (ignored by load)
//   path.corrupt-N  a corrupt `path` that store() moved aside (N = 1, 2, ... first unused)
// store(): write path.tmp + fsync; copy the valid current record to path.prev (via
// path.prev.tmp + fsync + rename); rename path.tmp -> path; fsync the directory; read back and
// verify. A power cut at any point leaves `path` holding the old or the new valid record (rename is
// atomic and the data was synced before it).
// load(): `path` valid -> it; `path` missing -> path.prev if valid, else kNotFound; `path` present
// but invalid (truncated, flipped bits, wrong magic) -> kCorrupt, deliberately NOT the older
// path.prev: a damaged calibration is reported, never silently replaced by an older one
// (load_previous() reads path.prev explicitly, e.g. for a revert). last_error() says why.
// A corrupt `path` is never overwritten: store() first renames it to path.corrupt-N.
// Concurrent store() calls of several processes are serialised by flock() on the directory.
#pragma once

#include <cstddef>
#include <cstdint>
#include <memory>
#include <span>
#include <string>
#include <vector>

#include "magvec/drivers/linux/linux_error.hpp"
#include "magvec/hal/param_store.hpp"

namespace magvec::drivers {

class FileParamStore final : public hal::ParamStore {
 public:
  static constexpr std::size_t kMaxBlobLimit = 16u << 20;  // sanity bound for max_blob

  // Checks that the directory of `path` exists (kept open for fsync) and that an existing
  // `path` is readable; nullptr and *err otherwise. max_blob in 1..kMaxBlobLimit.
  static std::unique_ptr<FileParamStore> open(const std::string& path, std::size_t max_blob,
                                              OsError* err);
  ~FileParamStore();
  FileParamStore(const FileParamStore&) = delete;
  FileParamStore& operator=(const FileParamStore&) = delete;

  // kOk, kNotFound, kCorrupt, kOverflow (out too small), kBusError (I/O error: last_error()).
  hal::Status load(std::span<std::uint8_t> out, std::size_t& length,
                   std::uint32_t& sequence) noexcept override;
  // kOk, kOverflow (blob > max_blob_size()), kBusError (I/O error), kCorrupt (read-back failed).
  hal::Status store(std::span<const std::uint8_t> blob) noexcept override;
  std::size_t max_blob_size() const noexcept override { return max_blob_; }

  // The record in path.prev (same statuses as load()).
  hal::Status load_previous(std::span<std::uint8_t> out, std::size_t& length,
                            std::uint32_t& sequence) noexcept;

  const std::string& path() const noexcept { return path_; }
  const std::string& previous_path() const noexcept { return prev_path_; }
  const OsError& last_error() const noexcept { return last_error_; }
  // Path of the last corrupt file store() moved aside (empty if none).
  const std::string& preserved_corrupt_path() const noexcept { return preserved_corrupt_; }

 private:
  FileParamStore(std::string path, int dir_fd, std::size_t max_blob);

  enum class FileState : std::uint8_t { kValid, kMissing, kInvalid, kIoError };
  struct FileInfo {
    FileState state{FileState::kMissing};
    std::uint32_t sequence{0};
    std::size_t length{0};  // payload bytes
    std::size_t size{0};    // record bytes in buffer_
  };
  // Reads the file into buffer_ and validates it; sets last_error_ on kInvalid/kIoError.
  FileInfo inspect(const std::string& file) noexcept;
  hal::Status copy_out(const FileInfo& info, std::span<std::uint8_t> out, std::size_t& length,
                       std::uint32_t& sequence) noexcept;
  bool write_file_synced(const std::string& file, std::span<const std::uint8_t> bytes) noexcept;
  bool sync_dir() noexcept;
  bool preserve_corrupt() noexcept;  // renames path_ to the first unused path.corrupt-N

  std::string path_;
  std::string name_;  // "param file <path>", for messages
  std::string tmp_path_;
  std::string prev_path_;
  std::string prev_tmp_path_;
  int dir_fd_{-1};
  std::size_t max_blob_{0};
  std::vector<std::uint8_t> buffer_;  // one record (header + max_blob), allocated at open
  std::vector<std::uint8_t> record_;  // the record being stored
  OsError last_error_;
  std::string preserved_corrupt_;
};

}  // namespace magvec::drivers
