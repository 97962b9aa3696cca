// SimG882: a simulated Geometrics G-882 cesium magnetometer writing its ASCII output line
// (drivers/codecs g882.hpp) into a hal::SerialPort, one line per cycle (10 Hz by default, as the
// instrument), the reading being the simulator's TRUE total field |h_n| at the cycle's sample
// plus Gaussian noise. The real SerialScalarSource decodes it unchanged.
// Faults, each from its own random stream, counted in injected(): garbage bytes before a line
// (letters, never the preamble or '\n'), a line cut short (its end lost: the next preamble
// restarts the decoder, which counts the cut line as malformed).
// Heap-free, noexcept, deterministic, portable (no OS headers).
#pragma once

#include <array>
#include <cstddef>
#include <cstdint>
#include <span>

#include "magvec/drivers/g882.hpp"
#include "magvec/drivers/sim/random.hpp"
#include "magvec/drivers/sim/serial_wire.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/hal/serial_port.hpp"

namespace magvec::drivers::sim {

struct SimG882Faults {
  double garbage_probability{0};  // per line: 1..garbage_max_bytes letters before it
  std::uint32_t garbage_max_bytes{16};
  double truncate_probability{0};  // per line: only its first half is sent
};

struct SimG882Config {
  G882LineConfig line{};
  double rate_hz{10};          // cycle rate; a line at the first sample of each cycle
  double noise_nT{0.002};      // 1-sigma of the reading (a cesium sensor's few pT)
  std::uint16_t signal{1500};  // channel-0 counts written into every line
  SimG882Faults faults{};
  std::uint64_t seed{3};
};

struct SimG882Injected {
  std::uint32_t lines{0};           // complete lines written
  std::uint32_t garbage_bytes{0};   // garbage bytes written
  std::uint32_t truncated{0};       // lines cut short
  std::uint32_t not_encodable{0};   // cycles whose reading the format cannot hold (none written)
  std::uint32_t overflow_bytes{0};  // bytes lost because the reader was too slow
};

class SimG882 final : public hal::SerialPort {
 public:
  static constexpr std::size_t kBuffer = 1024;

  explicit SimG882(const SimG882Config& config) noexcept;

  // Called with every simulator sample; writes a line when the sample starts a new cycle.
  // Returns true when it wrote one (with f_nT, the reading in the line, before rounding).
  bool transmit(const SimSample& s, double* f_nT = nullptr) noexcept;

  hal::Status read(std::span<std::uint8_t> buf, std::size_t& n_read,
                   std::uint32_t timeout_us) noexcept override;
  // Commands to the counter are accepted and ignored.
  hal::Status write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept override;

  const SimG882Injected& injected() const noexcept { return injected_; }
  std::size_t buffered() const noexcept { return wire_.size(); }

 private:
  void put(std::uint8_t b) noexcept;

  SimG882Config config_;
  G882LineDecoder encoder_;
  Gaussian noise_;
  Xoshiro256 garbage_rng_;
  Xoshiro256 truncate_rng_;
  SimG882Injected injected_{};
  double next_cycle_s_{-1};
  SerialWire<kBuffer> wire_;
};

}  // namespace magvec::drivers::sim
