// Calibration guidance (core/calibration_guidance.hpp, its words in guidance_text.hpp) and its
// use in magvecd's calibration state: progress is the smallest fraction of what the calibrator
// needs, the hint names the missing heading or tilt from the empty cells and the attitude, and
// during a simulated calibration the daemon's state goes from 0 to 1 with the hint following the
// coverage.
#include <gtest/gtest.h>

#include <algorithm>
#include <bit>
#include <cmath>
#include <cstdint>
#include <memory>
#include <set>
#include <string>
#include <vector>

#include "../daemon/logged_daemon.hpp"
#include "magvec/core/calibration_guidance.hpp"
#include "magvec/core/coverage.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/guidance_text.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/hil_session.hpp"

namespace magvec::host::daemon {
namespace {

using core::GuidanceHint;

// A mid-latitude field (ENU, nT): inclination about 66 deg down.
const core::Vec3<double> kField(1500.0, 20000.0, -45000.0);

core::Mat3<double> attitude(double heading_deg, double pitch_deg = 0, double roll_deg = 0) {
  return core::r_bn_from_ypr(core::YawPitchRoll<double>{
      core::deg_to_rad(heading_deg), core::deg_to_rad(pitch_deg), core::deg_to_rad(roll_deg)});
}

unsigned cell_at(const core::Mat3<double>& r_bn) {
  return core::coverage_cell<double>(r_bn * kField);
}

// A li-like calibrator's needs (10 of 32 cells, 300 samples) at an attitude.
core::GuidanceInput<double> li_input(std::uint32_t cells, std::size_t samples,
                                     const core::Mat3<double>& r_bn) {
  core::GuidanceInput<double> in;
  in.collecting = true;
  in.cells = cells;
  in.cells_needed = 10;
  in.samples = samples;
  in.samples_needed = 300;
  in.have_attitude = true;
  in.r_bn = r_bn;
  in.have_field = true;
  in.m_nT = r_bn * kField;
  return in;
}

TEST(CalibrationGuidance, EmptyCoverageNamesAHeadingToTurnTo) {
  const core::Mat3<double> now = attitude(0);
  const auto g = core::calibration_guidance(li_input(0, 0, now));
  EXPECT_EQ(g.progress, 0.0);
  ASSERT_EQ(g.hint, GuidanceHint::kTurn);
  EXPECT_NE(g.heading_deg, 0);  // the current cell is being filled: another heading
  EXPECT_GE(g.target_cells, 1);
  // Turning there reaches a cell other than the current one.
  EXPECT_NE(cell_at(attitude(g.heading_deg)), cell_at(now));
  const std::string text = guidance_text(g);
  EXPECT_NE(text.find("turn towards"), std::string::npos) << text;
  EXPECT_NE(text.find("heading " + std::to_string(g.heading_deg) + " deg"), std::string::npos)
      << text;
}

TEST(CalibrationGuidance, TurnGoesToTheNearestEmptyHeading) {
  // Everything from heading 0 to 180 is filled: the nearest empty cell is beyond 180 deg or
  // anticlockwise, never inside the filled half.
  std::uint32_t cells = 0;
  for (int h = 0; h <= 180; h += 5)
    cells |= 1U << cell_at(attitude(h));
  const auto g = core::calibration_guidance(li_input(cells, 300, attitude(90)));
  ASSERT_EQ(g.hint, GuidanceHint::kTurn);
  EXPECT_EQ(cells & (1U << cell_at(attitude(g.heading_deg))), 0U) << g.heading_deg;
}

TEST(CalibrationGuidance, FullCoverageIsReady) {
  const auto g = core::calibration_guidance(li_input(0xFFFFFFFFU, 300, attitude(30, 5, -3)));
  EXPECT_EQ(g.progress, 1.0);
  EXPECT_EQ(g.cells_hit, 32);
  EXPECT_EQ(g.hint, GuidanceHint::kReady);
  EXPECT_EQ(guidance_text(g), "ready: the solve can be tried");
}

TEST(CalibrationGuidance, LevelOnlyDataAsksForTilt) {
  // A level turn through every heading fills one band: 8 cells, not the 10 needed.
  std::uint32_t cells = 0;
  for (int h = 0; h < 360; h += 5)
    cells |= 1U << cell_at(attitude(h));
  ASSERT_EQ(std::popcount(cells), 8);
  const core::Mat3<double> now = attitude(120);
  const auto g = core::calibration_guidance(li_input(cells, 300, now));
  EXPECT_DOUBLE_EQ(g.progress, 0.8);
  EXPECT_DOUBLE_EQ(g.samples_fraction, 1.0);
  ASSERT_TRUE(g.hint == GuidanceHint::kPitch || g.hint == GuidanceHint::kRoll)
      << guidance_hint_name(g.hint);
  EXPECT_LE(std::abs(g.pitch_deg) + std::abs(g.roll_deg), core::kGuidanceMaxTiltDeg);
  // The tilt (then the heading, if one is named) reaches an empty cell.
  const int heading = g.heading_deg >= 0 ? g.heading_deg : 120;
  EXPECT_EQ(cells & (1U << cell_at(attitude(heading, g.pitch_deg, g.roll_deg))), 0U);
  const std::string text = guidance_text(g);
  EXPECT_TRUE(text.find("tilt nose-") != std::string::npos ||
              text.find("roll ") != std::string::npos)
      << text;
}

TEST(CalibrationGuidance, ProgressIsTheSmallestFraction) {
  std::uint32_t ten = (1U << 10) - 1U;
  auto g = core::calibration_guidance(li_input(ten, 150, attitude(0)));
  EXPECT_DOUBLE_EQ(g.progress, 0.5);  // samples
  EXPECT_EQ(g.hint, GuidanceHint::kKeepMoving);
  EXPECT_EQ(guidance_text(g), "keep turning: more samples needed");
  g = core::calibration_guidance(li_input(0x7U, 300, attitude(0)));
  EXPECT_DOUBLE_EQ(g.progress, 0.3);  // cells
  core::GuidanceInput<double> in = li_input(ten, 300, attitude(0));
  in.other_fraction = 0.25;  // e.g. the EKF's start-up set
  EXPECT_DOUBLE_EQ(core::calibration_guidance(in).progress, 0.25);
}

TEST(CalibrationGuidance, MissingInputsComeFirst) {
  core::GuidanceInput<double> in = li_input(0, 0, attitude(0));
  in.have_attitude = false;
  auto g = core::calibration_guidance(in);
  EXPECT_EQ(g.hint, GuidanceHint::kNoAttitude);
  EXPECT_EQ(guidance_text(g).rfind("keep still: attitude missing", 0), 0U);
  in.have_reference = false;
  g = core::calibration_guidance(in);
  EXPECT_EQ(g.hint, GuidanceHint::kNoReference);
  EXPECT_NE(guidance_text(g).find("needs the scalar reference"), std::string::npos);
  in.have_field = false;
  EXPECT_EQ(core::calibration_guidance(in).hint, GuidanceHint::kNoField);
  // A calibrator that needs neither goes on to the manoeuvre (without attitude: keep moving).
  in = li_input(0, 0, attitude(0));
  in.need_attitude = false;
  in.have_attitude = false;
  EXPECT_EQ(core::calibration_guidance(in).hint, GuidanceHint::kKeepMoving);
  // Not collecting: nothing to say.
  in.collecting = false;
  g = core::calibration_guidance(in);
  EXPECT_EQ(g.hint, GuidanceHint::kNone);
  EXPECT_EQ(guidance_text(g), "");
}

TEST(CalibrationGuidance, FloatGivesTheSameHint) {
  const core::GuidanceInput<double> d = li_input(0x0FU, 100, attitude(200, 10, 0));
  core::GuidanceInput<float> f;
  f.collecting = true;
  f.cells = d.cells;
  f.cells_needed = d.cells_needed;
  f.samples = d.samples;
  f.samples_needed = d.samples_needed;
  f.have_attitude = true;
  f.r_bn = d.r_bn.cast<float>();
  f.have_field = true;
  f.m_nT = d.m_nT.cast<float>();
  const auto gd = core::calibration_guidance(d);
  const auto gf = core::calibration_guidance(f);
  EXPECT_EQ(gd.hint, gf.hint);
  EXPECT_EQ(gd.heading_deg, gf.heading_deg);
  EXPECT_EQ(gd.pitch_deg, gf.pitch_deg);
  EXPECT_EQ(gd.roll_deg, gf.roll_deg);
}

// magvecd's pipeline during a simulated calibration: the state's progress rises from 0 to 1,
// the hint changes as the cells fill, and the state message carries it all.
struct Trace {
  std::vector<double> progress;
  std::set<std::string> hints;
  std::uint32_t cells{0};
  bool left_collecting{false};
  CalibrationStatus last{};
};

Trace run_calibration(const std::string& mode, int steps) {
  const Config c = test::fast_config(mode);
  drivers::sim::Simulator sim(sim_scenario(c), c.sim.seed);
  auto front = std::make_unique<hil::SimFrontEnd>(sim, sim_rig_config(c));
  EXPECT_EQ(front->init(), hal::Status::kOk);
  test::LoggedDaemon d;
  d.event(session_start_event(1, test::fast_config_text(mode)));
  d.event(start_calibration_event(2));
  Trace t;
  for (int i = 0; i < steps && !t.left_collecting; ++i) {
    EXPECT_TRUE(front->rig().step());
    front->poll(d);
    const CalibrationStatus st = d.ep.pipeline()->status();
    if (st.state != core::CalState::kCollecting) {
      t.left_collecting = true;
      t.last = st;
      break;
    }
    t.progress.push_back(st.progress);
    t.hints.insert(st.hint);
    t.cells = st.guidance.cells;
    t.last = st;
  }
  return t;
}

TEST(DaemonGuidance, LiProgressRisesFromZeroToOneWhileTheHintFollowsTheCoverage) {
  const Trace t = run_calibration("li", 20000);
  ASSERT_TRUE(t.left_collecting);
  ASSERT_GT(t.progress.size(), 5U);
  EXPECT_LT(t.progress.front(), 0.05);
  for (std::size_t i = 1; i < t.progress.size(); ++i)  // samples and cells only ever grow
    EXPECT_GE(t.progress[i], t.progress[i - 1]) << i;
  EXPECT_GE(t.progress.back(), 0.95);  // one or two samples short, then ready: solving
  EXPECT_EQ(t.last.hint, "");          // solving: nothing to ask for
  EXPECT_GE(t.hints.size(), 2U);
  EXPECT_EQ(t.hints.count(""), 0U);
  EXPECT_GE(std::popcount(t.cells), 9);
  // The state message carries what the status says.
  const magvec_lcm::calibration_state m = to_lcm(t.last, 7, 0);
  EXPECT_EQ(m.coverage_cells, static_cast<std::int32_t>(t.last.guidance.cells));
  EXPECT_EQ(m.coverage_needed, 10);
  EXPECT_EQ(m.samples_needed, 100);
  EXPECT_EQ(m.hint, t.last.hint);
  EXPECT_TRUE(std::isfinite(m.residual_nT));  // the simulator supplies F
}

TEST(DaemonGuidance, StateMessageRoundTripsTheGuidance) {
  CalibrationStatus st;
  st.calibrator = "li";
  st.state = core::CalState::kCollecting;
  st.progress = 0.4;
  st.guidance.cells = 0x80000001U;  // the top bit survives the int32 field
  st.guidance.cells_needed = 10;
  st.guidance.hint = GuidanceHint::kPitch;
  st.samples = 42;
  st.samples_needed = 300;
  st.hint = "tilt nose-down by 20 deg";
  st.residual_nT = 12.5;
  const magvec_lcm::calibration_state m = to_lcm(st, 5, 0);
  std::vector<std::uint8_t> buf(static_cast<std::size_t>(m.getEncodedSize()));
  ASSERT_EQ(m.encode(buf.data(), 0, static_cast<int>(buf.size())), static_cast<int>(buf.size()));
  magvec_lcm::calibration_state back;
  ASSERT_EQ(back.decode(buf.data(), 0, static_cast<int>(buf.size())), static_cast<int>(buf.size()));
  EXPECT_EQ(static_cast<std::uint32_t>(back.coverage_cells), 0x80000001U);
  EXPECT_EQ(back.hint_code, "pitch");
  EXPECT_EQ(back.hint, st.hint);
  EXPECT_EQ(back.samples, 42);
  EXPECT_EQ(back.samples_needed, 300);
  EXPECT_EQ(back.residual_nT, 12.5);
}

TEST(DaemonGuidance, EkfProgressRisesAndTheCellsAreShown) {
  const Trace t = run_calibration("ekf", 20000);
  ASSERT_GT(t.progress.size(), 5U);
  EXPECT_LT(t.progress.front(), 0.05);
  EXPECT_GT(*std::max_element(t.progress.begin(), t.progress.end()), 0.5);
  // The start-up set, then the filter's own need: progress does not fall back by much.
  for (std::size_t i = 1; i < t.progress.size(); ++i)
    EXPECT_GT(t.progress[i], t.progress[i - 1] - 0.1) << i;
  EXPECT_NE(t.cells, 0U);
  EXPECT_GE(t.hints.size(), 2U);
}

}  // namespace
}  // namespace magvec::host::daemon
