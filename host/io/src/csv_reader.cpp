// Streaming CSV reader for magvec recordings (docs/conventions.md#file-formats; rules in csv.hpp).
#include <charconv>
#include <cmath>
#include <iterator>
#include <limits>
#include <string>

#include "magvec/core/frames.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host::io {
namespace {

constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr std::size_t kReadBuffer = 1 << 20;

enum class Kind : std::uint8_t { kTime, kField, kAngle, kUnitless, kTemperature };

struct Quantity {
  std::string_view name;
  Kind kind;
};
constexpr Quantity kQuantities[] = {
    {"t", Kind::kTime},
    {"hx", Kind::kField},
    {"hy", Kind::kField},
    {"hz", Kind::kField},
    {"F", Kind::kField},
    {"alpha", Kind::kAngle},
    {"beta", Kind::kAngle},
    {"gamma", Kind::kAngle},
    {"yaw", Kind::kAngle},
    {"pitch", Kind::kAngle},
    {"roll", Kind::kAngle},
    {"theta", Kind::kAngle},
    {"qw", Kind::kUnitless},
    {"qx", Kind::kUnitless},
    {"qy", Kind::kUnitless},
    {"qz", Kind::kUnitless},
    {"temperature", Kind::kTemperature},
};

const Quantity* find_quantity(std::string_view q) {
  for (const Quantity& k : kQuantities) {
    if (k.name == q) return &k;
  }
  return nullptr;
}

// Scale to the interface unit (s, nT, deg); 0 when the unit is not accepted.
double unit_scale(Kind kind, std::string_view unit) {
  switch (kind) {
    case Kind::kTime:
      return unit == "s" ? 1.0 : 0.0;
    case Kind::kField:
      return unit == "nT" ? 1.0 : (unit == "uT" ? 1000.0 : 0.0);
    case Kind::kAngle:
      return unit == "deg" ? 1.0 : (unit == "rad" ? 180.0 / core::kPi<double> : 0.0);
    case Kind::kUnitless:
      return 0.0;
    case Kind::kTemperature:
      // "C" too: simulation CSVs before the column was named temperature_degC wrote temperature_C.
      return unit == "degC" || unit == "C" ? 1.0 : 0.0;
  }
  return 0.0;
}

const char* accepted_units(Kind kind) {
  switch (kind) {
    case Kind::kTime:
      return "s";
    case Kind::kField:
      return "nT or uT";
    case Kind::kAngle:
      return "deg or rad";
    case Kind::kUnitless:
      return "none";
    case Kind::kTemperature:
      return "degC or C";
  }
  return "";
}

std::string_view trim(std::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t'))
    s.remove_prefix(1);
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r'))
    s.remove_suffix(1);
  return s;
}

bool iequals(std::string_view a, std::string_view b) {
  if (a.size() != b.size()) return false;
  for (std::size_t i = 0; i < a.size(); ++i) {
    const char x = (a[i] >= 'A' && a[i] <= 'Z') ? static_cast<char>(a[i] - 'A' + 'a') : a[i];
    if (x != b[i]) return false;
  }
  return true;
}

}  // namespace

CsvError::CsvError(const std::string& file, std::uint64_t line, const std::string& column,
                   const std::string& message)
    : std::runtime_error(file + (line > 0 ? ":" + std::to_string(line) : std::string()) +
                         (column.empty() ? std::string() : ": column " + column) + ": " + message),
      file_(file),
      line_(line),
      column_(column) {}

CsvReader::CsvReader(const std::string& path, CsvReaderOptions options)
    : path_(path), options_(options), buffer_(new char[kReadBuffer]) {
  in_.rdbuf()->pubsetbuf(buffer_.get(), kReadBuffer);
  line_.reserve(4096);  // typical rows never reallocate: next() stays allocation-free
  in_.open(path, std::ios::in | std::ios::binary);
  if (!in_.is_open()) throw CsvError(path_, 0, "", "cannot open file for reading");
  parse_header();
}

CsvReader::~CsvReader() = default;

bool CsvReader::read_line() {
  while (std::getline(in_, line_)) {
    ++line_no_;
    // A UTF-8 byte-order mark (spreadsheet exports) is not part of the first column's name.
    if (line_no_ == 1 && line_.starts_with("\xEF\xBB\xBF")) line_.erase(0, 3);
    const std::string_view t = trim(line_);
    if (t.empty() || t.front() == '#') {
      if (names_.empty() && !t.empty()) {
        std::string_view c = t.substr(1);
        if (!c.empty() && c.front() == ' ') c.remove_prefix(1);
        comments_.emplace_back(c);
      }
      continue;
    }
    return true;
  }
  if (in_.bad()) throw CsvError(path_, line_no_, "", "read error");
  return false;
}

void CsvReader::split() {
  fields_.clear();
  char* const base = line_.data();
  const std::size_t n = line_.size();
  std::size_t i = 0;
  for (;;) {
    // Skip leading blanks of the field.
    while (i < n && (base[i] == ' ' || base[i] == '\t'))
      ++i;
    if (i < n && base[i] == '"') {
      // Quoted field: unescape "" in place (the text only shrinks).
      const std::size_t start = ++i;
      std::size_t w = start;
      bool closed = false;
      while (i < n) {
        if (base[i] == '"') {
          if (i + 1 < n && base[i + 1] == '"') {
            base[w++] = '"';
            i += 2;
            continue;
          }
          closed = true;
          ++i;
          break;
        }
        base[w++] = base[i++];
      }
      if (!closed) {
        throw CsvError(path_, line_no_, "field " + std::to_string(fields_.size() + 1),
                       "unterminated quoted field");
      }
      fields_.emplace_back(base + start, w - start);
      while (i < n && (base[i] == ' ' || base[i] == '\t' || base[i] == '\r'))
        ++i;
      if (i < n && base[i] != ',') {
        throw CsvError(path_, line_no_, "field " + std::to_string(fields_.size()),
                       "unexpected text after a quoted field");
      }
    } else {
      const std::size_t start = i;
      while (i < n && base[i] != ',')
        ++i;
      fields_.push_back(trim(std::string_view(base + start, i - start)));
    }
    if (i >= n) break;
    ++i;  // the comma
  }
}

void CsvReader::fail(std::size_t column, const std::string& message) const {
  const std::string name =
      column < names_.size() ? "'" + names_[column] + "' (field " + std::to_string(column + 1) + ")"
                             : "field " + std::to_string(column + 1);
  throw CsvError(path_, line_no_, name, message);
}

void CsvReader::parse_header() {
  if (!read_line()) throw CsvError(path_, line_no_, "", "no header line (file is empty)");
  split();
  fields_.reserve(fields_.size() + 8);
  names_.reserve(fields_.size());
  for (const std::string_view f : fields_)
    names_.emplace_back(f);

  std::optional<Column> found[std::size(kQuantities)];
  for (std::size_t c = 0; c < names_.size(); ++c) {
    const std::string& name = names_[c];
    if (name.empty()) fail(c, "empty column name");
    for (std::size_t d = 0; d < c; ++d) {
      if (names_[d] == name)
        fail(c, "duplicate column name (also field " + std::to_string(d + 1) + ")");
    }
    const std::size_t us = name.rfind('_');
    const std::string_view quantity =
        us == std::string::npos ? std::string_view(name) : std::string_view(name).substr(0, us);
    const std::string_view unit =
        us == std::string::npos ? std::string_view() : std::string_view(name).substr(us + 1);
    const Quantity* q = find_quantity(quantity);
    if (q == nullptr) continue;  // an extra column
    double scale = 1.0;
    if (q->kind == Kind::kUnitless) {
      if (us != std::string::npos)
        fail(c, "quaternion component " + std::string(quantity) + " takes no unit suffix");
    } else if (us == std::string::npos) {
      fail(c, "column needs a unit suffix (" + std::string(quantity) + "_<unit>, unit " +
                  accepted_units(q->kind) + ")");
    } else {
      scale = unit_scale(q->kind, unit);
      if (scale == 0.0) {
        fail(c, "unknown unit '" + std::string(unit) + "' for " + std::string(quantity) +
                    " (accepted: " + accepted_units(q->kind) + ")");
      }
    }
    const auto slot = static_cast<std::size_t>(q - kQuantities);
    if (found[slot]) fail(c, "quantity " + std::string(quantity) + " appears twice");
    found[slot] = Column{c, scale};
  }
  auto require = [&](std::size_t slot, const char* name) {
    if (!found[slot]) throw CsvError(path_, line_no_, name, "missing required column");
    return *found[slot];
  };
  if (options_.require_time || found[0]) {
    col_t_ = require(0, "t_s");
    has_time_ = true;
  }
  col_hx_ = require(1, "hx_nT");
  col_hy_ = require(2, "hy_nT");
  col_hz_ = require(3, "hz_nT");
  col_f_ = found[4];
  col_theta_ = found[11];
  col_temperature_ = found[16];

  struct Set {
    AttitudeColumns kind;
    std::size_t first;
    std::size_t count;
    const char* names;
  };
  const Set sets[] = {{AttitudeColumns::kLi, 5, 3, "alpha_deg, beta_deg, gamma_deg"},
                      {AttitudeColumns::kYawPitchRoll, 8, 3, "yaw_deg, pitch_deg, roll_deg"},
                      {AttitudeColumns::kQuaternion, 12, 4, "qw, qx, qy, qz"}};
  for (const Set& s : sets) {
    std::size_t present = 0;
    for (std::size_t k = 0; k < s.count; ++k)
      present += found[s.first + k] ? 1U : 0U;
    if (present == 0) continue;
    if (present != s.count) {
      throw CsvError(path_, line_no_, "",
                     std::string("incomplete attitude columns: need all of ") + s.names);
    }
    if (attitude_ != AttitudeColumns::kNone) {
      throw CsvError(path_, line_no_, "", "more than one attitude representation in the header");
    }
    attitude_ = s.kind;
    for (std::size_t k = 0; k < s.count; ++k)
      col_att_[k] = *found[s.first + k];
  }
  if (options_.f_nT && !std::isfinite(*options_.f_nT)) {
    throw CsvError(path_, 0, "", "the constant F option is not a finite number");
  }
}

double CsvReader::number_at(std::size_t index, double scale) const {
  const std::string_view s = trim(fields_[index]);
  if (s.empty()) fail(index, "empty field (write nan for a missing value)");
  std::string_view body = s;
  if (body.front() == '+') {
    body.remove_prefix(1);
    if (!body.empty() && (body.front() == '+' || body.front() == '-'))
      fail(index, "malformed number '" + std::string(s) + "'");
  }
  std::string_view mag = body;
  if (!mag.empty() && mag.front() == '-') mag.remove_prefix(1);
  if (iequals(mag, "nan")) return kNaN;
  double v = 0.0;
  const auto [ptr, ec] = std::from_chars(body.data(), body.data() + body.size(), v);
  if (ec == std::errc::result_out_of_range)
    fail(index, "number out of range '" + std::string(s) + "'");
  if (ec != std::errc() || ptr != body.data() + body.size() || body.empty() ||
      body.front() == '+') {
    fail(index, "malformed number '" + std::string(s) + "'");
  }
  if (!std::isfinite(v))
    fail(index, "non-finite number '" + std::string(s) + "' (only nan is allowed)");
  // Checked after the unit scaling: 1e306 uT or 1e307 rad are finite as read but not in nT / deg.
  const double scaled = v * scale;
  if (!std::isfinite(scaled))
    fail(index, "number out of range after unit conversion '" + std::string(s) + "'");
  return scaled;
}

double CsvReader::number(const Column& c) const {
  return number_at(c.index, c.scale);
}

bool CsvReader::next(CsvRecord* out) {
  have_row_ = false;
  if (!read_line()) return false;
  split();
  if (fields_.size() != names_.size()) {
    throw CsvError(path_, line_no_, "",
                   "wrong number of fields: expected " + std::to_string(names_.size()) +
                       ", found " + std::to_string(fields_.size()));
  }
  have_row_ = true;
  CsvRecord r;
  r.line = line_no_;
  if (has_time_) {
    r.t_s = number(col_t_);
    if (!std::isfinite(r.t_s)) fail(col_t_.index, "time must be a finite number");
  } else {
    r.t_s = kNaN;
  }
  r.m_nT = core::Vec3<double>(number(col_hx_), number(col_hy_), number(col_hz_));
  if (r.m_nT.array().isNaN().any()) {
    r.dropout = true;
    r.m_nT.setConstant(kNaN);
  }
  if (col_f_ && !(options_.f_nT && options_.f_replaces_column)) {
    const double f = number(*col_f_);
    if (!std::isnan(f)) r.f_nT = f;
  } else if (options_.f_nT) {
    r.f_nT = *options_.f_nT;
  }
  if (col_theta_) {
    const double th = number(*col_theta_);
    if (!std::isnan(th)) r.theta_deg = th;
  }
  if (col_temperature_) {
    const double temp = number(*col_temperature_);
    // Below absolute zero is not a temperature; above 1000 degC no magnetometer survives: both are
    // a broken column, not data.
    if (!std::isnan(temp) && !(temp >= kTemperatureMin_degC && temp <= kTemperatureMax_degC)) {
      fail(col_temperature_->index, "temperature " + format_double(temp) + " degC outside " +
                                        format_double(kTemperatureMin_degC) + " .. " +
                                        format_double(kTemperatureMax_degC) + " degC");
    }
    if (!std::isnan(temp)) r.temperature_degC = temp;
  }
  if (attitude_ != AttitudeColumns::kNone) {
    const std::size_t n = attitude_ == AttitudeColumns::kQuaternion ? 4 : 3;
    double a[4] = {0, 0, 0, 0};
    bool any_nan = false;
    for (std::size_t k = 0; k < n; ++k) {
      a[k] = number(col_att_[k]);
      any_nan = any_nan || std::isnan(a[k]);
    }
    if (!any_nan) {
      const auto rad = [](double d) { return core::deg_to_rad(d); };
      switch (attitude_) {
        case AttitudeColumns::kLi:
          r.r_bn = core::r_bn_from_li(core::LiEuler<double>{rad(a[0]), rad(a[1]), rad(a[2])});
          break;
        case AttitudeColumns::kYawPitchRoll:
          r.r_bn = core::r_bn_from_ypr(core::YawPitchRoll<double>{rad(a[0]), rad(a[1]), rad(a[2])});
          break;
        case AttitudeColumns::kQuaternion: {
          const core::Quat<double> q(a[0], a[1], a[2], a[3]);
          const double norm = q.norm();
          if (!(std::abs(norm - 1.0) <= 1e-3)) {  // also an overflowing norm (components ~1e200)
            fail(col_att_[0].index,
                 "quaternion is not unit (norm " +
                     (std::isfinite(norm) ? format_double(norm) : std::string("overflows")) + ")");
          }
          r.r_bn = core::r_bn_from_quat(q);
          break;
        }
        case AttitudeColumns::kNone:
          break;
      }
    }
  }
  *out = r;
  return true;
}

std::optional<std::size_t> CsvReader::column_index(std::string_view name) const noexcept {
  for (std::size_t c = 0; c < names_.size(); ++c) {
    if (names_[c] == name) return c;
  }
  return std::nullopt;
}

double CsvReader::value(std::size_t column) const {
  if (!have_row_ || column >= fields_.size())
    throw std::out_of_range("CsvReader::value: no such field");
  return number_at(column, 1.0);
}

std::string_view CsvReader::text(std::size_t column) const {
  if (!have_row_ || column >= fields_.size())
    throw std::out_of_range("CsvReader::text: no such field");
  return fields_[column];
}

}  // namespace magvec::host::io
