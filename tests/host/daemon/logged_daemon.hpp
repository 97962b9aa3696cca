// Test support for the daemon tests: a record sink that keeps every record, the embedded
// configuration made fast (fewer samples per attitude and for the calibration), and a daemon
// stand-in that feeds simulated device events into an EventPipeline through the LCM messages, as
// magvecd does, optionally writing them into an LCM log in publish order.
#pragma once

#include <gtest/gtest.h>

#include <cstddef>
#include <cstdint>
#include <lcm/lcm-cpp.hpp>
#include <string>
#include <vector>

#include "magvec/hal/record_sink.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"

namespace magvec::host::daemon::test {

struct VectorSink final : hal::RecordSink {
  std::vector<hal::OutputRecord> records;
  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    records.push_back(r);
    return hal::Status::kOk;
  }
};

inline std::string fast_config_text(const std::string& mode = "li", double mag_rate_hz = 100) {
  std::string text = default_config_text();
  auto patch = [&text](const std::string& from, const std::string& to) {
    text.replace(text.find(from), from.size(), to);
  };
  // The first rate_hz is the magnetometer's (the INS stays at 100 Hz).
  patch("rate_hz = 100.0", "rate_hz = " + std::to_string(mag_rate_hz));
  patch("samples_per_attitude = 10", "samples_per_attitude = 1");
  patch("li_min_samples = 300", "li_min_samples = 100");
  patch("validation_samples = 200", "validation_samples = 100");
  patch("mode = \"li\"", "mode = \"" + mode + "\"");
  return text;
}

inline Config fast_config(const std::string& mode, double mag_rate_hz = 100) {
  return parse_config(fast_config_text(mode, mag_rate_hz), "test");
}

// Drives SimFrontEnd events into an EventPipeline through the LCM messages (as magvecd does) and
// optionally writes them into an LCM log in publish order; a record is published when the
// pipeline emits it (on any input event: delayed fusion horizon), as magvecd's LCM sink does.
struct LoggedDaemon {
  struct LoggingSink final : hal::RecordSink {
    LoggedDaemon* d{nullptr};
    std::vector<hal::OutputRecord> records;
    hal::Status emit(const hal::OutputRecord& r) noexcept override {
      records.push_back(r);
      d->record("MAGVEC_OUTPUT", to_lcm(r));
      return hal::Status::kOk;
    }
  };
  LoggingSink sink;
  EventPipeline ep{sink};
  lcm::LogFile* log{nullptr};
  std::int64_t t{0};
  LoggedDaemon() { sink.d = this; }
  LoggedDaemon(const LoggedDaemon&) = delete;
  LoggedDaemon& operator=(const LoggedDaemon&) = delete;
  template <typename Msg>
  void record(const std::string& ch, const Msg& m) {
    if (log == nullptr) return;
    std::vector<std::uint8_t> buf(static_cast<std::size_t>(m.getEncodedSize()));
    m.encode(buf.data(), 0, static_cast<int>(buf.size()));
    lcm::LogEvent ev;
    ev.eventnum = 0;
    ev.timestamp = ++t;
    ev.channel = ch;
    ev.datalen = static_cast<std::int32_t>(buf.size());
    ev.data = buf.data();
    ASSERT_EQ(log->writeEvent(&ev), 0);
  }
  // raw_batch > 1: the samples wait in `pending` and are published as one mag_sample_batch, then
  // fed, when the batch is full or before any other input event (as magvecd with lcm.raw_batch).
  std::size_t raw_batch{1};
  magvec_lcm::mag_sample_batch pending{};
  std::size_t batches{0};
  void flush_batch() {
    if (pending.samples.empty()) return;
    pending.count = static_cast<std::int32_t>(pending.samples.size());
    record("MAGVEC_RAW_MAG_BATCH", pending);
    ep.apply(pending);
    pending.samples.clear();
    ++batches;
  }
  void event(const magvec_lcm::pipeline_event& e) {
    flush_batch();
    record("MAGVEC_PIPELINE", e);
    ep.apply(e);
  }
  void on_attitude(const hal::AttitudeSample& a) {
    flush_batch();
    const auto m = to_lcm(a);
    record("MAGVEC_ATTITUDE", m);
    ep.apply(m);
  }
  void on_magnetometer(const hal::MagnetometerSample& s, double f) {
    const auto m = to_lcm(s, f);
    if (raw_batch > 1) {
      pending.samples.push_back(m);
      if (pending.samples.size() >= raw_batch) flush_batch();
      return;
    }
    record("MAGVEC_RAW_MAG", m);
    ep.apply(m);
  }
  void on_read_error(hal::Status) {
    flush_batch();
    ep.pipeline()->on_read_error();
  }
  void stop() {
    flush_batch();
    ep.flush();
  }
};

}  // namespace magvec::host::daemon::test
