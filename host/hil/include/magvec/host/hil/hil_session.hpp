// Host-in-the-loop harness (docs/architecture.md#simulation):
//   simulated devices (drivers/sim SimRig: ADS131M04 on SPI + DRDY or serial ASCII fluxgate, SBG
//   INS on CAN) -> the REAL drivers (Ads131Fluxgate / SerialFluxgate / CanAttitudeSource, i.e.
//   the byte codecs) -> core::SamplePipeline (AttitudeBuffer with the delayed fusion horizon, slerp
//   at every magnetometer time) -> core::SensorLoop<double, Calibrator> -> hal::RecordSink.
// Simulated time only: each step() advances the rig by one magnetometer sample, no sleeping, so a
// run is as fast as the CPU allows and deterministic from the scenario seed.
//
// Plugging a calibrator: HilSession is templated on the SensorLoop's Calibrator concept
// (sensor_loop.hpp: begin/add/progress/ready/solve). Construct the calibrator yourself and pass it
// by reference; HilConfig::start_calibration starts a calibration at the first sample (the loop's
// state machine then collects, solves, validates on held-out samples and applies). A calibration
// loaded from a file is installed with session.loop().set_active(model, id) before running.
//
// Scalar reference: the calibrators need |h| per sample (f_ref_nT). The harness takes it from the
// simulator (SimSample::f_nT: a simulated scalar magnetometer, or NaN in scenarios without one);
// it is not part of the HAL path.
//
// Health: HilCounters (loop_core.hpp) on top of the drivers' counters and LoopHealth.
// The harness is split in two so magvecd reuses both halves: SimFrontEnd (simulated devices ->
// real drivers -> raw events) and LoopCore (raw events -> buffer -> loop -> records).
// Zero heap allocations per step after construction (proved by tests/host/hil/hil_session_test).
#pragma once

#include <cmath>
#include <cstdint>
#include <limits>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/hal/record_sink.hpp"
#include "magvec/host/hil/loop_core.hpp"

namespace magvec::host::hil {

// The device half: SimRig (simulated ADS131M04 + DRDY or serial fluxgate, SBG INS on CAN) read
// through the real drivers. poll() hands every event the drivers produced since the last rig step
// to a handler with on_attitude(const hal::AttitudeSample&), on_magnetometer(const
// hal::MagnetometerSample&, double f_ref_nT) and on_read_error(hal::Status): first the INS samples
// received by the magnetometer sample's time (SimRigConfig::ins_lead_s), then the magnetometer
// samples.
class SimFrontEnd {
 public:
  SimFrontEnd(drivers::sim::Simulator& sim, const drivers::sim::SimRigConfig& rig_config) noexcept
      : rig_(sim, rig_config),
        ads_(rig_.adc(), rig_.adc(), rig_config.adc.transfer),
        serial_(rig_.serial(), rig_.clock(), drivers::AsciiLineDecoder(rig_config.serial.line)),
        can_(rig_.ins(), can_decoder_config(rig_config)) {
    if (rig_config.link == drivers::sim::MagLink::kSpi) {
      mag_ = &ads_;
    } else {
      mag_ = &serial_;
    }
  }
  SimFrontEnd(const SimFrontEnd&) = delete;
  SimFrontEnd& operator=(const SimFrontEnd&) = delete;

  // Device start-up (ADC reset + gain configuration on SPI). kOk or the driver's status.
  hal::Status init() noexcept {
    if (mag_ == &ads_) return ads_.init();
    return hal::Status::kOk;
  }

  template <typename Handler>
  void poll(Handler& handler) noexcept {
    hal::AttitudeSample a;
    for (int guard = 0; guard < 256 && can_.read(a, 0) == hal::Status::kOk; ++guard)
      handler.on_attitude(a);
    for (int guard = 0; guard < 8; ++guard) {
      hal::MagnetometerSample s;
      const hal::Status st = mag_->read(s, 0);
      if (st == hal::Status::kTimeout || st == hal::Status::kNoData) break;
      if (st != hal::Status::kOk) {
        handler.on_read_error(st);
        continue;
      }
      // The scalar reference comes from the simulator (a simulated scalar magnetometer).
      handler.on_magnetometer(s, rig_.last().f_nT);
    }
  }

  drivers::sim::SimRig& rig() noexcept { return rig_; }
  const hal::MagCounters& mag_counters() const noexcept { return mag_->counters(); }
  const hal::AttitudeCounters& attitude_counters() const noexcept { return can_.counters(); }

 private:
  // The INS decoder listens to the CAN IDs the simulated INS sends.
  static drivers::sbg::DecoderConfig can_decoder_config(
      const drivers::sim::SimRigConfig& rc) noexcept {
    drivers::sbg::DecoderConfig c;
    c.ids = rc.ins.ids;
    return c;
  }

  drivers::sim::SimRig rig_;
  drivers::Ads131Fluxgate ads_;
  drivers::SerialFluxgate<drivers::AsciiLineDecoder> serial_;
  drivers::sbg::CanAttitudeSource can_;
  hal::MagnetometerSource* mag_{nullptr};
};

template <typename Calibrator, std::size_t BufferCapacity = 64>
class HilSession {
 public:
  HilSession(drivers::sim::Simulator& sim, const drivers::sim::SimRigConfig& rig_config,
             Calibrator& calibrator, hal::RecordSink& sink, const HilConfig& config) noexcept
      : config_(config),
        front_(sim, rig_config),
        core_(calibrator, sink, config, sim.config().rate_hz, rig_config.ins.rate_hz) {}

  // Device start-up (ADC reset + gain configuration on SPI). kOk or the driver's status.
  hal::Status init() noexcept { return front_.init(); }

  // One magnetometer sample period of simulated time; false when the scenario has ended (the
  // samples still waiting for INS samples are then processed: every sample gets its record).
  bool step() noexcept {
    if (!front_.rig().step()) {
      core_.flush();
      return false;
    }
    core_.count_step();
    if (config_.start_calibration && !started_) {
      core_.loop().start_calibration();
      started_ = true;
    }
    front_.poll(*this);
    return true;
  }

  std::uint64_t run(std::uint64_t max_steps = std::numeric_limits<std::uint64_t>::max()) noexcept {
    std::uint64_t n = 0;
    while (n < max_steps && step())
      ++n;
    return n;
  }

  // SimFrontEnd event handler.
  void on_attitude(const hal::AttitudeSample& a) noexcept { core_.on_attitude(a); }
  void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) noexcept {
    core_.on_magnetometer(s, f_ref_nT);
  }
  void on_read_error(hal::Status) noexcept { core_.on_read_error(); }

  drivers::sim::SimRig& rig() noexcept { return front_.rig(); }
  core::SensorLoop<double, Calibrator>& loop() noexcept { return core_.loop(); }
  const core::AttitudeBuffer<double, BufferCapacity>& buffer() const noexcept {
    return core_.buffer();
  }
  const HilCounters& counters() const noexcept { return core_.counters(); }
  const LoopCore<Calibrator, BufferCapacity>& core() const noexcept { return core_; }
  const hal::MagCounters& mag_counters() const noexcept { return front_.mag_counters(); }
  const hal::AttitudeCounters& attitude_counters() const noexcept {
    return front_.attitude_counters();
  }

 private:
  HilConfig config_;
  SimFrontEnd front_;
  LoopCore<Calibrator, BufferCapacity> core_;
  bool started_{false};
};

}  // namespace magvec::host::hil
