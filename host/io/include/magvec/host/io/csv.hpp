// CSV recordings (docs/conventions.md#file-formats): a streaming reader with columns by header name
// and a writer that replaces its output atomically.
//
// Reader rules
// - The first line that is neither blank nor a `#` comment is the header; `#` comment lines and
// blank
//   lines are skipped everywhere (comments before the header are kept, see comments()).
// - Fields are separated by commas; surrounding spaces/tabs are trimmed; a field may be
// double-quoted
//   ("" inside quotes is a literal quote); a quoted field may not span lines. CRLF line ends are
//   fine.
// - A column name is `<quantity>_<unit>`. Known quantities and accepted units:
//     t (s); hx, hy, hz, F (nT, uT -> x1000); alpha, beta, gamma, yaw, pitch, roll, theta (deg,
//     rad); qw, qx, qy, qz (no unit); temperature (degC; C is read as degC too).
//   A known quantity with another unit (hx_G, t_ms) or without a unit (hx) is an error. Any other
//   column (hx_true_nT, flags, ...) is ignored but its values remain available through value().
// - Required: t_s (unless CsvReaderOptions::require_time is false: then NaN), hx_nT, hy_nT,
//   hz_nT. Optional: F_nT; attitude as alpha/beta/gamma (Li: R_bn =
//   Ry(gamma) Rx(beta) Rz(alpha)), yaw/pitch/roll (aerospace NED/FRD) or qw..qz (rotates body
//   vectors into ENU; R_bn = R(q)^T, must be unit within 1e-3); theta; temperature_degC (the
//   sensor temperature, for calibrations with a temperature model). A partial or a second
//   attitude set is an error. A file without a temperature column reads as before (no
//   temperature in any record).
// - Numbers: anything std::from_chars accepts, an optional leading '+', and nan (any case, optional
//   sign). inf and empty fields are malformed. `nan` in any of hx/hy/hz marks a dropout (m
//   all-NaN); nan in F, theta or any attitude column means "not available" for that row; t_s must
//   be finite. A value that is no longer finite once scaled to nT / deg (1e306 uT) is an error, and
//   so is a temperature outside kTemperatureMin_degC .. kTemperatureMax_degC.
// - A UTF-8 byte-order mark at the start of the file is skipped.
// - Every row must have exactly as many fields as the header.
// - Errors throw CsvError naming file, line and column.
// Memory: one line at a time; after the first rows, next() does not allocate.
#pragma once

#include <cstdint>
#include <fstream>
#include <memory>
#include <optional>
#include <span>
#include <stdexcept>
#include <string>
#include <string_view>
#include <vector>

#include "magvec/core/types.hpp"

namespace magvec::host::io {

class CsvError : public std::runtime_error {
 public:
  // line 0: not tied to a line (e.g. cannot open); column empty: the whole line.
  CsvError(const std::string& file, std::uint64_t line, const std::string& column,
           const std::string& message);
  const std::string& file() const noexcept { return file_; }
  std::uint64_t line() const noexcept { return line_; }
  const std::string& column() const noexcept { return column_; }

 private:
  std::string file_;
  std::uint64_t line_;
  std::string column_;
};

enum class AttitudeColumns : std::uint8_t { kNone, kLi, kYawPitchRoll, kQuaternion };

struct CsvRecord {
  std::uint64_t line = 0;  // 1-based line number in the file
  double t_s = 0.0;
  core::Vec3<double> m_nT = core::Vec3<double>::Zero();  // all-NaN on a dropout
  bool dropout = false;
  std::optional<double> f_nT;  // per-row F, or CsvReaderOptions::f_nT
  std::optional<core::Mat3<double>>
      r_bn;  // attitude (n -> body), when the file has one and the row is not nan
  std::optional<double> theta_deg;
  std::optional<double> temperature_degC;  // sensor temperature, when the file has one (not nan)
};

// Plausible sensor temperatures: a value outside is a broken column, never a reading.
inline constexpr double kTemperatureMin_degC = -273.15;
inline constexpr double kTemperatureMax_degC = 1000.0;

struct CsvReaderOptions {
  // Scalar reference for every row when the file has no F column ("one value by option").
  std::optional<double> f_nT;
  // true: f_nT replaces the file's F column too (a model reference the user prefers to it).
  bool f_replaces_column = false;
  // false: a file without t_s is accepted (methods that do not use time); t_s is then NaN.
  bool require_time = true;
};

class CsvReader {
 public:
  // Opens the file and parses the header. Throws CsvError.
  explicit CsvReader(const std::string& path, CsvReaderOptions options = {});
  ~CsvReader();
  CsvReader(const CsvReader&) = delete;
  CsvReader& operator=(const CsvReader&) = delete;

  // Reads the next data row. Returns false at the end of the file. Throws CsvError.
  bool next(CsvRecord* out);

  const std::string& path() const noexcept { return path_; }
  const std::vector<std::string>& columns() const noexcept { return names_; }
  const std::vector<std::string>& comments() const noexcept {
    return comments_;
  }  // before header, '#' stripped
  AttitudeColumns attitude_columns() const noexcept { return attitude_; }
  bool has_f() const noexcept { return col_f_.has_value(); }
  bool has_theta() const noexcept { return col_theta_.has_value(); }
  bool has_temperature() const noexcept { return col_temperature_.has_value(); }
  bool has_time() const noexcept { return has_time_; }
  std::uint64_t line() const noexcept { return line_no_; }

  // Index of a column by exact header name.
  std::optional<std::size_t> column_index(std::string_view name) const noexcept;
  // Numeric value of a column of the current row (after a successful next()); nan allowed. Throws
  // CsvError on a malformed number and std::out_of_range on a bad index.
  double value(std::size_t column) const;
  // Raw text of a column of the current row.
  std::string_view text(std::size_t column) const;

 private:
  struct Column {
    std::size_t index;
    double scale;
  };
  bool read_line();  // next non-blank, non-comment line into line_; false at EOF
  void split();      // line_ -> fields_
  void parse_header();
  double number(const Column& c) const;
  double number_at(std::size_t index, double scale) const;
  [[noreturn]] void fail(std::size_t column, const std::string& message) const;

  std::string path_;
  CsvReaderOptions options_;
  std::unique_ptr<char[]> buffer_;
  std::ifstream in_;
  std::string line_;
  std::uint64_t line_no_ = 0;
  std::vector<std::string_view> fields_;
  std::vector<std::string> names_;
  std::vector<std::string> comments_;
  Column col_t_{}, col_hx_{}, col_hy_{}, col_hz_{};
  std::optional<Column> col_f_, col_theta_, col_temperature_;
  AttitudeColumns attitude_ = AttitudeColumns::kNone;
  Column col_att_[4]{};
  bool have_row_ = false;
  bool has_time_ = false;
};

// Formats a double with the shortest representation that reads back to the same value; "nan" for
// NaN. Throws std::domain_error for +-inf (the reader rejects it).
std::string format_double(double v);

// A file that appears at its final path only when complete: written to a temporary file in the same
// directory, then flushed, fsync'ed, renamed over the target and the directory fsync'ed. If
// commit() is never called (an exception, a crash) the target is untouched and the temporary file
// is removed (or, after a crash, left as <path>.tmp.<pid>.<n>). Throws std::system_error on I/O
// errors.
class AtomicFile {
 public:
  explicit AtomicFile(std::string path);
  ~AtomicFile();
  AtomicFile(const AtomicFile&) = delete;
  AtomicFile& operator=(const AtomicFile&) = delete;

  void write(std::string_view data);
  void commit();
  const std::string& path() const noexcept { return path_; }
  // The temporary files of `path` start with this (in the same directory; a pid and a counter
  // follow): a write killed before commit() leaves one, which is never the file at `path`.
  static std::string temporary_prefix(const std::string& path) { return path + ".tmp."; }

 private:
  void flush_buffer();
  std::string path_;
  std::string tmp_path_;
  int fd_ = -1;
  std::string buffer_;
  bool committed_ = false;
};

// CSV writer with a fixed set of columns, shortest round-trip (full precision) numbers and "nan".
class CsvWriter {
 public:
  // comment_lines are written first, each prefixed with "# ".
  CsvWriter(std::string path, std::vector<std::string> columns,
            const std::vector<std::string>& comment_lines = {});
  // Throws std::invalid_argument if values.size() != number of columns, std::domain_error for inf.
  void write_row(std::span<const double> values);
  // Makes the file appear at its path (atomically). Without it nothing is written.
  void commit();
  std::size_t column_count() const noexcept { return columns_.size(); }
  std::uint64_t rows() const noexcept { return rows_; }

 private:
  AtomicFile file_;
  std::vector<std::string> columns_;
  std::string row_;
  std::uint64_t rows_ = 0;
};

// Writes samples as a recording the reader reads back: t_s, hx_nT, hy_nT, hz_nT, then F_nT when
// any record has a reference, alpha_deg, beta_deg, gamma_deg (Li) when any has an attitude,
// theta_deg when any has a turntable angle, temperature_degC when any has a temperature; a record
// without such a value gets nan there (a dropout nan in hx..hz). Atomic like CsvWriter. Throws
// std::domain_error for an infinite value and std::invalid_argument for a temperature outside
// kTemperatureMin_degC .. kTemperatureMax_degC (the reader would refuse the file).
void write_recording_csv(const std::string& path, std::span<const CsvRecord> records,
                         const std::vector<std::string>& comment_lines = {});

}  // namespace magvec::host::io
