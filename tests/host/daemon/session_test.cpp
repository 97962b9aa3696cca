// plan_session (host/daemon session.hpp): the pipeline events that start a session at boot and
// on a reload, and what a reload carries over.
#include "magvec/host/daemon/session.hpp"

#include <gtest/gtest.h>

#include <vector>

#include "magvec/host/daemon/event_pipeline.hpp"

namespace magvec::host::daemon {
namespace {

struct NullSink final : hal::RecordSink {
  hal::Status emit(const hal::OutputRecord&) noexcept override { return hal::Status::kOk; }
};

std::vector<int> kinds(const SessionPlan& p) {
  std::vector<int> k;
  for (const auto& e : p.events)
    k.push_back(e.kind);
  return k;
}

using E = magvec_lcm::pipeline_event;

TEST(Session, BootInstallsThePersistedCalibrationAndStartsWhenConfigured) {
  Config c = parse_config("", "test");
  PersistedCalibration persisted;
  persisted.present = true;
  persisted.cal_id = 7;
  persisted.time_offset_s = 0.01;
  persisted.model.o = core::Vec3<double>(1, 2, 3);
  std::int64_t seq = 0;
  SessionPlan p = plan_session(c, "text", persisted, nullptr, &seq);
  EXPECT_EQ(kinds(p), (std::vector<int>{E::SESSION_START, E::SOLVE_ON_WORKER, E::SET_ACTIVE,
                                        E::START_CALIBRATION}));
  EXPECT_EQ(p.events[0].config_toml, "text");
  EXPECT_EQ(p.events[2].cal_id, 7);
  EXPECT_DOUBLE_EQ(p.events[2].time_offset_s, 0.01);
  EXPECT_DOUBLE_EQ(p.events[2].o_nT[2], 3.0);
  EXPECT_EQ(seq, 4);
  EXPECT_EQ(p.events[3].sequence, 4);
  EXPECT_FALSE(p.calibration_restarted);

  c.calibration.start_on_boot = false;
  c.calibration.solve_on_worker = false;
  p = plan_session(c, "text", PersistedCalibration{}, nullptr, &seq);
  EXPECT_EQ(kinds(p), (std::vector<int>{E::SESSION_START}));
  c.calibration.start_on_boot = true;
  c.calibration.mode = "none";
  p = plan_session(c, "text", PersistedCalibration{}, nullptr, &seq);
  EXPECT_EQ(kinds(p), (std::vector<int>{E::SESSION_START}));
}

TEST(Session, ReloadCarriesTheActiveCalibrationAndRestartsOneInProgress) {
  const Config c = parse_config("", "test");
  NullSink sink;
  EventPipeline ep(sink);
  core::SensorModel<double> m;
  m.o = core::Vec3<double>(5, 6, 7);
  ep.apply(session_start_event(1, ""));
  ep.apply(set_active_event(2, m, 3, 0.02, OutputQuality{true, 0.8, 15.0}));
  std::int64_t seq = 10;
  PersistedCalibration persisted;  // a different persisted calibration: not what a reload installs
  persisted.present = true;
  persisted.cal_id = 1;
  // Idle: carried over, not started.
  SessionPlan p = plan_session(c, "", persisted, ep.pipeline(), &seq);
  EXPECT_EQ(kinds(p), (std::vector<int>{E::SESSION_START, E::SOLVE_ON_WORKER, E::SET_ACTIVE}));
  EXPECT_EQ(p.events[2].cal_id, 3);
  EXPECT_DOUBLE_EQ(p.events[2].o_nT[0], 5.0);
  EXPECT_DOUBLE_EQ(p.events[2].time_offset_s, 0.02);
  const OutputQuality carried = output_quality_from(p.events[2]);
  EXPECT_TRUE(carried.aligned);
  EXPECT_EQ(carried.sigma_f_nT, 0.8);
  EXPECT_EQ(carried.sigma_enu_nT, 15.0);
  EXPECT_FALSE(p.calibration_restarted);
  // Collecting: starts again in the new session.
  ep.apply(start_calibration_event(3));
  p = plan_session(c, "", persisted, ep.pipeline(), &seq);
  EXPECT_EQ(kinds(p), (std::vector<int>{E::SESSION_START, E::SOLVE_ON_WORKER, E::SET_ACTIVE,
                                        E::START_CALIBRATION}));
  EXPECT_TRUE(p.calibration_restarted);
  // Applying the plan gives the new pipeline the carried calibration.
  for (const auto& e : p.events)
    ep.apply(e);
  EXPECT_EQ(ep.sessions(), 2u);
  EXPECT_EQ(ep.pipeline()->status().cal_id, 3u);
  EXPECT_EQ(ep.pipeline()->state(), core::CalState::kCollecting);
}

}  // namespace
}  // namespace magvec::host::daemon
