// `magvec ctl watch`'s frame (host/cli/watch_view.hpp) on canned calibration states: progress
// bar, the 4 x 8 coverage map in coverage.hpp's numbering, hint, residual and verdict.
#include "watch_view.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <limits>
#include <sstream>
#include <string>
#include <vector>

namespace magvec::host::cli {
namespace {

magvec_lcm::calibration_state collecting() {
  magvec_lcm::calibration_state s{};
  s.calibrator = "li";
  s.state = "collecting";
  s.failure = "none";
  s.progress = 0.5;
  // Band 0 (field pointing down the sensor's z: the bottom row) full, band 1 sector 0.
  s.coverage_cells = static_cast<std::int32_t>(0xFFU | (1U << 8));
  s.coverage_needed = 10;
  s.samples = 150;
  s.samples_needed = 300;
  s.hint_code = "pitch";
  s.hint = "tilt nose-down by 20 deg";
  s.residual_nT = 412.345;
  return s;
}

std::vector<std::string> lines(const std::string& frame) {
  std::vector<std::string> out;
  std::istringstream in(frame);
  for (std::string l; std::getline(in, l);)
    out.push_back(l);
  return out;
}

// The map's rows, top (z +0.5..+1) first.
std::vector<std::string> map_rows(const std::string& frame) {
  std::vector<std::string> rows;
  for (const std::string& l : lines(frame))
    if (l.rfind("  z ", 0) == 0) rows.push_back(l);
  return rows;
}

TEST(WatchView, CollectingFrame) {
  WatchContext c;
  c.url = "udpm://239.255.76.67:7667?ttl=0";
  const std::string f = render_watch(collecting(), c);
  EXPECT_NE(f.find("magvec ctl watch  udpm://239.255.76.67:7667?ttl=0\n"), std::string::npos);
  EXPECT_NE(f.find("calibrator li   state collecting   cal_id 0 (persisted 0)"), std::string::npos);
  EXPECT_NE(f.find("progress [###############...............] 50 %   samples 150/300   cells 9/10"),
            std::string::npos)
      << f;
  const std::vector<std::string> rows = map_rows(f);
  ASSERT_EQ(rows.size(), 4U) << f;
  EXPECT_EQ(rows[0], "  z +0.5..+1.0      .    .    .    .    .    .    .    .");
  EXPECT_EQ(rows[2], "  z -0.5.. 0.0      #    .    .    .    .    .    .    .");
  EXPECT_EQ(rows[3], "  z -1.0..-0.5      #    #    #    #    #    #    #    #");
  EXPECT_NE(f.find("hint: tilt nose-down by 20 deg\n"), std::string::npos);
  EXPECT_NE(f.find("residual |h|-F: 412.35 nT rms (active cal_id 0)"), std::string::npos);
  EXPECT_NE(f.find("verdict: -\n"), std::string::npos);
  EXPECT_EQ(f.find("no state for"), std::string::npos);
  EXPECT_EQ(f.find('\x1b'), std::string::npos);  // the caller owns the terminal codes
}

TEST(WatchView, TopBitIsTheLastCell) {
  magvec_lcm::calibration_state s = collecting();
  s.coverage_cells = static_cast<std::int32_t>(0x80000000U);
  const std::vector<std::string> rows = map_rows(render_watch(s, WatchContext{}));
  ASSERT_EQ(rows.size(), 4U);
  EXPECT_EQ(rows[0], "  z +0.5..+1.0      .    .    .    .    .    .    .    #");
}

TEST(WatchView, AppliedAndFailedVerdicts) {
  magvec_lcm::calibration_state s = collecting();
  s.state = "applied";
  s.progress = 1;
  s.cal_id = 3;
  s.hint = "";
  s.validation_rms_nT = 0.3141;
  s.residual_nT = 0.297;
  std::string f = render_watch(s, WatchContext{});
  EXPECT_NE(f.find("[##############################] 100 %"), std::string::npos) << f;
  EXPECT_NE(f.find("verdict: applied: cal_id 3, validation rms 0.314 nT"), std::string::npos) << f;
  EXPECT_NE(f.find("hint: -\n"), std::string::npos);
  s.state = "failed";
  s.failure = "solver_rejected";
  s.solver_reason = "insufficient_coverage";
  s.cal_id = 0;
  s.validation_rms_nT = std::numeric_limits<double>::quiet_NaN();
  s.residual_nT = std::numeric_limits<double>::quiet_NaN();
  f = render_watch(s, WatchContext{});
  EXPECT_NE(f.find("verdict: failed: solver_rejected (insufficient_coverage), validation rms - nT"),
            std::string::npos)
      << f;
  EXPECT_NE(f.find("residual |h|-F: - (no scalar reference)"), std::string::npos);
}

TEST(WatchView, StaleStateAndHealth) {
  magvec_lcm::health h{};
  h.mag_samples = 1234;
  h.att_samples = 617;
  h.records = 1200;
  WatchContext c;
  c.age_s = 7.4;
  c.health = &h;
  const std::string f = render_watch(collecting(), c);
  EXPECT_NE(f.find("(no state for 7 s)"), std::string::npos) << f;
  EXPECT_NE(f.find("health: mag 1234 samples, ins 617, records 1200"), std::string::npos) << f;
  EXPECT_EQ(f.find("mag resets"), std::string::npos) << "shown only when there are some";
  EXPECT_EQ(f.find("scalar:"), std::string::npos) << "no scalar magnetometer";
}

TEST(WatchView, ResetsDuplicatesAndTheScalarMagnetometer) {
  magvec_lcm::health h{};
  h.mag_samples = 1234;
  h.mag_device_resets = 2;
  h.att_duplicates = 5;
  h.scalar_present = true;
  h.scalar_samples = 61;
  h.scalar_malformed = 3;
  h.scalar_out_of_range = 1;
  h.scalar_garbage_bytes = 40;
  h.scalar_low_signal = 4;
  h.scalar_timeouts = 7;
  h.scalar_f_fallback = 90;
  WatchContext c;
  c.health = &h;
  const std::string f = render_watch(collecting(), c);
  EXPECT_NE(f.find("dropouts 0, mag resets 2, ins duplicates 5\n"), std::string::npos) << f;
  EXPECT_NE(f.find("scalar: 61 readings, 4 lines rejected, 40 garbage bytes, low signal 4, "
                   "timeouts 7, F fallback 90 samples\n"),
            std::string::npos)
      << f;
}

}  // namespace
}  // namespace magvec::host::cli
