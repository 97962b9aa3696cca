// CSV writer and atomic file replacement (temp file + fsync + rename + directory fsync), so a crash
// never leaves a half-written output at the target path.
#include <fcntl.h>
#include <unistd.h>

#include <atomic>
#include <cerrno>
#include <charconv>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <limits>
#include <stdexcept>
#include <system_error>

#include "magvec/core/frames.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host::io {
namespace {

constexpr std::size_t kFlushThreshold = 1 << 20;

[[noreturn]] void throw_errno(const std::string& what) {
  throw std::system_error(errno, std::generic_category(), what);
}

std::string directory_of(const std::string& path) {
  const std::size_t slash = path.rfind('/');
  if (slash == std::string::npos) return ".";
  if (slash == 0) return "/";
  return path.substr(0, slash);
}

void append_double(std::string* out, double v) {
  if (std::isnan(v)) {
    out->append("nan");
    return;
  }
  if (!std::isfinite(v)) throw std::domain_error("CSV writer: cannot write a non-finite value");
  char buf[32];
  const auto [ptr, ec] = std::to_chars(buf, buf + sizeof(buf), v);  // shortest round trip
  if (ec != std::errc()) throw std::domain_error("CSV writer: cannot format a number");
  out->append(buf, ptr);
}

}  // namespace

std::string format_double(double v) {
  std::string s;
  append_double(&s, v);
  return s;
}

AtomicFile::AtomicFile(std::string path) : path_(std::move(path)) {
  // O_EXCL on a fresh name (pid + counter) in the target's directory: same file system for
  // rename(), and mode 0666 filtered by the umask like any other output file (mkstemp would force
  // 0600).
  static std::atomic<unsigned> counter{0};
  for (int attempt = 0; attempt < 100 && fd_ < 0; ++attempt) {
    tmp_path_ = temporary_prefix(path_) + std::to_string(::getpid()) + "." +
                std::to_string(counter.fetch_add(1));
    fd_ = ::open(tmp_path_.c_str(), O_WRONLY | O_CREAT | O_EXCL | O_CLOEXEC, 0666);
    if (fd_ < 0 && errno != EEXIST) break;
  }
  if (fd_ < 0) {
    tmp_path_.clear();
    throw_errno("cannot create a temporary file for " + path_);
  }
  buffer_.reserve(kFlushThreshold + 4096);
}

AtomicFile::~AtomicFile() {
  if (!committed_) {
    if (fd_ >= 0) ::close(fd_);
    if (!tmp_path_.empty()) ::unlink(tmp_path_.c_str());
  }
}

void AtomicFile::flush_buffer() {
  const char* p = buffer_.data();
  std::size_t left = buffer_.size();
  while (left > 0) {
    const ssize_t n = ::write(fd_, p, left);
    if (n < 0) {
      if (errno == EINTR) continue;
      throw_errno("cannot write " + tmp_path_);
    }
    p += n;
    left -= static_cast<std::size_t>(n);
  }
  buffer_.clear();
}

void AtomicFile::write(std::string_view data) {
  if (committed_ || fd_ < 0) throw std::logic_error("AtomicFile::write after commit: " + path_);
  buffer_.append(data);
  if (buffer_.size() >= kFlushThreshold) flush_buffer();
}

void AtomicFile::commit() {
  if (committed_) return;
  flush_buffer();
  if (::fsync(fd_) != 0) throw_errno("cannot fsync " + tmp_path_);
  if (::close(fd_) != 0) {
    fd_ = -1;
    throw_errno("cannot close " + tmp_path_);
  }
  fd_ = -1;
  if (::rename(tmp_path_.c_str(), path_.c_str()) != 0)
    throw_errno("cannot rename " + tmp_path_ + " to " + path_);
  committed_ = true;
  // Make the rename itself durable.
  const int dir = ::open(directory_of(path_).c_str(), O_RDONLY | O_DIRECTORY);
  if (dir >= 0) {
    (void)::fsync(dir);
    ::close(dir);
  }
}

CsvWriter::CsvWriter(std::string path, std::vector<std::string> columns,
                     const std::vector<std::string>& comment_lines)
    : file_(std::move(path)), columns_(std::move(columns)) {
  if (columns_.empty()) throw std::invalid_argument("CSV writer: no columns");
  std::string head;
  for (const std::string& c : comment_lines) {
    head += "# ";
    head += c;
    head += '\n';
  }
  for (std::size_t i = 0; i < columns_.size(); ++i) {
    if (columns_[i].find_first_of(",\"\n\r") != std::string::npos) {
      throw std::invalid_argument("CSV writer: column name needs no quoting: " + columns_[i]);
    }
    if (i > 0) head += ',';
    head += columns_[i];
  }
  head += '\n';
  file_.write(head);
  row_.reserve(32 * columns_.size());
}

void CsvWriter::write_row(std::span<const double> values) {
  if (values.size() != columns_.size()) {
    throw std::invalid_argument("CSV writer: " + std::to_string(values.size()) + " values for " +
                                std::to_string(columns_.size()) + " columns");
  }
  row_.clear();
  for (std::size_t i = 0; i < values.size(); ++i) {
    if (i > 0) row_ += ',';
    append_double(&row_, values[i]);
  }
  row_ += '\n';
  file_.write(row_);
  ++rows_;
}

void CsvWriter::commit() {
  file_.commit();
}

void write_recording_csv(const std::string& path, std::span<const CsvRecord> records,
                         const std::vector<std::string>& comment_lines) {
  bool any_f = false, any_attitude = false, any_theta = false, any_temperature = false;
  for (const CsvRecord& r : records) {
    any_f = any_f || r.f_nT.has_value();
    any_attitude = any_attitude || r.r_bn.has_value();
    any_theta = any_theta || r.theta_deg.has_value();
    if (r.temperature_degC) {
      any_temperature = true;
      const double t = *r.temperature_degC;
      if (!(t >= kTemperatureMin_degC && t <= kTemperatureMax_degC)) {
        throw std::invalid_argument("CSV writer: temperature " + format_double(t) +
                                    " degC of the record at t = " + format_double(r.t_s) +
                                    " s is not a sensor temperature");
      }
    }
  }
  std::vector<std::string> columns = {"t_s", "hx_nT", "hy_nT", "hz_nT"};
  if (any_f) columns.emplace_back("F_nT");
  if (any_attitude) columns.insert(columns.end(), {"alpha_deg", "beta_deg", "gamma_deg"});
  if (any_theta) columns.emplace_back("theta_deg");
  if (any_temperature) columns.emplace_back("temperature_degC");
  CsvWriter w(path, columns, comment_lines);
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  std::vector<double> row(columns.size());
  for (const CsvRecord& r : records) {
    std::size_t k = 0;
    row[k++] = r.t_s;
    for (int i = 0; i < 3; ++i)
      row[k++] = r.dropout ? kNaN : r.m_nT(i);
    if (any_f) row[k++] = r.f_nT.value_or(kNaN);
    if (any_attitude) {
      core::LiEuler<double> li{kNaN, kNaN, kNaN};
      if (r.r_bn) li = core::li_from_r_bn(*r.r_bn);
      row[k++] = core::rad_to_deg(li.alpha);
      row[k++] = core::rad_to_deg(li.beta);
      row[k++] = core::rad_to_deg(li.gamma);
    }
    if (any_theta) row[k++] = r.theta_deg.value_or(kNaN);
    if (any_temperature) row[k++] = r.temperature_degC.value_or(kNaN);
    w.write_row(row);
  }
  w.commit();
}

}  // namespace magvec::host::io
