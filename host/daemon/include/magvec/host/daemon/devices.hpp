// magvecd's devices: where the raw input events come from and in which order.
//   - SimDevices (--sim): the simulated rig (drivers/sim SimRig) read through the real drivers
//     (hil::SimFrontEnd), one step per magnetometer period, paced on a clock;
//   - RealDevices: the Linux transports (spidev + libgpiod DRDY ADS131M04, or a termios serial
//     fluxgate; SocketCAN SBG INS; optionally a termios scalar magnetometer whose reading is F),
//     time-ordered by DeviceFeed (device_feed.hpp).
// Waiting is done through a callback so that the daemon serves its commands meanwhile.
#pragma once

#include <cstdint>
#include <functional>
#include <memory>
#include <optional>
#include <string>

#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/magnetometer_source.hpp"
#include "magvec/hal/position_source.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/scalar_health.hpp"

namespace magvec::host::daemon {

// Receives the raw events in feed order.
struct EventHandler {
  virtual void on_attitude(const hal::AttitudeSample& a) = 0;
  virtual void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) = 0;
  virtual void on_read_error(hal::Status s) = 0;
  // From now on the samples' F comes from the geomagnetic model `model` with 1-sigma sigma_nT
  // (position_reference.hpp); called once, before the first sample that carries it.
  virtual void on_model_reference(const std::string& /*model*/, double /*sigma_nT*/) {}

 protected:
  ~EventHandler() = default;
};

// Waits up to the given microseconds (serving commands meanwhile); may return early.
using WaitFn = std::function<void(std::uint32_t)>;
// Monotonic microseconds.
using NowFn = std::function<std::uint64_t()>;

class Devices {
 public:
  virtual ~Devices() = default;
  // Produces the events due now, waiting at most max_wait_us (through the WaitFn). false when the
  // source has ended (simulated scenario over).
  virtual bool poll(EventHandler& h, std::uint32_t max_wait_us) = 0;
  // Hands on the samples still held (waiting for a scalar reading) before the devices close.
  virtual void flush(EventHandler& /*h*/) {}
  virtual const hal::MagCounters& mag_counters() const = 0;
  virtual const hal::AttitudeCounters& attitude_counters() const = 0;
  // The scalar magnetometer's counters; nullopt without one.
  virtual std::optional<ScalarHealth> scalar_health() const { return std::nullopt; }
  virtual std::string describe() const = 0;
};

// The simulated rig of `c` (sim_setup.hpp), one step per magnetometer period of `now` (waking at
// each step's due time, or with sim.wake_period_us every that often for the steps due by then): a
// step is taken when it is due; more than 1 s behind, the schedule restarts from now (a stalled
// process does not replay the backlog at full speed). Throws DaemonError(kExitDevice).
std::unique_ptr<Devices> open_sim_devices(const Config& c, WaitFn wait, NowFn now);
// The real devices of `c`. Throws DaemonError(kExitDevice) naming the device that failed.
// `ins`, when given, is read instead of the configured CAN bus (tests on hosts without SocketCAN),
// and `positions` (if given) instead of the INS position fixes decoded from that bus.
// With uses_model_reference(c), F comes from the WMM2025 at the INS position
// (position_reference.hpp) from the first valid fix on; throws DaemonError(kExitConfig) when the
// model's data are missing.
std::unique_ptr<Devices> open_real_devices(const Config& c, WaitFn wait,
                                           hal::AttitudeSource* ins = nullptr,
                                           hal::PositionSource* positions = nullptr);

}  // namespace magvec::host::daemon
