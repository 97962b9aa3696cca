// End-to-end tests of the magvec CLI: --version, simulate (CSV + truth header, determinism, bad
// option values -> non-zero exit), apply's exit status on bad input, and the temporary demo.
#include <gtest/gtest.h>

#include <stdlib.h>
#include <sys/wait.h>
#include "support/process.hpp"

#include <cmath>
#include <cstdio>
#include <filesystem>
#include <fstream>
#include <sstream>
#include <string>
#include <vector>

#include "calibration/calibration_file.hpp"
#include "magvec/core/compensator.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/io/csv.hpp"

namespace {

namespace fs = std::filesystem;

using Result = magvec::test::CommandResult;

Result run(const std::string& args) {
  return magvec::test::run_shell(std::string(MAGVEC_CLI) + " " + args);
}

std::string slurp(const fs::path& p) {
  std::ifstream in(p, std::ios::binary);
  std::stringstream ss;
  ss << in.rdbuf();
  return ss.str();
}

class Cli : public ::testing::Test {
 protected:
  void SetUp() override {
    std::string templ = (fs::temp_directory_path() / "magvec_cli_XXXXXX").string();
    ASSERT_NE(::mkdtemp(templ.data()), nullptr);
    dir_ = templ;
  }
  void TearDown() override { fs::remove_all(dir_); }
  std::string file(const char* name) const { return (dir_ / name).string(); }
  fs::path dir_;
};

TEST_F(Cli, Version) {
  const Result r = run("--version");
  EXPECT_EQ(r.status, 0);
  EXPECT_NE(r.output.find("magvec 0."), std::string::npos) << r.output;
}

TEST_F(Cli, SimulateWritesAReadableCsvWithTruthHeader) {
  const Result r = run("simulate --scenario li2023 --seed 3 --out " + file("li.csv"));
  ASSERT_EQ(r.status, 0) << r.output;
  magvec::host::io::CsvReader reader(file("li.csv"));
  bool seed = false, li = false, ge = false, sine = false;
  for (const std::string& c : reader.comments()) {
    seed = seed || c.find("scenario li2023, seed 3") != std::string::npos;
    li = li || c.find("truth Li 2023: Ks = [1.08, 1.02") != std::string::npos;
    ge = ge || c.find("truth Ge 2017: C = ") != std::string::npos;
    sine = sine || c.find("truth sine fit: k = ") != std::string::npos;
  }
  EXPECT_TRUE(seed && li && ge && sine);
  EXPECT_EQ(reader.attitude_columns(), magvec::host::io::AttitudeColumns::kLi);
  // The file matches the simulator: compensating with the truth gives |h| within the noise.
  const magvec::drivers::sim::ScenarioConfig cfg = magvec::drivers::sim::scenario_li2023();
  const magvec::core::Compensator<double> comp(cfg.truth);
  magvec::host::io::CsvRecord rec;
  int n = 0;
  while (reader.next(&rec)) {
    magvec::core::Compensated<double> c;
    ASSERT_TRUE(comp.compensate(rec.m_nT, &c));
    EXPECT_NEAR(c.intensity, *rec.f_nT, 2.0);  // 0.3 nT noise: 2 nT is > 6 sigma
    ASSERT_TRUE(rec.r_bn.has_value());
    ++n;
  }
  EXPECT_EQ(n, 60);
}

TEST_F(Cli, SimulateIsDeterministicFromTheSeed) {
  ASSERT_EQ(run("simulate --scenario sine-xz --fixture housing-y --noise-nT 15 --seed 7 --out " +
                file("a.csv"))
                .status,
            0);
  ASSERT_EQ(run("simulate --scenario sine-xz --fixture housing-y --noise-nT 15 --seed 7 --out " +
                file("b.csv"))
                .status,
            0);
  ASSERT_EQ(run("simulate --scenario sine-xz --fixture housing-y --noise-nT 15 --seed 8 --out " +
                file("c.csv"))
                .status,
            0);
  EXPECT_EQ(slurp(file("a.csv")), slurp(file("b.csv")));
  EXPECT_NE(slurp(file("a.csv")), slurp(file("c.csv")));
  EXPECT_NE(slurp(file("a.csv")).find("sine-xz-housing-y"), std::string::npos);
}

TEST_F(Cli, SimulateOptionsChangeTheOutput) {
  ASSERT_EQ(
      run("simulate --scenario ge2017 --samples 5000 --dropout-rate 0.1 --spike-rate 0.05 --out " +
          file("ge.csv"))
          .status,
      0);
  magvec::host::io::CsvReader reader(file("ge.csv"));
  const std::size_t flags = reader.column_index("flags").value();
  magvec::host::io::CsvRecord rec;
  int n = 0, drop = 0, spikes = 0;
  while (reader.next(&rec)) {
    ++n;
    drop += rec.dropout ? 1 : 0;
    spikes += (static_cast<int>(reader.value(flags)) & 1) != 0 ? 1 : 0;
    EXPECT_FALSE(rec.r_bn.has_value());  // Ge: no INS
  }
  EXPECT_EQ(n, 5000);
  EXPECT_NEAR(drop, 500, 5 * std::sqrt(5000 * 0.1 * 0.9));
  EXPECT_NEAR(spikes, 250, 5 * std::sqrt(5000 * 0.05 * 0.95));
}

TEST_F(Cli, BadOptionValuesFailWithAMessage) {
  const std::string out = " --out " + file("x.csv");
  const struct {
    std::string args;
    std::string message;
  } cases[] = {
      {"simulate --scenario mars" + out, "mars not in"},
      {"simulate --scenario li2023 --spike-rate 2" + out, "--spike-rate"},
      {"simulate --scenario li2023 --dropout-rate -0.1" + out, "--dropout-rate"},
      {"simulate --scenario li2023 --noise-nT -1" + out, "--noise-nT"},
      {"simulate --scenario li2023 --samples 0" + out, "--samples"},
      {"simulate --scenario li2023 --samples many" + out, "--samples"},
      {"simulate --scenario li2023 --fixture housing-y" + out,
       "applies only to --scenario sine-xz"},
      {"simulate --scenario sine-xz --fixture sideways" + out, "sideways not in"},
      {"simulate --scenario ge2017 --ins-latency-s 0.1" + out, "has no INS"},
      {"simulate --scenario li2023 --step-nT 1,2,3" + out, "needs --step-time-s"},
      {"simulate --scenario li2023", "--out is required"},
      {"simulate --scenario li2023 --out " + file("missing/dir/x.csv"), "cannot create"},
      {"frobnicate", "frobnicate"},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.args);
    const Result r = run(c.args);
    EXPECT_NE(r.status, 0);
    EXPECT_NE(r.output.find(c.message), std::string::npos) << r.output;
  }
  EXPECT_FALSE(fs::exists(file("x.csv")));
}

// `magvec apply` on a bad recording or a bad cal.json exits 2 (bad input, as `magvec calibrate`),
// names the file and the cause, and leaves no output; an output that cannot be written is not
// bad input (exit 1).
TEST_F(Cli, ApplyBadInputExitsTwoNamingTheFileAndTheCause) {
  ASSERT_EQ(run("simulate --scenario li2023 --seed 1 --out " + file("li.csv")).status, 0);
  const Result cal =
      run("calibrate --method li-ml --in " + file("li.csv") + " --out " + file("cal.json"));
  ASSERT_EQ(cal.status, 0) << cal.output;
  const Result ok = run("apply --cal " + file("cal.json") + " --in " + file("li.csv") + " --out " +
                        file("o.csv"));
  ASSERT_EQ(ok.status, 0) << ok.output;
  fs::remove(file("o.csv"));

  const std::string good = slurp(file("cal.json"));
  const std::string key = "\"time_offset_s\": ";
  const std::size_t at = good.find(key);
  ASSERT_NE(at, std::string::npos) << good;
  const std::size_t end = good.find_first_of(",\n}", at + key.size());
  auto with_offset = [&](const std::string& value) {
    return good.substr(0, at + key.size()) + value + good.substr(end);
  };
  auto write = [&](const char* name, const std::string& text) {
    std::ofstream(file(name), std::ios::binary) << text;
  };
  write("garbage.json", "{\"schema\": \"magvec-calibration/1\", ");
  write("overflow.json", with_offset("1e474"));  // nlohmann: out_of_range while parsing
  write("type.json", with_offset("\"soon\""));   // nlohmann: a string where a number belongs
  write("bad.csv",
        "t_s,hx_nT,hy_nT,hz_nT,F_nT,alpha_deg,beta_deg,gamma_deg\n"
        "0,1,2,3,50000,0,0,0\n"
        "0.1,1,2,abc,50000,0,0,0\n");
  write("quat.csv",
        "t_s,hx_nT,hy_nT,hz_nT,qw,qx,qy,qz\n"
        "0,1,2,3,1,0,0,0\n"
        "0.1,1,2,3,1e200,0,0,0\n");

  const struct {
    std::string cal, in;
    std::vector<std::string> message;
  } cases[] = {
      {"nonexistent.json", "li.csv", {"nonexistent.json", "cannot open"}},
      {"garbage.json", "li.csv", {"garbage.json", "not valid JSON"}},
      {"overflow.json", "li.csv", {"overflow.json", "time_offset_s", "1e474"}},
      {"type.json", "li.csv", {"type.json", "'time_offset_s' must be a finite number"}},
      {"cal.json", "nonexistent.csv", {"nonexistent.csv", "cannot open"}},
      {"cal.json", "bad.csv", {"bad.csv:3", "hz_nT", "malformed number 'abc'"}},
      {"cal.json", "quat.csv", {"quat.csv:3", "qw", "quaternion is not unit (norm overflows)"}},
  };
  for (const auto& c : cases) {
    SCOPED_TRACE(c.cal + " " + c.in);
    const Result r = run("apply --cal " + file(c.cal.c_str()) + " --in " + file(c.in.c_str()) +
                         " --out " + file("o.csv"));
    EXPECT_EQ(r.status, 2) << r.output;
    for (const std::string& m : c.message)
      EXPECT_NE(r.output.find(m), std::string::npos) << m << "\n" << r.output;
    EXPECT_FALSE(fs::exists(file("o.csv")));
  }

  const Result unwritable = run("apply --cal " + file("cal.json") + " --in " + file("li.csv") +
                                " --out " + file("missing/dir/o.csv"));
  EXPECT_EQ(unwritable.status, 1) << unwritable.output;
  EXPECT_NE(unwritable.output.find("missing/dir/o.csv"), std::string::npos) << unwritable.output;
}

TEST_F(Cli, DemoCalibratesInTheLoopAndWritesRecordsAndCalibration) {
  const Result r = run("demo --out-dir " + file("demo"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_TRUE(fs::exists(dir_ / "demo" / "records.csv"));
  ASSERT_TRUE(fs::exists(dir_ / "demo" / "cal.json"));
  EXPECT_NE(r.output.find("Calibration: state applied, cal_id 1"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("verdict ok"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("RMS error"), std::string::npos);
  EXPECT_NE(r.output.find("North"), std::string::npos);
  EXPECT_NE(r.output.find("ADC CRC errors"), std::string::npos);
  // The calibration file round-trips and is close to the simulation truth.
  const magvec::host::CalibrationFile cal =
      magvec::host::read_calibration_file((dir_ / "demo" / "cal.json").string());
  const magvec::core::SensorModel<double> truth = magvec::drivers::sim::scenario_survey().truth;
  EXPECT_LT((cal.model.w - truth.w).norm(), 1e-3);
  // Offsets within 4 of their reported 1-sigma (a +-30 deg manoeuvre leaves Kof at ~0.2-1.2 nT).
  ASSERT_EQ(cal.sigma.count("Kof_nT"), 1u);
  for (int k = 0; k < 3; ++k) {
    const double sigma = cal.sigma.at("Kof_nT")[static_cast<std::size_t>(k)];
    EXPECT_GT(sigma, 0.0);
    EXPECT_LE(std::abs(cal.model.o(k) - truth.o(k)), 4.0 * sigma) << k;
  }
  EXPECT_LT(cal.model.rm.angularDistance(truth.rm), 1e-3);
  // The records carry cal_id 1 after the calibration was applied.
  magvec::host::io::CsvReader reader((dir_ / "demo" / "records.csv").string());
  const auto cal_col = reader.column_index("cal_id");
  ASSERT_TRUE(cal_col.has_value());
  magvec::host::io::CsvRecord rec;
  std::uint64_t rows = 0, calibrated = 0;
  while (reader.next(&rec)) {
    ++rows;
    calibrated += reader.value(*cal_col) == 1.0 ? 1u : 0u;
  }
  EXPECT_GT(rows, 60000u);
  EXPECT_GT(calibrated, rows / 2);
}

// Field-grade noise (a MEMS-class magnetometer, a tactical INS) that the loop is not told: the
// in-loop calibration estimates it, validates against its estimate and applies; the records'
// sigma_ENU agrees with the E/N/U error the demo scores against the simulation TRUTH.
TEST_F(Cli, DemoWithFieldNoiseCalibratesWithDefaultsAndReportsHonestSigmas) {
  const Result r = run("demo --noise-nT 3 --ins-noise-deg 0.05 --out-dir " + file("demo"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("Calibration: state applied, cal_id 1"), std::string::npos) << r.output;
  const magvec::host::CalibrationFile cal =
      magvec::host::read_calibration_file((dir_ / "demo" / "cal.json").string());
  ASSERT_TRUE(cal.noise.mag_estimated);
  EXPECT_NEAR(cal.noise.mag_nT, 3.0, 0.6);
  ASSERT_TRUE(cal.noise.ins_estimated);
  EXPECT_NEAR(cal.noise.ins_deg, 0.05, 0.015);
  ASSERT_TRUE(cal.output.has_value());
  EXPECT_TRUE(cal.output->aligned);
  // The scored E/N/U RMS error after calibration, against the truth, per component.
  std::vector<double> err_after;
  for (const char* name : {"  East ", "  North", "  Up   "}) {
    const auto pos = r.output.find(name);
    ASSERT_NE(pos, std::string::npos) << r.output;
    std::istringstream row(r.output.substr(pos + 7, 120));
    double sd_before = 0, sd_after = 0, rms_before = 0, rms_after = 0;
    row >> sd_before >> sd_after >> rms_before >> rms_after;
    err_after.push_back(rms_after);
  }
  const double err_rms = std::sqrt(
      (err_after[0] * err_after[0] + err_after[1] * err_after[1] + err_after[2] * err_after[2]) /
      3.0);
  // F sigma_att (~47 nT at 54 uT and 0.05 deg) dominates both.
  EXPECT_GT(cal.output->sigma_enu_nT, 0.7 * err_rms) << r.output;
  EXPECT_LT(cal.output->sigma_enu_nT, 1.5 * err_rms) << r.output;
  // Every calibrated record with attitude carries that sigma; records without it carry NaN.
  magvec::host::io::CsvReader reader((dir_ / "demo" / "records.csv").string());
  const auto sigma_col = reader.column_index("sigma_ENU_nT");
  const auto cal_col = reader.column_index("cal_id");
  const auto e_col = reader.column_index("hE_nT");
  ASSERT_TRUE(sigma_col && cal_col && e_col);
  magvec::host::io::CsvRecord rec;
  std::uint64_t with_sigma = 0;
  while (reader.next(&rec)) {
    const double sigma = reader.value(*sigma_col);
    const bool enu = reader.value(*cal_col) == 1.0 && std::isfinite(reader.value(*e_col));
    if (enu) {
      EXPECT_NEAR(sigma, cal.output->sigma_enu_nT, 1e-9 * cal.output->sigma_enu_nT);
      ++with_sigma;
    } else {
      EXPECT_TRUE(std::isnan(sigma));
    }
  }
  EXPECT_GT(with_sigma, 30000u);
}

// The E/N/U RMS errors after calibration that the demo scores against the simulation TRUTH.
std::vector<double> demo_enu_errors(const std::string& output) {
  std::vector<double> err_after;
  for (const char* name : {"  East ", "  North", "  Up   "}) {
    const auto pos = output.find(name);
    if (pos == std::string::npos) return {};
    std::istringstream row(output.substr(pos + 7, 120));
    double sd_before = 0, sd_after = 0, rms_before = 0, rms_after = 0;
    row >> sd_before >> sd_after >> rms_before >> rms_after;
    err_after.push_back(rms_after);
  }
  return err_after;
}

// The online vector calibration filter as the demo's calibrator, with default options (the noise
// is not told to it: it estimates it): it applies a calibration, and its E/N/U error against the
// TRUE field on the survey lines is within 1.2x of the Li calibrator's on the same data.
// Measured: E/N/U error 33.40 vs 33.41 nT (ratio 1.000); the noise reported is the filter's live
// innovation estimate (E-VF-10), 3.06 nT for the simulated 3 (the 48-sample start-up set alone
// gave 3.80 nT, outside the 25 % bound); the INS figure is that of the attitude interpolated to
// each magnetometer sample (0.043 deg for 0.05 deg at the INS epochs).
TEST_F(Cli, DemoWithTheVectorEkfCalibratorMatchesTheLiCalibratorAgainstTheTruth) {
  const std::string noise = "--noise-nT 3 --ins-noise-deg 0.05 --seed 2 ";
  const Result li = run("demo " + noise + "--out-dir " + file("li"));
  ASSERT_EQ(li.status, 0) << li.output;
  const Result vec = run("demo --calibrator vector-ekf " + noise + "--out-dir " + file("vec"));
  ASSERT_EQ(vec.status, 0) << vec.output;
  EXPECT_NE(vec.output.find("Calibration: state applied, cal_id 1"), std::string::npos)
      << vec.output;
  EXPECT_NE(vec.output.find("online vector calibration filter (in the loop)"), std::string::npos);
  const std::vector<double> e_li = demo_enu_errors(li.output);
  const std::vector<double> e_vec = demo_enu_errors(vec.output);
  ASSERT_EQ(e_li.size(), 3u) << li.output;
  ASSERT_EQ(e_vec.size(), 3u) << vec.output;
  double ss_li = 0, ss_vec = 0;
  for (int k = 0; k < 3; ++k) {
    const auto kk = static_cast<std::size_t>(k);
    EXPECT_GT(e_vec[kk], 0.0);
    EXPECT_LE(e_vec[kk], 1.2 * e_li[kk]) << "ENU"[k] << "\n" << vec.output << li.output;
    ss_li += e_li[kk] * e_li[kk];
    ss_vec += e_vec[kk] * e_vec[kk];
  }
  std::printf("E/N/U RMS error vs truth: vector-ekf %.2f nT, li %.2f nT (ratio %.3f)\n",
              std::sqrt(ss_vec / 3), std::sqrt(ss_li / 3), std::sqrt(ss_vec / ss_li));
  // The calibration file it wrote: aligned, the noise estimated near the simulated figures, the
  // model near the truth.
  const magvec::host::CalibrationFile cal =
      magvec::host::read_calibration_file((dir_ / "vec" / "cal.json").string());
  ASSERT_TRUE(cal.output.has_value());
  EXPECT_TRUE(cal.output->aligned);
  EXPECT_TRUE(cal.noise.mag_estimated);
  EXPECT_NEAR(cal.noise.mag_nT, 3.0, 0.75);
  EXPECT_NEAR(cal.noise.ins_deg, 0.05, 0.0125);
  const magvec::core::SensorModel<double> truth = magvec::drivers::sim::scenario_survey().truth;
  EXPECT_LT(cal.model.rm.angularDistance(truth.rm), 0.05 * magvec::core::kPi<double> / 180);
}

// Measured: applied after 90 s of the survey scenario (0.3 nT, 0.015 deg) with defaults; the
// calibration's 1-sigma over the survey envelope is 0.12 nT for |h| against 0.27 nT of noise
// (readiness at 0.5, E-VF-10). Under the earlier per-parameter rule it was still collecting
// (an offset's 1-sigma at 1.6x its limit), which this test recorded as a known gap.
TEST_F(Cli, RunWithTheVectorEkfCalibratorCalibratesWithDefaults) {
  const Result r = run("run --sim survey --duration 90 --seed 3 --calibrator vector-ekf --out " +
                       file("vec.csv"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("calibration: state applied"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("vector-ekf calibrator: seen"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("noise estimated"), std::string::npos) << r.output;
  EXPECT_NE(run("demo --calibrator bogus --out-dir " + file("x")).status, 0);
}

}  // namespace

namespace {

TEST_F(Cli, RunSimWritesRecordsAndCountsFaults) {
  const std::string out = file("records.csv");
  const Result r =
      run("run --sim survey --duration 20 --seed 4 --faults crc=0.02,dropout=0.01 --out " + out);
  ASSERT_EQ(r.status, 0) << r.output;
  magvec::host::io::CsvReader reader(out);
  const std::vector<std::string> expected{
      "t_s",   "hx_nT", "hy_nT", "hz_nT", "hsx_nT", "hsy_nT",     "hsz_nT",      "F_nT",
      "hE_nT", "hN_nT", "hU_nT", "flags", "cal_id", "sigma_F_nT", "sigma_ENU_nT"};
  EXPECT_EQ(reader.columns(), expected);
  magvec::host::io::CsvRecord rec;
  std::uint64_t rows = 0;
  while (reader.next(&rec))
    ++rows;
  // 4000 conversions minus the CRC-rejected ones, which the summary reports.
  const auto pos = r.output.find("crc errors ");
  ASSERT_NE(pos, std::string::npos) << r.output;
  const std::uint64_t crc = std::stoull(r.output.substr(pos + 11));
  EXPECT_GT(crc, 40u);
  EXPECT_EQ(rows + crc, 4000u);
  EXPECT_NE(r.output.find("injected: crc " + std::to_string(crc)), std::string::npos) << r.output;
}

TEST_F(Cli, RunRejectsUnknownFaultsAndCalibrators) {
  EXPECT_NE(run("run --sim survey --duration 1 --faults bogus=1 --out " + file("a.csv")).status, 0);
  EXPECT_NE(run("run --sim survey --duration 1 --faults crc=2 --out " + file("a.csv")).status, 0);
  EXPECT_NE(run("run --sim survey --duration 1 --calibrator bogus --out " + file("a.csv")).status,
            0);
  EXPECT_FALSE(fs::exists(file("a.csv")));
}

// --profile mcu fixes the run: everything that would configure it is refused by name, and a run
// needs --sim or --profile. (Its records against the MCU image: tests/mcu.)
TEST_F(Cli, RunProfileRefusesWhatItFixes) {
  for (const char* extra : {"--seed 3", "--sim survey", "--calibrator li", "--duration 10",
                            "--faults crc=0.01", "--noise-nT 0.3", "--fusion-horizon-us 0"}) {
    const Result r = run("run --profile mcu " + std::string(extra) + " --out " + file("p.csv"));
    EXPECT_NE(r.status, 0) << extra;
    const std::string opt = std::string(extra).substr(0, std::string(extra).find(' '));
    EXPECT_NE(r.output.find(opt), std::string::npos) << r.output;
  }
  const Result none = run("run --out " + file("p.csv"));
  EXPECT_NE(none.status, 0);
  EXPECT_NE(none.output.find("--sim or --profile is required"), std::string::npos) << none.output;
  EXPECT_NE(run("run --profile m7 --out " + file("p.csv")).status, 0);
  EXPECT_FALSE(fs::exists(file("p.csv")));
  const Result ok = run("run --profile mcu --out " + file("p.csv"));
  ASSERT_EQ(ok.status, 0) << ok.output;
  EXPECT_NE(ok.output.find("survey50, seed 20170817"), std::string::npos) << ok.output;
  EXPECT_NE(ok.output.find("calibration: state applied"), std::string::npos) << ok.output;
}

TEST_F(Cli, RunWithTheLiCalibratorCalibratesInTheLoop) {
  const Result r =
      run("run --sim survey --duration 90 --seed 3 --calibrator li --faults crc=0.01 "
          "--out " +
          file("li.csv"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("calibration: state applied"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("cal_id 1"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("li solve: verdict ok"), std::string::npos) << r.output;
}

TEST_F(Cli, RunWithTheEkfCalibratorReportsAlignment) {
  const Result r =
      run("run --sim survey --duration 90 --seed 3 --calibrator ekf --out " + file("ekf.csv"));
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("ekf calibrator: updates"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("calibration: state applied"), std::string::npos) << r.output;
  EXPECT_NE(r.output.find("alignment: Rm [deg]"), std::string::npos) << r.output;
  const Result na =
      run("run --sim survey --duration 90 --seed 3 --calibrator ekf --ekf-no-align "
          "--out " +
          file("ekf2.csv"));
  ASSERT_EQ(na.status, 0) << na.output;
  EXPECT_NE(na.output.find("NOT aligned to the INS"), std::string::npos) << na.output;
}

}  // namespace
