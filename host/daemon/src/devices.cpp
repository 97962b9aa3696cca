// magvecd's devices; see devices.hpp.
#include "magvec/host/daemon/devices.hpp"

#include <spdlog/spdlog.h>

#include <algorithm>
#include <exception>
#include <utility>

#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/g882.hpp"
#include "magvec/drivers/linux/gpiod_data_ready_line.hpp"
#include "magvec/drivers/linux/linux_clock.hpp"
#include "magvec/drivers/linux/socketcan_bus.hpp"
#include "magvec/drivers/linux/spidev_bus.hpp"
#include "magvec/drivers/linux/termios_serial_port.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"
#include "magvec/host/daemon/daemon_error.hpp"
#include "magvec/host/daemon/device_feed.hpp"
#include "magvec/host/daemon/position_reference.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/hil_session.hpp"

namespace magvec::host::daemon {
namespace {

class SimDevices final : public Devices {
 public:
  SimDevices(const Config& c, WaitFn wait, NowFn now)
      : sim_(sim_scenario(c), c.sim.seed),
        front_(sim_, sim_rig_config(c)),
        period_us_(1e6 / c.magnetometer.rate_hz),
        wake_period_us_(c.sim.wake_period_us),
        wait_(std::move(wait)),
        now_(std::move(now)),
        t0_us_(now_()) {
    if (front_.init() != hal::Status::kOk)
      throw DaemonError(kExitDevice, "simulated ADC did not initialise");
    if (c.scalar.enabled)
      spdlog::info("devices.scalar is for real devices: the simulated rig supplies F");
  }

  bool poll(EventHandler& h, std::uint32_t max_wait_us) override {
    if (ended_) {
      wait_(max_wait_us);
      return false;
    }
    const std::uint64_t due =
        t0_us_ + static_cast<std::uint64_t>(static_cast<double>(steps_) * period_us_);
    const std::uint64_t now = now_();
    if (now < due) {
      // With a wake period, the wake-up is the first multiple of it (from t0) at or after the
      // due time, and every conversion due by then is stepped before the next wait.
      std::uint64_t wake = due;
      if (wake_period_us_ != 0) {
        const std::uint64_t k = (due - t0_us_ + wake_period_us_ - 1) / wake_period_us_;
        wake = t0_us_ + k * wake_period_us_;
      }
      wait_(static_cast<std::uint32_t>(std::min<std::uint64_t>(wake - now, max_wait_us)));
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
    if (a.error) std::rethrow_exception(a.error);
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

 private:
  // SimFrontEnd::poll is noexcept: an exception of the handler (the daemon's exits, e.g. the
  // error streak's DaemonError) would terminate the process. It is kept, the events after it are
  // dropped, and poll() rethrows it.
  struct Adapter {
    EventHandler& h;
    std::exception_ptr error{};
    template <typename F>
    void guarded(F&& f) noexcept {
      if (error) return;
      try {
        f();
      } catch (...) {
        error = std::current_exception();
      }
    }
    void on_attitude(const hal::AttitudeSample& a) noexcept {
      guarded([&] { h.on_attitude(a); });
    }
    void on_magnetometer(const hal::MagnetometerSample& s, double f) noexcept {
      guarded([&] { h.on_magnetometer(s, f); });
    }
    void on_read_error(hal::Status s) noexcept {
      guarded([&] { h.on_read_error(s); });
    }
  };

  drivers::sim::Simulator sim_;
  hil::SimFrontEnd front_;
  double period_us_;
  std::uint64_t wake_period_us_;
  WaitFn wait_;
  NowFn now_;
  std::uint64_t t0_us_;
  std::uint64_t steps_{0};
  bool ended_{false};
};

class RealDevices final : public Devices {
 public:
  RealDevices(const Config& c, WaitFn wait, hal::AttitudeSource* ins_override,
              hal::PositionSource* positions_override)
      : reference_nT_(c.calibration.reference_field_nT), wait_(std::move(wait)) {
    drivers::OsError err;
    const auto& m = c.magnetometer;
    if (m.link == "spi") {
      drivers::SpidevConfig sc;
      sc.device = m.spi_device;
      sc.speed_hz = m.spi_speed_hz;
      spi_ = drivers::SpidevBus::open(sc, &err);
      if (!spi_) throw DaemonError(kExitDevice, "magnetometer SPI: " + err.message);
      drivers::GpiodConfig gc;
      gc.chip = m.drdy_chip;
      gc.line = m.drdy_line;
      gc.edge = hal::Edge::kFalling;
      gc.consumer = "magvecd";
      drdy_ = drivers::GpiodDataReadyLine::open(gc, &err);
      if (!drdy_) throw DaemonError(kExitDevice, "magnetometer data-ready line: " + err.message);
      ads_ = std::make_unique<drivers::Ads131Fluxgate>(*spi_, *drdy_, m.adc);
      const hal::Status s = ads_->init();
      if (s != hal::Status::kOk)
        throw DaemonError(kExitDevice, "ADS131M04 on " + m.spi_device +
                                           " did not initialise: " + hal::to_string(s));
      mag_ = ads_.get();
    } else {
      drivers::SerialConfig sc;
      sc.device = m.serial_device;
      sc.baud = m.serial_baud;
      sc.reconnect_interval_ms = m.serial_reconnect_ms;
      serial_ = drivers::TermiosSerialPort::open(sc, &err);
      if (!serial_) throw DaemonError(kExitDevice, "magnetometer serial port: " + err.message);
      serial_mag_ = std::make_unique<drivers::SerialFluxgate<drivers::AsciiLineDecoder>>(
          *serial_, clock_, drivers::AsciiLineDecoder(drivers::AsciiLineConfig{}),
          m.serial_latency_us);
      mag_ = serial_mag_.get();
    }
    if (ins_override != nullptr) {
      ins_ = ins_override;
    } else {
      open_can(c);
    }
    if (uses_model_reference(c)) open_model_reference(positions_override);
    if (c.scalar.enabled) {
      drivers::SerialConfig sc;
      sc.device = c.scalar.device;
      sc.baud = c.scalar.baud;
      sc.reconnect_interval_ms = c.scalar.reconnect_ms;
      scalar_port_ = drivers::TermiosSerialPort::open(sc, &err);
      if (!scalar_port_)
        throw DaemonError(kExitDevice, "scalar magnetometer serial port: " + err.message);
      scalar_ = std::make_unique<drivers::SerialScalarSource>(
          *scalar_port_, clock_, drivers::G882LineDecoder(c.scalar.line), c.scalar.latency_us);
      feed_ = std::make_unique<DeviceFeed>(*mag_, *ins_, *scalar_, c.scalar.align);
    } else {
      feed_ = std::make_unique<DeviceFeed>(*mag_, *ins_, reference_nT_);
    }
    describe_ =
        (m.link == "spi" ? "ADS131M04 on " + m.spi_device + " (DRDY " + m.drdy_chip + " line " +
                               std::to_string(m.drdy_line) + ")"
                         : "serial fluxgate on " + m.serial_device) +
        ", SBG INS on " + (ins_override != nullptr ? "(given source)" : c.ins.can_interface) +
        (c.scalar.enabled ? ", G-882 scalar magnetometer on " + c.scalar.device : "") +
        (model_ ? ", reference field from " + model_->model_name() + " at the INS position" : "");
  }

  ~RealDevices() override {
    if (const pipeline::ScalarAlignerCounters* a = feed_->aligner_counters()) {
      const hal::ScalarCounters& sc = scalar_->counters();
      spdlog::info(
          "scalar magnetometer: {} readings ({} malformed, {} out of range, {} overflows, {} "
          "garbage bytes, {} low signal, {} bus errors); F interpolated for {} samples, nearest "
          "reading {}, fallback {}, released by the horizon {}",
          sc.samples, sc.malformed, sc.out_of_range, sc.overflows, sc.garbage_bytes, sc.low_signal,
          sc.bus_errors, a->interpolated, a->nearest, a->fallback, a->expired);
    }
  }

  void flush(EventHandler& h) override { feed_->flush(h); }

  void open_can(const Config& c) {
    drivers::OsError err;
    drivers::SocketCanConfig cc;
    cc.interface = c.ins.can_interface;
    for (const std::uint32_t id :
         {c.ins.ids.status_01, c.ins.ids.status_03, c.ins.ids.ekf_info, c.ins.ids.ekf_quat,
          c.ins.ids.ekf_euler, c.ins.ids.ekf_orientation_acc, c.ins.ids.ekf_pos,
          c.ins.ids.ekf_altitude}) {
      drivers::CanFilterSpec f;
      f.id = id;
      f.mask = 0x7FF;
      f.extended = false;
      cc.filters.push_back(f);
    }
    cc.receive_error_frames = true;
    can_ = drivers::SocketCanBus::open(cc, &err);
    if (!can_) throw DaemonError(kExitDevice, "INS CAN bus: " + err.message);
    drivers::sbg::DecoderConfig dc;
    dc.ids = c.ins.ids;
    can_ins_ = std::make_unique<drivers::sbg::CanAttitudeSource>(*can_, dc);
    ins_ = can_ins_.get();
  }

  // DeviceFeed (device_feed.hpp): every INS sample as soon as it has been received, before the
  // magnetometer sample read after it; the pipeline's fusion horizon does the time ordering. (The
  // earlier rule, an INS sample only if not later than the magnetometer sample, left every query
  // past the newest INS sample: a held attitude instead of an interpolated one.)
  bool poll(EventHandler& h, std::uint32_t max_wait_us) override {
    const FeedResult r = feed_->poll(h, max_wait_us);
    if (model_) take_positions(h);
    // A failing device answers at once: wait out the period (serving commands) rather than spin.
    wait_(r == FeedResult::kError ? max_wait_us : 0);
    return true;
  }
  const hal::MagCounters& mag_counters() const override { return mag_->counters(); }
  const hal::AttitudeCounters& attitude_counters() const override { return ins_->counters(); }
  std::optional<ScalarHealth> scalar_health() const override {
    const pipeline::ScalarAlignerCounters* a = feed_->aligner_counters();
    if (a == nullptr) return std::nullopt;
    ScalarHealth h;
    h.source = scalar_->counters();
    h.read_errors = feed_->scalar_read_errors();
    h.timeouts = feed_->scalar_timeouts();
    h.f_interpolated = a->interpolated;
    h.f_nearest = a->nearest;
    h.f_fallback = a->fallback;
    return h;
  }
  std::string describe() const override { return describe_; }

 private:
  void open_model_reference(hal::PositionSource* positions_override) {
    positions_ = positions_override != nullptr ? positions_override
                 : can_ins_                    ? &can_ins_->positions()
                                               : nullptr;
    if (positions_ == nullptr) return;  // an INS given without positions (tests)
    try {
      model_ = std::make_unique<PositionReference>(geomag::MagneticModel::wmm2025(),
                                                   &PositionReference::utc_decimal_year_now);
    } catch (const geomag::GeomagError& e) {
      throw DaemonError(kExitConfig,
                        std::string("calibration.reference_model: ") + e.what() +
                            " (install the model data, or set calibration.reference_field_nT, "
                            "or reference_model = \"none\")");
    }
  }

  // The position fixes decoded meanwhile: the model's F for the samples read from now on. The
  // first F is announced (the pipeline then validates and flags by the model's sigma) before any
  // sample carries it.
  void take_positions(EventHandler& h) {
    hal::PositionSample p;
    for (int guard = 0; guard < 16 && positions_->read(p, 0) == hal::Status::kOk; ++guard) {
      const std::uint64_t errors = model_->counters().model_errors;
      const bool changed = model_->on_position(p);
      if (model_->counters().model_errors > errors && model_->counters().model_errors == 1)
        spdlog::warn("reference model: {} (position fix not used)", model_->last_error());
      if (!changed) continue;
      if (!model_announced_) {
        model_announced_ = true;
        spdlog::info("reference field: {}", model_->describe());
        h.on_model_reference(model_->field()->model, model_->sigma_nT());
      }
      feed_->set_reference_nT(model_->total_nT());
    }
  }

  double reference_nT_;
  WaitFn wait_;
  drivers::LinuxClock clock_;
  std::unique_ptr<drivers::SpidevBus> spi_;
  std::unique_ptr<drivers::GpiodDataReadyLine> drdy_;
  std::unique_ptr<drivers::Ads131Fluxgate> ads_;
  std::unique_ptr<drivers::TermiosSerialPort> serial_;
  std::unique_ptr<drivers::SerialFluxgate<drivers::AsciiLineDecoder>> serial_mag_;
  std::unique_ptr<drivers::SocketCanBus> can_;
  std::unique_ptr<drivers::sbg::CanAttitudeSource> can_ins_;
  hal::AttitudeSource* ins_{nullptr};
  std::unique_ptr<drivers::TermiosSerialPort> scalar_port_;
  std::unique_ptr<drivers::SerialScalarSource> scalar_;
  hal::MagnetometerSource* mag_{nullptr};
  std::unique_ptr<DeviceFeed> feed_;
  hal::PositionSource* positions_{nullptr};
  std::unique_ptr<PositionReference> model_;
  bool model_announced_{false};
  std::string describe_;
};

}  // namespace

std::unique_ptr<Devices> open_sim_devices(const Config& c, WaitFn wait, NowFn now) {
  return std::make_unique<SimDevices>(c, std::move(wait), std::move(now));
}

std::unique_ptr<Devices> open_real_devices(const Config& c, WaitFn wait, hal::AttitudeSource* ins,
                                           hal::PositionSource* positions) {
  return std::make_unique<RealDevices>(c, std::move(wait), ins, positions);
}

}  // namespace magvec::host::daemon
