// `magvec calibrate --site/--date` end to end: a recording without F takes its reference field
// from the WMM2025 model (host/geomag) and reaches the accuracy the model's stated uncertainty
// allows; a measured F column wins unless --model-f; malformed options exit 2 with the option
// named.
//
// The recording: the simulator's Li 2023 sensor (scale, non-orthogonality, offset, misalignment)
// under a rotating, tilting INS, in a true field equal to the model's at the site plus an offset
// within the model's 1-sigma (the model is never exact: the offset stands for its error).
#include <gtest/gtest.h>
#include <stdlib.h>

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <random>
#include <string>

#include "calibration/calibration_file.hpp"
#include "magvec/core/compensator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/geomag/reference_field.hpp"
#include "magvec/host/io/csv.hpp"
#include "support/process.hpp"

namespace {

namespace fs = std::filesystem;
namespace geomag = magvec::host::geomag;
using magvec::core::Mat3;
using magvec::core::Vec3;
using Result = magvec::test::CommandResult;

Result run(const std::string& args) {
  return magvec::test::run_shell(std::string(MAGVEC_CLI) + " " + args);
}

// The site: Lausanne, 400 m above the ellipsoid, mid-2026.
constexpr const char* kSite = "46.52,6.63,400";
constexpr const char* kDate = "2026-06-15";

Mat3<double> attitude(double t) {
  return magvec::core::r_bn_from_li(magvec::core::LiEuler<double>{
      magvec::core::deg_to_rad(40.0 * t), magvec::core::deg_to_rad(50.0 * std::sin(0.7 * t)),
      magvec::core::deg_to_rad(70.0 * std::sin(0.5 * t + 1))});
}

class CalibrateSite : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "magvec_site_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
    model_ = geomag::MagneticModel::wmm2025().field(geomag::parse_site(kSite),
                                                    geomag::parse_date(kDate));
    // The model's error, within its 1-sigma per component (89/137/141 nT): the true field.
    truth_ = model_.enu_nT + Vec3<double>(60.0, -70.0, 50.0);
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string file(const char* name) const { return (dir_ / name).string(); }

  // 1 nT noise, 2000 rows at 100 Hz; with_f adds the (scalar magnetometer's) true F column.
  void write_recording(const std::string& path, bool with_f) const {
    const magvec::drivers::sim::ScenarioConfig s = magvec::drivers::sim::scenario_li2023();
    std::mt19937_64 rng(11);
    std::normal_distribution<double> g(0.0, 1.0);
    std::vector<std::string> cols = {"t_s", "hx_nT", "hy_nT", "hz_nT", "qw", "qx", "qy", "qz"};
    if (with_f) cols.insert(cols.begin() + 4, "F_nT");
    magvec::host::io::CsvWriter w(path, cols);
    for (int i = 0; i < 2000; ++i) {
      const double t = 0.01 * i;
      const Vec3<double> m =
          s.truth.predict_raw(attitude(t), truth_) + Vec3<double>(g(rng), g(rng), g(rng));
      const magvec::core::Quat<double> q(Mat3<double>(attitude(t).transpose()));
      std::vector<double> row = {t, m(0), m(1), m(2), q.w(), q.x(), q.y(), q.z()};
      if (with_f) row.insert(row.begin() + 4, truth_.norm());
      w.write_row(row);
    }
    w.commit();
  }

  // Mean of the calibrated |h| - F_true and of h_n - truth over the recording.
  struct Errors {
    double f_nT = 0;
    Vec3<double> enu_nT = Vec3<double>::Zero();
  };
  Errors errors(const magvec::host::CalibrationFile& cal, const std::string& csv) const {
    const magvec::core::Compensator<double> comp(cal.model);
    magvec::host::io::CsvReaderOptions ropt;
    magvec::host::io::CsvReader reader(csv, ropt);
    magvec::host::io::CsvRecord rec;
    Errors e;
    int n = 0;
    while (reader.next(&rec)) {
      magvec::core::Compensated<double> c;
      if (!rec.r_bn || !comp.compensate(rec.m_nT, &c)) continue;
      e.f_nT += c.intensity - truth_.norm();
      e.enu_nT += magvec::core::Compensator<double>::to_nav(c.h_b, *rec.r_bn) - truth_;
      ++n;
    }
    EXPECT_EQ(n, 2000);
    e.f_nT /= n;
    e.enu_nT /= n;
    return e;
  }

  fs::path dir_;
  geomag::ReferenceField model_;
  Vec3<double> truth_;
};

TEST_F(CalibrateSite, WithoutFTheModelGivesTheAccuracyItsUncertaintyAllows) {
  write_recording(file("nof.csv"), false);
  const Result r = run("calibrate --in " + file("nof.csv") + " --out " + file("cal.json") +
                       " --site " + kSite + " --date " + kDate);
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("reference field: WMM2025 at 46.52000, 6.63000, 400.0 m on 2026-06-15"),
            std::string::npos)
      << r.output;
  EXPECT_NE(r.output.find("no F_nT column: the model's F is the reference"), std::string::npos);
  const magvec::host::CalibrationFile cal = magvec::host::read_calibration_file(file("cal.json"));
  ASSERT_TRUE(cal.reference.has_value());
  EXPECT_EQ(cal.reference->source, "model");
  EXPECT_NEAR(cal.reference->f_nT, model_.total_nT, 1e-6);
  EXPECT_EQ(cal.reference->sigma_f_nT, 138.0);
  ASSERT_TRUE(cal.reference->model.has_value());
  EXPECT_EQ(cal.reference->model->name, "WMM2025");
  EXPECT_EQ(cal.reference->model->date, kDate);
  EXPECT_NEAR((cal.reference->model->enu_nT - model_.enu_nT).norm(), 0.0, 1e-6);

  const Errors e = errors(cal, file("nof.csv"));
  // The scale follows the model's F: the calibrated |h| is off by the model's own F error, which
  // is within its stated 1-sigma; the calibration adds only noise-level error to it.
  const double model_f_error = model_.total_nT - truth_.norm();
  std::printf("F: model error %.1f nT (stated 1-sigma %.0f); calibrated |h| - F_true %.1f nT\n",
              model_f_error, model_.sigma.total_nT, e.f_nT);
  std::printf(
      "E/N/U: calibrated h_n - truth [%.1f, %.1f, %.1f] nT (model 1-sigma %.0f/%.0f/%.0f)\n",
      e.enu_nT(0), e.enu_nT(1), e.enu_nT(2), model_.sigma.enu_nT(0), model_.sigma.enu_nT(1),
      model_.sigma.enu_nT(2));
  EXPECT_LT(std::abs(e.f_nT), model_.sigma.total_nT);
  EXPECT_NEAR(e.f_nT, model_f_error, 2.0);
  for (int i = 0; i < 3; ++i)
    EXPECT_LT(std::abs(e.enu_nT(i)), model_.sigma.enu_nT(i)) << i;

  // Without a reference the scale is only relative (the median |m|): far outside the model's.
  const Result d = run("calibrate --in " + file("nof.csv") + " --out " + file("cal_data.json"));
  ASSERT_EQ(d.status, 0) << d.output;
  const Errors ed =
      errors(magvec::host::read_calibration_file(file("cal_data.json")), file("nof.csv"));
  std::printf("without --site: calibrated |h| - F_true %.1f nT\n", ed.f_nT);
  EXPECT_EQ(magvec::host::read_calibration_file(file("cal_data.json")).reference->source, "data");
}

TEST_F(CalibrateSite, AMeasuredFWinsUnlessModelFIsAsked) {
  write_recording(file("f.csv"), true);
  const Result r = run("calibrate --in " + file("f.csv") + " --out " + file("cal.json") +
                       " --site " + kSite + " --date " + kDate);
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("the file's measured F_nT is the reference"), std::string::npos)
      << r.output;
  const magvec::host::CalibrationFile cal = magvec::host::read_calibration_file(file("cal.json"));
  ASSERT_TRUE(cal.reference.has_value());
  EXPECT_EQ(cal.reference->source, "measured");
  EXPECT_TRUE(std::isnan(cal.reference->f_nT));
  ASSERT_TRUE(cal.reference->model.has_value());              // kept as a check
  EXPECT_LT(std::abs(errors(cal, file("f.csv")).f_nT), 1.0);  // the measured F: noise level
  EXPECT_NEAR(cal.quality.extra.at("h_n_minus_model_U_nT"), 50.0, 5.0);

  const Result m = run("calibrate --in " + file("f.csv") + " --out " + file("cal_m.json") +
                       " --site " + kSite + " --date " + kDate + " --model-f");
  ASSERT_EQ(m.status, 0) << m.output;
  EXPECT_NE(m.output.find("the model's F replaces the file's F_nT"), std::string::npos);
  const magvec::host::CalibrationFile cm = magvec::host::read_calibration_file(file("cal_m.json"));
  EXPECT_EQ(cm.reference->source, "model");
  EXPECT_NEAR(errors(cm, file("f.csv")).f_nT, model_.total_nT - truth_.norm(), 2.0);
}

TEST_F(CalibrateSite, MalformedOptionsExit2WithTheOptionNamed) {
  write_recording(file("nof.csv"), false);
  const std::string base = "calibrate --in " + file("nof.csv") + " --out " + file("cal.json");
  const auto expect = [&](const std::string& args, const std::string& message) {
    const Result r = run(base + " " + args);
    EXPECT_EQ(r.status, 2) << args << "\n" << r.output;
    EXPECT_NE(r.output.find(message), std::string::npos) << args << "\n" << r.output;
    EXPECT_FALSE(fs::exists(file("cal.json"))) << args;
  };
  expect("--site 46.5,6.6 --date 2026-06-15",
         "--site: site '46.5,6.6': expected three comma-separated numbers LAT,LON,ALT");
  expect("--site 46.5,east,400 --date 2026-06-15", "longitude 'east' is not a finite number");
  expect("--site 95,6.6,400 --date 2026-06-15", "latitude 95 deg is outside [-90, 90]");
  expect("--site 46.5,6.6,400 --date 15.06.2026", "--date: date '15.06.2026': expected YYYY-MM-DD");
  expect("--site 46.5,6.6,400 --date 2026-02-30", "day 30 does not exist in 2026-02");
  expect("--site 46.5,6.6,400 --date 2031-01-01",
         "--site/--date: date 2031 (decimal year) is outside the validity of wmm2025");
  expect("--site 46.5,6.6,900000 --date 2026-06-15", "height 900000 m is outside");
  expect("--site 46.5,6.6,400", "--site and --date go together");
  expect("--date 2026-06-15", "--site and --date go together");
  expect("--model-f", "--model-f needs --site and --date");
  expect("--site 46.5,6.6,400 --date 2026-06-15 --field-nT 48000",
         "--field-nT and --site/--date both give the reference field");
}

}  // namespace
