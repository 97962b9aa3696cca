// Simulated devices speaking the real devices' bytes; see sim_devices.hpp.
#include "magvec/drivers/sim/sim_devices.hpp"

#include <cmath>

namespace magvec::drivers::sim {
namespace {

// Distinct stream identifiers so that device faults never share draws with the simulator.
constexpr std::uint64_t kStreamAdcCrc = 0xADC0C4C0ULL;
constexpr std::uint64_t kStreamAdcSat = 0xADC05A70ULL;
constexpr std::uint64_t kStreamAdcReset = 0xADC0E5E7ULL;
constexpr std::uint64_t kStreamSerialGarbage = 0x5E41A16BULL;
constexpr std::uint64_t kStreamSerialChecksum = 0x5E41AC5CULL;
constexpr std::uint64_t kStreamInsCorrupt = 0x1A5C0BB7ULL;
constexpr std::uint64_t kStreamInsDuplicate = 0x1A5D0B1EULL;
constexpr std::uint64_t kStreamInsPosition = 0x9051710EULL;
// Mean Earth radius: the simulated platform's metres to degrees (a sphere is plenty for a
// reference-field input).
constexpr double kEarthRadius_m = 6'371'000.0;
// A gateway forwards an epoch again after its store-and-forward delay.
constexpr std::uint64_t kEpochRepeatDelayUs = 1000;

bool in_window(double t, double start, double length) noexcept {
  return t >= start && t < start + length;
}

}  // namespace

// ---------------------------------------------------------------- SimAds131Device

SimAds131Device::SimAds131Device(const SimAds131Config& config) noexcept
    : config_(config),
      crc_rng_(device_stream_seed(config.seed, kStreamAdcCrc)),
      sat_rng_(device_stream_seed(config.seed, kStreamAdcSat)),
      reset_rng_(device_stream_seed(config.seed, kStreamAdcReset)),
      pending_response_(ads131::kStatusResetValue) {}

void SimAds131Device::reset_registers() noexcept {
  reset_flag_ = true;
  gain1_ = 0;
  drdy_bits_ = 0;
  pending_is_status_ = true;
}

bool SimAds131Device::stuck_in(const std::array<std::int32_t, ads131::kChannels>& codes) noexcept {
  bool stuck = false;
  for (std::size_t axis = 0; axis < 3; ++axis) {
    const std::int32_t code = codes[config_.transfer.channel_of_axis[axis] & 3u];
    if (code == seen_code_[axis]) {
      if (seen_run_[axis] < 0xFFFFFFFFu) ++seen_run_[axis];
    } else {
      seen_code_[axis] = code;
      seen_run_[axis] = 1;
    }
    stuck = stuck ||
            (config_.transfer.stuck_count != 0 && seen_run_[axis] >= config_.transfer.stuck_count);
  }
  return stuck;
}

std::int32_t SimAds131Device::code_from_nT(double nT, double nT_per_volt, std::uint8_t gain_code,
                                           bool* clipped) noexcept {
  const double code = std::round(nT / nT_per_volt * ads131::gain_from_code(gain_code) /
                                 ads131::kVref * ads131::kCountsFullScale);
  bool clip = false;
  std::int32_t c = 0;
  if (!std::isfinite(code) || code >= static_cast<double>(ads131::kCodePositiveFullScale)) {
    c = ads131::kCodePositiveFullScale;
    clip = !std::isfinite(code) || code > static_cast<double>(ads131::kCodePositiveFullScale);
  } else if (code <= static_cast<double>(ads131::kCodeNegativeFullScale)) {
    c = ads131::kCodeNegativeFullScale;
    clip = code < static_cast<double>(ads131::kCodeNegativeFullScale);
  } else {
    c = static_cast<std::int32_t>(code);
  }
  if (clipped != nullptr) *clipped = clip;
  return c;
}

// Channel 3 carries the sensor temperature through the transfer the driver inverts
// (T = offset_degC + volts * degC_per_volt, ads131_fluxgate.hpp), or full scale while the sensor
// is open. Unused when the temperature channel is disabled (the channel keeps its zero code).
void SimAds131Device::convert_temperature(const SimSample& s) noexcept {
  const Ads131TemperatureConfig& tc = config_.transfer.temperature;
  if (!tc.enabled) return;
  const SimAds131Faults& fa = config_.faults;
  if (in_window(s.t_s, fa.temperature_open_start_s, fa.temperature_open_length_s)) {
    codes_[kAds131TemperatureChannel] = ads131::kCodePositiveFullScale;
    ++injected_.temperature_open;
    return;
  }
  const auto gain_code = static_cast<std::uint8_t>(
      (static_cast<unsigned>(gain1_) >> (4u * kAds131TemperatureChannel)) & 7u);
  bool clip = false;
  // code_from_nT's arithmetic is the generic volts -> code: value / (value per volt).
  codes_[kAds131TemperatureChannel] =
      code_from_nT(s.temperature_c - tc.offset_degC, tc.degC_per_volt, gain_code, &clip);
}

void SimAds131Device::convert(const SimSample& s, std::uint64_t t_us) noexcept {
  ++injected_.conversions;
  const SimAds131Faults& fa = config_.faults;
  if (draw(reset_rng_, fa.reset_probability)) {
    reset_registers();
    ++injected_.resets;
  }
  const bool dropout = !s.m_nT.allFinite();
  // Draw the saturation decision for every conversion so the stream does not depend on dropouts.
  const bool saturate = draw(sat_rng_, fa.saturation_probability);
  const std::uint64_t sat_pick = sat_rng_.next();
  const bool stuck = in_window(s.t_s, fa.stuck_start_s, fa.stuck_length_s);
  const std::uint8_t stuck_ch = config_.transfer.channel_of_axis[fa.stuck_axis % 3u] & 3u;
  const std::int32_t held = codes_[stuck_ch];
  if (stuck) ++injected_.stuck_conversions;
  if (dropout) {
    drdy_bits_ = 0;  // no new data: the codes of the previous conversion stay in the registers
    ++injected_.not_fresh;
  } else {
    bool any_clip = false;
    for (std::size_t axis = 0; axis < 3; ++axis) {
      const std::uint8_t ch = config_.transfer.channel_of_axis[axis] & 3u;
      bool clip = false;
      // The PGA gain the device has (GAIN1), not the configured one: they differ after a reset.
      const auto gain_code =
          static_cast<std::uint8_t>((static_cast<unsigned>(gain1_) >> (4u * ch)) & 7u);
      codes_[ch] = code_from_nT(s.m_nT[static_cast<Eigen::Index>(axis)],
                                config_.transfer.nT_per_volt[axis], gain_code, &clip);
      any_clip = any_clip || clip;
    }
    if (any_clip) ++injected_.range_clipped;
    const std::uint8_t sat_ch =
        config_.transfer.channel_of_axis[static_cast<std::size_t>(sat_pick % 3)] & 3u;
    if (saturate && !(stuck && sat_ch == stuck_ch)) {  // a stuck channel stays stuck
      codes_[sat_ch] =
          (sat_pick & 8u) != 0 ? ads131::kCodePositiveFullScale : ads131::kCodeNegativeFullScale;
      ++injected_.saturated;
    }
    if (stuck) codes_[stuck_ch] = held;
    convert_temperature(s);
    drdy_bits_ = ads131::kStatusDrdyMask;
  }
  if (edge_count_ == kEdgeQueue) {  // the host did not keep up: the oldest edge is lost
    edge_head_ = (edge_head_ + 1) % kEdgeQueue;
    --edge_count_;
    ++missed_edges_;
  }
  edges_[(edge_head_ + edge_count_) % kEdgeQueue] = hal::EdgeEvent{t_us, hal::Edge::kFalling};
  ++edge_count_;
}

hal::Status SimAds131Device::wait_edge(hal::EdgeEvent& out, std::uint32_t /*timeout_us*/) noexcept {
  // Simulated time does not pass inside a call: an empty queue is a timeout whatever the timeout.
  if (edge_count_ == 0) return hal::Status::kTimeout;
  out = edges_[edge_head_];
  edge_head_ = (edge_head_ + 1) % kEdgeQueue;
  --edge_count_;
  return hal::Status::kOk;
}

hal::Status SimAds131Device::transfer(std::span<const std::uint8_t> tx,
                                      std::span<std::uint8_t> rx) noexcept {
  if (tx.size() != rx.size() || tx.size() < ads131::kWordBytes) {
    ++injected_.bad_commands;
    return hal::Status::kInvalidArgument;
  }
  ++injected_.frames;
  const std::uint16_t cmd = ads131::decode_word16(tx.data());
  // Output frame: the response to the PREVIOUS command plus the latest conversion.
  std::uint16_t response = pending_response_;
  if (pending_is_status_) {
    response = static_cast<std::uint16_t>(ads131::kStatusWlength24 | drdy_bits_ |
                                          (reset_flag_ ? ads131::kStatusReset : 0u));
  }
  const bool data_frame = pending_is_status_;
  ads131::Frame out{};
  ads131::encode_response_frame(response, codes_, out);
  if (data_frame) drdy_bits_ = 0;  // reading the data clears the DRDY bits until the next one
  // The host reads data with NULL; the data in a frame that carries a command (RESET and WREG
  // while initialising) are not decoded, so faults and counts apply to NULL frames only.
  if (data_frame && cmd == ads131::kCmdNull) {
    if (draw(crc_rng_, config_.faults.crc_error_probability)) {
      const std::size_t byte = static_cast<std::size_t>(below(crc_rng_, ads131::kFrameBytes - 3));
      const auto flip = static_cast<std::uint8_t>(1u + below(crc_rng_, 255));
      out[byte] = static_cast<std::uint8_t>(out[byte] ^ flip);  // CRC-16 detects any 1-byte error
      ++injected_.crc_corrupted;
    } else {
      bool full_scale = false;
      for (std::size_t axis = 0; axis < 3; ++axis) {
        const std::int32_t c = codes_[config_.transfer.channel_of_axis[axis] & 3u];
        full_scale = full_scale || c == ads131::kCodePositiveFullScale ||
                     c == ads131::kCodeNegativeFullScale;
      }
      if (full_scale) ++injected_.saturated_frames;
      if ((response & ads131::kStatusReset) != 0) ++injected_.reset_frames;
      if (stuck_in(codes_)) ++injected_.stuck_frames;
    }
  }
  const std::size_t n = rx.size() < out.size() ? rx.size() : out.size();
  for (std::size_t i = 0; i < rx.size(); ++i)
    rx[i] = i < n ? out[i] : std::uint8_t{0};

  // The command of this frame; its response goes into the next frame.
  pending_is_status_ = false;
  if (cmd == ads131::kCmdReset) {
    reset_registers();
    seen_code_.fill(0);  // the driver's init() restarts its stuck detector
    seen_run_.fill(0);
    pending_is_status_ = false;
    pending_response_ = ads131::kResetResponse;
  } else if ((cmd & 0xE000u) == 0x6000u) {  // WREG
    const auto address = static_cast<std::uint8_t>((cmd >> 7) & 0x3Fu);
    const auto count = static_cast<std::uint8_t>((cmd & 0x7Fu) + 1u);
    if (tx.size() >= 2 * ads131::kWordBytes) {
      const std::uint16_t value = ads131::decode_word16(tx.data() + ads131::kWordBytes);
      if (address == ads131::kRegGain1) gain1_ = value;
      if (address == ads131::kRegMode && (value & ads131::kModeReset) == 0) reset_flag_ = false;
    }
    pending_response_ = ads131::wreg_response(address, count);
  } else {
    if (cmd != ads131::kCmdNull)
      ++injected_.bad_commands;  // not modelled: answered with STATUS like NULL
    pending_is_status_ = true;
  }
  return hal::Status::kOk;
}

// ---------------------------------------------------------------- SimSerialFluxgate

SimSerialFluxgate::SimSerialFluxgate(const SimSerialConfig& config) noexcept
    : config_(config),
      encoder_(config.line),
      garbage_rng_(device_stream_seed(config.seed, kStreamSerialGarbage)),
      checksum_rng_(device_stream_seed(config.seed, kStreamSerialChecksum)) {}

void SimSerialFluxgate::put(std::uint8_t b) noexcept {
  if (!wire_.put(b)) ++injected_.overflow_bytes;
}

void SimSerialFluxgate::transmit(const SimSample& s) noexcept {
  const bool garbage = draw(garbage_rng_, config_.faults.garbage_probability);
  const std::uint64_t garbage_len =
      1 + below(garbage_rng_,
                config_.faults.garbage_max_bytes > 0 ? config_.faults.garbage_max_bytes : 1);
  const bool bad_checksum = draw(checksum_rng_, config_.faults.bad_checksum_probability);
  const std::uint64_t digit_pick = checksum_rng_.next();
  if (garbage) {
    for (std::uint64_t i = 0; i < garbage_len; ++i)
      put(static_cast<std::uint8_t>('a' + below(garbage_rng_, 26)));
    injected_.garbage_bytes += static_cast<std::uint32_t>(garbage_len);
  }
  if (!s.m_nT.allFinite()) {
    ++injected_.dropouts;
    return;
  }
  std::array<char, AsciiLineDecoder::kMaxLine + 8> line{};
  const std::array<double, 3> m{s.m_nT.x(), s.m_nT.y(), s.m_nT.z()};
  const std::size_t n = encoder_.encode(m, config_.with_checksum, line);
  if (n == 0) return;
  if (bad_checksum && config_.with_checksum && n >= 5) {
    // "...*HH\r\n": replace the low hex digit by another one.
    static constexpr char kHex[] = "0123456789ABCDEF";
    char& d = line[n - 3];
    int v = d >= 'A' ? d - 'A' + 10 : d - '0';
    v = (v + 1 + static_cast<int>(digit_pick % 15)) % 16;
    d = kHex[v];
    ++injected_.bad_checksums;
  }
  for (std::size_t i = 0; i < n; ++i)
    put(static_cast<std::uint8_t>(line[i]));
  ++injected_.lines;
}

hal::Status SimSerialFluxgate::read(std::span<std::uint8_t> buf, std::size_t& n_read,
                                    std::uint32_t /*timeout_us*/) noexcept {
  return wire_.read(buf, n_read);
}

hal::Status SimSerialFluxgate::write(std::span<const std::uint8_t> data,
                                     std::size_t& n_written) noexcept {
  n_written = data.size();
  return hal::Status::kOk;
}

// ---------------------------------------------------------------- SimSbgIns

SimSbgIns::SimSbgIns(Simulator& sim, const SimSbgConfig& config) noexcept
    : sim_(sim),
      config_(config),
      corrupt_rng_(device_stream_seed(config.seed, kStreamInsCorrupt)),
      duplicate_rng_(device_stream_seed(config.seed, kStreamInsDuplicate)),
      position_rng_(device_stream_seed(config.seed, kStreamInsPosition)) {}

double SimSbgIns::lat_deg() const noexcept {
  return config_.site.lat_deg + north_m_ / kEarthRadius_m * 180.0 / core::kPi<double>;
}

double SimSbgIns::lon_deg() const noexcept {
  const double c = std::cos(config_.site.lat_deg * core::kPi<double> / 180.0);
  return config_.site.lon_deg + east_m_ / (kEarthRadius_m * c) * 180.0 / core::kPi<double>;
}

void SimSbgIns::emit_position(std::uint64_t t_rx_us) noexcept {
  std::array<hal::CanFrame, 2> frames{
      sbg::encode_ekf_pos(lat_deg(), lon_deg(), config_.ids),
      sbg::encode_ekf_altitude(config_.site.altitude_m, config_.site.undulation_m, config_.ids)};
  for (hal::CanFrame& f : frames) {
    f.t_us = t_rx_us;
    const bool hit = draw(position_rng_, config_.faults.corrupt_probability);
    if (hit) {
      f.dlc = static_cast<std::uint8_t>(position_rng_.next() % 6);  // below both messages' length
      for (std::size_t i = f.dlc; i < f.data.size(); ++i)
        f.data[i] = 0;
      ++injected_.corrupted_position_frames;
    }
    push(f);
  }
  ++injected_.position_fixes;
}

bool SimSbgIns::corrupt(hal::CanFrame& f, std::uint8_t min_dlc) noexcept {
  const bool hit = draw(corrupt_rng_, config_.faults.corrupt_probability);
  const std::uint64_t pick = corrupt_rng_.next();
  if (!hit) return false;
  f.dlc = static_cast<std::uint8_t>(pick % min_dlc);  // shorter than the message requires
  for (std::size_t i = f.dlc; i < f.data.size(); ++i)
    f.data[i] = 0;
  return true;
}

void SimSbgIns::push(const hal::CanFrame& f) noexcept {
  if (count_ == kQueue) {
    ++injected_.overflow_frames;
    return;
  }
  queue_[(head_ + count_) % kQueue] = f;
  ++count_;
  ++injected_.frames;
}

void SimSbgIns::emit_epoch(std::uint64_t k, const HostTimeMap& time) noexcept {
  const double t = static_cast<double>(k) / config_.rate_hz;
  const SimSbgFaults& fa = config_.faults;
  // The platform moves whether or not the INS is heard.
  if (config_.ground_speed_m_s != 0 && k > 0) {
    // Along the true heading (aerospace yaw, clockwise from north) over one epoch period.
    const double yaw = core::ypr_from_r_bn(sim_.true_attitude_at(t)).yaw;
    const double d = config_.ground_speed_m_s / config_.rate_hz;
    north_m_ += d * std::cos(yaw);
    east_m_ += d * std::sin(yaw);
  }
  if (in_window(t, fa.gap_start_s, fa.gap_length_s)) {
    ++injected_.gap_epochs;
    return;
  }
  const auto t_epoch_us = static_cast<std::int64_t>(std::llround(t * 1e6));
  const std::uint64_t t_rx = time.host_us(t) + config_.can_latency_us;
  const auto ins_time = static_cast<std::uint32_t>(static_cast<std::uint64_t>(t_epoch_us) +
                                                   config_.ins_clock_offset_us);
  const core::Mat3<double> r_bn = sim_.ins_attitude_at(t);
  const bool invalid = in_window(t, fa.invalid_start_s, fa.invalid_length_s);
  if (invalid) ++injected_.invalid_epochs;
  const std::uint32_t solution =
      invalid
          ? static_cast<std::uint32_t>(sbg::SolutionMode::kVerticalGyro)
          : (static_cast<std::uint32_t>(sbg::SolutionMode::kNavPosition) | sbg::kSolAttitudeValid |
             sbg::kSolHeadingValid | sbg::kSolVelocityValid | sbg::kSolPositionValid);
  const sbg::CanIds& ids = config_.ids;
  // The epoch's frames in bus order, each with the shortest length its message allows.
  struct Slot {
    hal::CanFrame frame;
    bool corrupted;
  };
  std::array<Slot, 6> slots{};
  std::size_t n = 0;
  auto add = [&](hal::CanFrame f, std::uint8_t min_dlc) {
    f.t_us = t_rx;
    const bool hit = corrupt(f, min_dlc);
    slots[n++] = Slot{f, hit};
  };
  if (config_.status01_every != 0 && k % config_.status01_every == 0)
    add(sbg::encode_status_01(ins_time, 0, 0, ids), 8);
  const std::size_t time_slot = n;
  add(sbg::encode_ekf_info(ins_time, ids), 4);
  add(sbg::encode_status_03(solution, 0, ids), 6);
  add(sbg::encode_orientation_acc(config_.accuracy_rad, config_.accuracy_rad, config_.accuracy_rad,
                                  ids),
      6);
  const core::YawPitchRoll<double> ypr = core::ypr_from_r_bn(r_bn);
  add(sbg::encode_ekf_euler(ypr.roll, ypr.pitch, ypr.yaw, ids), 6);
  const std::size_t attitude_slot = n;
  add(sbg::encode_ekf_quat(sbg::sbg_quat_from_r_bn(r_bn), ids), 8);
  // Drawn for every epoch so the stream does not depend on the other faults.
  const bool duplicate = draw(duplicate_rng_, fa.duplicate_probability);
  const std::uint64_t pick = duplicate_rng_.next();
  const bool repeat_epoch = duplicate && (pick & 1u) != 0;
  const std::size_t twice =
      duplicate && !repeat_epoch ? static_cast<std::size_t>((pick >> 1) % n) : n;

  const bool time_lost = slots[time_slot].corrupted;
  const bool attitude_lost = slots[attitude_slot].corrupted;
  const int sends = repeat_epoch ? 2 : 1;
  for (int copy = 0; copy < sends; ++copy) {
    for (std::size_t i = 0; i < n; ++i) {
      hal::CanFrame f = slots[i].frame;
      f.t_us += static_cast<std::uint64_t>(copy) * kEpochRepeatDelayUs;
      push(f);
      if (i == twice) push(f);  // the decoder counts the copy as a duplicate, not as malformed
      if (slots[i].corrupted) ++injected_.corrupted_frames;
    }
    if (time_lost && !attitude_lost) ++injected_.untimed_epochs;
  }
  if (config_.position_every != 0 && k % config_.position_every == 0) emit_position(t_rx);
  ++injected_.epochs;
  if (time_lost || attitude_lost) ++injected_.corrupted_epochs;
  if (twice < n) ++injected_.duplicated_frames;
  if (repeat_epoch) {
    ++injected_.repeated_epochs;
    if (!time_lost && !attitude_lost) ++injected_.repeated_sampled_epochs;
  }
}

void SimSbgIns::run_until(double t_s, const HostTimeMap& time) noexcept {
  while (static_cast<double>(next_epoch_) / config_.rate_hz <= t_s) {
    emit_epoch(next_epoch_, time);
    ++next_epoch_;
  }
}

hal::Status SimSbgIns::receive(hal::CanFrame& out, std::uint32_t /*timeout_us*/) noexcept {
  if (count_ == 0) return hal::Status::kTimeout;
  out = queue_[head_];
  head_ = (head_ + 1) % kQueue;
  --count_;
  return hal::Status::kOk;
}

hal::Status SimSbgIns::send(const hal::CanFrame& /*frame*/) noexcept {
  ++injected_.sent_by_host;
  return hal::Status::kOk;
}

// ---------------------------------------------------------------- SimRig

std::uint64_t HostTimeMap::host_us(double t_s) const noexcept {
  std::int64_t t =
      static_cast<std::int64_t>(std::llround(t_s * 1e6)) + static_cast<std::int64_t>(epoch_us);
  if (t_s >= jump_at_s) t += jump_us;
  return t > 0 ? static_cast<std::uint64_t>(t) : 0;
}

SimRig::SimRig(Simulator& sim, const SimRigConfig& config) noexcept
    : sim_(sim), config_(config), adc_(config.adc), serial_(config.serial), ins_(sim, config.ins) {
  clock_.set_us(config.time.host_us(0.0));
}

bool SimRig::step() noexcept {
  SimSample s;
  if (!sim_.next(&s)) return false;
  last_ = s;
  ++steps_;
  if (!jumped_ && s.t_s >= config_.time.jump_at_s && config_.time.jump_us != 0) {
    jumped_ = true;
    ++jumps_;
  }
  if ((s.flags & kFlagNoIns) == 0)  // a scenario without an INS leaves the CAN bus silent
    ins_.run_until(s.t_s + config_.ins_lead_s - 1e-6 * config_.ins.can_latency_us, config_.time);
  const std::uint64_t t_us = host_us(s.t_s);
  if (config_.link == MagLink::kSpi) {
    adc_.convert(s, t_us);
  } else {
    serial_.transmit(s);
  }
  clock_.set_us(t_us);
  return true;
}

}  // namespace magvec::drivers::sim
