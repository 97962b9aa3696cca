// EventPipeline: applies the LCM messages of a magvecd session to a Pipeline, in order. Both the
// live daemon (which publishes each message and then applies that same message) and `magvec
// replay` (which reads them back from a log) go through here, so they run the same code on the
// same values:
//   pipeline_event SESSION_START  -> Pipeline::create(parse_config(config_toml))
//   pipeline_event SET_ACTIVE     -> set_active(model, cal_id), set_time_offset_s
//   (a SESSION_START first flushes the previous pipeline: its pending samples get their records;
//   flush() does the same at the end of a stream: daemon stop, end of a replayed log)
//   pipeline_event START_CALIBRATION -> start_calibration()
//   pipeline_event SOLVE_ON_WORKER   -> set_external_solve(true): the session's solves come as
//   pipeline_event SOLVE_RESULT      -> install_solve (where it is in the event order)
//   mag_sample / attitude         -> on_magnetometer / on_attitude
//   mag_sample_batch              -> on_magnetometer for each of its samples, oldest first
// Samples before the first SESSION_START have no pipeline: they are counted and skipped.
#pragma once

#include <cstdint>
#include <memory>

#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

class EventPipeline {
 public:
  explicit EventPipeline(hal::RecordSink& sink) : sink_(sink) {}

  // Throws ConfigError when a SESSION_START carries an invalid configuration (the previous
  // pipeline is kept).
  void apply(const magvec_lcm::pipeline_event& e);
  void apply(const magvec_lcm::mag_sample& m) noexcept;
  // A batch whose count disagrees with its samples (never so when decoded) is skipped whole and
  // counted (malformed_batches).
  void apply(const magvec_lcm::mag_sample_batch& b) noexcept;
  void apply(const magvec_lcm::attitude& a) noexcept;
  void flush() noexcept;

  Pipeline* pipeline() noexcept { return pipeline_.get(); }
  const Config& config() const noexcept { return config_; }
  bool has_session() const noexcept { return pipeline_ != nullptr; }
  std::uint64_t sessions() const noexcept { return sessions_; }
  std::uint64_t skipped_before_session() const noexcept { return skipped_; }
  std::uint64_t unknown_events() const noexcept { return unknown_events_; }
  std::uint64_t stale_solves() const noexcept { return stale_solves_; }
  std::uint64_t malformed_batches() const noexcept { return malformed_batches_; }

 private:
  hal::RecordSink& sink_;
  std::unique_ptr<Pipeline> pipeline_;
  Config config_{};
  std::uint64_t sessions_{0};
  std::uint64_t skipped_{0};
  std::uint64_t unknown_events_{0};
  std::uint64_t stale_solves_{0};
  std::uint64_t malformed_batches_{0};
};

}  // namespace magvec::host::daemon
