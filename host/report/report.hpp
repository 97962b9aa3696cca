// `magvec report`: the numbers behind a calibration report. The C++ side computes
// everything that is shown -- compensation with the canonical model (docs/conventions.md: h_s = W
// (m - o), h_b = Rm^T h_s, h_n = R_bn^T h_b), intensity residuals |h| - F, E/N/U before/after, the
// fitted ellipsoid {m : |W (m - o)| = F} (Li et al. 2023 eq. (9)), equal-area coverage of the
// sphere of directions, the parameter table in the papers' forms with 1-sigma from cal.json -- and
// writes it to DIR/data/ (report.json + CSVs). The script host/report/magvec_report.py only draws
// these into PNGs and writes DIR/index.html.
#pragma once

#include <array>
#include <cstdint>
#include <limits>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "magvec/core/types.hpp"

namespace magvec::host::report {

class ReportError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct ReportOptions {
  std::string cal_path;
  std::string in_path;
  std::string trace_path;  // empty: no EKF trace
  std::string out_dir;
  std::optional<double> field_nT;  // reference total field when the CSV has no F_nT
  std::size_t max_points = 3000;   // plotted samples / time buckets
  std::size_t max_trace_points = 1500;
  int coverage_bands = 12;    // equal-area cells: bands uniform in z = sin(latitude) ...
  int coverage_sectors = 24;  // ... times sectors uniform in longitude
  std::string magvec_version;
};

// Equal-area partition of the unit sphere: `bands` zones of equal height in z (Archimedes: equal
// height = equal area) times `sectors` equal longitude sectors. Every cell has area 4 pi / cells.
class CoverageGrid {
 public:
  CoverageGrid(int bands, int sectors);
  // Adds the direction of v (need not be unit); ignores zero or non-finite vectors.
  void add(const core::Vec3<double>& v) noexcept;
  int bands() const noexcept { return bands_; }
  int sectors() const noexcept { return sectors_; }
  std::size_t cells() const noexcept { return counts_.size(); }
  std::size_t cell_of(const core::Vec3<double>& unit) const noexcept;
  std::uint64_t count(int band, int sector) const noexcept;
  std::size_t covered() const noexcept;  // cells with at least one sample
  double fraction() const noexcept;      // covered / cells
  // Latitude of the lower edge of a band, radians (band == bands: +pi/2).
  double band_edge_lat_rad(int band) const noexcept;

 private:
  int bands_;
  int sectors_;
  std::vector<std::uint64_t> counts_;
};

// Mean / min / max / RMS accumulator (NaNs are not added).
struct Summary {
  std::uint64_t n = 0;
  double sum = 0, sum_sq = 0;
  double min = std::numeric_limits<double>::infinity();
  double max = -std::numeric_limits<double>::infinity();
  void add(double x) noexcept;
  double mean() const noexcept;
  double rms() const noexcept;
  double sd() const noexcept;
};

struct ParamRow {
  std::string group;  // "Li et al. 2023", "Ge et al. 2017", ...
  std::string name;
  double value;
  double sigma;  // NaN when cal.json has none
  std::string unit;
};

// Parameter table in the papers' forms, with 1-sigma from cal.sigma (by the README's names).
std::vector<ParamRow> parameter_table(const CalibrationFile& cal);

// A generic numeric CSV (the EKF --trace file): header names, numeric or text columns.
struct TraceTable {
  std::vector<std::string> names;
  std::vector<bool> numeric;              // per column: every value parsed as a number (or nan)
  std::vector<std::vector<double>> rows;  // NaN in text columns
  std::vector<std::vector<std::string>> text;  // only for text columns (else empty strings)
};
TraceTable read_trace_csv(const std::string& path);

// States of a trace: the numeric columns with a 1-sigma column, sigma_<name> or sigma_<name
// without its unit suffix (the filter's states). Diagnostics: the other numeric columns except
// the bookkeeping ones (update, pass, row, t_s, status, initialised): nis, innovations, predicted
// sigmas; drawn without a band.
struct TraceParam {
  std::size_t column;
  std::optional<std::size_t> sigma_column;
  std::string name;
};
std::vector<TraceParam> trace_params(const TraceTable& t);
std::vector<TraceParam> trace_diagnostics(const TraceTable& t);

// The true values a `magvec simulate` file states in its header, by the names the traces use:
// W00..W22 (canonical W), o_x_nT.. (its offset), am_deg/bm_deg/gm_deg (Li misalignment),
// hE_nT/hN_nT/hU_nT (when the field neither varies nor steps), dt_s (magnetometer minus INS:
// minus the simulated INS latency), c_x_nT_per_degC.. (offset temperature coefficients) and
// b_x_nT.. (Ge offset). Ge's C^-1 is left out: a scalar-only filter determines it only up to a
// rotation, so its truth would look like an error that is none. Empty for other files.
std::map<std::string, double> simulation_truth(const std::vector<std::string>& comments);

struct ReportResult {
  std::vector<std::string> figures;  // PNG file names the page must show
  std::uint64_t rows = 0;
  std::uint64_t dropouts = 0;
  double rms_before_nT = std::numeric_limits<double>::quiet_NaN();
  double rms_after_nT = std::numeric_limits<double>::quiet_NaN();
  double coverage = 0;
};

// Reads cal.json, streams the CSV (twice: count, then bucket) and the trace, writes DIR/data/.
// Throws CalibrationFileError, io::CsvError or ReportError with a clear message.
ReportResult write_report_data(const ReportOptions& options);

// Locates magvec_report.py: $MAGVEC_REPORT_SCRIPT, next to the executable, ../share/magvec/, then
// the source tree (compile definition). Throws ReportError when none exists.
std::string locate_script();
// Runs `python script DIR` (python: $MAGVEC_PYTHON or /usr/bin/python3) and checks that index.html
// and every expected figure exist. Missing python3 / matplotlib / numpy -> ReportError naming the
// Debian package to install.
void render(const std::string& out_dir, const std::vector<std::string>& figures);

}  // namespace magvec::host::report
