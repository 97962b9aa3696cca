// BackgroundWorker (host/daemon background_worker.hpp): the hand-over (SolveWorker), the
// calibration written off the calling thread (PersistWorker), and the solve off the acquisition
// path end to end: a session whose solves run on the worker and are installed by SOLVE_RESULT
// events wherever they land in the event order replays bit-identically from its log, and calibrates
// like the inline path.
#include "magvec/host/daemon/background_worker.hpp"

#include <gtest/gtest.h>
#include <unistd.h>

#include <algorithm>
#include <atomic>
#include <chrono>
#include <cmath>
#include <filesystem>
#include <lcm/lcm-cpp.hpp>
#include <memory>
#include <thread>
#include <vector>

#include "logged_daemon.hpp"
#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/daemon/replay.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/hil_session.hpp"

namespace magvec::host::daemon {
namespace {

using test::fast_config_text;
using test::VectorSink;

SolveJob job_returning(std::uint32_t ticket, std::atomic<bool>* release = nullptr) {
  return [ticket, release] {
    while (release != nullptr && !release->load())
      std::this_thread::yield();
    SolveResult r;
    r.ticket = ticket;
    r.ok = true;
    return r;
  };
}

SolveWorker::Done wait_result(SolveWorker& w) {
  for (;;) {
    if (auto d = w.take_result()) return *d;
    std::this_thread::yield();
  }
}

TEST(SolveWorker, RunsAJobAndHandsBackItsTaggedResult) {
  SolveWorker w;
  EXPECT_FALSE(w.take_result().has_value());
  EXPECT_FALSE(w.submit(7, job_returning(3)));
  const SolveWorker::Done d = wait_result(w);
  EXPECT_EQ(d.tag, 7u);
  EXPECT_EQ(d.result.ticket, 3u);
  EXPECT_TRUE(d.result.ok);
  EXPECT_FALSE(w.take_result().has_value());  // taken once
}

// The hand-over holds one waiting job: a newer one replaces it (the older calibration was
// superseded), the running one finishes.
TEST(SolveWorker, ANewerJobReplacesTheWaitingOne) {
  SolveWorker w;
  std::atomic<bool> release{false};
  std::atomic<bool> started{false};
  EXPECT_FALSE(w.submit(1, [&] {
    started = true;
    return job_returning(1, &release)();
  }));
  while (!started.load())
    std::this_thread::yield();
  // Job 1 is running: jobs 2 and 3 wait in the one slot.
  std::atomic<bool> never_needed{true};
  (void)w.submit(2, job_returning(2, &never_needed));
  EXPECT_TRUE(w.submit(3, job_returning(3)));
  release = true;
  std::vector<std::uint64_t> tags;
  while (tags.empty() || tags.back() != 3)
    tags.push_back(wait_result(w).tag);
  EXPECT_EQ(std::count(tags.begin(), tags.end(), 2u), 0);  // replaced before it started
  EXPECT_FALSE(w.busy());
}

// A solve cannot be interrupted: destruction waits for the running one (a job not started yet is
// dropped: its result would have no one to take it).
TEST(SolveWorker, DestructionWaitsForTheRunningJob) {
  std::atomic<bool> started{false};
  std::atomic<bool> finished{false};
  {
    SolveWorker w;
    w.submit(1, [&] {
      started = true;
      std::this_thread::sleep_for(std::chrono::milliseconds(20));
      finished = true;
      return SolveResult{};
    });
    while (!started.load())
      std::this_thread::yield();
  }
  EXPECT_TRUE(finished.load());
}

// wait_idle() (the daemon's end, the accept command's write) returns once the job ran, not before.
TEST(SolveWorker, WaitIdleReturnsOnceTheJobRan) {
  SolveWorker w;
  std::atomic<bool> finished{false};
  w.submit(1, [&] {
    std::this_thread::sleep_for(std::chrono::milliseconds(20));
    finished = true;
    return SolveResult{};
  });
  w.wait_idle();
  EXPECT_TRUE(finished.load());
  EXPECT_FALSE(w.busy());
  ASSERT_TRUE(w.take_result().has_value());
  w.wait_idle();  // idle already: returns at once
}

// The auto-accepted calibration is written (atomically, fsync'd) on the worker's thread, and the
// outcome says what is now in the file, which loads back.
TEST(PersistWorker, WritesTheCalibrationOnItsOwnThread) {
  const std::filesystem::path dir = std::filesystem::temp_directory_path() /
                                    ("magvec_persist_worker_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  std::filesystem::create_directories(dir);
  CalibrationStore store(dir.string());
  CalibrationStatus st;
  st.calibrator = "li";
  st.cal_id = 4;
  st.active.o = core::Vec3<double>(12.5, -3.25, 0.5);
  std::thread::id writer;
  PersistWorker w;
  w.submit(st.cal_id, [&writer, path = store.path(), st] {
    writer = std::this_thread::get_id();
    return CalibrationStore::write(path, st, 0.02, "test");
  });
  w.wait_idle();
  std::optional<PersistWorker::Done> d = w.take_result();
  ASSERT_TRUE(d.has_value());
  ASSERT_TRUE(d->result.ok) << d->result.error;
  EXPECT_NE(writer, std::this_thread::get_id());
  EXPECT_EQ(d->tag, 4u);
  EXPECT_EQ(d->result.written.cal_id, 4u);
  EXPECT_FALSE(store.persisted().present);  // the store learns of it from the outcome
  store.mark_persisted(d->result.written);
  EXPECT_EQ(store.persisted().cal_id, 4u);
  CalibrationStore again(dir.string());
  const PersistedCalibration p = again.load();
  EXPECT_TRUE(p.present);
  EXPECT_EQ(p.cal_id, 4u);
  EXPECT_DOUBLE_EQ(p.model.o.x(), 12.5);
  EXPECT_DOUBLE_EQ(p.time_offset_s, 0.02);
  std::filesystem::remove_all(dir);
}

// A write that fails (here: the state directory is gone) comes back as a failed outcome with its
// reason, and nothing claims the calibration persisted.
TEST(PersistWorker, AFailedWriteComesBackWithItsReason) {
  const std::filesystem::path dir = std::filesystem::temp_directory_path() /
                                    ("magvec_persist_gone_" + std::to_string(::getpid()));
  std::filesystem::remove_all(dir);
  CalibrationStatus st;
  st.cal_id = 2;
  PersistWorker w;
  w.submit(st.cal_id, [path = (dir / "cal.json").string(), st] {
    return CalibrationStore::write(path, st, 0, "test");
  });
  w.wait_idle();
  std::optional<PersistWorker::Done> d = w.take_result();
  ASSERT_TRUE(d.has_value());
  EXPECT_FALSE(d->result.ok);
  EXPECT_FALSE(d->result.error.empty());
  EXPECT_FALSE(d->result.written.present);
  EXPECT_FALSE(std::filesystem::exists(dir));
}

// Publishes (into an LCM log) and applies, as magvecd does; the solve runs on a SolveWorker and
// its result is installed when it arrives, at whatever sample that is.
struct LiveDaemon : test::LoggedDaemon {
  explicit LiveDaemon(lcm::LogFile& l) { log = &l; }
  void after_event() {
    if (SolveJob job = ep.pipeline()->take_solve_job()) {
      worker.submit(1, std::move(job));
      ++jobs;
    }
    if (auto d = worker.take_result()) event(solve_result_event(++sequence, d->result));
  }

  SolveWorker worker;
  std::int64_t sequence{10};
  int jobs{0};
};

TEST(SolveOnWorker, CalibratesAndReplaysBitIdentically) {
  const std::filesystem::path path = std::filesystem::temp_directory_path() /
                                     ("magvec_solve_worker_" + std::to_string(::getpid()) + ".lcm");
  std::vector<hal::OutputRecord> live;
  int jobs = 0;
  {
    lcm::LogFile log(path.string(), "w");
    ASSERT_TRUE(log.good());
    const Config c = parse_config(fast_config_text(), "test");
    drivers::sim::Simulator sim(sim_scenario(c), c.sim.seed);
    auto front = std::make_unique<hil::SimFrontEnd>(sim, sim_rig_config(c));
    ASSERT_EQ(front->init(), hal::Status::kOk);
    auto d = std::make_unique<LiveDaemon>(log);
    d->event(session_start_event(1, fast_config_text()));
    d->event(solve_on_worker_event(2));
    d->event(start_calibration_event(3));
    // Samples keep coming while the worker solves, paced (as a real rig is) so that a loaded
    // machine only changes how many samples pass before the result is installed.
    for (int i = 0; i < 20'000; ++i) {
      if (i >= 1500 && d->ep.pipeline()->state() == core::CalState::kApplied) break;
      ASSERT_TRUE(front->rig().step());
      front->poll(*d);
      d->after_event();
      if (d->ep.pipeline()->state() == core::CalState::kSolving)
        std::this_thread::sleep_for(std::chrono::microseconds(200));
    }
    d->ep.flush();
    live = d->sink.records;
    jobs = d->jobs;
    EXPECT_EQ(d->ep.pipeline()->status().state, core::CalState::kApplied);
  }
  EXPECT_EQ(jobs, 1);
  ASSERT_FALSE(live.empty());
  EXPECT_EQ(live.back().cal_id, 1u);
  VectorSink replayed;
  const ReplayResult r = replay_log(path.string(), replayed);
  std::filesystem::remove(path);
  EXPECT_EQ(r.mismatches, 0u);
  EXPECT_EQ(r.compared, live.size());
  ASSERT_EQ(replayed.records.size(), live.size());
  for (std::size_t i = 0; i < live.size(); ++i)
    ASSERT_TRUE(bit_identical(live[i], replayed.records[i])) << "record " << i;
  EXPECT_EQ(r.final_status.state, core::CalState::kApplied);
}

// Without SOLVE_RESULT events (a log cut short while solving) the replay keeps waiting: it never
// solves inline what the live daemon solved on its worker.
TEST(SolveOnWorker, AReplayNeverSolvesInlineForAWorkerSession) {
  VectorSink sink;
  EventPipeline ep(sink);
  ep.apply(session_start_event(1, fast_config_text()));
  ep.apply(solve_on_worker_event(2));
  ep.apply(start_calibration_event(3));
  const Config c = parse_config(fast_config_text(), "test");
  drivers::sim::Simulator sim(sim_scenario(c), c.sim.seed);
  auto front = std::make_unique<hil::SimFrontEnd>(sim, sim_rig_config(c));
  ASSERT_EQ(front->init(), hal::Status::kOk);
  struct Feed {
    EventPipeline& ep;
    void on_attitude(const hal::AttitudeSample& a) { ep.apply(to_lcm(a)); }
    void on_magnetometer(const hal::MagnetometerSample& s, double f) { ep.apply(to_lcm(s, f)); }
    void on_read_error(hal::Status) {}
  } feed{ep};
  for (int i = 0; i < 1500; ++i) {
    ASSERT_TRUE(front->rig().step());
    front->poll(feed);
  }
  EXPECT_EQ(ep.pipeline()->state(), core::CalState::kSolving);
  // A stale ticket is ignored and counted; the right one is installed.
  SolveResult stale;
  stale.ticket = 99;
  ep.apply(solve_result_event(4, stale));
  EXPECT_EQ(ep.stale_solves(), 1u);
  SolveJob job = ep.pipeline()->take_solve_job();
  ASSERT_TRUE(job);
  EXPECT_FALSE(ep.pipeline()->take_solve_job());  // handed out once
  ep.apply(solve_result_event(5, job()));
  EXPECT_EQ(ep.pipeline()->state(), core::CalState::kValidating);
}

// The solve's whole outcome crosses the log: an unaligned candidate (scalar EKF without its
// alignment step) stays unaligned when a replay installs it, and the attitude noise the solve
// used sets the vector check's floor; a SOLVE_RESULT of an older log reads as aligned.
TEST(SolveResultEvent, CarriesAlignmentAndAttitudeNoise) {
  SolveResult r;
  r.ticket = 3;
  r.ok = true;
  r.aligned = false;
  r.attitude_noise_deg = 0.0375f;
  r.mag_noise_nT = 2.71828f;
  r.model.o = core::Vec3<double>(1.5, -2.0, 3.25);
  const SolveResult back = solve_result_from(solve_result_event(9, r));
  EXPECT_EQ(back.ticket, 3u);
  EXPECT_TRUE(back.ok);
  EXPECT_FALSE(back.aligned);
  EXPECT_EQ(back.attitude_noise_deg, 0.0375f);
  EXPECT_EQ(back.mag_noise_nT, 2.71828f);
  EXPECT_EQ(back.model.o, r.model.o);

  SolveResult refused;
  refused.code = 7;
  const SolveResult refused_back = solve_result_from(solve_result_event(10, refused));
  EXPECT_FALSE(refused_back.ok);
  EXPECT_EQ(refused_back.code, 7);
  EXPECT_TRUE(refused_back.aligned);
  EXPECT_TRUE(std::isnan(refused_back.attitude_noise_deg));

  magvec_lcm::pipeline_event old = solve_result_event(11, r);
  old.config_toml.clear();  // written before the keys existed
  const SolveResult old_back = solve_result_from(old);
  EXPECT_TRUE(old_back.aligned);
  EXPECT_TRUE(std::isnan(old_back.attitude_noise_deg));
  EXPECT_TRUE(std::isnan(old_back.mag_noise_nT));

  // A corrupt or hand-edited log never installs a negative, zero or non-numeric figure.
  magvec_lcm::pipeline_event bad = solve_result_event(12, r);
  bad.config_toml = "aligned = true\nattitude_noise_deg = -1\nmag_noise_nT = x\n";
  const SolveResult bad_back = solve_result_from(bad);
  EXPECT_TRUE(std::isnan(bad_back.attitude_noise_deg));
  EXPECT_TRUE(std::isnan(bad_back.mag_noise_nT));
}

// SET_ACTIVE carries the installed calibration's alignment and 1-sigmas bit for bit (a replayed
// or reloaded calibration gives the records the live one gave); old logs: aligned, not known.
TEST(SetActiveEvent, CarriesTheOutputQuality) {
  const OutputQuality q{false, 0.1 + 0.2, 1.0 / 3.0};
  const OutputQuality back =
      output_quality_from(set_active_event(1, core::SensorModel<double>{}, 4, 0.01, q));
  EXPECT_FALSE(back.aligned);
  EXPECT_EQ(back.sigma_f_nT, q.sigma_f_nT);
  EXPECT_EQ(back.sigma_enu_nT, q.sigma_enu_nT);
  magvec_lcm::pipeline_event old = set_active_event(2, core::SensorModel<double>{}, 4);
  old.config_toml.clear();
  const OutputQuality old_back = output_quality_from(old);
  EXPECT_TRUE(old_back.aligned);
  EXPECT_TRUE(std::isnan(old_back.sigma_f_nT));
  EXPECT_TRUE(std::isnan(old_back.sigma_enu_nT));
  old.config_toml = "sigma_f_nT = inf\nsigma_enu_nT = -3\n";
  EXPECT_TRUE(std::isnan(output_quality_from(old).sigma_f_nT));
  EXPECT_TRUE(std::isnan(output_quality_from(old).sigma_enu_nT));
}

}  // namespace
}  // namespace magvec::host::daemon
