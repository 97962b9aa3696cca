// `magvec report --cal cal.json --in data.csv [--trace trace.csv] --out DIR`: a calibration report
// The numbers are computed here (host/report/report.cpp -> DIR/data/); the script
// host/report/magvec_report.py draws them into DIR/*.png and writes DIR/index.html.
#include <CLI/CLI.hpp>
#include <cmath>
#include <filesystem>
#include <iostream>
#include <limits>
#include <memory>
#include <string>

#include "commands.hpp"
#include "magvec/version.hpp"
#include "report/report.hpp"
#include "stats.hpp"

namespace magvec::host::cli {
namespace {

struct ReportCliOptions {
  std::string cal_path;
  std::string in_path;
  std::string trace_path;
  std::string out_dir;
  double field_nT = std::numeric_limits<double>::quiet_NaN();
  std::size_t max_points = 3000;
};

void run(const ReportCliOptions& o) {
  report::ReportOptions ro;
  ro.cal_path = o.cal_path;
  ro.in_path = o.in_path;
  ro.trace_path = o.trace_path;
  ro.out_dir = o.out_dir;
  if (std::isfinite(o.field_nT)) ro.field_nT = o.field_nT;
  ro.max_points = o.max_points;
  ro.magvec_version = kVersion;
  const report::ReportResult r = report::write_report_data(ro);
  report::render(o.out_dir, r.figures);
  const std::string index = (std::filesystem::path(o.out_dir) / "index.html").string();
  std::cout << "magvec report: " << r.rows << " rows (" << r.dropouts << " dropouts), "
            << r.figures.size() << " figures, coverage " << fixed(100.0 * r.coverage, 1) << " %";
  if (std::isfinite(r.rms_after_nT)) {
    std::cout << ", intensity residual RMS " << fixed(r.rms_before_nT, 3) << " nT raw -> "
              << fixed(r.rms_after_nT, 3) << " nT calibrated";
  }
  std::cout << "\n  " << index << "\n";
}

}  // namespace

void register_report(CLI::App& app) {
  auto opts = std::make_shared<ReportCliOptions>();
  CLI::App* cmd = app.add_subcommand(
      "report",
      "Write a calibration report (DIR/index.html + PNG figures, needs python3-matplotlib)");
  cmd->add_option("--cal", opts->cal_path, "Calibration file (cal.json)")->required();
  cmd->add_option("--in", opts->in_path, "The recording (CSV) the calibration is judged on")
      ->required();
  cmd->add_option("--trace", opts->trace_path, "EKF trace CSV (magvec calibrate --trace)");
  cmd->add_option("--out", opts->out_dir, "Output directory")->required();
  cmd->add_option("--field-nT", opts->field_nT, "Reference total field when the input has no F_nT")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--max-points", opts->max_points,
                  "Plotted samples / time buckets (the statistics use every row)")
      ->check(CLI::Range(10, 1000000));
  cmd->callback([opts] { run(*opts); });
}

}  // namespace magvec::host::cli
