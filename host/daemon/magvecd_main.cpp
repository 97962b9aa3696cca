// magvecd: the Linux daemon of the survey vehicle.
//   magvecd [--config FILE] [--sim] [--state-dir DIR] [--lcm-url URL] [--check-config]
// Devices (real: spidev ADS131M04 + libgpiod DRDY or termios serial fluxgate, SocketCAN SBG INS;
// --sim: SimRig's simulated devices through the same drivers, paced in real time) -> raw events
// -> LCM (published BEFORE they are fed to the pipeline, in feed order) -> EventPipeline
// (AttitudeBuffer + SensorLoop) -> calibrated vectors on LCM. The pipeline events (session start
// with the configuration text, installed calibrations, calibration starts, solve results) are
// published on the pipeline channel the same way, so `magvec replay` of a recording is
// bit-identical. The daemon only publishes on lcm.url; commands (`magvec ctl`: start | accept |
// revert | status) come on lcm.command_url. The calibrator's solve runs on a worker thread.
// Persistence: the accepted calibration is state_dir/cal.json (atomic write, fsync); loaded at
// start; a corrupt file is never overwritten (exit 4).
// Signals: SIGTERM/SIGINT stop (persist, exit 0), SIGHUP reloads the configuration (a new
// session; the active calibration is carried over; an invalid new configuration is refused and
// the daemon keeps running). systemd: sd_notify READY/WATCHDOG/STATUS/RELOADING/STOPPING.
// Exit codes (daemon_error.hpp): 0 ok, 1 internal error, 2 bad configuration or usage, 3 device
// error, 4 corrupt parameter (calibration) file, 5 LCM unavailable.
// The pieces live in host/daemon/src (daemon.cpp wires them); this file parses the arguments.
#include <systemd/sd-daemon.h>

#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>
#include <csignal>
#include <string>

#include "magvec/host/daemon/daemon.hpp"
#include "magvec/host/daemon/daemon_error.hpp"
#include "magvec/version.hpp"

namespace {

using namespace magvec::host::daemon;

volatile std::sig_atomic_t g_stop = 0;
volatile std::sig_atomic_t g_reload = 0;

extern "C" void on_signal(int sig) {
  if (sig == SIGHUP) {
    g_reload = 1;
  } else {
    g_stop = 1;
  }
}

void install_signal_handlers() {
  struct sigaction sa {};
  sa.sa_handler = on_signal;
  sigemptyset(&sa.sa_mask);
  sa.sa_flags = 0;  // no SA_RESTART: a blocking wait returns early and the flag is seen at once
  sigaction(SIGTERM, &sa, nullptr);
  sigaction(SIGINT, &sa, nullptr);
  sigaction(SIGHUP, &sa, nullptr);
}

}  // namespace

int main(int argc, char** argv) {
  auto logger = spdlog::stderr_logger_mt("magvecd");
  logger->set_pattern("magvecd[%l] %v");
  spdlog::set_default_logger(logger);

  CLI::App app{"magvecd: magnetic vector calibration daemon (devices -> sensor loop -> LCM)"};
  app.set_version_flag("--version", std::string("magvecd ") + magvec::kVersion);
  DaemonOptions o;
  app.add_option("--config", o.config_path, "TOML configuration (default: the embedded one)");
  app.add_flag("--sim", o.sim, "Use the simulated devices (SimRig) instead of the real ones");
  app.add_option("--state-dir", o.state_dir, "State directory (overrides daemon.state_dir)");
  app.add_option("--lcm-url", o.lcm_url, "LCM URL (overrides lcm.url)");
  app.add_flag("--check-config", o.check_config, "Validate the configuration and exit");
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    const int code = app.exit(e);
    return code == 0 ? 0 : kExitConfig;
  }
  install_signal_handlers();
  try {
    Daemon d(o, DaemonSignals{&g_stop, &g_reload});
    const int code = d.run();
    spdlog::info("exit {}", code);
    return code;
  } catch (const DaemonError& e) {
    spdlog::critical("{} (exit {})", e.what(), e.code());
    sd_notifyf(0, "STATUS=failed (exit %d): %s", e.code(), e.what());
    return e.code();
  } catch (const std::exception& e) {
    spdlog::critical("internal error: {} (exit {})", e.what(), static_cast<int>(kExitInternal));
    return kExitInternal;
  }
}
