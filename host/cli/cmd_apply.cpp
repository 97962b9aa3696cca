// `magvec apply --cal cal.json --in data.csv --out comp.csv`: compensates a recording with a
// calibration (docs/conventions.md: h_s = W (m - o), h_b = Rm^T h_s, h_n = R_bn^T h_b), streaming,
// and writes t_s, raw, h_s, F (= |h_s|), E/N/U when the input has attitude, and flags.
// The magnetometer-INS time offset of the calibration (cal.json time_offset_s, or
// --time-offset-s) is applied: a reading stamped t gets the attitude at t - offset, slerped between
// the neighbouring rows (a first pass reads the attitudes); where no row on either side lies
// within 4 attitude periods the E/N/U are not computed (flag 4, no attitude).
// flags uses the SensorLoop's bits (core::OutputFlag): 1 dropout, 4 no attitude, 32 outlier
// (|F - F_ref| above the threshold; only when the input has a scalar reference).
// Exit status: 0 ok, 2 bad input (the recording or cal.json: the message names the file and the
// cause), 1 any other failure (e.g. the output cannot be written).
#include <CLI/CLI.hpp>
#include <algorithm>
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
  double time_offset_s = std::numeric_limits<double>::quiet_NaN();
};

// The recording's attitudes, for the attitude at t - offset.
class AttitudeTrack {
 public:
  AttitudeTrack(const std::string& path, const io::CsvReaderOptions& ropt) {
    io::CsvReader reader(path, ropt);
    io::CsvRecord rec;
    while (reader.next(&rec)) {
      if (!rec.r_bn || !rec.r_bn->allFinite()) continue;
      if (!t_.empty() && !(rec.t_s > t_.back())) continue;
      t_.push_back(rec.t_s);
      q_.push_back(core::Quat<double>(*rec.r_bn).normalized());
    }
    std::vector<double> d;
    for (std::size_t i = 1; i < t_.size(); ++i)
      d.push_back(t_[i] - t_[i - 1]);
    if (!d.empty()) {
      std::nth_element(d.begin(), d.begin() + static_cast<std::ptrdiff_t>(d.size() / 2), d.end());
      max_gap_s_ = 4.0 * d[d.size() / 2];
    }
  }
  bool at(double t, core::Mat3<double>* r_bn) const {
    const auto it = std::upper_bound(t_.begin(), t_.end(), t);
    if (it == t_.begin() || it == t_.end()) return false;
    const std::size_t i1 = static_cast<std::size_t>(it - t_.begin()), i0 = i1 - 1;
    const double dt = t_[i1] - t_[i0];
    if (!(dt > 0) || dt > max_gap_s_) return false;
    *r_bn = q_[i0].slerp((t - t_[i0]) / dt, q_[i1]).toRotationMatrix();
    return true;
  }

 private:
  std::vector<double> t_;
  std::vector<core::Quat<double>> q_;
  double max_gap_s_ = 0;
};

void run(const ApplyOptions& o) {
  const CalibrationFile cal = read_calibration_file(o.cal_path);
  io::CsvReaderOptions ropt;
  if (std::isfinite(o.field_nT)) ropt.f_nT = o.field_nT;
  io::CsvReader reader(o.in_path, ropt);
  const bool has_attitude = reader.attitude_columns() != io::AttitudeColumns::kNone;
  const double offset_s = std::isfinite(o.time_offset_s) ? o.time_offset_s : cal.time_offset_s;
  std::unique_ptr<AttitudeTrack> track;
  if (has_attitude && offset_s != 0) track = std::make_unique<AttitudeTrack>(o.in_path, ropt);
  // Default outlier bound: six times the calibration's residual RMS, at least 1 nT.
  const double outlier_nT = std::isfinite(o.outlier_nT)
                                ? o.outlier_nT
                                : std::fmax(6.0 * cal.quality.residual_rms_after_nT, 1.0);

  std::vector<std::string> columns = {"t_s",    "hx_nT",  "hy_nT",  "hz_nT",
                                      "hsx_nT", "hsy_nT", "hsz_nT", "F_nT"};
  if (has_attitude) columns.insert(columns.end(), {"hE_nT", "hN_nT", "hU_nT"});
  columns.emplace_back("flags");
  io::CsvWriter writer(o.out_path, columns,
                       {"magvec apply: calibration " + o.cal_path + " (method " +
                            cal.provenance.method + ") applied to " + o.in_path,
                        "magnetometer-INS time offset " + fixed(offset_s * 1e3, 3) +
                            " ms: attitude taken at t_s - offset",
                        "flags: 1 dropout, 4 no attitude, 32 outlier (|F - F_ref| > " +
                            fixed(outlier_nT, 3) + " nT)"});

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
        core::Mat3<double> r_bn;
        const bool att = track ? track->at(rec.t_s - offset_s, &r_bn)
                               : (rec.r_bn ? (r_bn = *rec.r_bn, true) : false);
        if (att) {
          const core::Vec3<double> h_n = core::Compensator<double>::to_nav(c.h_b, r_bn);
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
      app.add_subcommand("apply",
                         "Compensate a recording with a calibration (cal.json) (exit 0 ok, 2 bad "
                         "input: the recording or cal.json)");
  cmd->add_option("--cal", opts->cal_path, "Calibration file (cal.json)")->required();
  cmd->add_option("--in", opts->in_path, "Input CSV recording")->required();
  cmd->add_option("--out", opts->out_path, "Output CSV")->required();
  cmd->add_option("--field-nT", opts->field_nT, "Reference total field when the input has no F_nT")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--outlier-nT", opts->outlier_nT,
                  "Flag samples whose |F - F_ref| exceeds this (default 6x the calibration RMS)")
      ->check(CLI::PositiveNumber);
  cmd->add_option("--time-offset-s", opts->time_offset_s,
                  "Magnetometer-minus-INS time offset [s] (default: the calibration's "
                  "time_offset_s)")
      ->check(CLI::Range(-10.0, 10.0));
  // Bad input (the recording or cal.json unreadable, malformed or out of range) exits 2 like
  // `magvec calibrate`; the messages name the file and the cause (and the line and column of a
  // CSV). Other failures (e.g. the output cannot be written) exit 1 through main.
  cmd->callback([opts] {
    try {
      run(*opts);
    } catch (const io::CsvError& e) {
      throw CommandExit(2, e.what());
    } catch (const CalibrationFileError& e) {
      throw CommandExit(2, e.what());
    }
  });
}

}  // namespace magvec::host::cli
