// `magvec apply --cal cal.json --in data.csv --out comp.csv`: compensates a recording with a
// calibration (DESIGN.md: h_s = W (m - o), h_b = Rm^T h_s, h_n = R_bn^T h_b), streaming, and
// writes t_s, raw, h_s, F (= |h_s|), E/N/U when the input has attitude, and flags.
// flags uses the SensorLoop's bits (core::OutputFlag): 1 dropout, 32 outlier (|F - F_ref| above
// the threshold; only when the input has a scalar reference).
#include <CLI/CLI.hpp>
#include <cmath>
#include <iostream>
#include <limits>
#include <memory>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "commands.hpp"
#include "magvec/core/compensator.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/host/io/csv.hpp"
#include "stats.hpp"

namespace magvec::host::cli {
namespace {

struct ApplyOptions {
  std::string cal_path;
  std::string in_path;
  std::string out_path;
  double field_nT = std::numeric_limits<double>::quiet_NaN();
  double outlier_nT = std::numeric_limits<double>::quiet_NaN();
};

void run(const ApplyOptions& o) {
  const CalibrationFile cal = read_calibration_file(o.cal_path);
  io::CsvReaderOptions ropt;
  if (std::isfinite(o.field_nT)) ropt.f_nT = o.field_nT;
  io::CsvReader reader(o.in_path, ropt);
  const bool has_attitude = reader.attitude_columns() != io::AttitudeColumns::kNone;
  // Default outlier bound: six times the calibration's residual RMS, at least 1 nT.
  const double outlier_nT = std::isfinite(o.outlier_nT)
                                ? o.outlier_nT
                                : std::fmax(6.0 * cal.quality.residual_rms_after_nT, 1.0);

  std::vector<std::string> columns = {"t_s",    "hx_nT",  "hy_nT",  "hz_nT",
                                      "hsx_nT", "hsy_nT", "hsz_nT", "F_nT"};
  if (has_attitude) columns.insert(columns.end(), {"hE_nT", "hN_nT", "hU_nT"});
  columns.emplace_back("flags");
  io::CsvWriter writer(
      o.out_path, columns,
      {"magvec apply: calibration " + o.cal_path + " (method " + cal.provenance.method +
           ") applied to " + o.in_path,
       "flags: 1 dropout, 32 outlier (|F - F_ref| > " + fixed(outlier_nT, 3) + " nT)"});

  const core::Compensator<double> comp(cal.model);
  const double nan = std::numeric_limits<double>::quiet_NaN();
  Stats before, after;
  std::uint64_t rows = 0, dropouts = 0, outliers = 0, no_attitude = 0;
  std::vector<double> row(columns.size());
  io::CsvRecord rec;
  while (reader.next(&rec)) {
    ++rows;
    std::size_t k = 0;
    row[k++] = rec.t_s;
    for (int i = 0; i < 3; ++i)
      row[k++] = rec.m_nT(i);
    std::uint32_t flags = 0;
    core::Compensated<double> c;
    if (rec.dropout || !comp.compensate(rec.m_nT, &c)) {
      ++dropouts;
      flags |= core::kOutDropout;
      for (int i = 0; i < 4; ++i)
        row[k++] = nan;
      if (has_attitude) {
        for (int i = 0; i < 3; ++i)
          row[k++] = nan;
      }
    } else {
      for (int i = 0; i < 3; ++i)
        row[k++] = c.h_s(i);
      row[k++] = c.intensity;
      if (rec.f_nT && std::isfinite(*rec.f_nT)) {
        before.add(rec.m_nT.norm() - *rec.f_nT);
        after.add(c.intensity - *rec.f_nT);
        if (std::abs(c.intensity - *rec.f_nT) > outlier_nT) {
          flags |= core::kOutRejectedByCal;
          ++outliers;
        }
      }
      if (has_attitude) {
        if (rec.r_bn) {
          const core::Vec3<double> h_n = core::Compensator<double>::to_nav(c.h_b, *rec.r_bn);
          for (int i = 0; i < 3; ++i)
            row[k++] = h_n(i);
        } else {
          ++no_attitude;
          flags |= core::kOutNoAttitude;
          for (int i = 0; i < 3; ++i)
            row[k++] = nan;
        }
      }
    }
    row[k++] = static_cast<double>(flags);
    writer.write_row(row);
  }
  writer.commit();

  std::cout << "magvec apply: " << rows << " rows -> " << o.out_path << " (" << dropouts
            << " dropouts, " << outliers << " outliers, " << no_attitude << " without attitude)\n";
  if (after.count() > 0) {
    std::cout << "  intensity residual vs reference F: RMS " << fixed(before.rms(), 3)
              << " nT raw -> " << fixed(after.rms(), 3) << " nT compensated (mean "
              << fixed(after.mean(), 3) << " nT)\n";
  }
}

}  // namespace

void register_apply(CLI::App& app) {
  auto opts = std::make_shared<ApplyOptions>();
  CLI::App* cmd =
      app.add_subcommand("apply", "Compensate a recording with a calibration (cal.json)");
  cmd->add_option("--cal", opts->cal_path, "Calibration file (cal.json)")->required();
  cmd->add_option("--in", opts->in_path, "Input CSV recording")->required();
  cmd->add_option("--out", opts->out_path, "Output CSV")->required();
  cmd->add_option("--field-nT", opts->field_nT, "Reference total field when the input has no F_nT")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--outlier-nT", opts->outlier_nT,
                  "Flag samples whose |F - F_ref| exceeds this (default 6x the calibration RMS)")
      ->check(CLI::PositiveNumber);
  cmd->callback([opts] { run(*opts); });
}

}  // namespace magvec::host::cli
