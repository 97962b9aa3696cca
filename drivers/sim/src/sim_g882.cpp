// Simulated G-882; see sim_g882.hpp.
#include "magvec/drivers/sim/sim_g882.hpp"

#include <cmath>

namespace magvec::drivers::sim {
namespace {

// Stream identifiers of this device (distinct from sim_devices.cpp's and the simulator's).
constexpr std::uint64_t kStreamNoise = 0xC5A1A901ULL;
constexpr std::uint64_t kStreamGarbage = 0xC5A1A902ULL;
constexpr std::uint64_t kStreamTruncate = 0xC5A1A903ULL;

}  // namespace

SimG882::SimG882(const SimG882Config& config) noexcept
    : config_(config),
      encoder_(config.line),
      noise_(device_stream_seed(config.seed, kStreamNoise)),
      garbage_rng_(device_stream_seed(config.seed, kStreamGarbage)),
      truncate_rng_(device_stream_seed(config.seed, kStreamTruncate)) {}

void SimG882::put(std::uint8_t b) noexcept {
  if (!wire_.put(b)) ++injected_.overflow_bytes;
}

bool SimG882::transmit(const SimSample& s, double* f_nT) noexcept {
  const double period_s = config_.rate_hz > 0 ? 1.0 / config_.rate_hz : 0.1;
  if (next_cycle_s_ < 0) next_cycle_s_ = s.t_s;
  if (s.t_s < next_cycle_s_) return false;
  // The next cycle boundary after this sample (a long gap in the samples skips cycles).
  while (next_cycle_s_ <= s.t_s)
    next_cycle_s_ += period_s;
  // Every stream draws once per cycle, so enabling one fault does not move another.
  const double f = s.h_n_true_nT.norm() + config_.noise_nT * noise_.next();
  const bool garbage = draw(garbage_rng_, config_.faults.garbage_probability);
  const std::uint64_t garbage_len =
      1 + garbage_rng_.next() %
              (config_.faults.garbage_max_bytes > 0 ? config_.faults.garbage_max_bytes : 1);
  const bool truncate = draw(truncate_rng_, config_.faults.truncate_probability);
  if (garbage) {
    for (std::uint64_t i = 0; i < garbage_len; ++i) {
      char c = static_cast<char>('a' + garbage_rng_.next() % 26);
      if (c == config_.line.preamble) c = 'z' == c ? 'y' : 'z';
      put(static_cast<std::uint8_t>(c));
    }
    injected_.garbage_bytes += static_cast<std::uint32_t>(garbage_len);
  }
  std::array<char, G882LineDecoder::kMaxLine + 8> line{};
  const std::size_t n = encoder_.encode(f, config_.signal, line);
  if (n == 0) {
    ++injected_.not_encodable;
    return false;
  }
  const std::size_t sent = truncate ? n / 2 : n;
  for (std::size_t i = 0; i < sent; ++i)
    put(static_cast<std::uint8_t>(line[i]));
  if (truncate) {
    ++injected_.truncated;
    return false;
  }
  ++injected_.lines;
  if (f_nT != nullptr) *f_nT = f;
  return true;
}

hal::Status SimG882::read(std::span<std::uint8_t> buf, std::size_t& n_read,
                          std::uint32_t /*timeout_us*/) noexcept {
  return wire_.read(buf, n_read);
}

hal::Status SimG882::write(std::span<const std::uint8_t> data, std::size_t& n_written) noexcept {
  n_written = data.size();
  return hal::Status::kOk;
}

}  // namespace magvec::drivers::sim
