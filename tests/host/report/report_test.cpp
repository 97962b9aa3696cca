// Tests of `magvec report` (host/report): the numbers (equal-area coverage, parameter table, trace
// reading, residuals and the fitted ellipsoid written to DIR/data) and the whole report through the
// CLI: every figure a valid, non-trivial PNG that index.html references, clear errors for bad input
// and missing python3/matplotlib, and a headless Chromium screenshot of the page that is not blank.
#include <gtest/gtest.h>

#include <stdlib.h>
#include <sys/wait.h>
#include <unistd.h>
#include "support/process.hpp"

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <numbers>
#include <random>
#include <sstream>
#include <string>
#include <vector>

#include <nlohmann/json.hpp>

#include "calibration/calibration_file.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/io/csv.hpp"
#include "report/report.hpp"

namespace {

namespace fs = std::filesystem;
namespace rp = magvec::host::report;
using magvec::core::Vec3;

using Result = magvec::test::CommandResult;

Result shell(const std::string& cmd) {
  return magvec::test::run_shell(cmd);
}

Result magvec(const std::string& args, const std::string& env = "") {
  return shell(env + (env.empty() ? "" : " ") + MAGVEC_CLI + " " + args);
}

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

// A calibration "result" near the truth: the truth model slightly perturbed (Ks x 1.0002 on x,
// 3 nT more offset on y), with sigmas, quality, counts and provenance as a calibrator writes them.
magvec::host::CalibrationFile perturbed_cal(const magvec::core::SensorModel<double>& truth,
                                            const Vec3<double>& h_n, const std::string& method) {
  magvec::core::LiParams<double> li;
  EXPECT_EQ(magvec::core::to_li(truth, &li), magvec::core::ConversionStatus::kOk);
  li.ks(0) *= 1.0002;
  li.kof(1) += 3.0;
  magvec::host::CalibrationFile cal;
  cal.model = magvec::core::from_li(li);
  cal.h_n_nT = h_n;
  cal.sigma["ks"] = {1.1e-4, 1.2e-4, 1.3e-4};
  cal.sigma["O_deg"] = {0.01, 0.02, 0.03};
  cal.sigma["Kof_nT"] = {0.5, 0.6, 0.7};
  cal.sigma["Rm_deg"] = {0.02, 0.03, 0.04};
  cal.quality.verdict = "ok";
  cal.quality.reason = "residual 0.4 nT < 1 nT; coverage 0.81 >= 0.5";
  cal.quality.coverage = 0.81;
  cal.quality.condition = 123.0;
  cal.quality.residual_rms_before_nT = 2500.0;
  cal.quality.residual_rms_after_nT = 0.4;
  cal.counts = {6600, 6590, 7, 3};
  cal.provenance = {"survey.csv", method, "0.1.0", "2024-01-01T00:00:00Z"};
  return cal;
}

// EKF trace as `magvec calibrate --trace` writes it (update, t_s, status, C^-1, b, sigmas, nis):
// each state relaxes exponentially from its initial value to the calibration, its sigma shrinks.
void write_trace(const fs::path& path, const magvec::core::SensorModel<double>& m, int updates) {
  std::ofstream out(path);
  out << "# synthetic EKF trace\nupdate,t_s,status";
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c)
      out << ",cinv" << r << c;
  }
  out << ",b_x_nT,b_y_nT,b_z_nT";
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c)
      out << ",sigma_cinv" << r << c;
  }
  out << ",sigma_b_x_nT,sigma_b_y_nT,sigma_b_z_nT,nis\n";
  const magvec::core::GeParams<double> ge = magvec::core::to_ge(m);
  for (int k = 0; k < updates; ++k) {
    const double decay = std::exp(-k / 30.0);
    out << k << "," << 0.1 * k << "," << (k % 17 == 5 ? "rejected" : "ok");
    for (int r = 0; r < 3; ++r) {
      for (int c = 0; c < 3; ++c) {
        const double init = r == c ? 1.0 : 0.0;
        out << ","
            << ge.c_inv(r, c) + (init - ge.c_inv(r, c)) * decay +
                   2e-4 * std::sin(0.7 * k + r + 3 * c) * decay;
      }
    }
    for (int i = 0; i < 3; ++i)
      out << "," << ge.b(i) * (1.0 - decay);
    for (int i = 0; i < 9; ++i)
      out << "," << 0.05 * decay + 1e-4;
    for (int i = 0; i < 3; ++i)
      out << "," << 200.0 * decay + 0.5;
    out << "," << 1.0 + 0.5 * std::sin(0.3 * k) << "\n";
  }
}

struct Png {
  bool valid = false;
  std::uint32_t width = 0, height = 0;
  std::uintmax_t bytes = 0;
};

// PNG signature, then the IHDR chunk first with its width and height (big-endian).
Png read_png_header(const fs::path& p) {
  Png png;
  const std::string s = slurp(p);
  png.bytes = s.size();
  static const unsigned char kSig[] = {0x89, 'P', 'N', 'G', '\r', '\n', 0x1a, '\n'};
  if (s.size() < 33 || s.compare(0, 8, std::string(reinterpret_cast<const char*>(kSig), 8)) != 0 ||
      s.compare(12, 4, "IHDR") != 0) {
    return png;
  }
  const auto be32 = [&](std::size_t at) {
    std::uint32_t v = 0;
    for (std::size_t i = 0; i < 4; ++i)
      v = (v << 8) | static_cast<unsigned char>(s[at + i]);
    return v;
  };
  png.valid = be32(8) == 13;
  png.width = be32(16);
  png.height = be32(20);
  return png;
}

struct PixelStats {
  bool ok = false;
  int width = 0, height = 0, colours = 0;
  double non_background = 0;
};

// Decodes the PNG with Pillow (tests/host/report/png_stats.py).
PixelStats pixel_stats(const fs::path& png) {
  const Result r =
      shell(std::string("/usr/bin/python3 ") + MAGVEC_PNG_STATS + " '" + png.string() + "'");
  PixelStats s;
  std::istringstream in(r.output);
  s.ok = r.status == 0 &&
         static_cast<bool>(in >> s.width >> s.height >> s.colours >> s.non_background);
  if (!s.ok) ADD_FAILURE() << "png_stats.py failed on " << png << ": " << r.output;
  return s;
}

std::size_t col(const rp::TraceTable& t, const std::string& name) {
  for (std::size_t i = 0; i < t.names.size(); ++i) {
    if (t.names[i] == name) return i;
  }
  ADD_FAILURE() << "no column " << name;
  return 0;
}

class ReportData : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "magvec_report_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
  }
  void TearDown() override {
    if (std::getenv("MAGVEC_TEST_KEEP") == nullptr) fs::remove_all(dir_);
  }
  std::string file(const std::string& name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

// --------------------------------------------------------------------------------------------
// Library: the numbers

TEST(CoverageGrid, CellsHaveEqualArea) {
  rp::CoverageGrid g(12, 24);
  std::mt19937_64 rng(42);
  std::normal_distribution<double> n01;
  constexpr int kN = 288000;
  for (int i = 0; i < kN; ++i)
    g.add(Vec3<double>(n01(rng), n01(rng), n01(rng)));
  const double expected = static_cast<double>(kN) / static_cast<double>(g.cells());  // 1000
  for (int b = 0; b < g.bands(); ++b) {
    for (int s = 0; s < g.sectors(); ++s) {
      // Binomial SD ~ sqrt(1000) = 31.6: 5 SD.
      EXPECT_NEAR(static_cast<double>(g.count(b, s)), expected, 5 * std::sqrt(expected))
          << "band " << b << " sector " << s;
    }
  }
  EXPECT_EQ(g.covered(), g.cells());
  EXPECT_DOUBLE_EQ(g.fraction(), 1.0);
  EXPECT_NEAR(g.band_edge_lat_rad(0), -std::numbers::pi / 2, 1e-12);
  EXPECT_NEAR(g.band_edge_lat_rad(6), 0.0, 1e-12);
  EXPECT_NEAR(g.band_edge_lat_rad(12), std::numbers::pi / 2, 1e-12);
}

TEST(CoverageGrid, PlanarMotionCoversOneBandAndBadVectorsAreIgnored) {
  rp::CoverageGrid g(12, 24);
  for (int i = 0; i < 3600; ++i) {
    const double a = 2 * std::numbers::pi * (i + 0.5) / 3600.0;  // never on a sector edge
    g.add(Vec3<double>(std::cos(a), std::sin(a), 0.01));
  }
  g.add(Vec3<double>::Zero());
  g.add(Vec3<double>(std::nan(""), 1, 0));
  EXPECT_EQ(g.covered(), 24u);
  EXPECT_NEAR(g.fraction(), 1.0 / 12.0, 1e-12);
  for (int s = 0; s < 24; ++s)
    EXPECT_EQ(g.count(6, s), 150u);
}

TEST(ParameterTable, PaperFormsWithSigmaFromCalJson) {
  const magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_li2023();
  magvec::host::CalibrationFile cal = perturbed_cal(cfg.truth, cfg.h_n_nT, "batch");
  const std::vector<rp::ParamRow> rows = rp::parameter_table(cal);
  magvec::core::LiParams<double> li;
  ASSERT_EQ(magvec::core::to_li(cal.model, &li), magvec::core::ConversionStatus::kOk);
  const auto find = [&](const std::string& name) -> const rp::ParamRow& {
    for (const rp::ParamRow& r : rows) {
      if (r.name == name) return r;
    }
    ADD_FAILURE() << "no row " << name;
    return rows.front();
  };
  EXPECT_NEAR(find("Ksx").value, 1.08 * 1.0002, 1e-9);
  EXPECT_DOUBLE_EQ(find("Ksy").sigma, 1.2e-4);
  EXPECT_NEAR(find("O2").value, li.o_rad(1) * 180 / std::numbers::pi, 1e-12);
  EXPECT_EQ(find("O2").unit, "deg");
  EXPECT_DOUBLE_EQ(find("O3").sigma, 0.03);
  EXPECT_NEAR(find("Kofy").value, cfg.truth.o(1) + 3.0, 1e-9);
  EXPECT_DOUBLE_EQ(find("gamma_m").sigma, 0.04);
  const magvec::core::GeParams<double> ge = magvec::core::to_ge(cal.model);
  EXPECT_NEAR(find("Cinv12").value, ge.c_inv(1, 2), 1e-15);
  EXPECT_TRUE(std::isnan(find("Cinv12").sigma));  // none in cal.json
  EXPECT_NEAR(find("h_U").value, cfg.h_n_nT(2), 1e-9);
  EXPECT_EQ(rows.size(), 12u + 12u + 3u);  // Li, Ge, h_n; no sine block
}

TEST_F(ReportData, TraceColumnsPairWithTheirSigmas) {
  std::ofstream(file("t.csv")) << "# c\nupdate, t_s, status, cinv00, b_x_nT, sigma_cinv00, "
                                  "sigma_b_x, extra, nis\n0,0,ok,1,0,0.1,5,nan,1\n1,0.1,bad,1.1,"
                                  "2,0.05,4,3,0.9\n";
  const rp::TraceTable t = rp::read_trace_csv(file("t.csv"));
  ASSERT_EQ(t.rows.size(), 2u);
  EXPECT_FALSE(t.numeric[2]);
  const std::vector<rp::TraceParam> p = rp::trace_params(t);
  ASSERT_EQ(p.size(), 2u);  // the states: the columns with a sigma column
  EXPECT_EQ(p[0].name, "cinv00");
  EXPECT_EQ(p[0].sigma_column, std::optional<std::size_t>(5));
  EXPECT_EQ(p[1].name, "b_x_nT");
  EXPECT_EQ(p[1].sigma_column, std::optional<std::size_t>(6));  // sigma_b_x (unit dropped)
  // The rest but the bookkeeping columns are diagnostics, drawn without a band.
  const std::vector<rp::TraceParam> d = rp::trace_diagnostics(t);
  ASSERT_EQ(d.size(), 2u);
  EXPECT_EQ(d[0].name, "extra");
  EXPECT_EQ(d[1].name, "nis");
  EXPECT_DOUBLE_EQ(t.rows[1][3], 1.1);

  std::ofstream(file("bad.csv")) << "update,cinv00\n0,1\n1\n";
  try {
    rp::read_trace_csv(file("bad.csv"));
    FAIL() << "a ragged row must be an error";
  } catch (const rp::ReportError& e) {
    EXPECT_NE(std::string(e.what()).find("bad.csv:3"), std::string::npos) << e.what();
  }
  EXPECT_THROW(rp::read_trace_csv(file("missing.csv")), rp::ReportError);
}

// Writes a li2023-style recording (random attitudes, F and Li attitude columns) with the Simulator.
void write_sim(const std::string& path, magvec::drivers::sim::ScenarioConfig cfg, bool attitude,
               std::uint64_t seed) {
  magvec::drivers::sim::Simulator sim(cfg, seed);
  std::vector<std::string> cols = {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT"};
  if (attitude) cols.insert(cols.end(), {"alpha_deg", "beta_deg", "gamma_deg"});
  magvec::host::io::CsvWriter w(path, cols);
  magvec::drivers::sim::SimSample s;
  while (sim.next(&s)) {
    std::vector<double> row = {s.t_s, s.m_nT(0), s.m_nT(1), s.m_nT(2), s.f_nT};
    if (attitude) {
      const magvec::core::LiEuler<double> e = magvec::core::li_from_r_bn(s.r_bn_ins);
      for (double a : {e.alpha, e.beta, e.gamma})
        row.push_back(a * 180 / std::numbers::pi);
    }
    w.write_row(row);
  }
  w.commit();
}

TEST_F(ReportData, DataFilesHoldResidualsEllipsoidAndSubsampledSamples) {
  magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_li2023();
  cfg.num_samples = 5000;
  cfg.mag_noise_nT = 0.5;
  cfg.dropout_probability = 0.01;
  cfg.ins_noise_deg = 0.0;  // E/N/U then differ from h_n by the magnetometer noise only
  write_sim(file("li.csv"), cfg, true, 7);
  magvec::host::CalibrationFile cal;  // the exact truth
  cal.model = cfg.truth;
  cal.h_n_nT = cfg.h_n_nT;
  magvec::host::write_calibration_file(file("cal.json"), cal);

  rp::ReportOptions o;
  o.cal_path = file("cal.json");
  o.in_path = file("li.csv");
  o.out_dir = file("out");
  o.max_points = 700;
  const rp::ReportResult r = rp::write_report_data(o);
  EXPECT_EQ(r.rows, 5000u);
  EXPECT_GT(r.dropouts, 20u);
  EXPECT_LT(r.dropouts, 90u);
  // With the truth, |h_s| - F is the magnetometer noise (0.5 nT/axis -> ~0.5 nT along the field).
  EXPECT_LT(r.rms_after_nT, 0.7);
  EXPECT_GT(r.rms_after_nT, 0.3);
  EXPECT_GT(r.rms_before_nT, 100.0);  // Li's scale factors are several percent off
  EXPECT_GT(r.coverage, 0.9);         // random attitudes cover the sphere
  const std::vector<std::string> figs = {"fig_ellipsoid.png", "fig_residual.png", "fig_enu.png",
                                         "fig_coverage.png"};
  EXPECT_EQ(r.figures, figs);

  // The ellipsoid surface satisfies |W (e - o)| = F (the reference: mean F of the file).
  const rp::TraceTable surf = rp::read_trace_csv(file("out/data/surface.csv"));
  ASSERT_EQ(surf.rows.size(), 19u * 37u);
  const double f0 = cfg.h_n_nT.norm();
  for (const std::vector<double>& row : surf.rows) {
    const Vec3<double> e(row[2], row[3], row[4]);
    EXPECT_NEAR((cfg.truth.w * (e - cfg.truth.o)).norm(), f0, 1e-6);
    EXPECT_NEAR(Vec3<double>(row[5], row[6], row[7]).norm(), f0, 1e-6);
  }
  // One sample per bucket of ceil(5000/700) = 8 rows.
  const rp::TraceTable samples = rp::read_trace_csv(file("out/data/samples.csv"));
  EXPECT_GE(samples.rows.size(), 600u);
  EXPECT_LE(samples.rows.size(), 700u);
  const rp::TraceTable res = rp::read_trace_csv(file("out/data/residual.csv"));
  EXPECT_GE(res.rows.size(), 600u);
  const std::size_t mean = col(res, "after_mean"), lo = col(res, "after_min"),
                    hi = col(res, "after_max");
  for (const std::vector<double>& row : res.rows) {
    EXPECT_LE(row[lo], row[mean] + 1e-12);
    EXPECT_LE(row[mean], row[hi] + 1e-12);
    EXPECT_LT(std::abs(row[mean]), 1.0);
    EXPECT_GT(std::abs(row[col(res, "before_mean")]), 100.0);
  }
  // E/N/U after calibration (truth, exact attitude) match h_n within the magnetometer noise.
  const std::string json = slurp(file("out/data/report.json"));
  EXPECT_NE(json.find("\"schema\": \"magvec-report-data/1\""), std::string::npos);
  const rp::TraceTable enu = rp::read_trace_csv(file("out/data/enu.csv"));
  for (const std::vector<double>& row : enu.rows) {
    EXPECT_NEAR(row[3 + 9], cfg.h_n_nT(0), 2.0);   // E_after_mean
    EXPECT_NEAR(row[3 + 15], cfg.h_n_nT(2), 2.0);  // U_after_mean
  }
}

TEST_F(ReportData, ReferenceFieldFromOptionWhenTheFileHasNoF) {
  magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_li2023();
  cfg.num_samples = 400;
  cfg.mag_noise_nT = 0.0;
  {
    magvec::drivers::sim::Simulator sim(cfg, 11);
    magvec::host::io::CsvWriter w(file("nof.csv"), {"t_s", "hx_nT", "hy_nT", "hz_nT"});
    magvec::drivers::sim::SimSample s;
    while (sim.next(&s)) {
      const double row[] = {s.t_s, s.m_nT(0), s.m_nT(1), s.m_nT(2)};
      w.write_row(row);
    }
    w.commit();
  }
  magvec::host::CalibrationFile cal;
  cal.model = cfg.truth;
  magvec::host::write_calibration_file(file("cal.json"), cal);
  rp::ReportOptions o;
  o.cal_path = file("cal.json");
  o.in_path = file("nof.csv");
  o.out_dir = file("a");
  // No reference: no residual figure, and the sphere radius is the mean calibrated intensity.
  rp::ReportResult r = rp::write_report_data(o);
  EXPECT_EQ(r.figures, (std::vector<std::string>{"fig_ellipsoid.png", "fig_coverage.png"}));
  EXPECT_TRUE(std::isnan(r.rms_after_nT));
  EXPECT_NE(slurp(file("a/data/report.json")).find("mean calibrated intensity"), std::string::npos);
  o.field_nT = cfg.h_n_nT.norm();
  o.out_dir = file("b");
  r = rp::write_report_data(o);
  EXPECT_EQ(r.figures, (std::vector<std::string>{"fig_ellipsoid.png", "fig_residual.png",
                                                 "fig_coverage.png"}));
  EXPECT_LT(r.rms_after_nT, 1e-6);  // noise-free scenario, exact calibration
  EXPECT_NE(slurp(file("b/data/report.json")).find("--field-nT"), std::string::npos);
}

TEST_F(ReportData, BadInputsAreClearErrors) {
  rp::ReportOptions o;
  o.cal_path = file("none.json");
  o.in_path = file("none.csv");
  o.out_dir = file("out");
  EXPECT_THROW(rp::write_report_data(o), magvec::host::CalibrationFileError);
  magvec::host::CalibrationFile cal;
  magvec::host::write_calibration_file(file("cal.json"), cal);
  o.cal_path = file("cal.json");
  EXPECT_THROW(rp::write_report_data(o), magvec::host::io::CsvError);
  std::ofstream(file("empty.csv")) << "t_s,hx_nT,hy_nT,hz_nT\n";
  o.in_path = file("empty.csv");
  EXPECT_THROW(rp::write_report_data(o), rp::ReportError);
  std::ofstream(file("drop.csv")) << "t_s,hx_nT,hy_nT,hz_nT\n0,nan,nan,nan\n";
  o.in_path = file("drop.csv");
  EXPECT_THROW(rp::write_report_data(o), rp::ReportError);
}

// --------------------------------------------------------------------------------------------
// The whole report through the CLI

class ReportCli : public ReportData {
 protected:
  // A survey recording through `magvec simulate` (20 Hz, 6600 rows), a calibration near the
  // truth and a synthetic EKF trace, then `magvec report`.
  void build_full_report(const std::string& method = "batch (Li et al. 2023)") {
    const Result sim = magvec(
        "simulate --scenario survey --seed 5 --rate-hz 20 --samples 6600 "
        "--noise-nT 0.3 --dropout-rate 0.002 --out " +
        file("survey.csv"));
    ASSERT_EQ(sim.status, 0) << sim.output;
    const magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_survey();
    const magvec::host::CalibrationFile cal = perturbed_cal(cfg.truth, cfg.h_n_nT, method);
    magvec::host::write_calibration_file(file("cal.json"), cal);
    write_trace(file("trace.csv"), cal.model, 300);
    const Result r = magvec("report --cal " + file("cal.json") + " --in " + file("survey.csv") +
                            " --trace " + file("trace.csv") + " --out " + file("rep"));
    ASSERT_EQ(r.status, 0) << r.output;
    EXPECT_NE(r.output.find(file("rep/index.html")), std::string::npos) << r.output;
    html_ = slurp(file("rep/index.html"));
  }
  std::string html_;
};

const std::vector<std::string> kAllFigures = {"fig_ellipsoid.png", "fig_residual.png",
                                              "fig_enu.png", "fig_ekf.png", "fig_coverage.png"};

TEST_F(ReportCli, EveryFigureIsAValidPngReferencedByThePage) {
  ASSERT_NO_FATAL_FAILURE(build_full_report());
  for (const std::string& f : kAllFigures) {
    SCOPED_TRACE(f);
    const fs::path p = dir_ / "rep" / f;
    ASSERT_TRUE(fs::is_regular_file(p));
    const Png png = read_png_header(p);
    EXPECT_TRUE(png.valid);
    EXPECT_GE(png.width, 600u);
    EXPECT_GE(png.height, 300u);
    EXPECT_GT(png.bytes, 20000u);
    // Decoded: a drawing, not an empty canvas.
    const PixelStats s = pixel_stats(p);
    EXPECT_EQ(s.width, static_cast<int>(png.width));
    EXPECT_GT(s.colours, 200);
    EXPECT_GT(s.non_background, 0.03);
    EXPECT_NE(html_.find("<img src=\"" + f + "\""), std::string::npos);
  }
  // Self-contained, phone-readable, states data file, method, version and time.
  EXPECT_NE(html_.find("<meta name=\"viewport\" content=\"width=device-width"), std::string::npos);
  EXPECT_NE(html_.find("img{max-width:100%"), std::string::npos);
  EXPECT_EQ(html_.find("http://"), std::string::npos);
  EXPECT_EQ(html_.find("https://"), std::string::npos);
  EXPECT_NE(html_.find(file("survey.csv")), std::string::npos);
  EXPECT_NE(html_.find("batch (Li et al. 2023)"), std::string::npos);
  EXPECT_NE(html_.find("magvec 0."), std::string::npos);
  EXPECT_NE(html_.find("Verdict: ok"), std::string::npos);
  EXPECT_NE(html_.find("residual 0.4 nT &lt; 1 nT"), std::string::npos);  // escaped
  // The parameter table with the paper's names and sigmas (Ksx 1.08 x 1.0002, sigma 1.1e-4).
  EXPECT_NE(html_.find("Li et al. 2023"), std::string::npos);
  EXPECT_NE(html_.find("<td>Ksx</td><td class=\"n\">1.08022</td><td class=\"n\">0.00011</td>"),
            std::string::npos);
  EXPECT_NE(html_.find("Calibration: rejected outliers</th><td class=\"n\">3<"), std::string::npos);
  EXPECT_NE(html_.find("Calibration: skipped (non-finite)</th><td class=\"n\">7<"),
            std::string::npos);
  EXPECT_NE(html_.find("Ge et al. 2017"), std::string::npos);
  EXPECT_NE(html_.find("Filter: final estimates"), std::string::npos);
}

// The truth a simulated file states, in the names the traces use; nothing for other files.
TEST_F(ReportData, SimulationTruthFromTheFileHeader) {
  const Result sim = magvec("simulate --scenario survey --samples 50 --ins-latency-s 0.012 --out " +
                            file("s.csv"));
  ASSERT_EQ(sim.status, 0) << sim.output;
  const magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_survey();
  const auto truth = rp::simulation_truth(magvec::host::io::CsvReader(file("s.csv")).comments());
  const magvec::core::Mat3<double>& w = cfg.truth.w;
  EXPECT_DOUBLE_EQ(truth.at("W00"), w(0, 0));
  EXPECT_DOUBLE_EQ(truth.at("W12"), w(1, 2));
  EXPECT_DOUBLE_EQ(truth.at("W21"), w(2, 1));
  EXPECT_DOUBLE_EQ(truth.at("o_y_nT"), cfg.truth.o(1));
  EXPECT_DOUBLE_EQ(truth.at("b_z_nT"), cfg.truth.o(2));
  magvec::core::LiParams<double> li;
  ASSERT_EQ(magvec::core::to_li(cfg.truth, &li), magvec::core::ConversionStatus::kOk);
  EXPECT_NEAR(truth.at("bm_deg"), li.rm_rad(1) * 180 / std::numbers::pi, 1e-12);
  EXPECT_DOUBLE_EQ(truth.at("hN_nT"), cfg.h_n_nT(1));
  EXPECT_DOUBLE_EQ(truth.at("dt_s"), -0.012);  // magnetometer minus INS: the attitude is older
  EXPECT_DOUBLE_EQ(truth.at("c_x_nT_per_degC"), 0.0);
  EXPECT_EQ(truth.count("cinv00"), 0u);  // a scalar-only filter's C^-1 is free up to a rotation
  // A varying field has no single true h_n.
  ASSERT_EQ(
      magvec("simulate --scenario survey --samples 50 --diurnal-nT 0 0 20 --out " + file("d.csv"))
          .status,
      0);
  const auto varying = rp::simulation_truth(magvec::host::io::CsvReader(file("d.csv")).comments());
  EXPECT_EQ(varying.count("hE_nT"), 0u);
  EXPECT_EQ(varying.count("W00"), 1u);
  EXPECT_TRUE(rp::simulation_truth({"a recording", "truth canonical: W = A^-1 = [[1]]"}).empty());
}

// The vector filter's report: every state plotted with its 1-sigma band and the simulation's
// truth; the final estimates are scored against that truth in the page. On a survey with an
// unknown 10 ms INS latency every state lies within 4 of its 1-sigmas of the truth.
TEST_F(ReportCli, VectorEkfTraceStatesWithTheirBandsAndTheTruth) {
  ASSERT_EQ(magvec("simulate --scenario survey --samples 12000 --ins-latency-s 0.01 --seed 7 "
                   "--out " +
                   file("sv.csv"))
                .status,
            0);
  const Result c = magvec("calibrate --method vector-ekf --in " + file("sv.csv") + " --out " +
                          file("cal.json") + " --trace " + file("trace.csv"));
  ASSERT_EQ(c.status, 0) << c.output;
  const Result r = magvec("report --cal " + file("cal.json") + " --in " + file("sv.csv") +
                          " --trace " + file("trace.csv") + " --out " + file("rep"));
  ASSERT_EQ(r.status, 0) << r.output;
  const nlohmann::json rep = nlohmann::json::parse(slurp(file("rep/data/report.json")));
  const nlohmann::json& tr = rep.at("trace");
  EXPECT_EQ(tr.at("x"), "t_s");
  EXPECT_EQ(tr.at("params").size(), 19u);  // the filter's 19 states
  EXPECT_EQ(tr.at("truth_params"), 19u);
  EXPECT_EQ(tr.at("diagnostics").size(), 5u);  // nis and the four innovations
  int scored = 0;
  for (const nlohmann::json& f : tr.at("final")) {
    SCOPED_TRACE(f.dump());
    ASSERT_FALSE(f.at("z").is_null());
    EXPECT_LT(std::abs(f.at("z").get<double>()), 4.0);
    ++scored;
  }
  EXPECT_EQ(scored, 19);
  bool dt_ms = false;
  for (const nlohmann::json& f : tr.at("final"))
    dt_ms = dt_ms || (f.at("name") == "dt_ms" && f.at("truth").get<double>() == -10.0);
  EXPECT_TRUE(dt_ms);  // seconds shown in milliseconds
  const std::string html = slurp(file("rep/index.html"));
  EXPECT_NE(html.find("(value - truth) / 1-sigma"), std::string::npos);
  const PixelStats s = pixel_stats(dir_ / "rep" / "fig_ekf.png");
  EXPECT_GT(s.colours, 200);
}

TEST_F(ReportCli, TextFromFilesIsEscaped) {
  ASSERT_NO_FATAL_FAILURE(build_full_report("<script>alert(1)</script> & co"));
  EXPECT_EQ(html_.find("<script>"), std::string::npos);
  EXPECT_NE(html_.find("&lt;script&gt;alert(1)&lt;/script&gt; &amp; co"), std::string::npos);
}

TEST_F(ReportCli, WithoutAttitudeOrTraceThoseFiguresAreOmittedAndSaidSo) {
  magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_li2023();
  cfg.num_samples = 800;
  cfg.mag_noise_nT = 0.3;
  write_sim(file("noatt.csv"), cfg, false, 3);
  magvec::host::write_calibration_file(file("cal.json"),
                                       perturbed_cal(cfg.truth, cfg.h_n_nT, "ellipsoid"));
  const Result r = magvec("report --cal " + file("cal.json") + " --in " + file("noatt.csv") +
                          " --out " + file("rep"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_TRUE(fs::is_regular_file(dir_ / "rep" / "fig_ellipsoid.png"));
  EXPECT_TRUE(fs::is_regular_file(dir_ / "rep" / "fig_residual.png"));
  EXPECT_TRUE(fs::is_regular_file(dir_ / "rep" / "fig_coverage.png"));
  EXPECT_FALSE(fs::exists(dir_ / "rep" / "fig_enu.png"));
  EXPECT_FALSE(fs::exists(dir_ / "rep" / "fig_ekf.png"));
  const std::string html = slurp(file("rep/index.html"));
  EXPECT_NE(html.find("the data file has no attitude"), std::string::npos);
  EXPECT_NE(html.find("no trace given"), std::string::npos);
}

TEST_F(ReportCli, BadInputsAndMissingToolsAreClearErrors) {
  std::ofstream(file("d.csv")) << "t_s,hx_nT,hy_nT,hz_nT,F_nT\n0,1,2,3,4\n1,1,2,x,4\n";
  Result r = magvec("report --cal " + file("none.json") + " --in " + file("d.csv") + " --out " +
                    file("rep"));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("none.json"), std::string::npos) << r.output;

  std::ofstream(file("bad.json")) << "{\"schema\": \"magvec-calibration/1\", \"W\": [1,2]}";
  r = magvec("report --cal " + file("bad.json") + " --in " + file("d.csv") + " --out " +
             file("rep"));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("bad.json"), std::string::npos) << r.output;

  magvec::host::CalibrationFile cal;
  magvec::host::write_calibration_file(file("cal.json"), cal);
  r = magvec("report --cal " + file("cal.json") + " --in " + file("d.csv") + " --out " +
             file("rep"));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("d.csv"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("3"), std::string::npos) << r.output;  // line 3

  std::ofstream(file("ok.csv")) << "t_s,hx_nT,hy_nT,hz_nT,F_nT\n0,1,2,3,4\n1,3,2,1,4\n";
  const std::string args =
      "report --cal " + file("cal.json") + " --in " + file("ok.csv") + " --out " + file("rep");
  r = magvec(args, "MAGVEC_PYTHON=/nonexistent/python3");
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("install the Debian packages python3 python3-matplotlib"),
            std::string::npos)
      << r.output;

  // A python3 whose `import matplotlib` fails.
  fs::create_directories(dir_ / "fake" / "matplotlib");
  std::ofstream(dir_ / "fake" / "matplotlib" / "__init__.py")
      << "raise ImportError('No module named matplotlib')\n";
  r = magvec(args, "PYTHONPATH=" + file("fake"));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("install the Debian package python3-matplotlib"), std::string::npos)
      << r.output;

  r = magvec(args, "MAGVEC_REPORT_SCRIPT=" + file("nope.py"));
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("nope.py"), std::string::npos) << r.output;

  // And the same inputs with the real python3 work.
  r = magvec(args);
  EXPECT_EQ(r.status, 0) << r.output;
}

// Headless Chromium renders the page (phone width) to a screenshot that shows the figures.
TEST_F(ReportCli, ChromiumRendersThePage) {
  const char* chromium = nullptr;
  for (const char* c : {"/usr/bin/chromium", "/usr/bin/chromium-browser"}) {
    if (::access(c, X_OK) == 0) {
      chromium = c;
      break;
    }
  }
  if (chromium == nullptr) {
    GTEST_SKIP() << "chromium is not installed (Debian package chromium; toolchain/setup "
                    "installs it): the rendering check did not run";
  }
  ASSERT_NO_FATAL_FAILURE(build_full_report());
  const fs::path profile = dir_ / "chromium-profile";
  fs::create_directories(profile);
  const fs::path shot = dir_ / "screenshot.png";
  const std::string cmd = std::string("timeout 120 ") + chromium +
                          " --headless --no-sandbox --disable-gpu --disable-background-networking"
                          " --disable-component-update --disable-sync --no-first-run --disable-quic"
                          " --hide-scrollbars --user-data-dir='" +
                          profile.string() + "' --screenshot='" + shot.string() +
                          "' --window-size=412,2600 'file://" +
                          (dir_ / "rep" / "index.html").string() + "'";
  const Result r = shell(cmd);
  ASSERT_TRUE(fs::is_regular_file(shot)) << cmd << "\n" << r.output;
  const Png png = read_png_header(shot);
  ASSERT_TRUE(png.valid);
  EXPECT_EQ(png.width, 412u);
  const PixelStats s = pixel_stats(shot);
  // Text, the verdict box and the (scaled) figures: thousands of colours, much non-white.
  EXPECT_GT(s.colours, 500) << "blank screenshot? " << shot;
  EXPECT_GT(s.non_background, 0.10);
}

}  // namespace
