// magvecd's wiring; see daemon.hpp.
#include "magvec/host/daemon/daemon.hpp"

#include <pthread.h>
#include <sched.h>
#include <sys/mman.h>
#include <systemd/sd-daemon.h>

#include <spdlog/spdlog.h>

#include <cerrno>
#include <cstdio>
#include <cstring>
#include <filesystem>
#include <optional>
#include <utility>

#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/host/daemon/commands.hpp"
#include "magvec/host/daemon/daemon_error.hpp"
#include "magvec/host/daemon/session.hpp"
#include "magvec/version.hpp"

namespace magvec::host::daemon {
namespace {

std::uint64_t mono_us() {
  return drivers::monotonic_us();
}

// Stack of every thread created after this (the solve and persist workers, LCM's receive thread of
// the command link): mlockall(MCL_FUTURE) faults in and locks each whole stack, and glibc's default
// of 8 MiB each was 16 of the daemon's 30 MB peak RSS (and the page faults part of its start-up
// CPU). Measured without mlockall: a li solve that produced a candidate touched 40 KiB of its
// thread's stack, the LCM thread 12 KiB; 1 MiB leaves a wide margin.
constexpr std::size_t kThreadStackBytes = std::size_t{1} << 20;

void set_thread_stack_size() {
  pthread_attr_t a;
  if (pthread_attr_init(&a) != 0) return;
  if (pthread_attr_setstacksize(&a, kThreadStackBytes) != 0 || pthread_setattr_default_np(&a) != 0)
    spdlog::warn("thread stack size {} KiB not set: threads get the default",
                 kThreadStackBytes / 1024);
  pthread_attr_destroy(&a);
}

// Real-time hints: lock memory and run SCHED_FIFO when permitted; warnings otherwise.
void realtime_hints(const Config& c) {
  if (!c.daemon.realtime) return;
  if (mlockall(MCL_CURRENT | MCL_FUTURE) != 0) {
    spdlog::warn("mlockall failed ({}): running without locked memory", std::strerror(errno));
  } else {
    spdlog::info("memory locked (mlockall)");
  }
  sched_param sp{};
  sp.sched_priority = c.daemon.rt_priority;
  if (sched_setscheduler(0, SCHED_FIFO, &sp) != 0) {
    spdlog::warn("SCHED_FIFO priority {} not permitted ({}): running with the default scheduler",
                 c.daemon.rt_priority, std::strerror(errno));
  } else {
    spdlog::info("SCHED_FIFO priority {}", c.daemon.rt_priority);
  }
}

void set_log_level(const Config& c) {
  spdlog::set_level(spdlog::level::from_str(c.daemon.log_level));
}

void prepare_state_dir(const Config& c) {
  std::error_code ec;
  std::filesystem::create_directories(c.daemon.state_dir, ec);
  if (ec || !std::filesystem::is_directory(c.daemon.state_dir))
    throw DaemonError(kExitConfig, "state directory " + c.daemon.state_dir +
                                       " cannot be created: " + ec.message());
}

// Commands are looked at this often while the devices keep the loop busy (real mode reads one
// sample per poll without waiting on the command socket).
constexpr std::uint64_t kCommandPollUs = 10'000;

// What an operator's display shows of the guidance: a change of it is worth a message.
std::string guidance_key(const CalibrationStatus& st) {
  return std::to_string(static_cast<int>(st.progress * 100)) + " " +
         std::to_string(st.guidance.cells) + " " + st.hint;
}

}  // namespace

Daemon::Daemon(DaemonOptions o, DaemonSignals signals)
    : opt_(std::move(o)), signals_(signals), ep_(std::make_unique<EventPipeline>(sink_)) {}

Daemon::~Daemon() = default;

bool Daemon::stopping() const noexcept {
  return *signals_.stop != 0 || *signals_.reload != 0;
}

Config Daemon::load_config() {
  const std::string text =
      opt_.config_path.empty() ? default_config_text() : read_config_text(opt_.config_path);
  Config c = parse_config(text, opt_.config_path.empty() ? "<embedded default>" : opt_.config_path);
  // The logged session configuration is the file's text. The command-line overrides (state
  // directory, LCM URL) do not reach the pipeline, so a replay of the log is unaffected by them.
  config_text_ = text;
  if (!opt_.state_dir.empty()) c.daemon.state_dir = opt_.state_dir;
  if (!opt_.lcm_url.empty()) c.lcm.url = opt_.lcm_url;
  return c;
}

int Daemon::run() {
  Config config;
  try {
    config = load_config();
  } catch (const ConfigError& e) {
    throw DaemonError(kExitConfig, std::string("configuration error: ") + e.what());
  }
  if (opt_.check_config) {
    std::printf("configuration OK\n");
    return kExitOk;
  }
  set_log_level(config);
  spdlog::info("magvecd {} starting ({} mode, config {})", kVersion, opt_.sim ? "sim" : "real",
               opt_.config_path.empty() ? "embedded default" : opt_.config_path);
  prepare_state_dir(config);
  store_ = std::make_unique<CalibrationStore>(config.daemon.state_dir);
  store_->load();
  set_thread_stack_size();  // before the first thread (worker, LCM) is created
  worker_ = std::make_unique<SolveWorker>();
  persist_worker_ = std::make_unique<PersistWorker>();
  realtime_hints(config);
  start_us_ = mono_us();
  open_session(config, true);
  while (true) {
    loop_session();  // until SIGTERM/SIGINT or SIGHUP
    if (*signals_.stop != 0) break;
    *signals_.reload = 0;
    sd_notify(0, "RELOADING=1");
    try {
      Config next = load_config();
      if (next.daemon.state_dir != config.daemon.state_dir) {
        spdlog::warn("state_dir changes need a restart; keeping {}", config.daemon.state_dir);
        next.daemon.state_dir = config.daemon.state_dir;
      }
      config = next;
      set_log_level(config);
      spdlog::info("configuration reloaded: starting a new session");
      open_session(config, false);
    } catch (const ConfigError& e) {
      // The running session goes on untouched (no new session, no device re-open).
      spdlog::error("reload refused, keeping the running configuration: {}", e.what());
      sd_notify(0, "READY=1\nSTATUS=reload refused: invalid configuration");
    }
  }
  devices_->flush(*this);
  flush_raw_batch();
  spdlog::info("stopping ({} samples)", mag_events_);
  ep_->flush();                  // the samples still inside the fusion horizon get their records
  persist_worker_->wait_idle();  // a write in progress ends (and is recorded) first
  install_persist_results();
  shutdown_persist();
  publish_status();
  publish_health();
  sd_notify(0, "STOPPING=1");
  return kExitOk;
}

// ------------------------------------------------------------------ events

void Daemon::on_attitude(const hal::AttitudeSample& a) {
  flush_raw_batch();  // the samples read before it are fed before it, as without batching
  const magvec_lcm::attitude m = to_lcm(a);
  publisher_->publish(config_.lcm.channels.attitude, m);
  ep_->apply(m);
}

void Daemon::on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) {
  feed_magnetometer(to_lcm(s, f_ref_nT));
  error_streak_start_us_ = 0;
}

void Daemon::feed_magnetometer(const magvec_lcm::mag_sample& m) {
  if (config_.lcm.raw_batch <= 1) {
    // Publish first, then feed the very message that was published.
    const std::uint64_t t0 = mono_us();
    publisher_->publish(config_.lcm.channels.raw_mag, m);
    ep_->apply(m);
    note_processing_us(mono_us() - t0);
    last_t_us_ = static_cast<std::uint64_t>(m.t_us);
    ++mag_events_;
    return;
  }
  if (raw_batch_.samples.empty()) raw_batch_first_us_ = mono_us();
  raw_batch_.samples.push_back(m);
  if (raw_batch_.samples.size() >= config_.lcm.raw_batch) flush_raw_batch();
}

void Daemon::flush_raw_batch() {
  if (raw_batch_.samples.empty()) return;
  // Publish the batch, then feed the very samples it carries, in order.
  const std::uint64_t t0 = mono_us();
  raw_batch_.count = static_cast<std::int32_t>(raw_batch_.samples.size());
  publisher_->publish(config_.lcm.channels.raw_mag_batch, raw_batch_);
  for (const magvec_lcm::mag_sample& m : raw_batch_.samples)
    ep_->apply(m);
  note_processing_us(mono_us() - t0);
  last_t_us_ = static_cast<std::uint64_t>(raw_batch_.samples.back().t_us);
  mag_events_ += raw_batch_.samples.size();
  raw_batch_.samples.clear();  // keeps the capacity: no allocation per batch
  raw_batch_.count = 0;
}

void Daemon::note_processing_us(std::uint64_t dt_us) noexcept {
  if (solve_in_flight_) {
    ++samples_during_solve_;
    if (dt_us > worst_sample_us_during_solve_) worst_sample_us_during_solve_ = dt_us;
  } else if (dt_us > worst_sample_us_) {
    worst_sample_us_ = dt_us;
  }
}

void Daemon::on_read_error(hal::Status s) {
  flush_raw_batch();
  if (ep_->pipeline() != nullptr) ep_->pipeline()->on_read_error();
  if (++read_errors_ <= 5) spdlog::warn("magnetometer read error: {}", hal::to_string(s));
  // A device that only fails (unplugged, powered off) is not healed by pinging the watchdog:
  // exit with the device code so that systemd restarts the service and the journal says why.
  const std::uint64_t now = mono_us();
  if (error_streak_start_us_ == 0) error_streak_start_us_ = now;
  if (now - error_streak_start_us_ > kMaxErrorStreakUs)
    throw DaemonError(kExitDevice, "magnetometer: only read errors for " +
                                       std::to_string(kMaxErrorStreakUs / 1'000'000) +
                                       " s (last: " + hal::to_string(s) + ", " +
                                       std::to_string(read_errors_) + " errors in all)");
}

void Daemon::on_model_reference(const std::string& model, double sigma_nT) {
  // Before the first sample that carries the model's F; a calibration in progress starts over.
  event(reference_event(++sequence_, model, sigma_nT));
}

void Daemon::event(const magvec_lcm::pipeline_event& e) {
  flush_raw_batch();
  publisher_->publish(config_.lcm.channels.pipeline, e);
  ep_->apply(e);
}

// ------------------------------------------------------------------ sessions

void Daemon::open_session(const Config& config, bool first) {
  // The previous session's pending samples go out on its publisher and channel, fed to its
  // pipeline before the new session's events.
  if (devices_) devices_->flush(*this);
  if (publisher_) flush_raw_batch();
  auto publisher = std::make_unique<LcmPublisher>(config.lcm.url, config.lcm.channels.output);
  auto commands =
      std::make_unique<CommandLink>(command_url(config.lcm), config.lcm.channels.command,
                                    [this](const magvec_lcm::command& c) { on_command(c); });
  // The old devices are released before the new ones open (same device paths on reload).
  devices_.reset();
  WaitFn wait = [this](std::uint32_t us) { serve(us); };
  devices_ = opt_.sim ? open_sim_devices(config, wait, mono_us) : open_real_devices(config, wait);
  const SessionPlan plan = plan_session(config, config_text_, store_->persisted(),
                                        first ? nullptr : ep_->pipeline(), &sequence_);
  config_ = config;
  publisher_ = std::move(publisher);
  sink_.publisher = publisher_.get();
  commands_ = std::move(commands);
  raw_batch_.samples.reserve(config.lcm.raw_batch);
  ++session_;
  solve_in_flight_ = false;
  spdlog::info("devices: {}; LCM {} (commands on {})", devices_->describe(), config.lcm.url,
               command_url(config.lcm));
  if (plan.calibration_restarted)
    spdlog::info("calibration in progress restarted after the reload");
  for (const magvec_lcm::pipeline_event& e : plan.events)
    event(e);
  applied_seen_ = ep_->pipeline()->health().calibrations_applied;
  sd_notify(0, first ? "READY=1\nSTATUS=running" : "READY=1\nSTATUS=running (reloaded)");
}

void Daemon::loop_session() {
  std::uint64_t watchdog_us = 0;
  if (sd_watchdog_enabled(0, &watchdog_us) <= 0) watchdog_us = 0;
  std::uint64_t next_watchdog = 0, next_health = 0, next_status = 0;
  const auto health_us = static_cast<std::uint64_t>(config_.daemon.health_period_s * 1e6);
  const auto status_us = static_cast<std::uint64_t>(config_.daemon.status_period_s * 1e6);

  while (!stopping()) {
    devices_->poll(*this, 20'000);
    // A device that goes quiet must not hold back the samples read before (nor their records).
    if (!raw_batch_.samples.empty() && mono_us() - raw_batch_first_us_ >= kMaxRawBatchHoldUs)
      flush_raw_batch();
    hand_over_solve();
    install_solve_results();
    check_auto_accept();
    install_persist_results();
    if (ep_->pipeline()->state() != last_state_enum_) {
      last_state_enum_ = ep_->pipeline()->state();
      publish_status();
    }
    const std::uint64_t now = mono_us();
    if (watchdog_us != 0 && now >= next_watchdog) {
      sd_notify(0, "WATCHDOG=1");
      next_watchdog = now + watchdog_us / 2;
    }
    if (now >= next_health) {
      publish_health();
      next_health = now + health_us;
    }
    if (now >= next_status) {
      publish_status();
      next_status = now + status_us;
    } else if (now >= next_guidance_us_) {
      publish_guidance_changes();
      next_guidance_us_ = now + kGuidancePeriodUs;
    }
  }
}

void Daemon::serve(std::uint32_t us) {
  if (stopping()) return;
  if (us == 0) {
    const std::uint64_t now = mono_us();
    if (now < next_command_poll_us_) return;
    next_command_poll_us_ = now + kCommandPollUs;
  }
  commands_->wait(us);
}

// ------------------------------------------------------------------ solving off the loop

void Daemon::hand_over_solve() {
  SolveJob job = ep_->pipeline()->take_solve_job();
  if (!job) return;
  if (worker_->submit(session_, std::move(job)))
    spdlog::info("a solve of an earlier calibration was dropped before it started");
  solve_in_flight_ = true;
  samples_during_solve_ = 0;
  worst_sample_us_during_solve_ = 0;
}

void Daemon::install_solve_results() {
  std::optional<SolveWorker::Done> d = worker_->take_result();
  if (!d) return;
  solve_in_flight_ = worker_->busy();
  if (d->tag != session_) return;  // the solve of an earlier session's calibration
  spdlog::info(
      "solve on the worker: {:.1f} ms ({}); meanwhile {} raw messages, worst processing of one "
      "(publish + pipeline) {} us (outside solves {} us)",
      1e-3 * static_cast<double>(d->run_us), d->result.ok ? "candidate" : "refused",
      samples_during_solve_, worst_sample_us_during_solve_, worst_sample_us_);
  // Published and applied here, in the event order, so that a replay installs it at the same
  // sample (a stale result is ignored there too).
  event(solve_result_event(++sequence_, d->result));
}

// ------------------------------------------------------------------ calibration persistence

void Daemon::check_auto_accept() {
  Pipeline* p = ep_->pipeline();
  const std::uint64_t applied = p->health().calibrations_applied;
  if (applied == applied_seen_) return;
  applied_seen_ = applied;
  const CalibrationStatus st = p->status();
  spdlog::info("calibration applied: cal_id {} (validation intensity rms {:.3f} nT)", st.cal_id,
               st.validation_rms_nT);
  publish_status();
  if (config_.calibration.auto_accept) persist_in_background(st, "auto-accept");
}

void Daemon::persist_in_background(const CalibrationStatus& st, const char* why) {
  if (st.cal_id == 0) return;
  const double offset_s = ep_->pipeline()->time_offset_s();
  PersistWorker::Job job = [path = store_->path(), st, offset_s, why = std::string(why)] {
    return CalibrationStore::write(path, st, offset_s, why);
  };
  if (persist_worker_->submit(st.cal_id, std::move(job)))
    spdlog::info("a write of an earlier calibration was superseded before it started");
}

void Daemon::install_persist_results() {
  std::optional<PersistWorker::Done> d = persist_worker_->take_result();
  if (!d) return;
  const double ms = 1e-3 * static_cast<double>(d->run_us);
  if (d->result.ok) {
    store_->mark_persisted(d->result.written);
    spdlog::info("calibration {} persisted to {} ({}) in {:.1f} ms, off the acquisition thread",
                 d->tag, store_->path(), d->result.why, ms);
    publish_status();
  } else {
    spdlog::error("persisting calibration {} failed ({:.1f} ms): {}", d->tag, ms, d->result.error);
  }
  // The accept commands waiting for this write: those of its calibration, and of older ones whose
  // write it replaced before that started (the file then holds the newer one, and the reply says
  // so). An accept of a newer calibration waits on for its own write (this one was running when
  // it came).
  std::vector<PendingAccept> later;
  for (PendingAccept& a : pending_accepts_) {
    if (a.cal_id > d->tag) {
      later.push_back(std::move(a));
      continue;
    }
    magvec_lcm::command_reply& r = a.reply;
    if (!d->result.ok) {
      r.ok = false;
      r.message = "persisting calibration " + std::to_string(d->tag) +
                  " failed: " + d->result.error + " (the previous file is intact)";
    } else if (d->tag != a.cal_id) {
      r.message = "calibration " + std::to_string(d->tag) + " (newer than " +
                  std::to_string(a.cal_id) + ") persisted to " + store_->path();
    }
    r.state = to_lcm(ep_->pipeline()->status(), last_t_us_, store_->persisted().cal_id);
    commands_->reply(config_.lcm.channels.reply, r);
    publisher_->publish(config_.lcm.channels.reply, r);  // a recording shows it, as on_command
  }
  pending_accepts_ = std::move(later);
}

bool Daemon::persist(const CalibrationStatus& st, const char* why) {
  if (st.cal_id == 0) return false;
  // One writer of the file at a time, in the order asked: a background write ends first.
  persist_worker_->wait_idle();
  install_persist_results();
  std::string error;
  const std::uint64_t t0 = mono_us();
  if (!store_->save(st, ep_->pipeline()->time_offset_s(), why, &error)) {
    spdlog::error("persisting calibration {} failed: {}", st.cal_id, error);
    return false;
  }
  spdlog::info("calibration {} persisted to {} ({}) in {:.1f} ms", st.cal_id, store_->path(), why,
               1e-3 * static_cast<double>(mono_us() - t0));
  return true;
}

void Daemon::shutdown_persist() {
  Pipeline* p = ep_->pipeline();
  if (p == nullptr) return;
  const CalibrationStatus st = p->status();
  if (st.cal_id != 0 && st.cal_id != store_->persisted().cal_id && config_.calibration.auto_accept)
    persist(st, "shutdown");
}

// ------------------------------------------------------------------ state, health, commands

void Daemon::publish_guidance_changes() {
  if (ep_->pipeline()->state() != core::CalState::kCollecting) return;
  const CalibrationStatus st = ep_->pipeline()->status();
  if (guidance_key(st) != last_guidance_) publish_status(st);
}

void Daemon::publish_status() {
  publish_status(ep_->pipeline()->status());
}

void Daemon::publish_status(const CalibrationStatus& st) {
  const magvec_lcm::calibration_state s = to_lcm(st, last_t_us_, store_->persisted().cal_id);
  publisher_->publish(config_.lcm.channels.cal_state, s);
  last_guidance_ = guidance_key(st);
  if (s.state != last_state_ || s.cal_id != last_cal_id_) {
    spdlog::info("calibration state {} (progress {:.2f}, cal_id {}{}{})", s.state, s.progress,
                 s.cal_id, s.state == "failed" ? ", failure " + s.failure + " " : "",
                 s.state == "failed" ? s.solver_reason : "");
    last_state_ = s.state;
    last_cal_id_ = s.cal_id;
  }
  const std::string text = "STATUS=" + s.state + ", cal_id " + std::to_string(s.cal_id) +
                           ", samples " + std::to_string(mag_events_);
  sd_notify(0, text.c_str());
}

void Daemon::publish_health() {
  magvec_lcm::health h{};
  auto i64 = [](std::uint64_t v) { return static_cast<std::int64_t>(v); };
  h.t_us = i64(last_t_us_);
  h.uptime_ms = i64((mono_us() - start_us_) / 1000);
  const std::optional<ScalarHealth> scalar = devices_->scalar_health();
  set_device_health(h, devices_->mag_counters(), devices_->attitude_counters(),
                    scalar ? &*scalar : nullptr);
  const hil::HilCounters& c = ep_->pipeline()->counters();
  h.mag_read_errors = i64(c.mag_read_errors);
  h.mag_not_fresh = i64(c.mag_not_fresh);
  h.mag_missing = i64(c.mag_missing);
  h.mag_time_jumps = i64(c.mag_time_jumps);
  h.att_invalid = i64(c.att_invalid);
  h.att_gaps = i64(c.att_gaps);
  h.att_time_jumps = i64(c.att_time_jumps);
  h.att_rejected = i64(c.att_rejected);
  const core::LoopHealth& lh = ep_->pipeline()->health();
  h.records = i64(c.records);
  h.dropouts = i64(lh.dropouts);
  h.device_errors = i64(lh.device_errors);
  h.no_attitude = i64(lh.no_attitude);
  h.calibrations_applied = i64(lh.calibrations_applied);
  h.calibrations_failed = i64(lh.calibrations_failed);
  h.publish_errors = i64(publisher_->errors());
  publisher_->publish(config_.lcm.channels.health, h);
}

void Daemon::on_command(const magvec_lcm::command& cmd) {
  spdlog::info("command '{}' (request {})", cmd.command, cmd.request_id);
  Pipeline* p = ep_->pipeline();
  CommandContext ctx;
  ctx.calibration_mode = config_.calibration.mode;
  ctx.status = p->status();
  ctx.persisted = store_->persisted();
  ctx.persisted_path = store_->path();
  ctx.samples = mag_events_;
  CommandActions act;
  act.start_calibration = [this] { event(start_calibration_event(++sequence_)); };
  act.persist = [this](const CalibrationStatus& st) {
    persist_in_background(st, "accept command");
  };
  act.set_active = [this](const core::SensorModel<double>& m, std::uint32_t id, double offset_s,
                          const OutputQuality& output) {
    event(set_active_event(++sequence_, m, id, offset_s, output));
  };
  const CommandOutcome out = run_command(cmd.command, ctx, act);
  magvec_lcm::command_reply r{};
  r.request_id = cmd.request_id;
  r.ok = out.ok;
  r.message = out.message;
  r.state = to_lcm(p->status(), last_t_us_, store_->persisted().cal_id);
  if (out.state_changed) publish_status();
  if (out.reply_when_persisted) {
    pending_accepts_.push_back(PendingAccept{r, ctx.status.cal_id});
    return;
  }
  commands_->reply(config_.lcm.channels.reply, r);
  // Also on the data URL, so that a recording shows what the operator did.
  publisher_->publish(config_.lcm.channels.reply, r);
}

}  // namespace magvec::host::daemon
