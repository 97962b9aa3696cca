#include "calibration/calibration_file.hpp"

#include <gtest/gtest.h>

#include <nlohmann/json.hpp>

#include <filesystem>
#include <fstream>
#include <string>
#include <utility>
#include <vector>

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
  cal.output = OutputQuality{false, 0.45, 11.25};
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
  ASSERT_TRUE(back.output.has_value());
  EXPECT_FALSE(back.output->aligned);
  EXPECT_EQ(back.output->sigma_f_nT, 0.45);
  EXPECT_EQ(back.output->sigma_enu_nT, 11.25);
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

// The error message of reading `text`, "" when it reads; any other exception fails the test.
std::string read_error(const std::string& text) {
  try {
    (void)from_json_text(text, "dir/cal.json");
  } catch (const CalibrationFileError& e) {
    return e.what();
  }
  return "";
}

// `good` with one member replaced: path is a JSON pointer ("/quality/counts/samples"), value raw
// JSON text spliced in where the replacement is a marker (so that 1e474 reaches the parser).
std::string with_member(const std::string& pointer, const std::string& raw_value) {
  nlohmann::json j = nlohmann::json::parse(to_json_text(sample_file()));
  j[nlohmann::json::json_pointer(pointer)] = "@@VALUE@@";
  std::string text = j.dump();
  text.replace(text.find("\"@@VALUE@@\""), 11, raw_value);
  return text;
}

// Regression: nlohmann's out_of_range (a number overflowing a double) escaped the reader.
TEST(CalibrationFile, OverflowingNumbersNameFileAndField) {
  for (const auto& [pointer, name] : std::vector<std::pair<std::string, std::string>>{
           {"/W/4", "'W'"},
           {"/quality/counts/samples", "'quality.counts.samples'"},
           {"/time_offset_s", "'time_offset_s'"},
           {"/sigma/ks/1", "'sigma.ks'"}}) {
    for (const char* raw :
         {"1e474", "-1e400",
          "1"
          "000000000000000000000000000000000000000000000000"
          "000000000000000000000000000000000000000000000000000000000000000000000"
          "000000000000000000000000000000000000000000000000000000000000000000000"
          "000000000000000000000000000000000000000000000000000000000000000000000"
          "000000000000000000000000000000000000000000000000000000000000000000000"}) {
      SCOPED_TRACE(pointer + " = " + raw);
      const std::string msg = read_error(with_member(pointer, raw));
      EXPECT_NE(msg.find("dir/cal.json: "), std::string::npos) << msg;
      EXPECT_NE(msg.find(name), std::string::npos) << msg;
    }
  }
}

// Regression: a wrong type escaped as nlohmann's type_error without the file or field.
TEST(CalibrationFile, WrongTypesNameFileAndField) {
  struct Case {
    std::string pointer, raw, needle;
  };
  for (const Case& c : std::vector<Case>{
           {"/quality", "5", "'quality' must be an object"},
           {"/quality/verdict", "3", "'quality.verdict' must be a string"},
           {"/quality/reason", "null", "'quality.reason' must be a string"},
           {"/quality/coverage", "\"high\"", "'quality.coverage' must be a finite number"},
           {"/quality/residual_rms_nT", "[1, 2]", "'quality.residual_rms_nT' must be an object"},
           {"/quality/residual_rms_nT/before", "{}", "'quality.residual_rms_nT.before'"},
           {"/quality/counts", "true", "'quality.counts' must be an object"},
           {"/quality/counts/used", "\"980\"", "'quality.counts.used' must be a non-negative"},
           {"/provenance", "\"x\"", "'provenance' must be an object"},
           {"/provenance/input", "[]", "'provenance.input' must be a string"},
           {"/noise", "[]", "'noise' must be an object"},
           {"/noise/mag_nT", "\"1\"", "'noise.mag_nT' must be a finite number"},
           {"/noise/mag_source", "1", "'noise.mag_source' must be a string"},
           {"/noise/ins_source", "\"guessed\"", "'noise.ins_source' must be \"estimated\""},
           {"/time_offset_sigma_s", "\"0.1\"", "'time_offset_sigma_s' must be a finite number"},
           {"/sine", "1", "'sine' must be an object"},
           {"/ge", "[]", "'ge' must be an object"},
           {"/sigma", "2", "'sigma' must be an object"},
           {"/h_n_nT", "{}", "'h_n_nT' must be an array of 3"},
           {"/output", "[]", "'output' must be an object"},
           {"/output/aligned", "\"yes\"", "'output.aligned' must be true or false"},
           {"/output/sigma_f_nT", "\"1\"", "'output.sigma_f_nT' must be a finite number"},
       }) {
    SCOPED_TRACE(c.pointer + " = " + c.raw);
    const std::string msg = read_error(with_member(c.pointer, c.raw));
    EXPECT_NE(msg.find("dir/cal.json: "), std::string::npos) << msg;
    EXPECT_NE(msg.find(c.needle), std::string::npos) << msg;
  }
}

// Regression: "samples": -1.0 was a float-to-unsigned conversion out of range (undefined
// behaviour); negative integers were accepted silently.
TEST(CalibrationFile, CountsMustBeNonNegativeIntegersThatFit) {
  for (const char* raw : {"-1.0", "-1", "1.5", "-0.5", "1e20", "18446744073709551616.0", "1e300"}) {
    SCOPED_TRACE(raw);
    const std::string msg = read_error(with_member("/quality/counts/samples", raw));
    EXPECT_NE(msg.find("'quality.counts.samples' must be a non-negative integer"),
              std::string::npos)
        << msg;
  }
  const auto samples = [](const char* raw) {
    return from_json_text(with_member("/quality/counts/samples", raw), "cal.json").counts.samples;
  };
  EXPECT_EQ(samples("1000"), 1000u);
  EXPECT_EQ(samples("1000.0"), 1000u);
  EXPECT_EQ(samples("0"), 0u);
  EXPECT_EQ(samples("-0"), 0u);
  EXPECT_EQ(samples("18446744073709551615"), 18446744073709551615u);
  EXPECT_EQ(samples("1.8446744073709550e19"), 18446744073709549568u);  // largest double < 2^64
}

TEST(CalibrationFile, SigmasAndNoiseFiguresMustNotBeNegative) {
  for (const char* pointer :
       {"/time_offset_sigma_s", "/noise/mag_nT", "/noise/mag_sigma_nT", "/noise/ins_deg",
        "/noise/ins_sigma_deg", "/output/sigma_f_nT", "/output/sigma_enu_nT"}) {
    SCOPED_TRACE(pointer);
    EXPECT_NE(read_error(with_member(pointer, "-0.1")).find("must not be negative"),
              std::string::npos);
    EXPECT_EQ(read_error(with_member(pointer, "0.1")), "");
  }
}

// magvecd's calibrations from a geomagnetic model's F say so, and keep saying so after a restart.
TEST(CalibrationFile, ModelReferenceOfTheOutputRoundTripsAndIsABoolean) {
  CalibrationFile cal = sample_file();
  EXPECT_EQ(to_json_text(cal).find("model_reference"), std::string::npos);  // absent: false
  cal.output->model_reference = true;
  const CalibrationFile back = from_json_text(to_json_text(cal), "mem");
  ASSERT_TRUE(back.output.has_value());
  EXPECT_TRUE(back.output->model_reference);
  EXPECT_NE(read_error(with_member("/output/model_reference", "1"))
                .find("field 'output.model_reference' must be true or false"),
            std::string::npos);
}

TEST(CalibrationFile, HugeButFiniteModelIsRejected) {
  nlohmann::json j = nlohmann::json::parse(to_json_text(sample_file()));
  j["W"] = {1e200, 0, 0, 0, 1e200, 0, 0, 0, 1e200};
  j.erase("ge");
  EXPECT_NE(read_error(j.dump()).find("'W' is out of range"), std::string::npos);
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
