// Linux transports: power-cut-safe file ParamStore; protocol and file names in
// file_param_store.hpp, record format in param_record.hpp (shared with FlashParamStore).
#include "magvec/drivers/linux/file_param_store.hpp"

#include <fcntl.h>
#include <sys/file.h>
#include <sys/stat.h>
#include <unistd.h>

#include <cerrno>
#include <cstdio>
#include <cstring>

#include "magvec/drivers/param_record.hpp"

namespace magvec::drivers {
namespace {

std::string directory_of(const std::string& path) {
  const std::size_t slash = path.find_last_of('/');
  if (slash == std::string::npos) return ".";
  if (slash == 0) return "/";
  return path.substr(0, slash);
}

}  // namespace

std::unique_ptr<FileParamStore> FileParamStore::open(const std::string& path, std::size_t max_blob,
                                                     OsError* err) {
  const std::string name = "param file " + path;
  if (path.empty() || path.back() == '/') {
    report_error(err, make_error(name, "configure", "the path must name a file", EINVAL));
    return nullptr;
  }
  if (max_blob == 0 || max_blob > kMaxBlobLimit) {
    report_error(
        err, make_error(name, "configure",
                        "max_blob must be 1.." + std::to_string(kMaxBlobLimit) + " bytes", EINVAL));
    return nullptr;
  }
  const std::string dir = directory_of(path);
  const int dir_fd = ::open(dir.c_str(), O_RDONLY | O_DIRECTORY | O_CLOEXEC);
  if (dir_fd < 0) {
    report_error(err, make_os_error(name, "open directory " + dir, errno));
    return nullptr;
  }
  const int fd = ::open(path.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0 && errno != ENOENT) {
    const int e = errno;
    ::close(dir_fd);
    report_error(err, make_os_error(name, "open", e));
    return nullptr;
  }
  if (fd >= 0) ::close(fd);
  return std::unique_ptr<FileParamStore>(new FileParamStore(path, dir_fd, max_blob));
}

FileParamStore::FileParamStore(std::string path, int dir_fd, std::size_t max_blob)
    : path_(std::move(path)),
      name_("param file " + path_),
      tmp_path_(path_ + ".tmp"),
      prev_path_(path_ + ".prev"),
      prev_tmp_path_(path_ + ".prev.tmp"),
      dir_fd_(dir_fd),
      max_blob_(max_blob),
      // One byte more than the largest record, so that an over-long file is detected.
      buffer_(kParamRecordHeaderSize + max_blob + 1),
      record_(kParamRecordHeaderSize + max_blob) {}

FileParamStore::~FileParamStore() {
  if (dir_fd_ >= 0) ::close(dir_fd_);
}

FileParamStore::FileInfo FileParamStore::inspect(const std::string& file) noexcept {
  FileInfo info;
  const int fd = ::open(file.c_str(), O_RDONLY | O_CLOEXEC);
  if (fd < 0) {
    if (errno == ENOENT) return info;  // kMissing
    assign_os_error(last_error_, "param file " + file, "open", errno);
    info.state = FileState::kIoError;
    return info;
  }
  std::size_t n = 0;
  while (n < buffer_.size()) {
    const ssize_t r = ::read(fd, buffer_.data() + n, buffer_.size() - n);
    if (r < 0 && errno == EINTR) continue;
    if (r < 0) {
      const int e = errno;
      ::close(fd);
      assign_os_error(last_error_, "param file " + file, "read", e);
      info.state = FileState::kIoError;
      return info;
    }
    if (r == 0) break;
    n += static_cast<std::size_t>(r);
  }
  ::close(fd);
  info.size = n;
  info.state = FileState::kInvalid;
  const std::span<const std::uint8_t> bytes(buffer_.data(), n);
  try {
    const std::string what = "param file " + file;
    if (n < kParamRecordHeaderSize) {
      assign_error(last_error_, what, "validate",
                   "truncated: " + std::to_string(n) + " bytes, shorter than the record header");
      return info;
    }
    const ParamRecordHeader h =
        parse_param_record_header(bytes.first<kParamRecordHeaderSize>(), max_blob_);
    if (!h.valid) {
      assign_error(last_error_, what, "validate",
                   h.length > max_blob_ ? "payload length larger than max_blob"
                                        : "not a magvec parameter record (magic/version)");
      return info;
    }
    if (n != kParamRecordHeaderSize + h.length) {
      assign_error(last_error_, what, "validate",
                   "size " + std::to_string(n) + " bytes, the record needs " +
                       std::to_string(kParamRecordHeaderSize + h.length) +
                       " (truncated or extended)");
      return info;
    }
    if (!check_param_record(bytes, max_blob_).valid) {
      assign_error(last_error_, what, "validate", "CRC-32 mismatch (corrupt contents)");
      return info;
    }
    info.state = FileState::kValid;
    info.sequence = h.sequence;
    info.length = h.length;
  } catch (...) {
    info.state = FileState::kIoError;  // out of memory while formatting the message
  }
  return info;
}

hal::Status FileParamStore::copy_out(const FileInfo& info, std::span<std::uint8_t> out,
                                     std::size_t& length, std::uint32_t& sequence) noexcept {
  switch (info.state) {
    case FileState::kMissing:
      return hal::Status::kNotFound;
    case FileState::kInvalid:
      return hal::Status::kCorrupt;
    case FileState::kIoError:
      return hal::Status::kBusError;
    case FileState::kValid:
      break;
  }
  if (info.length > out.size()) return hal::Status::kOverflow;
  if (info.length > 0) {
    std::memcpy(out.data(), buffer_.data() + kParamRecordHeaderSize, info.length);
  }
  length = info.length;
  sequence = info.sequence;
  return hal::Status::kOk;
}

hal::Status FileParamStore::load(std::span<std::uint8_t> out, std::size_t& length,
                                 std::uint32_t& sequence) noexcept {
  length = 0;
  const FileInfo cur = inspect(path_);
  // Only a missing current file falls back to the previous one; a damaged one is reported.
  if (cur.state != FileState::kMissing) return copy_out(cur, out, length, sequence);
  return copy_out(inspect(prev_path_), out, length, sequence);
}

hal::Status FileParamStore::load_previous(std::span<std::uint8_t> out, std::size_t& length,
                                          std::uint32_t& sequence) noexcept {
  length = 0;
  return copy_out(inspect(prev_path_), out, length, sequence);
}

bool FileParamStore::write_file_synced(const std::string& file,
                                       std::span<const std::uint8_t> bytes) noexcept {
  const char* op = "open";
  const int fd = ::open(file.c_str(), O_WRONLY | O_CREAT | O_TRUNC | O_CLOEXEC, 0644);
  if (fd >= 0) {
    std::size_t done = 0;
    while (done < bytes.size()) {
      const ssize_t r = ::write(fd, bytes.data() + done, bytes.size() - done);
      if (r < 0 && errno == EINTR) continue;
      if (r <= 0) break;
      done += static_cast<std::size_t>(r);
    }
    op = done < bytes.size() ? "write" : ::fsync(fd) < 0 ? "fsync" : nullptr;
    const int e = errno;
    if (::close(fd) < 0 && op == nullptr) op = "close";
    if (op == nullptr) return true;
    errno = e != 0 ? e : EIO;
    ::unlink(file.c_str());
  }
  assign_os_error(last_error_, "param file " + file, op, errno);
  return false;
}

bool FileParamStore::sync_dir() noexcept {
  if (::fsync(dir_fd_) == 0) return true;
  assign_os_error(last_error_, name_, "fsync directory", errno);
  return false;
}

bool FileParamStore::preserve_corrupt() noexcept {
  try {
    for (unsigned n = 1; n < 10000; ++n) {
      std::string target = path_ + ".corrupt-" + std::to_string(n);
      struct stat st {};
      if (::lstat(target.c_str(), &st) == 0) continue;
      if (::rename(path_.c_str(), target.c_str()) < 0) {
        assign_os_error(last_error_, name_, "rename to " + target, errno);
        return false;
      }
      preserved_corrupt_ = std::move(target);
      return true;
    }
    assign_error(last_error_, name_, "preserve corrupt file", "too many .corrupt-N files", EEXIST);
  } catch (...) {
  }
  return false;
}

hal::Status FileParamStore::store(std::span<const std::uint8_t> blob) noexcept {
  if (blob.size() > max_blob_) return hal::Status::kOverflow;
  // Serialises stores of several processes on the same directory (the temp names are shared).
  struct DirLock {
    int fd;
    ~DirLock() { ::flock(fd, LOCK_UN); }
  };
  while (::flock(dir_fd_, LOCK_EX) < 0) {
    if (errno != EINTR) {
      assign_os_error(last_error_, name_, "flock directory", errno);
      return hal::Status::kBusError;
    }
  }
  const DirLock lock{dir_fd_};
  FileInfo cur = inspect(path_);
  if (cur.state == FileState::kIoError) return hal::Status::kBusError;
  std::uint32_t sequence = 1;
  if (cur.state == FileState::kValid) {
    sequence = cur.sequence + 1;
  } else {
    const FileInfo prev = inspect(prev_path_);
    if (prev.state == FileState::kValid) sequence = prev.sequence + 1;
  }

  // 1. The new record, complete and on disk, under a name load() never reads.
  const std::size_t size = kParamRecordHeaderSize + blob.size();
  encode_param_record_header(
      std::span<std::uint8_t, kParamRecordHeaderSize>(record_.data(), kParamRecordHeaderSize),
      sequence, blob);
  if (!blob.empty()) {
    std::memcpy(record_.data() + kParamRecordHeaderSize, blob.data(), blob.size());
  }
  const std::span<const std::uint8_t> record(record_.data(), size);
  if (!write_file_synced(tmp_path_, record)) return hal::Status::kBusError;

  // 2. The current record becomes the previous one (atomically replacing the older .prev), or a
  // corrupt current file is moved aside, never overwritten.
  if (cur.state == FileState::kValid) {
    // buffer_ still holds the validated current record (nothing else was read since).
    if (!write_file_synced(prev_tmp_path_,
                           std::span<const std::uint8_t>(buffer_.data(), cur.size))) {
      ::unlink(tmp_path_.c_str());
      return hal::Status::kBusError;
    }
    if (::rename(prev_tmp_path_.c_str(), prev_path_.c_str()) < 0) {
      assign_os_error(last_error_, name_, "rename .prev.tmp to .prev", errno);
      ::unlink(tmp_path_.c_str());
      return hal::Status::kBusError;
    }
  } else if (cur.state == FileState::kInvalid) {
    if (!preserve_corrupt()) {
      ::unlink(tmp_path_.c_str());
      return hal::Status::kBusError;
    }
  }

  // 3. Commit: atomic replace, then make the directory entries durable.
  if (::rename(tmp_path_.c_str(), path_.c_str()) < 0) {
    assign_os_error(last_error_, name_, "rename .tmp to the parameter file", errno);
    ::unlink(tmp_path_.c_str());
    return hal::Status::kBusError;
  }
  if (!sync_dir()) return hal::Status::kBusError;

  // 4. Read back.
  const FileInfo check = inspect(path_);
  if (check.state != FileState::kValid || check.sequence != sequence ||
      check.length != blob.size() ||
      (!blob.empty() &&
       std::memcmp(buffer_.data() + kParamRecordHeaderSize, blob.data(), blob.size()) != 0)) {
    if (check.state == FileState::kIoError) return hal::Status::kBusError;
    assign_error(last_error_, name_, "verify", "read-back differs from the stored record", EIO);
    return hal::Status::kCorrupt;
  }
  return hal::Status::kOk;
}

}  // namespace magvec::drivers
