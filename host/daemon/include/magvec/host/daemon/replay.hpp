// Deterministic replay of a magvecd LCM log: the raw channels (per-sample and batched raw
// magnetometer messages alike, lcm.raw_batch) and the pipeline
// events are read in log order (lcm::LogFile) and fed to the same EventPipeline the daemon used,
// as fast as possible. The records go to `sink`; the live outputs recorded in the log (output
// channel) can be written to `logged_sink` and are compared bit for bit with the replayed ones.
// Channel names come from the SESSION_START configuration in the log (the pipeline channel itself
// is given, default MAGVEC_PIPELINE).
#pragma once

#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>

#include "magvec/hal/record_sink.hpp"
#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

class ReplayError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct ReplayResult {
  std::uint64_t log_events{0};
  std::uint64_t sessions{0};
  std::uint64_t mag_samples{0};  // raw magnetometer samples, single or in batches
  std::uint64_t mag_batches{0};  // mag_sample_batch messages
  std::uint64_t attitude_samples{0};
  std::uint64_t pipeline_events{0};
  std::uint64_t records{0};         // replayed records
  std::uint64_t logged_records{0};  // live records found in the log
  std::uint64_t compared{0};        // pairs compared (in order)
  std::uint64_t mismatches{0};      // pairs that differ in any bit
  std::uint64_t uncompared{0};      // replayed records without a logged counterpart
  std::uint64_t decode_errors{0};
  std::uint64_t skipped_before_session{0};
  bool have_status{false};
  CalibrationStatus final_status{};
};

// Throws ReplayError if the log cannot be opened or holds no session start. A finite
// time_offset_override_s replaces the magnetometer<->INS time offset of every session (the
// configured and the installed calibrations' alike): the replayed records then answer "what if
// the offset had been this", and differ from the live ones.
ReplayResult replay_log(const std::string& path, hal::RecordSink& sink,
                        hal::RecordSink* logged_sink = nullptr,
                        const std::string& pipeline_channel = "MAGVEC_PIPELINE",
                        double time_offset_override_s = std::numeric_limits<double>::quiet_NaN());

}  // namespace magvec::host::daemon
