// magvecd configuration (TOML, parsed with toml++): devices, rates, CAN IDs, ADC transfer
// coefficients, calibration mode and thresholds, LCM URL and channels, state directory.
// The annotated example is host/daemon/magvecd.toml; default_config_text() is the embedded default
// (the simulated rig), so `magvecd --sim` needs no file.
// Everything the pipeline's output depends on is derived from the config *text*: the daemon
// publishes that text in the SESSION_START pipeline event and `magvec replay` parses it with
// parse_config(), so a replay builds exactly the live pipeline.
#pragma once

#include <array>
#include <cmath>
#include <cstdint>
#include <limits>
#include <stdexcept>
#include <string>

#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/g882.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/pipeline/scalar_aligner.hpp"

namespace magvec::host::daemon {

class ConfigError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct LcmChannels {
  std::string raw_mag{"MAGVEC_RAW_MAG"};
  std::string raw_mag_batch{"MAGVEC_RAW_MAG_BATCH"};  // lcm.raw_batch > 1
  std::string attitude{"MAGVEC_ATTITUDE"};
  std::string pipeline{"MAGVEC_PIPELINE"};
  std::string output{"MAGVEC_OUTPUT"};
  std::string cal_state{"MAGVEC_CAL_STATE"};
  std::string health{"MAGVEC_HEALTH"};
  std::string command{"MAGVEC_CMD"};
  std::string reply{"MAGVEC_CMD_REPLY"};
};

struct MagnetometerConfig {
  std::string link{"spi"};  // spi (ADS131M04 + DRDY) | serial (ASCII fluxgate)
  double rate_hz{100};
  std::string spi_device{"/dev/spidev0.0"};
  std::uint32_t spi_speed_hz{4'000'000};
  std::string drdy_chip{"/dev/gpiochip0"};
  unsigned drdy_line{0};
  std::string serial_device{"/dev/ttyUSB0"};
  std::uint32_t serial_baud{115200};
  std::uint32_t serial_reconnect_ms{1000};
  std::uint32_t serial_latency_us{0};
  // Fluxgate electronics 100 uT/V into the ADC at gain 1: +/-120 uT range (as `magvec run`).
  drivers::Ads131FluxgateConfig adc{{0, 1, 2}, {1e5, 1e5, 1e5}, {0, 0, 0, 0}, 64};
};

struct InsConfig {
  std::string can_interface{"can0"};
  double rate_hz{100};
  std::uint32_t latency_comp_us{500};  // subtracted from CAN receive times
  // Delayed fusion horizon: how long (magnetometer time) a sample waits for the INS samples that
  // bracket it before its attitude is extrapolated and flagged.
  std::uint32_t fusion_horizon_us{50'000};
  // Magnetometer time stamp minus INS time of its attitude; nan: the calibration's (cal.json).
  double time_offset_s{std::numeric_limits<double>::quiet_NaN()};
  bool require_attitude_valid{true};
  drivers::sbg::CanIds ids{};
};

// A total-field magnetometer on a serial line (real mode): each magnetometer sample takes the
// scalar reading at its own time as F (pipeline::ScalarAligner); calibration.reference_field_nT
// is then only the fallback for samples without a reading near them.
struct ScalarConfig {
  bool enabled{false};
  std::string format{"g882"};  // Geometrics G-882 ASCII output (drivers/codecs g882.hpp)
  std::string device{"/dev/ttyUSB1"};
  std::uint32_t baud{9600};
  std::uint32_t reconnect_ms{1000};
  std::uint32_t latency_us{50'000};  // subtracted from line receive times
  drivers::G882LineConfig line{};
  pipeline::ScalarAlignerConfig align{};  // fallback_nT: calibration.reference_field_nT
};

struct CalibrationConfig {
  std::string mode{"li"};  // li | ekf | vector-ekf | none
  bool start_on_boot{true};
  bool auto_accept{true};  // persist a calibration as soon as the loop validated and applied it
  // Known noise figures (magnetometer per axis, INS per angle, 1-sigma); nan: the calibrator
  // estimates them from its data, and validation judges each candidate by its estimate.
  double noise_nT{std::numeric_limits<double>::quiet_NaN()};
  double attitude_noise_deg{std::numeric_limits<double>::quiet_NaN()};
  std::uint32_t validation_samples{200};
  double validation_max_rms_factor{3};
  double validation_min_rms_nT{1};
  bool validate_against_active{true};
  bool ekf_align{true};
  std::uint32_t li_min_samples{300};  // li: kept (decimated) samples before solving
  // Scalar reference |h| for real devices (nan: none; the simulated rig provides its own).
  double reference_field_nT{std::numeric_limits<double>::quiet_NaN()};
  // Real devices with neither a scalar magnetometer nor reference_field_nT: F from this
  // geomagnetic model at the INS position (position_reference.hpp); "none": no reference then.
  std::string reference_model{"wmm2025"};
  // The calibrator's solve runs on a worker thread (the result is installed, and logged, as a
  // SOLVE_RESULT pipeline event), so no sample waits for it; false: inline, as on the MCU.
  bool solve_on_worker{true};
};

struct SimConfig {
  std::string scenario{"li2023"};  // li2023 (random attitudes) | survey
  std::uint64_t seed{1};
  std::uint32_t samples_per_attitude{10};
  // Host pacing of the simulated devices. 0: one wake-up per conversion at its due time (a
  // data-ready driven ADC). P > 0: one wake-up every P us that delivers every conversion due by
  // then (a device read in blocks: FIFO, serial burst). Same samples, same order, same outputs.
  std::uint32_t wake_period_us{0};
  // Injected faults, the syntax of `magvec run --faults` (host/hil/fault_spec.hpp); empty: none.
  std::string faults{};
};

struct DaemonSection {
  std::string state_dir{"/var/lib/magvecd"};
  std::string log_level{"info"};
  bool realtime{true};
  int rt_priority{20};
  double health_period_s{1.0};
  double status_period_s{1.0};
};

struct LcmConfig {
  // Data: raw inputs, pipeline events, outputs, state, health (publish only: the daemon never
  // receives its own publications).
  std::string url{"udpm://239.255.76.67:7667?ttl=0"};
  // Commands and replies (`magvec ctl`); empty: derived from url (command_url_for).
  std::string command_url{};
  // Raw magnetometer samples per message: 1, one mag_sample per sample on channels.raw_mag (the
  // format of every earlier log); N > 1, mag_sample_batch messages of up to N samples on
  // channels.raw_mag_batch (fewer sends per sample; a batch is published, and its samples fed,
  // when it is full or before any other input event). The outputs stay one per sample.
  std::uint32_t raw_batch{1};
  LcmChannels channels{};
};

// Magnetometer samples the scalar aligner holds (devices.scalar.horizon_us at the rate must fit).
inline constexpr std::size_t kScalarQueueSamples = 1024;

// Largest lcm.raw_batch: a batch of 1000 samples is 60 kB, under one UDP datagram's 64 kB.
inline constexpr std::uint32_t kMaxRawBatch = 1000;

// The command URL of a daemon on `url` when lcm.command_url is empty: a udpm URL with the port
// + 1 (another multicast port, so the daemon's command socket never receives the data traffic);
// any other provider: url itself.
std::string command_url_for(const std::string& url);
// lcm.command_url, or the one derived from lcm.url.
std::string command_url(const LcmConfig& c);

struct Config {
  DaemonSection daemon{};
  LcmConfig lcm{};
  MagnetometerConfig magnetometer{};
  InsConfig ins{};
  ScalarConfig scalar{};
  CalibrationConfig calibration{};
  SimConfig sim{};
};

// Real mode takes F from the geomagnetic model at the INS position: no scalar magnetometer, no
// configured reference_field_nT, and reference_model not "none".
inline bool uses_model_reference(const Config& c) noexcept {
  return !c.scalar.enabled && !std::isfinite(c.calibration.reference_field_nT) &&
         c.calibration.reference_model != "none";
}

// Parses and validates; throws ConfigError naming `source`, the key and the problem.
// Unknown keys are errors (a typo must not silently fall back to a default).
Config parse_config(const std::string& text, const std::string& source);
// Reads a file (ConfigError if it cannot be read) and parses it.
std::string read_config_text(const std::string& path);

// The embedded default configuration (simulated rig, LCM udpm ttl=0, li calibration); it states
// every key with the value a missing key gets (tested).
const std::string& default_config_text();

}  // namespace magvec::host::daemon
