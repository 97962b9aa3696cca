// Simulated devices that speak the same bytes as the real ones (docs/architecture.md#simulation),
// driven by the deterministic Simulator (simulator.hpp):
//   - SimAds131Device: TI ADS131M04 front end of a 3-axis analogue fluxgate (frame format:
//     ads131m04.hpp) behind hal::SpiBus + hal::DataReadyLine.
//   - SimSerialFluxgate: a fluxgate writing NMEA-like ASCII lines (serial_fluxgate.hpp) into a
//     hal::SerialPort.
//   - SimSbgIns: an SBG INS emitting its CAN output messages (sbg_can.hpp) on a hal::CanBus.
//   - SimClock: the simulated hal::Clock shared by all of them; SimRig steps everything.
// The real drivers (Ads131Fluxgate, SerialFluxgate, CanAttitudeSource) run unchanged on top.
//
// Fault injection (each fault from its own random stream so enabling one does not move another;
// every injected fault is counted in the device's `injected()` so tests can compare with the
// counters of the real driver):
//   ADC: output-frame byte corruption (-> driver crc_errors), forced saturation of one channel
//        (-> driver saturated), simulator dropouts (NaN), a stuck channel (one axis repeats the
//        code it had for a time window: the driver's stuck detector), device resets mid-stream
//        (every register back to its default, STATUS.RESET set until MODE.RESET is written 0:
//        the driver flags the sample and re-initialises). The conversion uses the gain in the
//        device's GAIN1 register, so a reset the host ignored would show in the values.
//        DECISION on dropouts: the ADC keeps converting and DRDY keeps toggling (it is the
//        fluxgate electronics, not the ADC, that drops out), but the conversion is not new: the
//        STATUS DRDY bits of all channels are clear and the channel words repeat the previous
//        codes. The driver flags the sample kMagNotFresh; the consumer must not use it (the HIL
//        harness turns it into a dropout record, counted by the loop). The sample cadence stays
//        regular, so a missing DRDY edge always means a lost edge, never a dropout.
//   Serial: garbage bytes before a line (letters, never '$' or '\n', so each one is counted as a
//        garbage byte by the decoder), bad checksums (-> crc_errors). Dropouts: the line is not
//        sent (the consumer sees a time gap of one period).
//   INS: a gap (no CAN frame at all for a time window), "attitude invalid" status for a window
//        (STATUS_03 without ATTITUDE/HEADING_VALID), CAN receive latency, corrupted frames
//        (truncated DLC: always rejected as malformed by the decoder), duplicates: an epoch has
//        one of its frames received twice back to back (CAN double reception) or, as often, is
//        repeated whole 1 ms later (a gateway); the copies carry the original's bytes, corrupted
//        or not.
//   Clock jumps: SimRig shifts every host timestamp (DRDY edges, CAN receive times, SimClock) by
//        a signed amount from a given time on. A backwards jump violates the hal::Clock contract
//        on purpose: it is the fault under test.
// Heap-free, exception-free, noexcept, deterministic; portable (no OS headers).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <limits>
#include <span>

#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"
#include "magvec/drivers/sim/random.hpp"
#include "magvec/drivers/sim/serial_wire.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/hal/can_bus.hpp"
#include "magvec/hal/clock.hpp"
#include "magvec/hal/data_ready_line.hpp"
#include "magvec/hal/serial_port.hpp"
#include "magvec/hal/spi_bus.hpp"

namespace magvec::drivers::sim {

// Simulated monotonic clock (set by SimRig or a test; never sleeps).
class SimClock final : public hal::Clock {
 public:
  std::uint64_t now_us() const noexcept override { return now_us_; }
  void set_us(std::uint64_t t_us) noexcept { now_us_ = t_us; }

 private:
  std::uint64_t now_us_{0};
};

// Simulation time (s) -> host clock (us): host_epoch_us at t = 0, plus a signed clock jump from
// jump_at_s on (the injected fault).
struct HostTimeMap {
  std::uint64_t epoch_us{10'000'000};  // room for backwards jumps
  double jump_at_s{std::numeric_limits<double>::infinity()};
  std::int64_t jump_us{0};
  std::uint64_t host_us(double t_s) const noexcept;
};

// ---------------------------------------------------------------- ADS131M04 fluxgate front end

struct SimAds131Faults {
  double crc_error_probability{0};   // per data frame: one byte of the output frame corrupted
  double saturation_probability{0};  // per conversion: one channel forced to +/- full scale
  double reset_probability{0};       // per conversion: the device resets just before it
  // The channel of stuck_axis repeats its last code for the conversions in [start, start + len).
  double stuck_start_s{std::numeric_limits<double>::infinity()};
  double stuck_length_s{0};
  std::uint8_t stuck_axis{0};
  // The temperature sensor on channel 3 (transfer.temperature.enabled) is open for the
  // conversions in [start, start + len): its amplifier rails, the channel reads positive full
  // scale (the driver gives no temperature for those samples and counts them).
  double temperature_open_start_s{std::numeric_limits<double>::infinity()};
  double temperature_open_length_s{0};
};

struct SimAds131Config {
  // The transfer the real driver will invert: code = nT / nT_per_volt * gain / VREF * 2^23.
  Ads131FluxgateConfig transfer{};
  SimAds131Faults faults{};
  std::uint64_t seed{1};
};

struct SimAds131Injected {
  std::uint32_t conversions{0};        // DRDY edges queued
  std::uint32_t not_fresh{0};          // conversions from a simulator dropout (DRDY bits clear)
  std::uint32_t crc_corrupted{0};      // output frames with a corrupted byte
  std::uint32_t saturated{0};          // conversions with a forced full-scale channel
  std::uint32_t saturated_frames{0};   // intact data frames (as reset_frames) carrying a full-scale
                                       // code of a used channel (the driver's saturated)
  std::uint32_t resets{0};             // device resets injected
  std::uint32_t stuck_conversions{0};  // conversions in the stuck window
  // Conversions with the temperature channel open (full scale; transfer.temperature.enabled).
  std::uint32_t temperature_open{0};
  // What the driver must see in the data frames it reads (NULL command, CRC intact): frames with
  // STATUS.RESET (-> device_resets), frames a used channel of which has had one code for
  // transfer.stuck_count or more such frames since the last RESET command (-> stuck).
  std::uint32_t reset_frames{0};
  std::uint32_t stuck_frames{0};
  std::uint32_t range_clipped{0};  // conversions clipped because the field exceeded the range
  std::uint32_t frames{0};         // SPI transfers answered
  std::uint32_t bad_commands{0};   // transfers with an unknown command or a wrong size
};

class SimAds131Device final : public hal::SpiBus, public hal::DataReadyLine {
 public:
  static constexpr std::size_t kEdgeQueue = 8;

  explicit SimAds131Device(const SimAds131Config& config) noexcept;

  // A conversion of the simulated sample completes at host time t_us: latches the codes (or, on a
  // dropout, keeps the previous ones and clears the DRDY bits) and queues a falling DRDY edge.
  void convert(const SimSample& s, std::uint64_t t_us) noexcept;

  // hal::SpiBus: one 18-byte frame. Answers RESET (FF24h in the next frame), WREG (acknowledge
  // in the next frame; GAIN1 is stored), NULL (STATUS + channel data), other commands (echoed
  // as in the datasheet's "response to an unknown command": STATUS is returned).
  hal::Status transfer(std::span<const std::uint8_t> tx,
                       std::span<std::uint8_t> rx) noexcept override;
  // hal::DataReadyLine: falling edges only (the line is configured for falling edges).
  hal::Status wait_edge(hal::EdgeEvent& out, std::uint32_t timeout_us) noexcept override;
  std::uint32_t missed_edges() const noexcept override { return missed_edges_; }

  // Exact inverse of the driver's transfer, rounded to the nearest code and clamped to the ADC
  // range; `clipped` tells whether clamping happened.
  static std::int32_t code_from_nT(double nT, double nT_per_volt, std::uint8_t gain_code,
                                   bool* clipped = nullptr) noexcept;

  const SimAds131Injected& injected() const noexcept { return injected_; }
  std::uint16_t gain1() const noexcept { return gain1_; }

 private:
  // Channel 3 from the sample's temperature (transfer.temperature), or open (full scale).
  void convert_temperature(const SimSample& s) noexcept;
  // Back to the register defaults (the RESET command or the injected fault).
  void reset_registers() noexcept;
  // The driver's stuck detector on a data frame it decodes.
  bool stuck_in(const std::array<std::int32_t, ads131::kChannels>& codes) noexcept;

  SimAds131Config config_;
  Xoshiro256 crc_rng_;
  Xoshiro256 sat_rng_;
  Xoshiro256 reset_rng_;
  SimAds131Injected injected_{};
  std::array<std::int32_t, 3> seen_code_{};  // the stuck detector: last code and run per axis
  std::array<std::uint32_t, 3> seen_run_{};
  std::array<std::int32_t, ads131::kChannels> codes_{};
  std::uint16_t drdy_bits_{0};
  std::uint16_t pending_response_{0};  // response word of the next frame
  bool reset_flag_{true};              // MODE.RESET (shown in STATUS) until written 0
  bool pending_is_status_{true};
  std::uint16_t gain1_{0};
  std::array<hal::EdgeEvent, kEdgeQueue> edges_{};
  std::size_t edge_head_{0};
  std::size_t edge_count_{0};
  std::uint32_t missed_edges_{0};
};

// ---------------------------------------------------------------- serial ASCII fluxgate

struct SimSerialFaults {
  double garbage_probability{0};        // per line: garbage bytes are written before it
  std::uint32_t garbage_max_bytes{16};  // 1..max bytes of garbage
  double bad_checksum_probability{0};   // per line: one checksum digit wrong
};

struct SimSerialConfig {
  AsciiLineConfig line{};
  bool with_checksum{true};
  SimSerialFaults faults{};
  std::uint64_t seed{2};
};

struct SimSerialInjected {
  std::uint32_t lines{0};          // lines written (including those with a bad checksum)
  std::uint32_t dropouts{0};       // simulator dropouts: no line written
  std::uint32_t garbage_bytes{0};  // garbage bytes written
  std::uint32_t bad_checksums{0};
  std::uint32_t overflow_bytes{0};  // bytes lost because the reader was too slow
};

class SimSerialFluxgate final : public hal::SerialPort {
 public:
  static constexpr std::size_t kBuffer = 1024;

  explicit SimSerialFluxgate(const SimSerialConfig& config) noexcept;

  // The instrument outputs the sample as one line (or nothing on a dropout).
  void transmit(const SimSample& s) noexcept;

  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n_read,
                   std::uint32_t timeout_us) noexcept override;
  // Commands to the instrument are accepted and ignored.
  hal::Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept override;

  const SimSerialInjected& injected() const noexcept { return injected_; }
  std::size_t buffered() const noexcept { return wire_.size(); }

 private:
  void put(std::uint8_t b) noexcept;

  SimSerialConfig config_;
  AsciiLineDecoder encoder_;
  Xoshiro256 garbage_rng_;
  Xoshiro256 checksum_rng_;
  SimSerialInjected injected_{};
  SerialWire<kBuffer> wire_;
};

// ---------------------------------------------------------------- SBG INS on CAN

struct SimSbgFaults {
  double corrupt_probability{0};  // per frame: DLC truncated (decoder: malformed)
  double gap_start_s{std::numeric_limits<double>::infinity()};  // no frames in [start, start+len)
  double gap_length_s{0};
  double invalid_start_s{std::numeric_limits<double>::infinity()};  // attitude invalid window
  double invalid_length_s{0};
  double duplicate_probability{0};  // per epoch: a frame received twice, or the epoch repeated
};

// Where the simulated platform is (the INS position messages; a geomagnetic model's input).
// Default: a plausible survey site in the Bavarian Alpine foreland.
struct SimSite {
  double lat_deg{47.9};
  double lon_deg{11.3};
  double altitude_m{600.0};   // above mean sea level
  double undulation_m{47.4};  // geoid above the WGS84 ellipsoid there (EGM2008, rounded)
};

struct SimSbgConfig {
  double rate_hz{100};                        // output rate (one epoch per period, from t = 0)
  std::uint32_t can_latency_us{500};          // CAN receive time - epoch time
  std::uint32_t ins_clock_offset_us{123456};  // INS time since power-on at host time 0
  double accuracy_rad{2.6e-4};                // reported 1-sigma (about 0.015 deg)
  std::uint32_t status01_every{10};           // STATUS_01 every N epochs
  // EKF_POS + EKF_ALTITUDE after the attitude frames of every N-th epoch (0: none), of a platform
  // that starts at `site` and moves at ground_speed_m_s along its true heading (0: it stays).
  std::uint32_t position_every{10};
  SimSite site{};
  double ground_speed_m_s{0};
  sbg::CanIds ids{};
  SimSbgFaults faults{};
  std::uint64_t seed{3};
};

struct SimSbgInjected {
  std::uint32_t epochs{0};          // epochs with attitude frames sent
  std::uint32_t gap_epochs{0};      // epochs not sent (gap)
  std::uint32_t invalid_epochs{0};  // epochs sent with attitude invalid
  // Corrupted frames queued: a repeated epoch's count again, a frame received twice once (the
  // decoder counts its copy as a duplicate).
  std::uint32_t corrupted_frames{0};
  std::uint32_t corrupted_epochs{0};  // epochs whose attitude sample the decoder cannot produce
  // Attitude frames queued intact after a corrupted EKF_INFO (time) frame of their epoch: the
  // decoder sees an attitude frame without its time (its missing_time counter); a repeated
  // epoch's counts again.
  std::uint32_t untimed_epochs{0};
  std::uint32_t duplicated_frames{0};  // frames received twice back to back (one copy each)
  std::uint32_t repeated_epochs{0};    // epochs sent twice
  // Of those, the epochs the decoder turned into a sample the first time: the repeat is a
  // duplicate epoch. The others fail again as the first time did.
  std::uint32_t repeated_sampled_epochs{0};
  std::uint32_t frames{0};           // frames queued
  std::uint32_t overflow_frames{0};  // frames lost because the bus queue was full
  std::uint32_t sent_by_host{0};     // frames the host sent to the INS (ignored)
  std::uint32_t position_fixes{0};   // epochs with position frames sent
  // Position frames truncated (corrupt_probability, a stream of their own so that the attitude
  // frames' faults stay as they were): the decoder's position malformed.
  std::uint32_t corrupted_position_frames{0};
};

class SimSbgIns final : public hal::CanBus {
 public:
  static constexpr std::size_t kQueue = 64;

  SimSbgIns(Simulator& sim, const SimSbgConfig& config) noexcept;

  // Emits every epoch with epoch time <= t_s (simulation time). Host timestamps of the frames
  // are time.host_us(epoch time) + CAN latency.
  void run_until(double t_s, const HostTimeMap& time = {}) noexcept;

  hal::Status receive(hal::CanFrame& out, std::uint32_t timeout_us) noexcept override;
  hal::Status send(const hal::CanFrame& frame) noexcept override;

  const SimSbgInjected& injected() const noexcept { return injected_; }
  double period_s() const noexcept { return 1.0 / config_.rate_hz; }
  // The platform's true position at the last epoch emitted (the site until one moved it).
  double lat_deg() const noexcept;
  double lon_deg() const noexcept;

 private:
  void emit_epoch(std::uint64_t k, const HostTimeMap& time) noexcept;
  void emit_position(std::uint64_t t_rx_us) noexcept;
  // Truncates `f` below min_dlc with the corruption probability; true if it did.
  bool corrupt(hal::CanFrame& f, std::uint8_t min_dlc) noexcept;
  void push(const hal::CanFrame& f) noexcept;

  Simulator& sim_;
  SimSbgConfig config_;
  Xoshiro256 corrupt_rng_;
  Xoshiro256 duplicate_rng_;
  Xoshiro256 position_rng_;
  SimSbgInjected injected_{};
  double north_m_{0};  // travelled from the site
  double east_m_{0};
  std::uint64_t next_epoch_{0};
  std::array<hal::CanFrame, kQueue> queue_{};
  std::size_t head_{0};
  std::size_t count_{0};
};

// ---------------------------------------------------------------- the rig

enum class MagLink : std::uint8_t { kSpi, kSerial };

struct SimRigConfig {
  MagLink link{MagLink::kSpi};
  SimAds131Config adc{};
  SimSerialConfig serial{};
  SimSbgConfig ins{};
  // INS frames are delivered as on real hardware: with the magnetometer sample at t come the
  // frames received by then, i.e. of the epochs up to t + ins_lead_s - CAN latency. So the epoch
  // that brackets a sample arrives after it and the consumer must wait for it (the delayed fusion
  // horizon of core::SamplePipeline). A positive lead delivers the INS early (ahead of reality).
  double ins_lead_s{0.0};
  HostTimeMap time{};  // clock jump fault: time.jump_at_s, time.jump_us
};

// Owns the three devices and the clock; step() advances the simulation by one magnetometer
// sample: the INS frames received by t + lead, then the conversion (SPI) or the line (serial).
class SimRig {
 public:
  SimRig(Simulator& sim, const SimRigConfig& config) noexcept;

  bool step() noexcept;  // false when the scenario is finished

  // Host timestamp of simulation time t_s (including an injected clock jump).
  std::uint64_t host_us(double t_s) const noexcept { return config_.time.host_us(t_s); }

  SimClock& clock() noexcept { return clock_; }
  SimAds131Device& adc() noexcept { return adc_; }
  SimSerialFluxgate& serial() noexcept { return serial_; }
  SimSbgIns& ins() noexcept { return ins_; }
  const SimSample& last() const noexcept { return last_; }
  const SimRigConfig& config() const noexcept { return config_; }
  Simulator& simulator() noexcept { return sim_; }
  std::uint32_t clock_jumps_injected() const noexcept { return jumps_; }
  std::uint32_t steps() const noexcept { return steps_; }

 private:
  Simulator& sim_;
  SimRigConfig config_;
  SimClock clock_;
  SimAds131Device adc_;
  SimSerialFluxgate serial_;
  SimSbgIns ins_;
  SimSample last_{};
  std::uint32_t jumps_{0};
  std::uint32_t steps_{0};
  bool jumped_{false};
};

}  // namespace magvec::drivers::sim
