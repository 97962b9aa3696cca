// magvecd log replay; see replay.hpp.
#include "magvec/host/daemon/replay.hpp"

#include <deque>
#include <lcm/lcm-cpp.hpp>

#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"

namespace magvec::host::daemon {
namespace {

// Forwards to the caller's sink and keeps the record for the comparison with the logged one.
class TeeSink final : public hal::RecordSink {
 public:
  TeeSink(hal::RecordSink& out, std::deque<hal::OutputRecord>* queue) : out_(out), queue_(queue) {}
  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    ++count_;
    if (queue_ != nullptr) {
      // The live outputs follow their inputs in the log within a few events; a log without them
      // (output channel not recorded) must not keep every replayed record in memory.
      if (queue_->size() >= kMaxPending) {
        queue_->pop_front();
        ++dropped_;
      }
      queue_->push_back(r);
    }
    return out_.emit(r);
  }
  std::uint64_t dropped() const noexcept { return dropped_; }
  std::uint64_t count() const noexcept { return count_; }

 private:
  static constexpr std::size_t kMaxPending = 1u << 16;
  hal::RecordSink& out_;
  std::deque<hal::OutputRecord>* queue_;
  std::uint64_t count_{0};
  std::uint64_t dropped_{0};
};

template <typename Msg>
bool decode(const lcm::LogEvent* ev, Msg* msg) {
  return msg->decode(ev->data, 0, static_cast<int>(ev->datalen)) >= 0;
}

}  // namespace

ReplayResult replay_log(const std::string& path, hal::RecordSink& sink,
                        hal::RecordSink* logged_sink, const std::string& pipeline_channel,
                        double time_offset_override_s) {
  lcm::LogFile log(path, "r");
  if (!log.good()) throw ReplayError(path + ": cannot open the LCM log");
  ReplayResult r;
  std::deque<hal::OutputRecord> replayed;
  std::deque<hal::OutputRecord> logged;
  TeeSink tee(sink, &replayed);
  EventPipeline ep(tee);
  auto compare = [&] {
    while (!replayed.empty() && !logged.empty()) {
      ++r.compared;
      if (!bit_identical(replayed.front(), logged.front())) ++r.mismatches;
      replayed.pop_front();
      logged.pop_front();
    }
  };
  const lcm::LogEvent* ev = nullptr;
  while ((ev = log.readNextEvent()) != nullptr) {
    ++r.log_events;
    const std::string& ch = ev->channel;
    if (ch == pipeline_channel) {
      magvec_lcm::pipeline_event e;
      if (!decode(ev, &e)) {
        ++r.decode_errors;
        continue;
      }
      ++r.pipeline_events;
      try {
        ep.apply(e);
      } catch (const ConfigError& err) {
        throw ReplayError(path + ": event " + std::to_string(r.log_events) +
                          ": invalid session configuration: " + err.what());
      }
      if (e.kind == magvec_lcm::pipeline_event::SESSION_START && ep.has_session())
        ep.pipeline()->override_time_offset_s(time_offset_override_s);
      continue;
    }
    if (!ep.has_session()) continue;  // channel names come from the session configuration
    const LcmChannels& c = ep.config().lcm.channels;
    if (ch == c.raw_mag) {
      magvec_lcm::mag_sample m;
      if (!decode(ev, &m)) {
        ++r.decode_errors;
        continue;
      }
      ++r.mag_samples;
      ep.apply(m);
    } else if (ch == c.raw_mag_batch) {
      magvec_lcm::mag_sample_batch b;
      if (!decode(ev, &b)) {
        ++r.decode_errors;
        continue;
      }
      ++r.mag_batches;
      r.mag_samples += b.samples.size();
      ep.apply(b);
    } else if (ch == c.attitude) {
      magvec_lcm::attitude a;
      if (!decode(ev, &a)) {
        ++r.decode_errors;
        continue;
      }
      ++r.attitude_samples;
      ep.apply(a);
    } else if (ch == c.output) {
      magvec_lcm::calibrated_vector v;
      if (!decode(ev, &v)) {
        ++r.decode_errors;
        continue;
      }
      ++r.logged_records;
      const hal::OutputRecord rec = from_lcm(v);
      logged.push_back(rec);
      if (logged_sink != nullptr) logged_sink->emit(rec);
    }
    compare();
  }
  ep.flush();  // as the daemon does when it stops
  compare();
  if (ep.sessions() == 0)
    throw ReplayError(path + ": no SESSION_START event on channel " + pipeline_channel +
                      " (not a magvecd log, or the recording started after the daemon)");
  r.sessions = ep.sessions();
  r.records = tee.count();
  r.uncompared = tee.dropped() + replayed.size();
  r.skipped_before_session = ep.skipped_before_session();
  if (ep.pipeline() != nullptr) {
    r.have_status = true;
    r.final_status = ep.pipeline()->status();
  }
  return r;
}

}  // namespace magvec::host::daemon
