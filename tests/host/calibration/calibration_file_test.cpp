#include "calibration/calibration_file.hpp"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>

namespace magvec::host {
namespace {

constexpr double kDeg = core::kPi<double> / 180.0;

CalibrationFile sample_file() {
  core::LiParams<double> p;
  p.ks = {1.08, 1.02, 1.033};
  p.o_rad = core::Vec3<double>(1.7, 3.5, 2.1) * kDeg;
  p.kof = {4.9, 3.4, 0.7};
  p.rm_rad = core::Vec3<double>(5.7, 2.1, 3.5) * kDeg;
  CalibrationFile cal;
  cal.model = core::from_li(p);
  cal.h_n_nT = core::Vec3<double>(-4053, 25022, -47374);
  cal.sigma["ks"] = {1e-6, 2e-6, 3e-6};
  cal.sigma["Rm_deg"] = {0.002, 0.002, 0.0021};
  cal.quality.verdict = "ok";
  cal.quality.coverage = 0.93;
  cal.quality.condition = 12.5;
  cal.quality.residual_rms_before_nT = 3200;
  cal.quality.residual_rms_after_nT = 0.3;
  cal.counts = {1000, 980, 12, 8};
  cal.provenance = {"survey.csv", "li-ml", "0.1.0", "2026-11-21T00:00:00Z"};
  return cal;
}

TEST(CalibrationFile, RoundTripsThroughJson) {
  const CalibrationFile cal = sample_file();
  const std::string text = to_json_text(cal);
  const CalibrationFile back = from_json_text(text, "mem");
  EXPECT_LT((back.model.w - cal.model.w).norm(), 1e-15);
  EXPECT_LT((back.model.o - cal.model.o).norm(), 1e-15);
  EXPECT_NEAR(std::abs(back.model.rm.dot(cal.model.rm)), 1.0, 1e-15);
  ASSERT_TRUE(back.h_n_nT.has_value());
  EXPECT_EQ(*back.h_n_nT, *cal.h_n_nT);
  EXPECT_EQ(back.sigma.at("Rm_deg"), cal.sigma.at("Rm_deg"));
  EXPECT_EQ(back.quality.verdict, "ok");
  EXPECT_EQ(back.counts.rejected_outliers, 8u);
  EXPECT_EQ(back.provenance.method, "li-ml");
  // The Li block carries the paper's parameters in degrees.
  EXPECT_NE(text.find("\"Rm_deg\""), std::string::npos);
  EXPECT_NE(text.find("\"Cinv\""), std::string::npos);
}

TEST(CalibrationFile, RejectsBadFilesWithClearErrors) {
  const std::string good = to_json_text(sample_file());
  auto expect_error = [](const std::string& text, const std::string& needle) {
    try {
      (void)from_json_text(text, "cal.json");
      FAIL() << "no error for: " << needle;
    } catch (const CalibrationFileError& e) {
      EXPECT_NE(std::string(e.what()).find(needle), std::string::npos) << e.what();
      EXPECT_NE(std::string(e.what()).find("cal.json"), std::string::npos);
    }
  };
  expect_error("{not json", "not valid JSON");
  expect_error("[]", "object");
  expect_error(R"({"schema":"other/9"})", "schema");
  expect_error(R"({"schema":"magvec-calibration/1"})", "'W'");
  nlohmann::json bad_w = nlohmann::json::parse(good);
  bad_w["W"][4] = "x";
  expect_error(bad_w.dump(), "'W' holds a non-number");
  bad_w["W"] = {1, 2, 3};
  expect_error(bad_w.dump(), "'W' must be an array of 9");
  expect_error(
      R"({"schema":"magvec-calibration/1","W":[0,0,0,0,0,0,0,0,0],"o_nT":[0,0,0],"Rm_quat":[1,0,0,0]})",
      "singular");
  expect_error(
      R"({"schema":"magvec-calibration/1","W":[1,0,0,0,1,0,0,0,1],"o_nT":[0,0,0],"Rm_quat":[2,0,0,0]})",
      "unit quaternion");
  nlohmann::json edited = nlohmann::json::parse(good);
  edited["ge"]["Cinv"][0] = 50.0;  // a hand edit of a derived block
  expect_error(edited.dump(), "disagrees");
}

TEST(CalibrationFile, AtomicWriteReplacesAndLeavesNoTemporaries) {
  const std::filesystem::path dir = std::filesystem::temp_directory_path() / "magvec_calfile_test";
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  const std::string path = (dir / "cal.json").string();
  write_calibration_file(path, sample_file());
  CalibrationFile second = sample_file();
  second.quality.verdict = "insufficient_coverage";
  write_calibration_file(path, second);
  EXPECT_EQ(read_calibration_file(path).quality.verdict, "insufficient_coverage");
  int files = 0;
  for ([[maybe_unused]] const auto& e : std::filesystem::directory_iterator(dir))
    ++files;
  EXPECT_EQ(files, 1);
  EXPECT_THROW((void)read_calibration_file((dir / "missing.json").string()), CalibrationFileError);
  std::filesystem::remove_all(dir);
}

}  // namespace
}  // namespace magvec::host
