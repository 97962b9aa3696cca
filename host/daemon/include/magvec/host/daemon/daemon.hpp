// magvecd's wiring: configuration -> devices -> raw events published on LCM, then applied to the
// EventPipeline (AttitudeBuffer + SensorLoop) -> records on LCM; commands on the command URL;
// the calibrator's solve on a SolveWorker; the accepted calibration in the CalibrationStore
// (written on a PersistWorker);
// sessions (SIGHUP reloads); systemd notifications. main() parses the arguments and runs this.
#pragma once

#include <csignal>
#include <cstdint>
#include <memory>
#include <string>
#include <vector>

#include "magvec/host/daemon/background_worker.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/devices.hpp"
#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/lcm_link.hpp"
#include "magvec/host/daemon/persistence.hpp"

namespace magvec::host::daemon {

struct DaemonOptions {
  std::string config_path;  // empty: the embedded default
  bool sim{false};
  std::string state_dir;  // overrides daemon.state_dir
  std::string lcm_url;    // overrides lcm.url
  bool check_config{false};
};

// Set by the signal handlers: SIGTERM/SIGINT stop, SIGHUP reloads.
struct DaemonSignals {
  volatile std::sig_atomic_t* stop{nullptr};
  volatile std::sig_atomic_t* reload{nullptr};
};

class Daemon final : public EventHandler {
 public:
  Daemon(DaemonOptions o, DaemonSignals signals);
  ~Daemon();
  // Runs until stopped; the exit code. Throws DaemonError for the failures with their own code.
  int run();

  void on_attitude(const hal::AttitudeSample& a) override;
  void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) override;
  void on_read_error(hal::Status s) override;
  void on_model_reference(const std::string& model, double sigma_nT) override;

 private:
  Config load_config();
  void open_session(const Config& config, bool first);
  void loop_session();
  void serve(std::uint32_t us);
  void event(const magvec_lcm::pipeline_event& e);
  // Feeds one raw sample (publish, then apply); with lcm.raw_batch > 1 the sample joins the
  // pending batch, which flush_raw_batch() publishes and then feeds.
  void feed_magnetometer(const magvec_lcm::mag_sample& m);
  void flush_raw_batch();
  void note_processing_us(std::uint64_t dt_us) noexcept;
  void hand_over_solve();
  void install_solve_results();
  void check_auto_accept();
  // Writes the calibration on this thread (the end of the daemon).
  bool persist(const CalibrationStatus& st, const char* why);
  // Writes it on the PersistWorker (auto-accept, the accept command: the acquisition goes on
  // meanwhile); the store learns of it, and the accept commands waiting for it get their reply,
  // in install_persist_results().
  void persist_in_background(const CalibrationStatus& st, const char* why);
  void install_persist_results();
  void shutdown_persist();
  void publish_status();
  void publish_status(const CalibrationStatus& st);
  // While collecting: the state again when its progress, cells or hint changed (at most every
  // kGuidancePeriodUs), so that an operator's display follows the manoeuvre.
  void publish_guidance_changes();
  void publish_health();
  void on_command(const magvec_lcm::command& cmd);
  bool stopping() const noexcept;

  DaemonOptions opt_;
  DaemonSignals signals_;
  std::string config_text_;
  Config config_{};
  std::unique_ptr<LcmPublisher> publisher_;
  std::unique_ptr<CommandLink> commands_;
  std::unique_ptr<EventPipeline> ep_;
  std::unique_ptr<Devices> devices_;
  std::unique_ptr<CalibrationStore> store_;
  std::unique_ptr<SolveWorker> worker_;
  std::unique_ptr<PersistWorker> persist_worker_;
  // accept commands whose reply waits for the end of the write they started (their success reply
  // prepared, and the calibration they asked for).
  struct PendingAccept {
    magvec_lcm::command_reply reply;
    std::uint32_t cal_id{0};
  };
  std::vector<PendingAccept> pending_accepts_;
  // Forwards the records to the publisher of the current session (the EventPipeline outlives it).
  struct Sink final : hal::RecordSink {
    LcmPublisher* publisher{nullptr};
    hal::Status emit(const hal::OutputRecord& r) noexcept override {
      return publisher != nullptr ? publisher->emit(r) : hal::Status::kNotReady;
    }
  } sink_;
  // Raw samples read but not yet published nor fed (lcm.raw_batch > 1), oldest first. Every
  // other input event, and the end of a session, flushes them first, so that the log holds the
  // feed order; a batch is also flushed once its first sample has waited kMaxRawBatchHoldUs.
  magvec_lcm::mag_sample_batch raw_batch_{};
  std::uint64_t raw_batch_first_us_{0};
  static constexpr std::uint64_t kMaxRawBatchHoldUs = 50'000;
  std::int64_t sequence_{0};
  std::uint64_t session_{0};  // tags the solves: a result of an earlier session is dropped
  std::uint64_t applied_seen_{0};
  std::uint64_t last_t_us_{0};
  std::uint64_t mag_events_{0};
  std::uint64_t read_errors_{0};
  std::uint64_t error_streak_start_us_{0};  // first error since the last good sample (0: none)
  static constexpr std::uint64_t kMaxErrorStreakUs = 10'000'000;
  std::uint64_t next_command_poll_us_{0};
  std::uint64_t start_us_{0};
  std::string last_state_;
  core::CalState last_state_enum_{core::CalState::kIdle};
  std::int32_t last_cal_id_{-1};
  std::string last_guidance_;  // progress (percent), cells and hint last published
  std::uint64_t next_guidance_us_{0};
  static constexpr std::uint64_t kGuidancePeriodUs = 200'000;
  // Processing time of a raw message (publish + pipeline: one sample, or with lcm.raw_batch > 1
  // one batch), worst while a solve ran and otherwise.
  bool solve_in_flight_{false};
  std::uint64_t samples_during_solve_{0};
  std::uint64_t worst_sample_us_during_solve_{0};
  std::uint64_t worst_sample_us_{0};
};

}  // namespace magvec::host::daemon
