// magvecd: the Linux daemon of the survey vehicle.
//   magvecd [--config FILE] [--sim] [--state-dir DIR] [--lcm-url URL] [--check-config]
// Devices (real: spidev ADS131M04 + libgpiod DRDY or termios serial fluxgate, SocketCAN SBG INS;
// --sim: SimRig's simulated devices through the same drivers, paced in real time) -> raw events
// -> LCM (published BEFORE they are fed to the pipeline, in feed order) -> EventPipeline
// (AttitudeBuffer + SensorLoop) -> calibrated vectors on LCM. The pipeline events (session start
// with the configuration text, installed calibrations, calibration starts) are published on the
// pipeline channel the same way, so `magvec replay` of a recording is bit-identical.
// Commands over LCM (`magvec ctl`): start | accept | revert | status.
// Persistence: the accepted calibration is state_dir/cal.json (atomic write, fsync); loaded at
// start; a corrupt file is never overwritten (exit 4).
// Signals: SIGTERM/SIGINT stop (persist, exit 0), SIGHUP reloads the configuration (a new
// session; the active calibration is carried over; an invalid new configuration is refused and
// the daemon keeps running). systemd: sd_notify READY/WATCHDOG/STATUS/RELOADING/STOPPING.
// Exit codes: 0 ok, 1 internal error, 2 bad configuration or usage, 3 device error, 4 corrupt
// parameter (calibration) file, 5 LCM unavailable.
#include <sched.h>
#include <sys/mman.h>
#include <sys/stat.h>
#include <systemd/sd-daemon.h>

#include <spdlog/sinks/stdout_sinks.h>
#include <spdlog/spdlog.h>
#include <CLI/CLI.hpp>
#include <algorithm>
#include <cerrno>
#include <csignal>
#include <cstring>
#include <filesystem>
#include <functional>
#include <lcm/lcm-cpp.hpp>
#include <limits>
#include <memory>
#include <string>

#include "calibration/calibration_file.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/linux/gpiod_data_ready_line.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/linux/socketcan_bus.hpp"
#include "magvec/drivers/linux/spidev_bus.hpp"
#include "magvec/drivers/linux/termios_serial_port.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/device_feed.hpp"
#include "magvec/host/daemon/event_pipeline.hpp"
#include "magvec/host/daemon/lcm_codec.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/hil_session.hpp"
#include "magvec/version.hpp"

namespace {

using namespace magvec;
using namespace magvec::host::daemon;

enum ExitCode : int {
  kExitOk = 0,
  kExitInternal = 1,
  kExitConfig = 2,
  kExitDevice = 3,
  kExitCorruptParams = 4,
  kExitLcm = 5,
};

class Fatal : public std::runtime_error {
 public:
  Fatal(int code, const std::string& what) : std::runtime_error(what), code_(code) {}
  int code() const noexcept { return code_; }

 private:
  int code_;
};

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

std::uint64_t mono_us() {
  return drivers::monotonic_us();
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

// ------------------------------------------------------------------ persisted calibration

struct Persisted {
  bool present{false};
  core::SensorModel<double> model{};
  std::uint32_t cal_id{0};
  double time_offset_s{0};  // cal.json time_offset_s
};

std::string cal_path(const Config& c) {
  return (std::filesystem::path(c.daemon.state_dir) / "cal.json").string();
}

Persisted load_persisted(const Config& c) {
  Persisted p;
  const std::string path = cal_path(c);
  std::error_code ec;
  if (!std::filesystem::exists(path, ec)) {
    spdlog::info("no persisted calibration ({}): starting uncalibrated", path);
    return p;
  }
  try {
    const host::CalibrationFile f = host::read_calibration_file(path);
    p.present = true;
    p.model = f.model;
    p.time_offset_s = f.time_offset_s;
    const auto it = f.quality.extra.find("cal_id");
    p.cal_id = it != f.quality.extra.end() && it->second >= 1 && it->second < 4e9
                   ? static_cast<std::uint32_t>(it->second)
                   : 1;
    spdlog::info("loaded persisted calibration {} (cal_id {}, method {}, {})", path, p.cal_id,
                 f.provenance.method, f.provenance.created_utc);
  } catch (const std::exception& e) {
    throw Fatal(kExitCorruptParams,
                std::string("corrupt calibration file: ") + e.what() +
                    " - the file is left untouched; repair or remove it (magvecd does not "
                    "overwrite it)");
  }
  return p;
}

// ------------------------------------------------------------------ devices

struct EventHandler {
  virtual void on_attitude(const hal::AttitudeSample& a) = 0;
  virtual void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) = 0;
  virtual void on_read_error(hal::Status s) = 0;

 protected:
  ~EventHandler() = default;
};

class Devices {
 public:
  virtual ~Devices() = default;
  // Produces the events due now, waiting at most max_wait_us; the waiting is done through the
  // `wait` callback (LCM handleTimeout) so commands are served meanwhile. false when the source
  // has ended (scenario over).
  virtual bool poll(EventHandler& h, std::uint32_t max_wait_us) = 0;
  virtual const hal::MagCounters& mag_counters() const = 0;
  virtual const hal::AttitudeCounters& attitude_counters() const = 0;
  virtual std::string describe() const = 0;
};

// SimRig devices read through the real drivers (hil::SimFrontEnd), paced in real time.
class SimDevices final : public Devices {
 public:
  explicit SimDevices(const Config& c)
      : sim_(sim_scenario(c), c.sim.seed),
        front_(sim_, sim_rig_config(c)),
        period_us_(1e6 / c.magnetometer.rate_hz),
        t0_us_(mono_us()) {
    if (front_.init() != hal::Status::kOk)
      throw Fatal(kExitDevice, "simulated ADC did not initialise");
  }

  bool poll(EventHandler& h, std::uint32_t max_wait_us) override {
    if (ended_) {
      wait(max_wait_us);
      return false;
    }
    const std::uint64_t due =
        t0_us_ + static_cast<std::uint64_t>(static_cast<double>(steps_) * period_us_);
    const std::uint64_t now = mono_us();
    if (now < due) {
      wait(static_cast<std::uint32_t>(std::min<std::uint64_t>(due - now, max_wait_us)));
      return true;
    }
    if (now - due > 1'000'000) {
      spdlog::warn("simulation fell {} ms behind real time: rescheduling", (now - due) / 1000);
      t0_us_ = now - static_cast<std::uint64_t>(static_cast<double>(steps_) * period_us_);
    }
    if (!front_.rig().step()) {
      spdlog::info("simulated scenario ended after {} samples", steps_);
      ended_ = true;
      return false;
    }
    ++steps_;
    Adapter a{h};
    front_.poll(a);
    return true;
  }
  const hal::MagCounters& mag_counters() const override { return front_.mag_counters(); }
  const hal::AttitudeCounters& attitude_counters() const override {
    return front_.attitude_counters();
  }
  std::string describe() const override {
    return std::string("simulated rig (scenario ") + sim_.config().name + ", " +
           std::to_string(sim_.config().rate_hz) + " Hz)";
  }
  // Set by the daemon: serves LCM while waiting.
  std::function<void(std::uint32_t)> wait;

 private:
  struct Adapter {
    EventHandler& h;
    void on_attitude(const hal::AttitudeSample& a) { h.on_attitude(a); }
    void on_magnetometer(const hal::MagnetometerSample& s, double f) { h.on_magnetometer(s, f); }
    void on_read_error(hal::Status s) { h.on_read_error(s); }
  };

  drivers::sim::Simulator sim_;
  host::hil::SimFrontEnd front_;
  double period_us_;
  std::uint64_t t0_us_;
  std::uint64_t steps_{0};
  bool ended_{false};
};

// Real devices through the Linux transports.
class RealDevices final : public Devices {
 public:
  explicit RealDevices(const Config& c) : reference_nT_(c.calibration.reference_field_nT) {
    drivers::OsError err;
    const auto& m = c.magnetometer;
    if (m.link == "spi") {
      drivers::SpidevConfig sc;
      sc.device = m.spi_device;
      sc.speed_hz = m.spi_speed_hz;
      spi_ = drivers::SpidevBus::open(sc, &err);
      if (!spi_) throw Fatal(kExitDevice, "magnetometer SPI: " + err.message);
      drivers::GpiodConfig gc;
      gc.chip = m.drdy_chip;
      gc.line = m.drdy_line;
      gc.edge = hal::Edge::kFalling;
      gc.consumer = "magvecd";
      drdy_ = drivers::GpiodDataReadyLine::open(gc, &err);
      if (!drdy_) throw Fatal(kExitDevice, "magnetometer data-ready line: " + err.message);
      ads_ = std::make_unique<drivers::Ads131Fluxgate>(*spi_, *drdy_, m.adc);
      const hal::Status s = ads_->init();
      if (s != hal::Status::kOk)
        throw Fatal(kExitDevice,
                    "ADS131M04 on " + m.spi_device + " did not initialise: " + hal::to_string(s));
      mag_ = ads_.get();
    } else {
      drivers::SerialConfig sc;
      sc.device = m.serial_device;
      sc.baud = m.serial_baud;
      sc.reconnect_interval_ms = m.serial_reconnect_ms;
      serial_ = drivers::TermiosSerialPort::open(sc, &err);
      if (!serial_) throw Fatal(kExitDevice, "magnetometer serial port: " + err.message);
      serial_mag_ = std::make_unique<drivers::SerialFluxgate<drivers::AsciiLineDecoder>>(
          *serial_, clock_, drivers::AsciiLineDecoder(drivers::AsciiLineConfig{}),
          m.serial_latency_us);
      mag_ = serial_mag_.get();
    }
    drivers::SocketCanConfig cc;
    cc.interface = c.ins.can_interface;
    for (const std::uint32_t id :
         {c.ins.ids.status_01, c.ins.ids.status_03, c.ins.ids.ekf_info, c.ins.ids.ekf_quat,
          c.ins.ids.ekf_euler, c.ins.ids.ekf_orientation_acc}) {
      drivers::CanFilterSpec f;
      f.id = id;
      f.mask = 0x7FF;
      f.extended = false;
      cc.filters.push_back(f);
    }
    cc.receive_error_frames = true;
    can_ = drivers::SocketCanBus::open(cc, &err);
    if (!can_) throw Fatal(kExitDevice, "INS CAN bus: " + err.message);
    drivers::sbg::DecoderConfig dc;
    dc.ids = c.ins.ids;
    ins_ = std::make_unique<drivers::sbg::CanAttitudeSource>(*can_, dc);
    feed_ = std::make_unique<DeviceFeed>(*mag_, *ins_, reference_nT_);
    describe_ = (m.link == "spi" ? "ADS131M04 on " + m.spi_device + " (DRDY " + m.drdy_chip +
                                       " line " + std::to_string(m.drdy_line) + ")"
                                 : "serial fluxgate on " + m.serial_device) +
                ", SBG INS on " + c.ins.can_interface;
  }

  // DeviceFeed (device_feed.hpp): every INS sample as soon as it has been received, before the
  // magnetometer sample read after it; the pipeline's fusion horizon does the time ordering. (The
  // earlier rule, an INS sample only if not later than the magnetometer sample, left every query
  // past the newest INS sample: a held attitude instead of an interpolated one.)
  bool poll(EventHandler& h, std::uint32_t max_wait_us) override {
    const FeedResult r = feed_->poll(h, max_wait_us);
    // A failing device answers at once: wait out the period (serving LCM) rather than spin.
    if (wait) wait(r == FeedResult::kError ? max_wait_us : 0);
    return true;
  }
  const hal::MagCounters& mag_counters() const override { return mag_->counters(); }
  const hal::AttitudeCounters& attitude_counters() const override { return ins_->counters(); }
  std::string describe() const override { return describe_; }
  std::function<void(std::uint32_t)> wait;

 private:
  double reference_nT_;
  drivers::LinuxClock clock_;
  std::unique_ptr<drivers::SpidevBus> spi_;
  std::unique_ptr<drivers::GpiodDataReadyLine> drdy_;
  std::unique_ptr<drivers::Ads131Fluxgate> ads_;
  std::unique_ptr<drivers::TermiosSerialPort> serial_;
  std::unique_ptr<drivers::SerialFluxgate<drivers::AsciiLineDecoder>> serial_mag_;
  std::unique_ptr<drivers::SocketCanBus> can_;
  std::unique_ptr<drivers::sbg::CanAttitudeSource> ins_;
  hal::MagnetometerSource* mag_{nullptr};
  std::unique_ptr<DeviceFeed> feed_;
  std::string describe_;
};

// ------------------------------------------------------------------ the daemon

// Publishes every record of the pipeline on the output channel.
class LcmRecordSink final : public hal::RecordSink {
 public:
  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    if (lcm_ == nullptr) return hal::Status::kNotReady;
    const magvec_lcm::calibrated_vector v = to_lcm(r);
    if (lcm_->publish(channel_, &v) != 0) {
      ++errors_;
      return hal::Status::kBusError;
    }
    return hal::Status::kOk;
  }
  void attach(lcm::LCM* l, const std::string& channel) {
    lcm_ = l;
    channel_ = channel;
  }
  std::uint64_t errors() const noexcept { return errors_; }

 private:
  lcm::LCM* lcm_{nullptr};
  std::string channel_;
  std::uint64_t errors_{0};
};

struct Options {
  std::string config_path;
  bool sim{false};
  std::string state_dir;
  std::string lcm_url;
  bool check_config{false};
};

class Daemon final : public EventHandler {
 public:
  explicit Daemon(const Options& o) : opt_(o), ep_(sink_) {}

  Config load_config() {
    const std::string text =
        opt_.config_path.empty() ? default_config_text() : read_config_text(opt_.config_path);
    Config c =
        parse_config(text, opt_.config_path.empty() ? "<embedded default>" : opt_.config_path);
    // The logged session configuration is the file's text. The command-line overrides (state
    // directory, LCM URL) do not reach the pipeline, so a replay of the log is unaffected by them.
    config_text_ = text;
    if (!opt_.state_dir.empty()) c.daemon.state_dir = opt_.state_dir;
    if (!opt_.lcm_url.empty()) c.lcm.url = opt_.lcm_url;
    return c;
  }

  int run() {
    Config config;
    try {
      config = load_config();
    } catch (const ConfigError& e) {
      throw Fatal(kExitConfig, std::string("configuration error: ") + e.what());
    }
    if (opt_.check_config) {
      std::printf("configuration OK\n");
      return kExitOk;
    }
    set_log_level(config);
    spdlog::info("magvecd {} starting ({} mode, config {})", kVersion, opt_.sim ? "sim" : "real",
                 opt_.config_path.empty() ? "embedded default" : opt_.config_path);
    prepare_state_dir(config);
    persisted_ = load_persisted(config);
    realtime_hints(config);
    start_us_ = mono_us();
    open_session(config, true);
    while (true) {
      loop_session();  // until SIGTERM/SIGINT or SIGHUP
      if (g_stop != 0) break;
      g_reload = 0;
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
    spdlog::info("stopping ({} samples)", mag_events_);
    ep_.flush();  // the samples still inside the fusion horizon get their records
    shutdown_persist();
    publish_status();
    publish_health();
    sd_notify(0, "STOPPING=1");
    return kExitOk;
  }

  // EventHandler: publish first, then feed the very message that was published.
  void on_attitude(const hal::AttitudeSample& a) override {
    const magvec_lcm::attitude m = to_lcm(a);
    publish(config_.lcm.channels.attitude, m);
    ep_.apply(m);
  }
  void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) override {
    const magvec_lcm::mag_sample m = to_lcm(s, f_ref_nT);
    publish(config_.lcm.channels.raw_mag, m);
    ep_.apply(m);
    last_t_us_ = s.t_us;
    ++mag_events_;
    error_streak_start_us_ = 0;
  }
  void on_read_error(hal::Status s) override {
    if (ep_.pipeline() != nullptr) ep_.pipeline()->on_read_error();
    if (++read_errors_ <= 5) spdlog::warn("magnetometer read error: {}", hal::to_string(s));
    // A device that only fails (unplugged, powered off) is not healed by pinging the watchdog:
    // exit with the device code so that systemd restarts the service and the journal says why.
    const std::uint64_t now = mono_us();
    if (error_streak_start_us_ == 0) error_streak_start_us_ = now;
    if (now - error_streak_start_us_ > kMaxErrorStreakUs)
      throw Fatal(kExitDevice, "magnetometer: only read errors for " +
                                   std::to_string(kMaxErrorStreakUs / 1'000'000) +
                                   " s (last: " + hal::to_string(s) + ", " +
                                   std::to_string(read_errors_) + " errors in all)");
  }

 private:
  template <typename Msg>
  void publish(const std::string& channel, const Msg& m) {
    if (lcm_->publish(channel, &m) != 0) ++publish_errors_;
  }

  void event(const magvec_lcm::pipeline_event& e) {
    publish(config_.lcm.channels.pipeline, e);
    ep_.apply(e);
  }

  static void set_log_level(const Config& c) {
    spdlog::set_level(spdlog::level::from_str(c.daemon.log_level));
  }

  static void prepare_state_dir(const Config& c) {
    std::error_code ec;
    std::filesystem::create_directories(c.daemon.state_dir, ec);
    if (ec || !std::filesystem::is_directory(c.daemon.state_dir))
      throw Fatal(kExitConfig,
                  "state directory " + c.daemon.state_dir + " cannot be created: " + ec.message());
  }

  // Opens LCM and the devices of `config` and starts a session (pipeline events published).
  void open_session(const Config& config, bool first) {
    config_ = config;
    auto l = std::make_unique<lcm::LCM>(config.lcm.url);
    if (!l->good()) throw Fatal(kExitLcm, "LCM provider " + config.lcm.url + " is not available");
    // The old devices are released before the new ones open (same device paths on reload).
    devices_.reset();
    std::unique_ptr<Devices> devices;
    std::function<void(std::uint32_t)> wait = [this](std::uint32_t us) { serve(us); };
    if (opt_.sim) {
      auto d = std::make_unique<SimDevices>(config);
      d->wait = wait;
      devices = std::move(d);
    } else {
      auto d = std::make_unique<RealDevices>(config);
      d->wait = wait;
      devices = std::move(d);
    }
    // Carry the active calibration over a reload; a calibration in progress starts again (its
    // collected data belong to the old session and configuration).
    Persisted carried;
    bool restart_calibration = false;
    if (!first && ep_.pipeline() != nullptr) {
      const CalibrationStatus st = ep_.pipeline()->status();
      carried.present = st.cal_id != 0;
      carried.model = st.active;
      carried.cal_id = st.cal_id;
      carried.time_offset_s = ep_.pipeline()->time_offset_s();
      restart_calibration = st.state == core::CalState::kCollecting ||
                            st.state == core::CalState::kSolving ||
                            st.state == core::CalState::kValidating;
    }
    lcm_ = std::move(l);
    sink_.attach(lcm_.get(), config.lcm.channels.output);
    lcm_->subscribe(config.lcm.channels.command, &Daemon::on_command, this);
    devices_ = std::move(devices);
    spdlog::info("devices: {}; LCM {}", devices_->describe(), config.lcm.url);

    // The text as read: the command-line overrides (state directory, LCM URL) do not reach the
    // pipeline.
    event(session_start_event(++sequence_, config_text_));
    const Persisted& install = first ? persisted_ : carried;
    if (install.present)
      event(set_active_event(++sequence_, install.model, install.cal_id, install.time_offset_s));
    if (config.calibration.mode != "none" &&
        ((first && config.calibration.start_on_boot) || restart_calibration)) {
      if (restart_calibration) spdlog::info("calibration in progress restarted after the reload");
      event(start_calibration_event(++sequence_));
    }
    applied_seen_ = ep_.pipeline()->health().calibrations_applied;

    sd_notify(0, first ? "READY=1\nSTATUS=running" : "READY=1\nSTATUS=running (reloaded)");
  }

  // Runs the open session until a signal flag is set.
  void loop_session() {
    std::uint64_t watchdog_us = 0;
    if (sd_watchdog_enabled(0, &watchdog_us) <= 0) watchdog_us = 0;
    std::uint64_t next_watchdog = 0, next_health = 0, next_status = 0;
    const auto health_us = static_cast<std::uint64_t>(config_.daemon.health_period_s * 1e6);
    const auto status_us = static_cast<std::uint64_t>(config_.daemon.status_period_s * 1e6);

    while (g_stop == 0 && g_reload == 0) {
      devices_->poll(*this, 20'000);
      check_auto_accept();
      if (ep_.pipeline()->state() != last_state_enum_) {
        last_state_enum_ = ep_.pipeline()->state();
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
      }
    }
  }

  void serve(std::uint32_t us) {
    if (g_stop != 0 || g_reload != 0) return;
    const int ms = static_cast<int>((us + 999) / 1000);
    lcm_->handleTimeout(ms);
  }

  void check_auto_accept() {
    Pipeline* p = ep_.pipeline();
    const std::uint64_t applied = p->health().calibrations_applied;
    if (applied == applied_seen_) return;
    applied_seen_ = applied;
    const CalibrationStatus st = p->status();
    spdlog::info("calibration applied: cal_id {} (validation intensity rms {:.3f} nT)", st.cal_id,
                 st.validation_rms_nT);
    publish_status();
    if (config_.calibration.auto_accept) persist(st, "auto-accept");
  }

  bool persist(const CalibrationStatus& st, const char* why) {
    if (st.cal_id == 0) return false;
    host::CalibrationFile f;
    f.model = st.active;
    // The loop's calibrators do not estimate the time offset: the one in use is kept.
    f.time_offset_s = ep_.pipeline()->time_offset_s();
    f.quality.verdict = "ok";
    f.quality.reason = std::string("accepted by magvecd (") + why + ")";
    f.quality.extra["cal_id"] = st.cal_id;
    f.quality.extra["validation_rms_nT"] = st.validation_rms_nT;
    f.provenance.input = "magvecd live calibration";
    f.provenance.method = st.calibrator;
    f.provenance.magvec_version = kVersion;
    f.provenance.created_utc = host::utc_now_iso8601();
    const std::string path = cal_path(config_);
    try {
      host::write_calibration_file(path, f);
    } catch (const std::exception& e) {
      spdlog::error("persisting calibration {} failed: {}", st.cal_id, e.what());
      return false;
    }
    persisted_.present = true;
    persisted_.model = st.active;
    persisted_.cal_id = st.cal_id;
    persisted_.time_offset_s = f.time_offset_s;
    spdlog::info("calibration {} persisted to {} ({})", st.cal_id, path, why);
    return true;
  }

  void shutdown_persist() {
    Pipeline* p = ep_.pipeline();
    if (p == nullptr) return;
    const CalibrationStatus st = p->status();
    if (st.cal_id != 0 && st.cal_id != persisted_.cal_id && config_.calibration.auto_accept)
      persist(st, "shutdown");
  }

  void publish_status() {
    const magvec_lcm::calibration_state s =
        to_lcm(ep_.pipeline()->status(), last_t_us_, persisted_.cal_id);
    publish(config_.lcm.channels.cal_state, s);
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

  void publish_health() {
    magvec_lcm::health h{};
    auto i64 = [](std::uint64_t v) { return static_cast<std::int64_t>(v); };
    h.t_us = i64(last_t_us_);
    h.uptime_ms = i64((mono_us() - start_us_) / 1000);
    const hal::MagCounters& mc = devices_->mag_counters();
    h.mag_samples = mc.samples;
    h.mag_crc_errors = mc.crc_errors;
    h.mag_malformed = mc.malformed;
    h.mag_bus_errors = mc.bus_errors;
    h.mag_timeouts = mc.timeouts;
    h.mag_saturated = mc.saturated;
    const host::hil::HilCounters& c = ep_.pipeline()->counters();
    h.mag_read_errors = i64(c.mag_read_errors);
    h.mag_not_fresh = i64(c.mag_not_fresh);
    h.mag_missing = i64(c.mag_missing);
    h.mag_time_jumps = i64(c.mag_time_jumps);
    const hal::AttitudeCounters& ac = devices_->attitude_counters();
    h.att_samples = ac.samples;
    h.att_malformed = ac.malformed;
    h.att_invalid = i64(c.att_invalid);
    h.att_gaps = i64(c.att_gaps);
    h.att_time_jumps = i64(c.att_time_jumps);
    h.att_rejected = i64(c.att_rejected);
    const core::LoopHealth& lh = ep_.pipeline()->health();
    h.records = i64(c.records);
    h.dropouts = i64(lh.dropouts);
    h.device_errors = i64(lh.device_errors);
    h.no_attitude = i64(lh.no_attitude);
    h.calibrations_applied = i64(lh.calibrations_applied);
    h.calibrations_failed = i64(lh.calibrations_failed);
    h.publish_errors = i64(publish_errors_ + sink_.errors());
    publish(config_.lcm.channels.health, h);
  }

  void on_command(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::command* cmd) {
    magvec_lcm::command_reply r{};
    r.request_id = cmd->request_id;
    Pipeline* p = ep_.pipeline();
    const std::string& c = cmd->command;
    spdlog::info("command '{}' (request {})", c, cmd->request_id);
    if (c == "start") {
      if (config_.calibration.mode == "none") {
        r.ok = false;
        r.message = "calibration mode is 'none': nothing to start";
      } else {
        event(start_calibration_event(++sequence_));
        r.ok = true;
        r.message = "calibration started (" + config_.calibration.mode + ")";
      }
    } else if (c == "accept") {
      const CalibrationStatus st = p->status();
      if (st.cal_id == 0) {
        r.ok = false;
        r.message = "no calibration is active: nothing to accept";
      } else if (persisted_.present && st.cal_id == persisted_.cal_id) {
        r.ok = true;
        r.message = "calibration " + std::to_string(st.cal_id) + " is already persisted";
      } else {
        r.ok = persist(st, "accept command");
        r.message =
            r.ok ? "calibration " + std::to_string(st.cal_id) + " persisted to " + cal_path(config_)
                 : "persisting failed (see the daemon log)";
      }
    } else if (c == "revert") {
      const core::SensorModel<double> identity;
      const core::SensorModel<double>& m = persisted_.present ? persisted_.model : identity;
      const std::uint32_t id = persisted_.present ? persisted_.cal_id : 0;
      event(
          set_active_event(++sequence_, m, id, persisted_.present ? persisted_.time_offset_s : 0));
      r.ok = true;
      r.message = persisted_.present
                      ? "reverted to the persisted calibration " + std::to_string(id)
                      : "no persisted calibration: reverted to the identity (uncalibrated)";
    } else if (c == "status") {
      r.ok = true;
      r.message = "running, " + std::to_string(mag_events_) + " samples";
    } else {
      r.ok = false;
      r.message = "unknown command '" + c + "' (start, accept, revert, status)";
    }
    r.state = to_lcm(p->status(), last_t_us_, persisted_.cal_id);
    if (c == "status" || c == "start" || c == "revert") publish_status();
    publish(config_.lcm.channels.reply, r);
  }

  Options opt_;
  std::string config_text_;
  Config config_{};
  LcmRecordSink sink_;
  EventPipeline ep_;
  std::unique_ptr<lcm::LCM> lcm_;
  std::unique_ptr<Devices> devices_;
  Persisted persisted_{};
  std::int64_t sequence_{0};
  std::uint64_t applied_seen_{0};
  std::uint64_t last_t_us_{0};
  std::uint64_t mag_events_{0};
  std::uint64_t read_errors_{0};
  std::uint64_t error_streak_start_us_{0};  // first error since the last good sample (0: none)
  static constexpr std::uint64_t kMaxErrorStreakUs = 10'000'000;
  std::uint64_t publish_errors_{0};
  std::uint64_t start_us_{0};
  std::string last_state_;
  core::CalState last_state_enum_{core::CalState::kIdle};
  std::int32_t last_cal_id_{-1};
};

}  // namespace

int main(int argc, char** argv) {
  auto logger = spdlog::stderr_logger_mt("magvecd");
  logger->set_pattern("magvecd[%l] %v");
  spdlog::set_default_logger(logger);

  CLI::App app{"magvecd: magnetic vector calibration daemon (devices -> sensor loop -> LCM)"};
  app.set_version_flag("--version", std::string("magvecd ") + magvec::kVersion);
  Options o;
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
    Daemon d(o);
    const int code = d.run();
    spdlog::info("exit {}", code);
    return code;
  } catch (const Fatal& e) {
    spdlog::critical("{} (exit {})", e.what(), e.code());
    sd_notifyf(0, "STATUS=failed (exit %d): %s", e.code(), e.what());
    return e.code();
  } catch (const std::exception& e) {
    spdlog::critical("internal error: {} (exit {})", e.what(), static_cast<int>(kExitInternal));
    return kExitInternal;
  }
}
