// `magvec replay --lcm-log FILE --out FILE.csv`: runs the sensor loop deterministically over a
// magvecd LCM log: the raw magnetometer/attitude channels and the pipeline events
// (session configuration, installed calibrations, calibration starts) in log order through the
// daemon's own EventPipeline, as fast as possible. Writes the record CSV of `magvec run` (the
// `magvec apply` columns t_s, hx..hz, hsx..hsz, F, hE/hN/hU, flags, plus cal_id, sigma_F_nT and
// sigma_ENU_nT).
// The live outputs recorded in the log are compared bit for bit with the replayed ones;
// --logged-out also writes them as CSV; --check makes any difference an error (exit 3).
#include <CLI/CLI.hpp>
#include <cmath>
#include <iostream>
#include <limits>
#include <memory>
#include <optional>
#include <string>

#include "commands.hpp"
#include "magvec/host/daemon/replay.hpp"
#include "magvec/host/hil/csv_record_sink.hpp"

namespace magvec::host::cli {
namespace {

struct ReplayOptions {
  std::string log;
  std::string out;
  std::string logged_out;
  std::string pipeline_channel = "MAGVEC_PIPELINE";
  bool check = false;
  double time_offset_s = std::numeric_limits<double>::quiet_NaN();
};

void run(const ReplayOptions& o) {
  const bool overridden = std::isfinite(o.time_offset_s);
  if (overridden && o.check)
    throw CommandExit(2,
                      "--check compares with the live outputs, which used the logged time offset: "
                      "drop --check to replay with --time-offset-s, or drop --time-offset-s");
  hil::CsvRecordSink sink(o.out, {"magvec replay --lcm-log " + o.log});
  std::optional<hil::CsvRecordSink> logged;
  if (!o.logged_out.empty())
    logged.emplace(o.logged_out, std::vector<std::string>{"live outputs recorded in " + o.log});
  daemon::ReplayResult r;
  try {
    r = daemon::replay_log(o.log, sink, logged ? &*logged : nullptr, o.pipeline_channel,
                           o.time_offset_s);
  } catch (const daemon::ReplayError& e) {
    throw CommandExit(2, e.what());
  }
  sink.commit();
  if (logged) logged->commit();
  std::cout << "magvec replay: " << o.log << ": " << r.log_events << " events, " << r.sessions
            << " session(s), " << r.mag_samples << " magnetometer samples, " << r.attitude_samples
            << " attitude samples, " << r.pipeline_events << " pipeline events -> " << r.records
            << " records -> " << o.out << "\n";
  if (r.decode_errors != 0 || r.skipped_before_session != 0)
    std::cout << "  decode errors " << r.decode_errors << ", samples before the first session "
              << r.skipped_before_session << "\n";
  if (r.have_status) {
    const auto& s = r.final_status;
    std::cout << "  calibration: " << s.calibrator << ", state " << core::cal_state_name(s.state)
              << ", cal_id " << s.cal_id << ", validation rms " << s.validation_rms_nT << " nT\n";
  }
  if (overridden)
    std::cout << "  time offset overridden: " << o.time_offset_s
              << " s in every session (the live outputs used the logged one: differences are "
                 "expected)\n";
  const bool identical =
      r.logged_records == r.records && r.compared == r.records && r.mismatches == 0;
  std::cout << "  live outputs in the log: " << r.logged_records << ", compared " << r.compared
            << ", differing " << r.mismatches << ", without a live counterpart " << r.uncompared
            << " -> " << (identical ? "bit-identical" : "NOT identical") << "\n";
  if (o.check && !identical)
    throw CommandExit(3, "replayed outputs differ from the live outputs recorded in the log");
}

}  // namespace

void register_replay(CLI::App& app) {
  auto opt = std::make_shared<ReplayOptions>();
  CLI::App* sub = app.add_subcommand(
      "replay",
      "Re-run the sensor loop over a magvecd LCM log (deterministic, as fast as possible)");
  sub->add_option("--lcm-log", opt->log, "LCM log recorded from magvecd (lcm-logger)")
      ->required()
      ->check(CLI::ExistingFile);
  sub->add_option("--out", opt->out, "Record CSV of the replayed outputs")->required();
  sub->add_option("--logged-out", opt->logged_out,
                  "Also write the live outputs recorded in the log as a record CSV");
  sub->add_option("--pipeline-channel", opt->pipeline_channel, "Pipeline event channel")
      ->capture_default_str();
  sub->add_option("--time-offset-s", opt->time_offset_s,
                  "Replay with this magnetometer-INS time offset [s] instead of the logged one "
                  "(magnetometer stamp minus the INS time of its attitude)")
      ->check(CLI::Range(-10.0, 10.0));
  sub->add_flag("--check", opt->check,
                "Exit 3 unless the replayed outputs are bit-identical to the logged ones");
  sub->callback([opt] { run(*opt); });
}

}  // namespace magvec::host::cli
