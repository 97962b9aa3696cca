// `magvec soak`: a short run end to end (exit status, the JSON report, every counter equal to the
// injection, faults really injected), bad options, and the pass/fail rules of soak_checks.hpp fed
// with values that must fail.
#include <gtest/gtest.h>
#include <stdlib.h>

#include <cstdint>
#include <filesystem>
#include <fstream>
#include <map>
#include <nlohmann/json.hpp>
#include <random>
#include <string>
#include <vector>

#include "soak_checks.hpp"
#include "support/process.hpp"

namespace magvec::host::cli {
namespace {

namespace fs = std::filesystem;

magvec::test::CommandResult soak(const std::string& args) {
  return magvec::test::run_shell(std::string(MAGVEC_CLI) + " soak " + args);
}

class SoakCommand : public ::testing::Test {
 protected:
  void SetUp() override {
    char tmpl[] = "/tmp/magvec_soak_test_XXXXXX";
    ASSERT_NE(::mkdtemp(tmpl), nullptr);
    dir_ = tmpl;
  }
  void TearDown() override { fs::remove_all(dir_); }
  fs::path dir_;
};

TEST_F(SoakCommand, ShortRunWithEveryFaultPassesAndCountsEachInjection) {
  const fs::path json = dir_ / "soak.json";
  // 72 s at 1 kHz in four 18-s intervals; rates high enough that every fault happens. Not a stuck
  // channel: the 62 held conversions before the detector fires are wrong values nothing flags,
  // and they move their interval's mean |h| past the drift bound (stuck=30:0.5: 0.24 nT, 1.36x).
  const auto r =
      soak("--hours 0.02 --interval-s 18 --seed 3 --json " + json.string() +
           " --faults crc=1e-3,dropout=1e-3,saturation=5e-4,ins-corrupt=1e-3,ins-gap=20:0.5,"
           "ins-invalid=40:1,clock-jump=60:-1,ins-duplicate=5e-3,adc-reset=2e-4");
  ASSERT_EQ(r.status, 0) << r.output;
  EXPECT_NE(r.output.find("soak: PASS"), std::string::npos) << r.output;
  std::ifstream f(json);
  ASSERT_TRUE(f.good());
  const nlohmann::json j = nlohmann::json::parse(f);
  EXPECT_TRUE(j.at("ok").get<bool>());
  EXPECT_EQ(j.at("samples").get<std::uint64_t>(), 72'000u);
  ASSERT_EQ(j.at("intervals").size(), 4u);
  EXPECT_EQ(j.at("drift").at("checks").size(), 3u * kComponents);
  EXPECT_TRUE(j.at("rss").at("ok").get<bool>());
  std::map<std::string, std::uint64_t> counted;
  for (const auto& c : j.at("counters")) {
    EXPECT_EQ(c.at("counted"), c.at("expected")) << c.dump();
    EXPECT_TRUE(c.at("ok").get<bool>()) << c.dump();
    counted[c.at("counter").get<std::string>()] = c.at("counted").get<std::uint64_t>();
  }
  // Every fault was injected (a run without faults would pass trivially).
  EXPECT_GT(counted.at("mag.crc_errors"), 20u);
  EXPECT_GT(counted.at("mag_not_fresh"), 20u);
  EXPECT_GT(counted.at("mag.saturated"), 10u);
  EXPECT_GT(counted.at("att.malformed"), 10u);
  EXPECT_GT(counted.at("att.duplicates"), 10u);
  EXPECT_GT(counted.at("mag.device_resets"), 5u);
  EXPECT_EQ(counted.at("att_invalid"), 100u);  // 1 s at 100 Hz, minus lost epochs: none here
  EXPECT_EQ(counted.at("mag_time_jumps"), 1u);
  EXPECT_EQ(counted.at("att_time_jumps"), 1u);
  EXPECT_GT(j.at("info").at("no_attitude").get<std::uint64_t>(), 0u);
  for (const auto& iv : j.at("intervals"))
    EXPECT_GT(iv.at("error").at("|h|").at("n").get<std::uint64_t>(), 15'000u);
}

TEST_F(SoakCommand, RejectsBadOptions) {
  auto r = soak("--hours 0.01 --faults bogus=1");
  EXPECT_NE(r.status, 0);
  EXPECT_NE(r.output.find("unknown fault 'bogus'"), std::string::npos) << r.output;
  r = soak("--hours 0.01 --rate-hz 50");
  EXPECT_NE(r.status, 0);
}

ErrorStats gaussian(double mean, double sd, std::uint64_t n, std::uint32_t seed) {
  std::mt19937_64 g(seed);
  std::normal_distribution<double> d(mean, sd);
  ErrorStats s;
  for (std::uint64_t i = 0; i < n; ++i)
    s.add(d(g));
  return s;
}

std::vector<IntervalStats> intervals(const std::vector<double>& means, double sd) {
  std::vector<IntervalStats> v;
  std::uint32_t seed = 1;
  for (double m : means) {
    IntervalStats iv;
    for (ErrorStats& e : iv.err)
      e = gaussian(m, sd, 20'000, seed++);
    v.push_back(iv);
  }
  return v;
}

bool all_pass(const std::vector<DriftCheck>& checks) {
  for (const DriftCheck& d : checks)
    if (!d.ok()) return false;
  return true;
}

TEST(SoakChecks, DriftWithinNoisePasses) {
  // |h| (n_eff = n): se = 1/sqrt(20000) = 0.007; means equal, noise only.
  const auto checks = drift_checks(intervals({0.0, 0.0, 0.0}, 1.0), 1000, 100);
  ASSERT_EQ(checks.size(), 2u * kComponents);
  EXPECT_TRUE(all_pass(checks));
}

TEST(SoakChecks, DriftOfTheMeanFails) {
  // 0.1 nT on 1-nT noise over 20000 samples is 10 standard errors of the difference for |h|.
  const auto checks = drift_checks(intervals({0.0, 0.0, 0.1}, 1.0), 1000, 100);
  bool h_failed = false;
  for (const DriftCheck& d : checks)
    if (d.interval == 2 && d.component == 3) h_failed = !d.ok();
  EXPECT_TRUE(h_failed);
  EXPECT_FALSE(all_pass(checks));
}

TEST(SoakChecks, EnuBoundIsWiderByTheInsSampling) {
  // E/N/U carry one independent attitude error per INS epoch: the bound grows by
  // sqrt(1 / (2/3 * 100/1000)) = 3.87 over |h|'s.
  const auto checks = drift_checks(intervals({0.0, 0.0}, 1.0), 1000, 100);
  ASSERT_EQ(checks.size(), kComponents);
  EXPECT_NEAR(checks[0].bound_nT / checks[3].bound_nT, std::sqrt(15.0), 0.1);
}

TEST(SoakChecks, IntervalWithoutScoredRecordsFails) {
  auto iv = intervals({0.0, 0.0}, 1.0);
  iv[1] = IntervalStats{};
  EXPECT_FALSE(all_pass(drift_checks(iv, 1000, 100)));
}

TEST(SoakChecks, RssGrowthBeyondTheSlackFails) {
  EXPECT_TRUE(rss_check({20'000, 20'100, 20'400, 20'300}).ok());
  const RssCheck grown = rss_check({20'000, 20'500, 21'100});
  EXPECT_FALSE(grown.ok());
  EXPECT_EQ(grown.growth_kib, 1'100);
  EXPECT_FALSE(rss_check({20'000, -1}).ok());  // unread
  EXPECT_FALSE(rss_check({}).ok());
}

}  // namespace
}  // namespace magvec::host::cli
