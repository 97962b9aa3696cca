// Tests of the CSV reader/writer (host/io/csv.hpp): format rules, every malformed-input case,
// streaming over 1e6 rows without per-row allocation, round trip and atomic replacement.
#include "magvec/host/io/csv.hpp"

#include <gtest/gtest.h>
#include <stdlib.h>
#include <unistd.h>

#include <cmath>
#include <cstring>
#include <filesystem>
#include <fstream>
#include <limits>
#include <random>

#include "magvec/core/frames.hpp"
#include "support/alloc_counter.hpp"

namespace magvec::host::io {
namespace {

namespace fs = std::filesystem;
using core::Mat3;
using core::Vec3;
constexpr double kDeg = core::kPi<double> / 180.0;

class Csv : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "magvec_csv_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string write(const std::string& name, const std::string& text) {
    const std::string p = (dir_ / name).string();
    std::ofstream(p, std::ios::binary) << text;
    return p;
  }
  // Reads every row; returns the CsvError message or "" when the file reads cleanly.
  std::string error_of(const std::string& text, std::uint64_t* line = nullptr,
                       std::string* column = nullptr) {
    const std::string p = write("bad.csv", text);
    try {
      CsvReader r(p);
      CsvRecord rec;
      while (r.next(&rec)) {
      }
    } catch (const CsvError& e) {
      if (line != nullptr) *line = e.line();
      if (column != nullptr) *column = e.column();
      EXPECT_EQ(e.file(), p);
      EXPECT_NE(std::string(e.what()).find(p), std::string::npos);
      return e.what();
    }
    return "";
  }
  fs::path dir_;
};

TEST_F(Csv, ReadsColumnsByNameInAnyOrderWithCommentsExtrasAndDropouts) {
  const std::string p = write("a.csv",
                              "# scenario: test\n"
                              "#second comment\n"
                              "\n"
                              "hz_nT,flags,t_s,hy_nT,F_nT,hx_nT,theta_deg,note_txt\n"
                              "3,0,0.5,2,50000,1,10,x\n"
                              "# a comment between rows\n"
                              "\n"
                              "nan,2,1.0,nan,nan,nan,nan,y\r\n"
                              "-3e2,0,1.5,+2.5,NaN,1.25,-20,z\n");
  CsvReader r(p);
  EXPECT_EQ(r.comments().size(), 2U);
  EXPECT_EQ(r.comments()[0], "scenario: test");
  EXPECT_EQ(r.comments()[1], "second comment");
  EXPECT_TRUE(r.has_f());
  EXPECT_TRUE(r.has_theta());
  EXPECT_EQ(r.attitude_columns(), AttitudeColumns::kNone);
  const std::size_t flags = r.column_index("flags").value();
  EXPECT_FALSE(r.column_index("nope").has_value());
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.line, 5U);
  EXPECT_EQ(rec.t_s, 0.5);
  EXPECT_EQ(rec.m_nT, Vec3<double>(1, 2, 3));
  EXPECT_FALSE(rec.dropout);
  EXPECT_EQ(rec.f_nT.value(), 50000.0);
  EXPECT_EQ(rec.theta_deg.value(), 10.0);
  EXPECT_FALSE(rec.r_bn.has_value());
  EXPECT_EQ(r.value(flags), 0.0);
  EXPECT_EQ(r.text(7), "x");
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.line, 8U);
  EXPECT_TRUE(rec.dropout);
  EXPECT_TRUE(rec.m_nT.array().isNaN().all());
  EXPECT_FALSE(rec.f_nT.has_value());
  EXPECT_FALSE(rec.theta_deg.has_value());
  EXPECT_EQ(r.value(flags), 2.0);
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.m_nT, Vec3<double>(1.25, 2.5, -300));
  EXPECT_EQ(rec.theta_deg.value(), -20.0);
  EXPECT_FALSE(r.next(&rec));
  EXPECT_FALSE(r.next(&rec));
}

TEST_F(Csv, PartialDropoutMarksTheWholeSample) {
  const std::string p = write("d.csv", "t_s,hx_nT,hy_nT,hz_nT\n0,1,nan,3\n");
  CsvReader r(p);
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_TRUE(rec.dropout);
  EXPECT_TRUE(rec.m_nT.array().isNaN().all());
}

TEST_F(Csv, QuotedFieldsAndWhitespace) {
  const std::string p = write("q.csv",
                              "\"t_s\" , hx_nT,\"hy_nT\",  hz_nT\t, \"a \"\"quoted\"\" note\"\n"
                              "  1 ,\" 2 \", 3 ,\t4, \"x, y\"\n");
  CsvReader r(p);
  EXPECT_EQ(r.columns()[4], "a \"quoted\" note");
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.t_s, 1.0);
  EXPECT_EQ(rec.m_nT, Vec3<double>(2, 3, 4));
  EXPECT_EQ(r.text(4), "x, y");
}

TEST_F(Csv, AttitudeRepresentationsConvertThroughTheCoreFrames) {
  const double a = 30, b = -10, g = 5;
  const Mat3<double> li = core::r_bn_from_li(core::LiEuler<double>{a * kDeg, b * kDeg, g * kDeg});
  const Mat3<double> ypr =
      core::r_bn_from_ypr(core::YawPitchRoll<double>{a * kDeg, b * kDeg, g * kDeg});
  const core::Quat<double> q = core::quat_from_r_bn(li);
  struct Case {
    std::string header;
    std::string angles;
    AttitudeColumns kind;
    Mat3<double> expected;
  };
  const Case cases[] = {
      {"alpha_deg,beta_deg,gamma_deg", "30,-10,5", AttitudeColumns::kLi, li},
      {"gamma_rad,alpha_rad,beta_rad",
       format_double(g * kDeg) + "," + format_double(a * kDeg) + "," + format_double(b * kDeg),
       AttitudeColumns::kLi, li},
      {"yaw_deg,pitch_deg,roll_deg", "30,-10,5", AttitudeColumns::kYawPitchRoll, ypr},
      {"qw,qx,qy,qz",
       format_double(q.w()) + "," + format_double(q.x()) + "," + format_double(q.y()) + "," +
           format_double(q.z()),
       AttitudeColumns::kQuaternion, li},
  };
  for (const Case& c : cases) {
    SCOPED_TRACE(c.header);
    const std::string p =
        write("att.csv", "t_s,hx_nT,hy_nT,hz_nT," + c.header + "\n0,1,2,3," + c.angles +
                             "\n1,1,2,3,nan,nan,nan" +
                             (c.kind == AttitudeColumns::kQuaternion ? ",nan" : "") + "\n");
    CsvReader r(p);
    EXPECT_EQ(r.attitude_columns(), c.kind);
    CsvRecord rec;
    ASSERT_TRUE(r.next(&rec));
    ASSERT_TRUE(rec.r_bn.has_value());
    EXPECT_LT((*rec.r_bn - c.expected).norm(), 1e-12);
    ASSERT_TRUE(r.next(&rec));
    EXPECT_FALSE(rec.r_bn.has_value());
    EXPECT_FALSE(rec.dropout);
  }
}

TEST_F(Csv, MicroteslaColumnsAreConvertedAndConstantFOptionApplies) {
  const std::string p = write("ut.csv", "t_s,hx_uT,hy_uT,hz_uT\n0,1.5,-2,0.001\n");
  CsvReaderOptions opt;
  opt.f_nT = 48000.0;
  CsvReader r(p, opt);
  EXPECT_FALSE(r.has_f());
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.m_nT, Vec3<double>(1500, -2000, 1));
  EXPECT_EQ(rec.f_nT.value(), 48000.0);
}

TEST_F(Csv, MalformedNumberNamesFileLineAndColumn) {
  std::uint64_t line = 0;
  std::string column;
  const std::string msg =
      error_of("t_s,hx_nT,hy_nT,hz_nT\n0,1,2,3\n# c\n1,1,2x,3\n", &line, &column);
  EXPECT_EQ(line, 4U);
  EXPECT_EQ(column, "'hy_nT' (field 3)");
  EXPECT_NE(msg.find(":4: column 'hy_nT' (field 3): malformed number '2x'"), std::string::npos)
      << msg;
  for (const char* bad : {"1..2", "--1", "0x10", "1e", "abc", "1 2", "+-1"}) {
    SCOPED_TRACE(bad);
    EXPECT_NE(error_of(std::string("t_s,hx_nT,hy_nT,hz_nT\n0,1,") + bad + ",3\n")
                  .find("malformed number"),
              std::string::npos);
  }
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT\n0,1,,3\n").find("empty field"), std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT\n0,1,inf,3\n").find("non-finite"), std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT\n0,1,1e999,3\n").find("out of range"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT\nnan,1,2,3\n").find("time must be a finite"),
            std::string::npos);
  // An unused extra column is not parsed, so its content does not matter.
  EXPECT_EQ(error_of("t_s,hx_nT,hy_nT,hz_nT,note\n0,1,2,3,hello\n"), "");
}

TEST_F(Csv, WrongNumberOfFieldsIsAnError) {
  std::uint64_t line = 0;
  std::string msg = error_of("t_s,hx_nT,hy_nT,hz_nT\n0,1,2,3\n1,1,2\n", &line);
  EXPECT_EQ(line, 3U);
  EXPECT_NE(msg.find("wrong number of fields: expected 4, found 3"), std::string::npos) << msg;
  msg = error_of("t_s,hx_nT,hy_nT,hz_nT\n0,1,2,3,4\n", &line);
  EXPECT_EQ(line, 2U);
  EXPECT_NE(msg.find("expected 4, found 5"), std::string::npos) << msg;
}

TEST_F(Csv, UnknownOrMissingUnitIsAnError) {
  std::string column;
  std::string msg = error_of("t_s,hx_G,hy_nT,hz_nT\n0,1,2,3\n", nullptr, &column);
  EXPECT_EQ(column, "'hx_G' (field 2)");
  EXPECT_NE(msg.find("unknown unit 'G' for hx"), std::string::npos) << msg;
  EXPECT_NE(error_of("t_ms,hx_nT,hy_nT,hz_nT\n0,1,2,3\n").find("unknown unit 'ms' for t"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,pitch_mrad,roll_deg,yaw_deg\n0,1,2,3,1,2,3\n")
                .find("unknown unit 'mrad'"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx,hy_nT,hz_nT\n0,1,2,3\n").find("needs a unit suffix"),
            std::string::npos);
  EXPECT_NE(
      error_of("t_s,hx_nT,hy_nT,hz_nT,qw_x,qx,qy,qz\n0,1,2,3,1,0,0,0\n").find("takes no unit"),
      std::string::npos);
}

TEST_F(Csv, HeaderProblemsAreErrors) {
  std::uint64_t line = 0;
  std::string column;
  std::string msg = error_of("# c\nt_s,hx_nT,hy_nT\n0,1,2\n", &line, &column);
  EXPECT_EQ(line, 2U);
  EXPECT_EQ(column, "hz_nT");
  EXPECT_NE(msg.find("missing required column"), std::string::npos) << msg;
  EXPECT_NE(error_of("hx_nT,hy_nT,hz_nT\n1,2,3\n").find("t_s: missing required column"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,hx_nT\n0,1,2,3,4\n").find("duplicate column"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,hx_uT\n0,1,2,3,4\n").find("appears twice"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,alpha_deg,beta_deg\n0,1,2,3,4,5\n")
                .find("incomplete attitude"),
            std::string::npos);
  EXPECT_NE(
      error_of(
          "t_s,hx_nT,hy_nT,hz_nT,alpha_deg,beta_deg,gamma_deg,qw,qx,qy,qz\n0,1,2,3,0,0,0,1,0,0,0\n")
          .find("more than one attitude"),
      std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,\n0,1,2,3,4\n").find("empty column name"),
            std::string::npos);
  EXPECT_NE(error_of("").find("no header line"), std::string::npos);
  EXPECT_NE(error_of("# only a comment\n\n").find("no header line"), std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,\"hy_nT,hz_nT\n").find("unterminated quoted field"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,\"hy\"_nT,hz_nT\n").find("unexpected text after a quoted field"),
            std::string::npos);
}

TEST_F(Csv, NonUnitQuaternionIsAnError) {
  const std::string msg = error_of("t_s,hx_nT,hy_nT,hz_nT,qw,qx,qy,qz\n0,1,2,3,1,1,0,0\n");
  EXPECT_NE(msg.find("quaternion is not unit"), std::string::npos) << msg;
}

// Regression: a huge component overflowed the norm to inf and the error message's formatter threw
// std::domain_error (no file, line or column).
TEST_F(Csv, OverflowingQuaternionIsACsvError) {
  std::uint64_t line = 0;
  std::string column;
  const std::string msg =
      error_of("t_s,hx_nT,hy_nT,hz_nT,qw,qx,qy,qz\n0,1,2,3,1e200,0,0,0\n", &line, &column);
  EXPECT_EQ(line, 2U);
  EXPECT_EQ(column, "'qw' (field 5)");
  EXPECT_NE(msg.find("quaternion is not unit (norm overflows)"), std::string::npos) << msg;
}

// Regression: the finiteness check ran before the unit scaling, so 1e306 uT became inf nT and
// 1e307 rad an infinite angle (a NaN attitude).
TEST_F(Csv, ValuesThatOverflowInTheirInterfaceUnitAreRejected) {
  struct Case {
    const char* text;
    const char* column;
  };
  for (const Case& c : {
           Case{"t_s,hx_uT,hy_uT,hz_uT\n0,1e306,2,3\n", "'hx_uT' (field 2)"},
           Case{"t_s,hx_nT,hy_nT,hz_nT,F_uT\n0,1,2,3,-1e306\n", "'F_uT' (field 5)"},
           Case{"t_s,hx_nT,hy_nT,hz_nT,alpha_rad,beta_rad,gamma_rad\n0,1,2,3,1e307,0,0\n",
                "'alpha_rad' (field 5)"},
           Case{"t_s,hx_nT,hy_nT,hz_nT,theta_rad\n0,1,2,3,-1e307\n", "'theta_rad' (field 5)"},
       }) {
    SCOPED_TRACE(c.text);
    std::uint64_t line = 0;
    std::string column;
    const std::string msg = error_of(c.text, &line, &column);
    EXPECT_EQ(line, 2U);
    EXPECT_EQ(column, c.column);
    EXPECT_NE(msg.find("out of range after unit conversion"), std::string::npos) << msg;
  }
  // The largest values that still fit are read (and scaled) exactly as before.
  const std::string p = write("big.csv", "t_s,hx_uT,hy_uT,hz_uT\n0,1e305,-1e305,0.5\n");
  CsvReader r(p);
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.m_nT, Vec3<double>(1e305 * 1000.0, -1e305 * 1000.0, 500.0));
}

TEST_F(Csv, Utf8ByteOrderMarkBeforeTheHeaderIsSkipped) {
  const std::string p = write("bom.csv", "\xEF\xBB\xBFt_s,hx_nT,hy_nT,hz_nT\n0.5,1,2,3\n");
  CsvReader r(p);
  ASSERT_EQ(r.columns().size(), 4U);
  EXPECT_EQ(r.columns()[0], "t_s");
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.t_s, 0.5);
  EXPECT_EQ(rec.m_nT, Vec3<double>(1, 2, 3));
  // Also before a leading comment line; a BOM anywhere else is ordinary (bad) text.
  EXPECT_EQ(error_of("\xEF\xBB\xBF# made by a spreadsheet\nt_s,hx_nT,hy_nT,hz_nT\n0,1,2,3\n"), "");
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT\n\xEF\xBB\xBF"
                     "0,1,2,3\n")
                .find("malformed number"),
            std::string::npos);
}

TEST_F(Csv, MissingFileIsAnError) {
  try {
    CsvReader r((dir_ / "does_not_exist.csv").string());
    FAIL() << "no exception";
  } catch (const CsvError& e) {
    EXPECT_NE(std::string(e.what()).find("cannot open"), std::string::npos);
  }
}

TEST_F(Csv, StreamsMillionsOfRowsWithoutPerRowAllocation) {
  constexpr int kRows = 1000000;
  const std::string p = (dir_ / "big.csv").string();
  {
    CsvWriter w(p, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT"}, {"big file"});
    double row[5];
    for (int i = 0; i < kRows; ++i) {
      row[0] = i * 0.005;
      row[1] = i % 1000;
      row[2] = -(i % 777);
      row[3] = i % 3 == 0 ? std::numeric_limits<double>::quiet_NaN() : 0.5;
      row[4] = 50000;
      w.write_row(row);
    }
    w.commit();
  }
  ASSERT_GT(fs::file_size(p), 20U * 1000 * 1000);
  CsvReader r(p);
  CsvRecord rec;
  long long n = 0, dropouts = 0;
  double sum_x = 0;
  for (int i = 0; i < 10; ++i) {  // let the line buffer reach its working size
    ASSERT_TRUE(r.next(&rec));
    dropouts += rec.dropout ? 1 : 0;
    sum_x += rec.dropout ? 0.0 : rec.m_nT.x();
    ++n;
  }
  const test::AllocationScope scope;
  while (r.next(&rec)) {
    dropouts += rec.dropout ? 1 : 0;
    sum_x += rec.dropout ? 0.0 : rec.m_nT.x();
    ++n;
  }
  const std::size_t allocations = scope.count();
  EXPECT_EQ(allocations, 0U);  // nothing grows with the file: one line at a time
  EXPECT_EQ(n, kRows);
  EXPECT_EQ(dropouts, (kRows + 2) / 3);
  double expected = 0;
  for (int i = 0; i < kRows; ++i)
    expected += i % 3 == 0 ? 0.0 : i % 1000;
  EXPECT_EQ(sum_x, expected);
  EXPECT_EQ(rec.t_s, (kRows - 1) * 0.005);
}

TEST_F(Csv, WriterReaderRoundTripIsBitExact) {
  std::mt19937_64 rng(1);
  std::uniform_real_distribution<double> u(-1e5, 1e5);
  const std::string p = (dir_ / "rt.csv").string();
  std::vector<std::array<double, 6>> rows;
  const double specials[] = {
      0.0, -0.0, 5e-324, 1.7976931348623157e308, -2.2250738585072014e-308, 0.1, 1.0 / 3.0};
  for (double s : specials)
    rows.push_back({s, s, s, s, s, s});
  for (int i = 0; i < 1000; ++i)
    rows.push_back({i * 0.01, u(rng), u(rng), u(rng), u(rng) * 1e-7, u(rng)});
  rows.push_back({1, std::numeric_limits<double>::quiet_NaN(), 1, 1,
                  std::numeric_limits<double>::quiet_NaN(), 2});
  {
    CsvWriter w(p, {"t_s", "hx_nT", "hy_nT", "hz_nT", "F_nT", "extra_x"}, {"round trip", "second"});
    for (const auto& row : rows)
      w.write_row(row);
    EXPECT_EQ(w.rows(), rows.size());
    w.commit();
  }
  CsvReader r(p);
  EXPECT_EQ(r.comments(), (std::vector<std::string>{"round trip", "second"}));
  CsvRecord rec;
  for (const auto& row : rows) {
    ASSERT_TRUE(r.next(&rec));
    EXPECT_EQ(std::memcmp(&rec.t_s, &row[0], sizeof(double)), 0);
    if (std::isnan(row[1])) {
      EXPECT_TRUE(rec.dropout);
      EXPECT_FALSE(rec.f_nT.has_value());
    } else {
      for (int k = 0; k < 3; ++k)
        EXPECT_EQ(std::memcmp(&rec.m_nT(k), &row[static_cast<std::size_t>(k) + 1], sizeof(double)),
                  0);
      EXPECT_EQ(std::memcmp(&*rec.f_nT, &row[4], sizeof(double)), 0);
    }
    const double extra = r.value(5);
    EXPECT_EQ(std::memcmp(&extra, &row[5], sizeof(double)), 0);
  }
  EXPECT_FALSE(r.next(&rec));
}

TEST_F(Csv, WriterRejectsBadRows) {
  const std::string p = (dir_ / "w.csv").string();
  CsvWriter w(p, {"a", "b"});
  const double one[] = {1.0};
  EXPECT_THROW(w.write_row(one), std::invalid_argument);
  const double inf[] = {1.0, std::numeric_limits<double>::infinity()};
  EXPECT_THROW(w.write_row(inf), std::domain_error);
  EXPECT_THROW(CsvWriter((dir_ / "x.csv").string(), {"a,b"}), std::invalid_argument);
  EXPECT_THROW(CsvWriter((dir_ / "no_such_dir" / "x.csv").string(), {"a"}), std::system_error);
}

TEST_F(Csv, TemperatureColumnIsReadWhenPresent) {
  const std::string p = write("t.csv",
                              "t_s,hx_nT,hy_nT,hz_nT,temperature_degC\n"
                              "0,1,2,3,21.5\n"
                              "1,1,2,3,nan\n"
                              "2,nan,nan,nan,-40\n");
  CsvReader r(p);
  EXPECT_TRUE(r.has_temperature());
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.temperature_degC.value(), 21.5);
  ASSERT_TRUE(r.next(&rec));
  EXPECT_FALSE(rec.temperature_degC.has_value());  // nan: no temperature for this row
  ASSERT_TRUE(r.next(&rec));
  EXPECT_TRUE(rec.dropout);
  EXPECT_EQ(rec.temperature_degC.value(), -40.0);  // the temperature channel outlives a dropout
  EXPECT_FALSE(r.next(&rec));
}

TEST_F(Csv, RecordingWithoutTemperatureColumnStillReads) {
  // A recording from before the column existed: no temperature in any record, nothing else moves.
  const std::string p = write("old.csv",
                              "t_s,hx_nT,hy_nT,hz_nT,F_nT\n"
                              "0,1,2,3,50000\n");
  CsvReader r(p);
  EXPECT_FALSE(r.has_temperature());
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.m_nT, Vec3<double>(1, 2, 3));
  EXPECT_EQ(rec.f_nT.value(), 50000.0);
  EXPECT_FALSE(rec.temperature_degC.has_value());
}

TEST_F(Csv, OlderSimulationTemperatureColumnInCIsRead) {
  const std::string p = write("sim.csv", "t_s,hx_nT,hy_nT,hz_nT,temperature_C\n0,1,2,3,20\n");
  CsvReader r(p);
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.temperature_degC.value(), 20.0);
}

TEST_F(Csv, BadTemperatureColumnsAndValuesAreErrors) {
  std::string column;
  std::uint64_t line = 0;
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_K\n0,1,2,3,300\n", &line, &column)
                .find("unknown unit 'K' for temperature (accepted: degC or C)"),
            std::string::npos);
  EXPECT_EQ(column, "'temperature_K' (field 5)");
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature\n0,1,2,3,20\n")
                .find("column needs a unit suffix"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_degC,temperature_C\n0,1,2,3,20,20\n")
                .find("quantity temperature appears twice"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_degC\n0,1,2,3,warm\n")
                .find("malformed number 'warm'"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_degC\n0,1,2,3,inf\n").find("non-finite"),
            std::string::npos);
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_degC\n0,1,2,3,\n").find("empty field"),
            std::string::npos);
  EXPECT_NE(
      error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_degC\n0,1,2,3,20\n1,1,2,3,-300\n", &line, &column)
          .find("temperature -300 degC outside -273.15 .. 1000 degC"),
      std::string::npos);
  EXPECT_EQ(line, 3U);
  EXPECT_EQ(column, "'temperature_degC' (field 5)");
  EXPECT_NE(error_of("t_s,hx_nT,hy_nT,hz_nT,temperature_degC\n0,1,2,3,1e4\n").find("outside"),
            std::string::npos);
}

TEST_F(Csv, RecordingWriterAddsTheTemperatureColumnOnlyWhenASampleHasIt) {
  const double nan = std::numeric_limits<double>::quiet_NaN();
  std::vector<CsvRecord> recs(3);
  for (std::size_t i = 0; i < recs.size(); ++i) {
    recs[i].t_s = 0.01 * static_cast<double>(i);
    recs[i].m_nT = Vec3<double>(1.0 / 3.0, -2.5, 4e4 + static_cast<double>(i));
    recs[i].f_nT = 5e4;
  }
  recs[1].dropout = true;
  recs[1].m_nT.setConstant(nan);
  recs[2].r_bn = core::r_bn_from_li(core::LiEuler<double>{0.1, 0.2, -0.3});
  const std::string without = (dir_ / "without.csv").string();
  write_recording_csv(without, recs, {"no temperature"});
  {
    CsvReader r(without);
    EXPECT_FALSE(r.has_temperature());
    EXPECT_FALSE(r.column_index("temperature_degC").has_value());
  }
  recs[0].temperature_degC = 23.125;
  recs[2].temperature_degC = -0.1;
  const std::string with = (dir_ / "with.csv").string();
  write_recording_csv(with, recs);
  CsvReader r(with);
  EXPECT_TRUE(r.has_temperature());
  EXPECT_EQ(r.attitude_columns(), AttitudeColumns::kLi);
  CsvRecord rec;
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.m_nT, recs[0].m_nT);
  EXPECT_EQ(rec.temperature_degC.value(), 23.125);
  EXPECT_FALSE(rec.r_bn.has_value());
  ASSERT_TRUE(r.next(&rec));
  EXPECT_TRUE(rec.dropout);
  EXPECT_FALSE(rec.temperature_degC.has_value());
  ASSERT_TRUE(r.next(&rec));
  EXPECT_EQ(rec.temperature_degC.value(), -0.1);
  ASSERT_TRUE(rec.r_bn.has_value());
  EXPECT_LT((*rec.r_bn - *recs[2].r_bn).cwiseAbs().maxCoeff(), 1e-12);
  EXPECT_FALSE(r.next(&rec));

  recs[0].temperature_degC = -300.0;
  EXPECT_THROW(write_recording_csv((dir_ / "bad.csv").string(), recs), std::invalid_argument);
  EXPECT_FALSE(fs::exists(dir_ / "bad.csv"));
}

TEST_F(Csv, WriterIsAtomic) {
  const std::string p = write("out.csv", "old content\n");
  {
    CsvWriter w(p, {"t_s", "hx_nT", "hy_nT", "hz_nT"});
    const double row[] = {0, 1, 2, 3};
    w.write_row(row);
    // Until commit the old file is untouched; the new content lives in a temporary file.
    std::ifstream in(p);
    std::string first;
    std::getline(in, first);
    EXPECT_EQ(first, "old content");
    // Abandoned without commit (e.g. an exception): the target stays as it was.
  }
  {
    std::ifstream in(p);
    std::string first;
    std::getline(in, first);
    EXPECT_EQ(first, "old content");
  }
  int files = 0;
  for (const auto& e : fs::directory_iterator(dir_)) {
    (void)e;
    ++files;
  }
  EXPECT_EQ(files, 1) << "temporary file left behind";
  {
    CsvWriter w(p, {"t_s", "hx_nT", "hy_nT", "hz_nT"}, {"new"});
    const double row[] = {0, 1, 2, 3};
    w.write_row(row);
    w.commit();
  }
  std::ifstream in(p);
  std::stringstream ss;
  ss << in.rdbuf();
  EXPECT_EQ(ss.str(), "# new\nt_s,hx_nT,hy_nT,hz_nT\n0,1,2,3\n");
  files = 0;
  for (const auto& e : fs::directory_iterator(dir_)) {
    (void)e;
    ++files;
  }
  EXPECT_EQ(files, 1);
}

}  // namespace
}  // namespace magvec::host::io
