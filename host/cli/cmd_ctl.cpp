// `magvec ctl start|accept|revert|status [--lcm-url URL] [--command-url URL]`: sends a command to
// magvecd over LCM and prints its reply (magvec_lcm.command / command_reply). Exit 0 when the
// daemon accepted the command, 3 when it refused it, 4 when no reply came within --timeout.
// Commands and replies travel on the daemon's command URL (lcm.command_url; by default its data
// URL's udpm port + 1), so ctl does not receive the daemon's data traffic.
// `magvec ctl watch [--url URL] [--once] [--timeout S]`: listens to the calibration state (and
// health) on the daemon's data URL and redraws a compact view (watch_view.hpp) on every change;
// exit 0 on Ctrl-C (or after one frame with --once), 4 when no state came within --timeout.
#include <CLI/CLI.hpp>
#include <chrono>
#include <csignal>
#include <iomanip>
#include <iostream>
#include <lcm/lcm-cpp.hpp>
#include <magvec_lcm/calibration_state.hpp>
#include <magvec_lcm/command.hpp>
#include <magvec_lcm/command_reply.hpp>
#include <magvec_lcm/health.hpp>
#include <memory>
#include <optional>
#include <random>
#include <string>

#include "commands.hpp"
#include "magvec/host/daemon/config.hpp"
#include "watch_view.hpp"

namespace magvec::host::cli {
namespace {

struct CtlOptions {
  std::string command;
  std::string url = "udpm://239.255.76.67:7667?ttl=0";
  std::string command_url;  // empty: derived from url as the daemon does
  std::string command_channel = "MAGVEC_CMD";
  std::string reply_channel = "MAGVEC_CMD_REPLY";
  double timeout_s = 2.0;
  bool once = false;  // watch: one frame, then exit
  std::string state_channel = "MAGVEC_CAL_STATE";
  std::string health_channel = "MAGVEC_HEALTH";
};

struct ReplyWaiter {
  std::int64_t id{0};
  bool got{false};
  magvec_lcm::command_reply reply;
  void on_reply(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::command_reply* r) {
    if (r->request_id != id) return;
    reply = *r;
    got = true;
  }
};

volatile std::sig_atomic_t g_watch_stop = 0;
extern "C" void on_watch_signal(int) {
  g_watch_stop = 1;
}

struct StateWatcher {
  std::optional<magvec_lcm::calibration_state> state;
  std::optional<magvec_lcm::health> health;
  bool changed{false};
  void on_state(const lcm::ReceiveBuffer*, const std::string&,
                const magvec_lcm::calibration_state* s) {
    state = *s;
    changed = true;
  }
  void on_health(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::health* h) {
    health = *h;
  }
};

void watch(const CtlOptions& o) {
  lcm::LCM l(o.url);
  if (!l.good()) throw CommandExit(5, "LCM provider " + o.url + " is not available");
  StateWatcher w;
  l.subscribe(o.state_channel, &StateWatcher::on_state, &w);
  l.subscribe(o.health_channel, &StateWatcher::on_health, &w);
  g_watch_stop = 0;
  std::signal(SIGINT, on_watch_signal);
  std::signal(SIGTERM, on_watch_signal);
  using Clock = std::chrono::steady_clock;
  const auto start = Clock::now();
  auto last_state = start;
  auto last_draw = start - std::chrono::hours(1);
  // Redraws follow the state messages (magvecd sends at most 5 per second while collecting);
  // a quiet daemon still gets a redraw a second, to show how stale the view is.
  while (g_watch_stop == 0) {
    l.handleTimeout(100);
    const auto now = Clock::now();
    if (!w.state) {
      if (now - start > std::chrono::duration<double>(o.timeout_s))
        throw CommandExit(4, "no calibration state from magvecd on " + o.url + " (channel " +
                                 o.state_channel + ") within " + std::to_string(o.timeout_s) +
                                 " s: is magvecd running with lcm.url = " + o.url + "?");
      continue;
    }
    if (w.changed) last_state = now;
    if (!w.changed && now - last_draw < std::chrono::seconds(1)) continue;
    w.changed = false;
    last_draw = now;
    WatchContext ctx;
    ctx.url = o.url;
    ctx.age_s = std::chrono::duration<double>(now - last_state).count();
    ctx.health = w.health ? &*w.health : nullptr;
    const std::string frame = render_watch(*w.state, ctx);
    if (o.once) {
      std::cout << frame << std::flush;
      return;
    }
    std::cout << "\x1b[H\x1b[2J" << frame << std::flush;  // home + clear: any ANSI terminal
  }
  std::cout << "\n";
}

void run(const CtlOptions& o) {
  if (o.command == "watch") {
    watch(o);
    return;
  }
  if (o.once) throw CommandExit(2, "--once: only for ctl watch");
  const std::string url = o.command_url.empty() ? daemon::command_url_for(o.url) : o.command_url;
  lcm::LCM l(url);
  if (!l.good()) throw CommandExit(5, "LCM provider " + url + " is not available");
  ReplyWaiter w;
  std::random_device rd;
  w.id =
      static_cast<std::int64_t>((static_cast<std::uint64_t>(rd()) << 31) ^ rd()) & 0x7FFFFFFFFFFF;
  lcm::Subscription* sub = l.subscribe(o.reply_channel, &ReplyWaiter::on_reply, &w);
  (void)sub;
  magvec_lcm::command c;
  c.request_id = w.id;
  c.command = o.command;
  using Clock = std::chrono::steady_clock;
  const auto deadline = Clock::now() + std::chrono::duration<double>(o.timeout_s);
  // One send; `status` (idempotent) is re-sent every 250 ms until answered, as a udpm datagram
  // can be lost. The other commands are sent once so the daemon never executes them twice.
  auto next_send = Clock::now();
  bool sent = false;
  while (!w.got && Clock::now() < deadline) {
    if (!sent || (o.command == "status" && Clock::now() >= next_send)) {
      if (l.publish(o.command_channel, &c) != 0)
        throw CommandExit(5, "publishing on " + o.command_channel + " failed");
      sent = true;
      next_send = Clock::now() + std::chrono::milliseconds(250);
    }
    l.handleTimeout(50);
  }
  if (!w.got)
    throw CommandExit(4, "no reply from magvecd on " + o.reply_channel + " within " +
                             std::to_string(o.timeout_s) + " s (is it running with commands on " +
                             url + "?)");
  const auto& r = w.reply;
  const auto& s = r.state;
  std::cout << (r.ok ? "ok: " : "refused: ") << r.message << "\n";
  std::cout << "calibration: " << s.calibrator << ", state " << s.state << ", progress "
            << std::setprecision(3) << s.progress << ", cal_id " << s.cal_id
            << ", persisted cal_id " << s.persisted_cal_id;
  if (s.state == "failed") std::cout << ", failure " << s.failure << " " << s.solver_reason;
  std::cout << ", validation rms " << s.validation_rms_nT << " nT\n";
  if (!s.hint.empty()) std::cout << "hint: " << s.hint << "\n";
  if (!r.ok) throw CommandExit(3, "");
}

}  // namespace

void register_ctl(CLI::App& app) {
  auto opt = std::make_shared<CtlOptions>();
  CLI::App* sub = app.add_subcommand("ctl", "Send a command to magvecd over LCM");
  sub->add_option("command", opt->command, "start | accept | revert | status | watch")
      ->required()
      ->check(CLI::IsMember({"start", "accept", "revert", "status", "watch"}));
  sub->add_option("--lcm-url,--url", opt->url, "LCM URL of the daemon (lcm.url)")
      ->capture_default_str();
  sub->add_option("--command-url", opt->command_url,
                  "The daemon's lcm.command_url (default: --lcm-url with the udpm port + 1)");
  sub->add_option("--command-channel", opt->command_channel)->capture_default_str();
  sub->add_option("--reply-channel", opt->reply_channel)->capture_default_str();
  sub->add_flag("--once", opt->once, "watch: print one frame and exit");
  sub->add_option("--state-channel", opt->state_channel)->capture_default_str();
  sub->add_option("--health-channel", opt->health_channel)->capture_default_str();
  sub->add_option("--timeout", opt->timeout_s,
                  "Seconds to wait for the reply (watch: for the first calibration state)")
      ->check(CLI::Range(0.05, 60.0))
      ->capture_default_str();
  sub->callback([opt] { run(*opt); });
}

}  // namespace magvec::host::cli
