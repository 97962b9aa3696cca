// Numbers of `magvec report` (see report.hpp).
#include "report/report.hpp"

#include <algorithm>
#include <charconv>
#include <cmath>
#include <filesystem>
#include <fstream>
#include <nlohmann/json.hpp>
#include <numbers>
#include <utility>

#include "magvec/core/compensator.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/host/io/csv.hpp"

namespace magvec::host::report {
namespace {

namespace fs = std::filesystem;
using json = nlohmann::json;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
constexpr double kRadToDeg = 180.0 / std::numbers::pi;

// JSON has no NaN: missing numbers are null.
json num(double v) {
  return std::isfinite(v) ? json(v) : json(nullptr);
}

double sigma_at(const CalibrationFile& cal, const std::string& key, std::size_t i) {
  const auto it = cal.sigma.find(key);
  if (it == cal.sigma.end() || i >= it->second.size()) return kNaN;
  return it->second[i];
}

// Bucketed time series: mean/min/max of each quantity over `bucket` consecutive rows.
class Buckets {
 public:
  explicit Buckets(std::size_t quantities) : acc_(quantities) {}
  void add(std::size_t q, double x) noexcept {
    if (std::isfinite(x)) acc_[q].add(x);
  }
  bool any() const noexcept {
    return std::any_of(acc_.begin(), acc_.end(), [](const Summary& s) { return s.n > 0; });
  }
  // Appends mean,min,max per quantity to row and resets.
  void flush(std::vector<double>* row) {
    for (Summary& s : acc_) {
      row->push_back(s.n ? s.mean() : kNaN);
      row->push_back(s.n ? s.min : kNaN);
      row->push_back(s.n ? s.max : kNaN);
      s = Summary{};
    }
  }

 private:
  std::vector<Summary> acc_;
};

std::vector<std::string> bucket_columns(const std::vector<std::string>& quantities) {
  std::vector<std::string> cols;
  for (const std::string& q : quantities) {
    cols.push_back(q + "_mean");
    cols.push_back(q + "_min");
    cols.push_back(q + "_max");
  }
  return cols;
}

std::string trim(std::string_view s) {
  while (!s.empty() && (s.front() == ' ' || s.front() == '\t'))
    s.remove_prefix(1);
  while (!s.empty() && (s.back() == ' ' || s.back() == '\t' || s.back() == '\r'))
    s.remove_suffix(1);
  return std::string(s);
}

std::vector<std::string> split_csv_line(const std::string& line) {
  std::vector<std::string> out;
  std::size_t start = 0;
  for (;;) {
    const std::size_t comma = line.find(',', start);
    out.push_back(trim(std::string_view(line).substr(start, comma - start)));
    if (comma == std::string::npos) break;
    start = comma + 1;
  }
  return out;
}

std::optional<double> parse_number(const std::string& s) {
  std::string_view v = s;
  if (!v.empty() && v.front() == '+') v.remove_prefix(1);
  std::string lower;
  for (char c : v)
    lower.push_back(static_cast<char>(std::tolower(static_cast<unsigned char>(c))));
  if (lower == "nan" || lower == "-nan") return kNaN;
  double x = 0;
  const auto [p, ec] = std::from_chars(v.data(), v.data() + v.size(), x);
  if (ec != std::errc() || p != v.data() + v.size() || !std::isfinite(x)) return std::nullopt;
  return x;
}

}  // namespace

// ---------------------------------------------------------------------------------------------
CoverageGrid::CoverageGrid(int bands, int sectors) : bands_(bands), sectors_(sectors) {
  if (bands < 1 || sectors < 1) throw ReportError("coverage grid needs at least one cell");
  counts_.assign(static_cast<std::size_t>(bands) * static_cast<std::size_t>(sectors), 0);
}

std::size_t CoverageGrid::cell_of(const core::Vec3<double>& u) const noexcept {
  const double z = std::clamp(u.z(), -1.0, 1.0);
  const int band =
      std::clamp(static_cast<int>(std::floor((z + 1.0) * 0.5 * bands_)), 0, bands_ - 1);
  const double lon = std::atan2(u.y(), u.x());  // [-pi, pi]
  const int sector = std::clamp(
      static_cast<int>(std::floor((lon + std::numbers::pi) / (2.0 * std::numbers::pi) * sectors_)),
      0, sectors_ - 1);
  return static_cast<std::size_t>(band) * static_cast<std::size_t>(sectors_) +
         static_cast<std::size_t>(sector);
}

void CoverageGrid::add(const core::Vec3<double>& v) noexcept {
  const double n = v.norm();
  if (!std::isfinite(n) || n <= 0) return;
  ++counts_[cell_of(v / n)];
}

std::uint64_t CoverageGrid::count(int band, int sector) const noexcept {
  return counts_[static_cast<std::size_t>(band) * static_cast<std::size_t>(sectors_) +
                 static_cast<std::size_t>(sector)];
}

std::size_t CoverageGrid::covered() const noexcept {
  return static_cast<std::size_t>(
      std::count_if(counts_.begin(), counts_.end(), [](std::uint64_t c) { return c > 0; }));
}

double CoverageGrid::fraction() const noexcept {
  return static_cast<double>(covered()) / static_cast<double>(cells());
}

double CoverageGrid::band_edge_lat_rad(int band) const noexcept {
  return std::asin(std::clamp(-1.0 + 2.0 * band / bands_, -1.0, 1.0));
}

// ---------------------------------------------------------------------------------------------
void Summary::add(double x) noexcept {
  if (!std::isfinite(x)) return;
  ++n;
  sum += x;
  sum_sq += x * x;
  min = std::min(min, x);
  max = std::max(max, x);
}
double Summary::mean() const noexcept {
  return n ? sum / static_cast<double>(n) : kNaN;
}
double Summary::rms() const noexcept {
  return n ? std::sqrt(sum_sq / static_cast<double>(n)) : kNaN;
}
double Summary::sd() const noexcept {
  if (n < 2) return kNaN;
  const double m = mean();
  const double var = (sum_sq - static_cast<double>(n) * m * m) / static_cast<double>(n - 1);
  return std::sqrt(std::max(var, 0.0));
}

// ---------------------------------------------------------------------------------------------
std::vector<ParamRow> parameter_table(const CalibrationFile& cal) {
  std::vector<ParamRow> rows;
  static const char* const kXyz[] = {"x", "y", "z"};
  const std::string li_group = "Li et al. 2023 (A = Ks Ko, Kof, Rm)";
  core::LiParams<double> li;
  if (core::to_li(cal.model, &li) == core::ConversionStatus::kOk) {
    for (std::size_t i = 0; i < 3; ++i) {
      const auto k = static_cast<Eigen::Index>(i);
      rows.push_back({li_group, std::string("Ks") + kXyz[i], li.ks(k), sigma_at(cal, "ks", i), ""});
    }
    for (std::size_t i = 0; i < 3; ++i) {
      const auto k = static_cast<Eigen::Index>(i);
      rows.push_back({li_group, "O" + std::to_string(i + 1), li.o_rad(k) * kRadToDeg,
                      sigma_at(cal, "O_deg", i), "deg"});
    }
    for (std::size_t i = 0; i < 3; ++i) {
      const auto k = static_cast<Eigen::Index>(i);
      rows.push_back(
          {li_group, std::string("Kof") + kXyz[i], li.kof(k), sigma_at(cal, "Kof_nT", i), "nT"});
    }
    static const char* const kRm[] = {"alpha_m", "beta_m", "gamma_m"};
    for (std::size_t i = 0; i < 3; ++i) {
      const auto k = static_cast<Eigen::Index>(i);
      rows.push_back(
          {li_group, kRm[i], li.rm_rad(k) * kRadToDeg, sigma_at(cal, "Rm_deg", i), "deg"});
    }
  }
  const std::string ge_group = "Ge et al. 2017 (C^-1, b)";
  const core::GeParams<double> ge = core::to_ge(cal.model);
  for (std::size_t r = 0; r < 3; ++r) {
    for (std::size_t c = 0; c < 3; ++c) {
      rows.push_back({ge_group, "Cinv" + std::to_string(r) + std::to_string(c),
                      ge.c_inv(static_cast<Eigen::Index>(r), static_cast<Eigen::Index>(c)),
                      sigma_at(cal, "Cinv", 3 * r + c), ""});
    }
  }
  for (std::size_t i = 0; i < 3; ++i) {
    rows.push_back({ge_group, std::string("b") + kXyz[i], ge.b(static_cast<Eigen::Index>(i)),
                    sigma_at(cal, "b_nT", i), "nT"});
  }
  if (cal.sine) {
    const std::string g = "sine fit (K, B0)";
    const core::SineParams<double>& s = cal.sine->params;
    for (std::size_t i = 0; i < 3; ++i) {
      rows.push_back({g, std::string("k") + kXyz[i], s.k(static_cast<Eigen::Index>(i)),
                      sigma_at(cal, "k", i), ""});
    }
    rows.push_back({g, "alpha", s.alpha_rad * kRadToDeg, sigma_at(cal, "alpha_deg", 0), "deg"});
    rows.push_back({g, "beta", s.beta_rad * kRadToDeg, sigma_at(cal, "beta_deg", 0), "deg"});
    rows.push_back({g, "gamma", s.gamma_rad * kRadToDeg, sigma_at(cal, "gamma_deg", 0), "deg"});
    for (std::size_t i = 0; i < 3; ++i) {
      rows.push_back({g, std::string("B0") + kXyz[i], s.b0(static_cast<Eigen::Index>(i)),
                      sigma_at(cal, "B0_nT", i), "nT"});
    }
    rows.push_back({g, "inclination", cal.sine->inclination_rad * kRadToDeg,
                    sigma_at(cal, "inclination_deg", 0), "deg"});
  }
  if (cal.h_n_nT) {
    static const char* const kEnu[] = {"E", "N", "U"};
    for (std::size_t i = 0; i < 3; ++i) {
      rows.push_back({"local field h_n (ENU)", std::string("h_") + kEnu[i],
                      (*cal.h_n_nT)(static_cast<Eigen::Index>(i)), sigma_at(cal, "h_n_nT", i),
                      "nT"});
    }
  }
  return rows;
}

// ---------------------------------------------------------------------------------------------
TraceTable read_trace_csv(const std::string& path) {
  std::ifstream in(path);
  if (!in) throw ReportError(path + ": cannot open the trace file");
  TraceTable t;
  std::string line;
  std::uint64_t line_no = 0;
  bool header = false;
  while (std::getline(in, line)) {
    ++line_no;
    const std::string s = trim(line);
    if (s.empty() || s.front() == '#') continue;
    std::vector<std::string> fields = split_csv_line(s);
    if (!header) {
      t.names = std::move(fields);
      t.numeric.assign(t.names.size(), true);
      header = true;
      continue;
    }
    if (fields.size() != t.names.size()) {
      throw ReportError(path + ":" + std::to_string(line_no) + ": " +
                        std::to_string(fields.size()) + " fields, the header has " +
                        std::to_string(t.names.size()));
    }
    std::vector<double> row(fields.size(), kNaN);
    std::vector<std::string> text(fields.size());
    for (std::size_t i = 0; i < fields.size(); ++i) {
      const std::optional<double> v = parse_number(fields[i]);
      if (v) {
        row[i] = *v;
      } else {
        t.numeric[i] = false;
        text[i] = fields[i];
      }
    }
    t.rows.push_back(std::move(row));
    t.text.push_back(std::move(text));
  }
  if (!header) throw ReportError(path + ": the trace file has no header");
  if (t.rows.empty()) throw ReportError(path + ": the trace file has no rows");
  return t;
}

namespace {
// Every numeric non-bookkeeping, non-sigma column with its sigma column (when it has one).
std::vector<TraceParam> trace_columns(const TraceTable& t) {
  std::vector<TraceParam> out;
  const auto index_of = [&](const std::string& name) -> std::optional<std::size_t> {
    for (std::size_t i = 0; i < t.names.size(); ++i) {
      if (t.names[i] == name && t.numeric[i]) return i;
    }
    return std::nullopt;
  };
  for (std::size_t i = 0; i < t.names.size(); ++i) {
    const std::string& n = t.names[i];
    if (!t.numeric[i] || n == "update" || n == "pass" || n == "row" || n == "t_s" ||
        n == "status" || n == "initialised" || n.rfind("sigma_", 0) == 0) {
      continue;
    }
    TraceParam p{i, index_of("sigma_" + n), n};
    const std::size_t us = n.rfind('_');
    if (!p.sigma_column && us != std::string::npos)
      p.sigma_column = index_of("sigma_" + n.substr(0, us));
    out.push_back(p);
  }
  return out;
}

// The numbers of the first [...] after key (nested brackets flattened); empty when absent.
std::vector<double> numbers_after(const std::string& line, const std::string& key) {
  std::vector<double> v;
  const std::size_t k = line.find(key);
  if (k == std::string::npos) return v;
  std::size_t i = line.find('[', k + key.size());
  if (i == std::string::npos) return v;
  int depth = 0;
  std::string token;
  const auto take = [&] {
    if (token.empty()) return;
    double x = 0;
    const auto r = std::from_chars(token.data(), token.data() + token.size(), x);
    v.push_back(r.ec == std::errc() ? x : kNaN);
    token.clear();
  };
  for (; i < line.size(); ++i) {
    const char c = line[i];
    if (c == '[') {
      ++depth;
    } else if (c == ']') {
      take();
      if (--depth == 0) break;
    } else if (c == ',' || c == ' ') {
      take();
    } else {
      token.push_back(c);
    }
  }
  return v;
}

// The number after key (up to the next space); NaN when absent.
double number_after(const std::string& line, const std::string& key) {
  const std::size_t k = line.find(key);
  if (k == std::string::npos) return kNaN;
  const std::size_t b = k + key.size();
  const std::size_t e = line.find(' ', b);
  const std::string token = line.substr(b, e == std::string::npos ? std::string::npos : e - b);
  double x = 0;
  const auto r = std::from_chars(token.data(), token.data() + token.size(), x);
  return r.ec == std::errc() ? x : kNaN;
}
}  // namespace

std::vector<TraceParam> trace_params(const TraceTable& t) {
  std::vector<TraceParam> out;
  for (const TraceParam& p : trace_columns(t))
    if (p.sigma_column) out.push_back(p);
  return out;
}

std::vector<TraceParam> trace_diagnostics(const TraceTable& t) {
  std::vector<TraceParam> out;
  for (const TraceParam& p : trace_columns(t))
    if (!p.sigma_column) out.push_back(p);
  return out;
}

std::map<std::string, double> simulation_truth(const std::vector<std::string>& comments) {
  std::map<std::string, double> t;
  bool simulated = false;
  for (const std::string& c : comments)
    simulated = simulated || c.find(" simulate: scenario ") != std::string::npos;
  if (!simulated) return t;
  static const char* const kAxis[3] = {"x", "y", "z"};
  const auto put = [&](const std::vector<double>& v, const std::array<std::string, 3>& names) {
    if (v.size() != 3) return;
    for (std::size_t i = 0; i < 3; ++i)
      t[names[i]] = v[i];
  };
  const auto put3 = [&](const std::vector<double>& v, const std::string& prefix,
                        const std::string& suffix) {
    put(v, {prefix + kAxis[0] + suffix, prefix + kAxis[1] + suffix, prefix + kAxis[2] + suffix});
  };
  for (const std::string& c : comments) {
    if (c.rfind("truth canonical:", 0) == 0) {
      const std::vector<double> w = numbers_after(c, "W = A^-1 = ");
      if (w.size() == 9) {
        for (int r = 0; r < 3; ++r)
          for (int k = 0; k < 3; ++k)
            t["W" + std::to_string(r) + std::to_string(k)] = w[static_cast<std::size_t>(3 * r + k)];
      }
      put3(numbers_after(c, "o_nT = "), "o_", "_nT");
    } else if (c.rfind("truth Li 2023:", 0) == 0) {
      put(numbers_after(c, "Rm_deg (alpha_m, beta_m, gamma_m) = "), {"am_deg", "bm_deg", "gm_deg"});
    } else if (c.rfind("truth Ge 2017:", 0) == 0) {
      put3(numbers_after(c, "b_nT = "), "b_", "_nT");
    } else if (c.rfind("truth h_n (ENU) nT:", 0) == 0) {
      const std::vector<double> h = numbers_after(c, "nT: ");
      const std::vector<double> diurnal = numbers_after(c, "diurnal ");
      const std::vector<double> step = numbers_after(c, "step ");
      const auto zero = [](const std::vector<double>& v) {
        return std::all_of(v.begin(), v.end(), [](double x) { return x == 0; });
      };
      if (zero(diurnal) && zero(step)) put(h, {"hE_nT", "hN_nT", "hU_nT"});
    } else if (c.rfind("truth offset temperature coefficients nT/degC:", 0) == 0) {
      put3(numbers_after(c, "nT/degC: "), "c_", "_nT_per_degC");
    } else if (c.rfind("noise:", 0) == 0) {
      const double latency = number_after(c, "INS latency ");
      if (std::isfinite(latency)) t["dt_s"] = -latency;
    }
  }
  return t;
}

// ---------------------------------------------------------------------------------------------
ReportResult write_report_data(const ReportOptions& o) {
  const CalibrationFile cal = read_calibration_file(o.cal_path);
  io::CsvReaderOptions ropt;
  ropt.f_nT = o.field_nT;
  const fs::path dir = fs::path(o.out_dir);
  const fs::path data = dir / "data";
  std::error_code ec;
  fs::create_directories(data, ec);
  if (ec) throw ReportError(data.string() + ": cannot create the directory: " + ec.message());

  // Pass 1: row count (sets the bucket size) and the mean reference field.
  std::uint64_t rows = 0;
  Summary f_ref;
  Summary f_cal;
  bool has_attitude = false;
  bool file_has_f = false;
  const core::Compensator<double> comp(cal.model);
  std::map<std::string, double> truth;
  {
    io::CsvReader reader(o.in_path, ropt);
    truth = simulation_truth(reader.comments());
    has_attitude = reader.attitude_columns() != io::AttitudeColumns::kNone;
    file_has_f = reader.has_f();
    io::CsvRecord rec;
    core::Compensated<double> c;
    while (reader.next(&rec)) {
      ++rows;
      if (rec.f_nT) f_ref.add(*rec.f_nT);
      if (!rec.dropout && comp.compensate(rec.m_nT, &c)) f_cal.add(c.intensity);
    }
  }
  if (rows == 0) throw ReportError(o.in_path + ": the CSV has no data rows");
  if (f_cal.n == 0) throw ReportError(o.in_path + ": every row is a dropout; nothing to report");
  // Reference total field for the ellipsoid and sphere: the mean F of the file, else |h_n| of the
  // calibration, else the mean calibrated intensity.
  double f0 = kNaN;
  std::string f0_source;
  if (f_ref.n > 0) {
    f0 = f_ref.mean();
    f0_source = file_has_f ? "mean F_nT of the data file" : "--field-nT";
  } else if (cal.h_n_nT) {
    f0 = cal.h_n_nT->norm();
    f0_source = "|h_n| of the calibration";
  } else {
    f0 = f_cal.mean();
    f0_source = "mean calibrated intensity (no reference F)";
  }

  const std::size_t max_points = std::max<std::size_t>(o.max_points, 1);
  const std::uint64_t bucket = (rows + max_points - 1) / max_points;
  const double outlier_nT = std::fmax(6.0 * cal.quality.residual_rms_after_nT, 1.0);

  io::CsvWriter samples_csv(
      (data / "samples.csv").string(),
      {"index", "t_s", "mx_nT", "my_nT", "mz_nT", "hsx_nT", "hsy_nT", "hsz_nT"});
  std::vector<std::string> res_cols = {"index", "t_s", "n"};
  for (const std::string& c : bucket_columns({"before", "after"}))
    res_cols.push_back(c);
  io::CsvWriter residual_csv((data / "residual.csv").string(), res_cols);
  std::vector<std::string> enu_cols = {"index", "t_s", "n"};
  for (const std::string& c :
       bucket_columns({"E_before", "N_before", "U_before", "E_after", "N_after", "U_after"})) {
    enu_cols.push_back(c);
  }
  io::CsvWriter enu_csv((data / "enu.csv").string(), enu_cols);

  CoverageGrid grid(o.coverage_bands, o.coverage_sectors);
  Summary res_before, res_after;
  std::array<Summary, 3> enu_before, enu_after;
  Buckets res_b(2), enu_b(6);
  std::uint64_t dropouts = 0, no_ref = 0, no_att = 0, outliers = 0, in_bucket = 0, index = 0;
  std::uint64_t res_n = 0, enu_n = 0;
  double bucket_t0 = 0, bucket_i0 = 0;
  bool sample_taken = false;
  std::vector<double> out_row;
  const auto flush = [&]() {
    if (in_bucket == 0) return;
    const double mid_i = bucket_i0 + 0.5 * static_cast<double>(in_bucket - 1);
    if (res_b.any()) {
      out_row = {mid_i, bucket_t0, static_cast<double>(res_n)};
      res_b.flush(&out_row);
      residual_csv.write_row(out_row);
    }
    if (enu_b.any()) {
      out_row = {mid_i, bucket_t0, static_cast<double>(enu_n)};
      enu_b.flush(&out_row);
      enu_csv.write_row(out_row);
    }
    in_bucket = res_n = enu_n = 0;
    sample_taken = false;
  };

  {
    io::CsvReader reader(o.in_path, ropt);
    io::CsvRecord rec;
    core::Compensated<double> c;
    while (reader.next(&rec)) {
      if (in_bucket == 0) {
        bucket_t0 = rec.t_s;
        bucket_i0 = static_cast<double>(index);
      }
      ++in_bucket;
      if (rec.dropout || !comp.compensate(rec.m_nT, &c)) {
        ++dropouts;
      } else {
        grid.add(c.h_s);
        if (!sample_taken) {
          const double r[] = {static_cast<double>(index),
                              rec.t_s,
                              rec.m_nT.x(),
                              rec.m_nT.y(),
                              rec.m_nT.z(),
                              c.h_s.x(),
                              c.h_s.y(),
                              c.h_s.z()};
          samples_csv.write_row(r);
          sample_taken = true;
        }
        if (rec.f_nT && std::isfinite(*rec.f_nT)) {
          const double before = rec.m_nT.norm() - *rec.f_nT;
          const double after = c.intensity - *rec.f_nT;
          res_before.add(before);
          res_after.add(after);
          res_b.add(0, before);
          res_b.add(1, after);
          ++res_n;
          if (std::abs(after) > outlier_nT) ++outliers;
        } else {
          ++no_ref;
        }
        if (rec.r_bn) {
          // Before: the raw reading taken as the body-frame field (no calibration at all).
          const core::Vec3<double> nb = rec.r_bn->transpose() * rec.m_nT;
          const core::Vec3<double> na = core::Compensator<double>::to_nav(c.h_b, *rec.r_bn);
          for (int i = 0; i < 3; ++i) {
            enu_before[static_cast<std::size_t>(i)].add(nb(i));
            enu_after[static_cast<std::size_t>(i)].add(na(i));
            enu_b.add(static_cast<std::size_t>(i), nb(i));
            enu_b.add(static_cast<std::size_t>(3 + i), na(i));
          }
          ++enu_n;
        } else if (has_attitude) {
          ++no_att;
        }
      }
      ++index;
      if (in_bucket == bucket) flush();
    }
    flush();
  }
  samples_csv.commit();
  residual_csv.commit();
  enu_csv.commit();

  // Fitted ellipsoid {m = o + F A u} and the sphere {F u} on a latitude/longitude grid.
  constexpr int kLat = 19, kLon = 37;
  io::CsvWriter surface_csv((data / "surface.csv").string(), {"i_lat", "i_lon", "ex_nT", "ey_nT",
                                                              "ez_nT", "sx_nT", "sy_nT", "sz_nT"});
  const core::Mat3<double> a = cal.model.a();
  for (int i = 0; i < kLat; ++i) {
    const double lat = -std::numbers::pi / 2 + std::numbers::pi * i / (kLat - 1);
    for (int j = 0; j < kLon; ++j) {
      const double lon = -std::numbers::pi + 2 * std::numbers::pi * j / (kLon - 1);
      const core::Vec3<double> u(std::cos(lat) * std::cos(lon), std::cos(lat) * std::sin(lon),
                                 std::sin(lat));
      const core::Vec3<double> e = cal.model.o + f0 * (a * u);
      const core::Vec3<double> s = f0 * u;
      const double r[] = {
          static_cast<double>(i), static_cast<double>(j), e.x(), e.y(), e.z(), s.x(), s.y(), s.z()};
      surface_csv.write_row(r);
    }
  }
  surface_csv.commit();

  io::CsvWriter coverage_csv(
      (data / "coverage.csv").string(),
      {"band", "sector", "lat_lo_deg", "lat_hi_deg", "lon_lo_deg", "lon_hi_deg", "count"});
  for (int b = 0; b < grid.bands(); ++b) {
    for (int s = 0; s < grid.sectors(); ++s) {
      const double r[] = {static_cast<double>(b),
                          static_cast<double>(s),
                          grid.band_edge_lat_rad(b) * kRadToDeg,
                          grid.band_edge_lat_rad(b + 1) * kRadToDeg,
                          -180.0 + 360.0 * s / grid.sectors(),
                          -180.0 + 360.0 * (s + 1) / grid.sectors(),
                          static_cast<double>(grid.count(b, s))};
      coverage_csv.write_row(r);
    }
  }
  coverage_csv.commit();

  // EKF trace (optional), subsampled to at most max_trace_points updates (the last one always).
  json trace_j = nullptr;
  if (!o.trace_path.empty()) {
    const TraceTable t = read_trace_csv(o.trace_path);
    const std::vector<TraceParam> params = trace_params(t);
    const std::vector<TraceParam> diags = trace_diagnostics(t);
    if (params.empty()) {
      throw ReportError(o.trace_path +
                        ": the trace has no state columns (a column with its sigma_ column)");
    }
    std::optional<std::size_t> col_update, col_nis, col_t;
    for (std::size_t i = 0; i < t.names.size(); ++i) {
      if ((t.names[i] == "update" || t.names[i] == "row") && t.numeric[i] && !col_update)
        col_update = i;
      if (t.names[i] == "nis" && t.numeric[i]) col_nis = i;
      if (t.names[i] == "t_s" && t.numeric[i]) col_t = i;
    }
    // Seconds are shown in milliseconds (the time offset: a few ms, at microsecond precision).
    const auto shown = [](const std::string& name) -> std::pair<std::string, double> {
      if (name.size() > 2 && name.compare(name.size() - 2, 2, "_s") == 0)
        return {name.substr(0, name.size() - 2) + "_ms", 1e3};
      return {name, 1.0};
    };
    std::vector<std::string> cols = {"update", "t_s"};
    json pj = json::array();
    for (const TraceParam& p : params) {
      const auto [name, scale] = shown(p.name);
      cols.push_back(name);
      cols.push_back("sigma_" + name);
      const auto it = truth.find(p.name);
      pj.push_back({{"name", name},
                    {"has_sigma", true},
                    {"truth", num(it == truth.end() ? kNaN : it->second * scale)}});
    }
    json dj = json::array();
    for (const TraceParam& p : diags) {
      cols.push_back(p.name);
      dj.push_back(p.name);
    }
    io::CsvWriter trace_csv((data / "trace.csv").string(), cols);
    const std::size_t n = t.rows.size();
    const std::size_t step =
        (n + o.max_trace_points - 1) / std::max<std::size_t>(o.max_trace_points, 1);
    std::vector<double> r;
    for (std::size_t k = 0; k < n; k += std::max<std::size_t>(step, 1)) {
      const auto emit = [&](std::size_t row) {
        const std::vector<double>& v = t.rows[row];
        r = {col_update ? v[*col_update] : static_cast<double>(row), col_t ? v[*col_t] : kNaN};
        for (const TraceParam& p : params) {
          const double scale = shown(p.name).second;
          r.push_back(v[p.column] * scale);
          r.push_back(v[*p.sigma_column] * scale);
        }
        for (const TraceParam& p : diags)
          r.push_back(v[p.column]);
        trace_csv.write_row(r);
      };
      emit(k);
      if (k + step >= n && k != n - 1) emit(n - 1);
    }
    trace_csv.commit();
    json final_j = json::array();
    const std::vector<double>& last = t.rows.back();
    std::size_t with_truth = 0;
    for (const TraceParam& p : params) {
      const auto [name, scale] = shown(p.name);
      const double value = last[p.column] * scale;
      const double sigma = last[*p.sigma_column] * scale;
      const auto it = truth.find(p.name);
      const double tv = it == truth.end() ? kNaN : it->second * scale;
      if (std::isfinite(tv)) ++with_truth;
      final_j.push_back({{"name", name},
                         {"value", num(value)},
                         {"sigma", num(sigma)},
                         {"truth", num(tv)},
                         {"z", num(sigma > 0 ? (value - tv) / sigma : kNaN)}});
    }
    trace_j = {{"file", o.trace_path},
               {"updates", n},
               {"x", col_t ? "t_s" : "update"},
               {"params", pj},
               {"diagnostics", dj},
               {"final", final_j},
               {"truth_params", with_truth},
               {"has_nis", col_nis.has_value()}};
  }

  ReportResult result;
  result.figures = {"fig_ellipsoid.png", "fig_residual.png"};
  if (enu_after[0].n > 0) result.figures.emplace_back("fig_enu.png");
  if (!o.trace_path.empty()) result.figures.emplace_back("fig_ekf.png");
  result.figures.emplace_back("fig_coverage.png");
  if (res_after.n == 0) {
    // Without a reference there is no residual to plot.
    result.figures.erase(
        std::find(result.figures.begin(), result.figures.end(), "fig_residual.png"));
  }
  result.rows = rows;
  result.dropouts = dropouts;
  result.rms_before_nT = res_before.rms();
  result.rms_after_nT = res_after.rms();
  result.coverage = grid.fraction();

  json table = json::array();
  for (const ParamRow& r : parameter_table(cal)) {
    table.push_back({{"group", r.group},
                     {"name", r.name},
                     {"value", num(r.value)},
                     {"sigma", num(r.sigma)},
                     {"unit", r.unit}});
  }
  const auto summary = [](const Summary& s) {
    return json{{"n", s.n},
                {"mean", num(s.mean())},
                {"sd", num(s.sd())},
                {"rms", num(s.rms())},
                {"min", num(s.n ? s.min : kNaN)},
                {"max", num(s.n ? s.max : kNaN)}};
  };
  json enu_j = nullptr;
  if (enu_after[0].n > 0) {
    json comps = json::array();
    static const char* const kEnu[] = {"E", "N", "U"};
    for (std::size_t i = 0; i < 3; ++i) {
      comps.push_back(
          {{"name", kEnu[i]},
           {"before", summary(enu_before[i])},
           {"after", summary(enu_after[i])},
           {"reference", num(cal.h_n_nT ? (*cal.h_n_nT)(static_cast<Eigen::Index>(i)) : kNaN)}});
    }
    enu_j = {{"components", comps},
             {"reference_source", cal.h_n_nT ? "h_n_nT of the calibration" : "none"}};
  }

  json j;
  j["schema"] = "magvec-report-data/1";
  j["meta"] = {{"data_file", o.in_path},
               {"cal_file", o.cal_path},
               {"trace_file", o.trace_path},
               {"method", cal.provenance.method},
               {"cal_input", cal.provenance.input},
               {"cal_magvec_version", cal.provenance.magvec_version},
               {"cal_created_utc", cal.provenance.created_utc},
               {"magvec_version", o.magvec_version},
               {"created_utc", utc_now_iso8601()}};
  j["quality"] = {{"verdict", cal.quality.verdict},
                  {"reason", cal.quality.reason},
                  {"coverage", num(cal.quality.coverage)},
                  {"condition", num(cal.quality.condition)},
                  {"residual_rms_before_nT", num(cal.quality.residual_rms_before_nT)},
                  {"residual_rms_after_nT", num(cal.quality.residual_rms_after_nT)}};
  j["cal_counts"] = {{"samples", cal.counts.samples},
                     {"used", cal.counts.used},
                     {"skipped_nonfinite", cal.counts.skipped_nonfinite},
                     {"rejected_outliers", cal.counts.rejected_outliers}};
  j["file_counts"] = {{"rows", rows},
                      {"dropouts", dropouts},
                      {"without_reference", no_ref},
                      {"without_attitude", no_att},
                      {"outliers", outliers},
                      {"outlier_threshold_nT", outlier_nT},
                      {"bucket_rows", bucket}};
  j["reference"] = {{"F_nT", num(f0)}, {"source", f0_source}};
  j["residual"] = {{"before", summary(res_before)}, {"after", summary(res_after)}};
  j["coverage"] = {{"bands", grid.bands()},
                   {"sectors", grid.sectors()},
                   {"cells", grid.cells()},
                   {"covered", grid.covered()},
                   {"fraction", grid.fraction()}};
  j["surface"] = {{"n_lat", kLat}, {"n_lon", kLon}};
  j["enu"] = enu_j;
  j["trace"] = trace_j;
  j["table"] = table;
  j["figures"] = result.figures;
  io::AtomicFile f((data / "report.json").string());
  f.write(j.dump(2));
  f.write("\n");
  f.commit();
  return result;
}

}  // namespace magvec::host::report
