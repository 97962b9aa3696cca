// Test tool for the magvecd end-to-end test.
//   magvec_lcm_probe rate LOG CHANNEL...        per channel: count and rate from the log's
//                                               receive timestamps (lcm-logger's clock)
//   magvec_lcm_probe subscribe URL CHANNEL OUT.csv [IDLE_S]
//                                               subscribes CHANNEL (magvec_lcm.calibrated_vector)
//                                               on URL (e.g. file:///log?speed=0) and writes the
//                                               records as the record CSV until IDLE_S (default
//                                               1 s) pass without a message
#include <chrono>
#include <cstdio>
#include <cstdlib>
#include <lcm/lcm-cpp.hpp>
#include <map>
#include <string>

#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/hil/csv_record_sink.hpp"

namespace {

int rate(const std::string& path, int n, char** channels) {
  lcm::LogFile log(path, "r");
  if (!log.good()) {
    std::fprintf(stderr, "cannot open %s\n", path.c_str());
    return 2;
  }
  struct Stat {
    std::uint64_t count{0};
    std::int64_t first{0};
    std::int64_t last{0};
  };
  std::map<std::string, Stat> stats;
  const lcm::LogEvent* ev = nullptr;
  while ((ev = log.readNextEvent()) != nullptr) {
    Stat& s = stats[ev->channel];
    if (s.count == 0) s.first = ev->timestamp;
    s.last = ev->timestamp;
    ++s.count;
  }
  for (int i = 0; i < n; ++i) {
    const Stat s = stats[channels[i]];
    const double span = static_cast<double>(s.last - s.first) * 1e-6;
    const double hz = s.count > 1 && span > 0 ? static_cast<double>(s.count - 1) / span : 0.0;
    std::printf("%s %llu %.3f\n", channels[i], static_cast<unsigned long long>(s.count), hz);
  }
  return 0;
}

struct Writer {
  magvec::host::hil::CsvRecordSink* sink;
  std::uint64_t n{0};
  void on(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::calibrated_vector* m) {
    sink->emit(magvec::host::daemon::from_lcm(*m));
    ++n;
  }
};

int subscribe(const std::string& url, const std::string& channel, const std::string& out,
              double idle_s) {
  lcm::LCM l(url);
  if (!l.good()) {
    std::fprintf(stderr, "LCM %s not available\n", url.c_str());
    return 2;
  }
  magvec::host::hil::CsvRecordSink sink(out, {"subscriber of " + channel + " on " + url});
  Writer w{&sink};
  l.subscribe(channel, &Writer::on, &w);
  const auto idle = std::chrono::duration<double>(idle_s);
  auto last = std::chrono::steady_clock::now();
  while (std::chrono::steady_clock::now() - last < idle) {
    const int r = l.handleTimeout(100);
    if (r > 0) last = std::chrono::steady_clock::now();
    if (r < 0) break;  // file provider: end of log
  }
  sink.commit();
  std::printf("received %llu\n", static_cast<unsigned long long>(w.n));
  return 0;
}

}  // namespace

int main(int argc, char** argv) {
  const std::string mode = argc > 1 ? argv[1] : "";
  if (mode == "rate" && argc >= 4) return rate(argv[2], argc - 3, argv + 3);
  if (mode == "subscribe" && (argc == 5 || argc == 6))
    return subscribe(argv[2], argv[3], argv[4], argc == 6 ? std::atof(argv[5]) : 1.0);
  std::fprintf(stderr,
               "usage: magvec_lcm_probe rate LOG CHANNEL... | subscribe URL CHANNEL OUT.csv "
               "[IDLE_S]\n");
  return 2;
}
