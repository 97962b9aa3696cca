// SBG CAN codec; format and conventions documented in sbg_can.hpp.
#include "magvec/drivers/sbg_can.hpp"

#include <cmath>

namespace magvec::drivers::sbg {
namespace {

std::uint16_t get_u16(const hal::CanFrame& f, std::size_t off) noexcept {
  return static_cast<std::uint16_t>(f.data[off] | (f.data[off + 1] << 8));
}
std::int16_t get_i16(const hal::CanFrame& f, std::size_t off) noexcept {
  return static_cast<std::int16_t>(get_u16(f, off));
}
std::uint32_t get_u32(const hal::CanFrame& f, std::size_t off) noexcept {
  return static_cast<std::uint32_t>(f.data[off]) |
         (static_cast<std::uint32_t>(f.data[off + 1]) << 8) |
         (static_cast<std::uint32_t>(f.data[off + 2]) << 16) |
         (static_cast<std::uint32_t>(f.data[off + 3]) << 24);
}
void put_u16(hal::CanFrame& f, std::size_t off, std::uint16_t v) noexcept {
  f.data[off] = static_cast<std::uint8_t>(v);
  f.data[off + 1] = static_cast<std::uint8_t>(v >> 8);
}
void put_u32(hal::CanFrame& f, std::size_t off, std::uint32_t v) noexcept {
  for (std::size_t i = 0; i < 4; ++i)
    f.data[off + i] = static_cast<std::uint8_t>(v >> (8 * i));
}
std::int16_t to_i16(double v) noexcept {
  if (!std::isfinite(v)) return 0;
  const double r = std::round(v);
  if (r > 32767.0) return 32767;
  if (r < -32768.0) return -32768;
  return static_cast<std::int16_t>(r);
}
std::int32_t get_i32(const hal::CanFrame& f, std::size_t off) noexcept {
  return static_cast<std::int32_t>(get_u32(f, off));
}
std::int32_t to_i32(double v) noexcept {
  if (!std::isfinite(v)) return 0;
  const double r = std::round(v);
  if (r > 2147483647.0) return 2147483647;
  if (r < -2147483648.0) return -2147483647 - 1;
  return static_cast<std::int32_t>(r);
}
std::uint16_t to_u16(double v) noexcept {
  if (!std::isfinite(v) || v <= 0) return 0;
  const double r = std::round(v);
  return r > 65535.0 ? std::uint16_t{65535} : static_cast<std::uint16_t>(r);
}
hal::CanFrame make_frame(std::uint32_t id, std::uint8_t dlc) noexcept {
  hal::CanFrame f;
  f.id = id;
  f.dlc = dlc;
  return f;
}
constexpr double kPi = core::kPi<double>;

}  // namespace

core::Mat3<double> r_bn_from_sbg_quat(const std::array<double, 4>& q) noexcept {
  const core::Quat<double> q_ned_frd(q[0], q[1], q[2], q[3]);
  const core::Mat3<double> c_ned_frd = q_ned_frd.normalized().toRotationMatrix();
  const core::Mat3<double> p = core::enu_ned_swap<double>();
  return p * c_ned_frd.transpose() * p;
}

std::array<double, 4> sbg_quat_from_r_bn(const core::Mat3<double>& r_bn) noexcept {
  const core::Mat3<double> p = core::enu_ned_swap<double>();
  const core::Mat3<double> c_ned_frd = (p * r_bn * p).transpose();
  core::Quat<double> q(c_ned_frd);
  q.normalize();
  if (q.w() < 0) q.coeffs() = -q.coeffs();
  return {q.w(), q.x(), q.y(), q.z()};
}

void CanDecoder::emit(const core::Mat3<double>& r_bn, std::uint64_t t_rx_us) noexcept {
  const core::Quat<double> q_nb = core::quat_from_r_bn(r_bn);
  sample_.t_us = t_rx_us;
  sample_.t_ins_us = raw_.ekf_time_us;
  sample_.q_nb = {q_nb.w(), q_nb.x(), q_nb.y(), q_nb.z()};
  for (std::size_t i = 0; i < 3; ++i)
    sample_.sigma_rad[i] = raw_.accuracy[i] * kAngleScale;
  std::uint32_t flags = 0;
  if (status_known_) {
    flags |= hal::kAttStatusKnown;
    if ((raw_.solution_status & kSolAttitudeValid) != 0) flags |= hal::kAttAttitudeValid;
    if ((raw_.solution_status & kSolHeadingValid) != 0) flags |= hal::kAttHeadingValid;
  }
  if (accuracy_known_) flags |= hal::kAttAccuracyKnown;
  sample_.flags = flags;
  sample_.solution_mode = static_cast<std::uint8_t>(raw_.solution_status & kSolutionModeMask);
  time_fresh_ = false;
  have_sample_ = true;
  ++counters_.samples;
}

bool CanDecoder::same_as_last(const hal::CanFrame& f) noexcept {
  bool same = have_last_frame_ && f.id == last_frame_.id && f.dlc == last_frame_.dlc;
  for (std::size_t i = 0; same && i < f.dlc && i < f.data.size(); ++i)
    same = f.data[i] == last_frame_.data[i];
  last_frame_ = f;
  have_last_frame_ = true;
  return same;
}

bool CanDecoder::epoch_already_sampled() noexcept {
  if (!have_sample_ || raw_.ekf_time_us != sample_.t_ins_us) return false;
  time_fresh_ = false;
  ++counters_.duplicates;
  return true;
}

FeedResult CanDecoder::feed_position(const hal::CanFrame& f) noexcept {
  const bool lat_lon = f.id == config_.ids.ekf_pos;
  if (same_as_last(f)) {
    ++position_counters_.duplicates;
    return FeedResult::kDuplicate;
  }
  // A rejected half ends the pair: the other half must not be combined with an older one.
  auto reject = [&](std::uint32_t* counter, FeedResult r) {
    (lat_lon ? lat_lon_fresh_ : altitude_fresh_) = false;
    ++*counter;
    return r;
  };
  if (lat_lon) {
    if (f.dlc != 8) return reject(&position_counters_.malformed, FeedResult::kMalformed);
    const std::int32_t lat = get_i32(f, 0), lon = get_i32(f, 4);
    if (std::abs(static_cast<double>(lat)) * kLatLonScale > 90.0 ||
        std::abs(static_cast<double>(lon)) * kLatLonScale > 180.0) {
      return reject(&position_counters_.out_of_range, FeedResult::kOutOfRange);
    }
    raw_.lat = lat;
    raw_.lon = lon;
    lat_lon_fresh_ = true;
  } else {
    if (f.dlc < 6 || f.dlc > 8)
      return reject(&position_counters_.malformed, FeedResult::kMalformed);
    const std::int32_t alt = get_i32(f, 0);
    const std::int16_t und = get_i16(f, 4);
    const double alt_m = alt * kAltitudeScale, und_m = und * kUndulationScale;
    if (alt_m < kMinAltitude_m || alt_m > kMaxAltitude_m || std::fabs(und_m) > kMaxUndulation_m)
      return reject(&position_counters_.out_of_range, FeedResult::kOutOfRange);
    raw_.altitude = alt;
    raw_.undulation = und;
    altitude_fresh_ = true;
  }
  if (!lat_lon_fresh_ || !altitude_fresh_) return FeedResult::kConsumed;
  position_.t_us = f.t_us;
  position_.t_ins_us = raw_.ekf_time_us;
  position_.lat_deg = raw_.lat * kLatLonScale;
  position_.lon_deg = raw_.lon * kLatLonScale;
  position_.altitude_m = raw_.altitude * kAltitudeScale;
  position_.undulation_m = raw_.undulation * kUndulationScale;
  std::uint32_t flags = 0;
  if (status_known_) {
    flags |= hal::kPosStatusKnown;
    if ((raw_.solution_status & kSolPositionValid) != 0) flags |= hal::kPosValid;
  }
  position_.flags = flags;
  lat_lon_fresh_ = false;
  altitude_fresh_ = false;
  ++position_counters_.samples;
  return FeedResult::kPosition;
}

FeedResult CanDecoder::feed(const hal::CanFrame& f) noexcept {
  const CanIds& ids = config_.ids;
  const bool position = f.id == ids.ekf_pos || f.id == ids.ekf_altitude;
  const bool known = position || f.id == ids.status_01 || f.id == ids.status_03 ||
                     f.id == ids.ekf_info || f.id == ids.ekf_quat || f.id == ids.ekf_euler ||
                     f.id == ids.ekf_orientation_acc;
  if (!known || f.extended) {
    ++counters_.ignored;
    return FeedResult::kIgnored;
  }
  if (position) return feed_position(f);
  if (same_as_last(f)) {
    ++counters_.duplicates;
    return FeedResult::kDuplicate;
  }
  auto malformed = [&] {
    // A corrupt time or attitude frame ends the epoch: the next attitude frame must not be paired
    // with a time stamp of an earlier epoch.
    const std::uint32_t attitude_id =
        config_.source == AttitudeMessage::kQuaternion ? ids.ekf_quat : ids.ekf_euler;
    if (f.id == ids.ekf_info || f.id == attitude_id) time_fresh_ = false;
    ++counters_.malformed;
    return FeedResult::kMalformed;
  };
  if (f.dlc > 8) return malformed();
  if (f.id == ids.ekf_info) {
    if (f.dlc < 4) return malformed();
    raw_.ekf_time_us = get_u32(f, 0);
    time_fresh_ = true;
    return FeedResult::kConsumed;
  }
  if (f.id == ids.status_03) {
    if (f.dlc < 6) return malformed();
    const std::uint32_t status = get_u32(f, 0);
    if ((status & kSolutionModeMask) > 4) return malformed();
    raw_.solution_status = status;
    status_known_ = true;
    return FeedResult::kConsumed;
  }
  if (f.id == ids.status_01) {
    if (f.dlc < 8) return malformed();
    raw_.status01_time_us = get_u32(f, 0);
    raw_.general_status = get_u16(f, 4);
    raw_.clock_status = get_u16(f, 6);
    return FeedResult::kConsumed;
  }
  if (f.id == ids.ekf_orientation_acc) {
    if (f.dlc < 6) return malformed();
    const std::array<std::uint16_t, 3> acc{get_u16(f, 0), get_u16(f, 2), get_u16(f, 4)};
    // Ranges from the message definition: roll [0, pi], pitch [0, pi/2], yaw [0, pi].
    if (acc[0] * kAngleScale > kPi + 1e-4 || acc[1] * kAngleScale > kPi / 2 + 1e-4 ||
        acc[2] * kAngleScale > kPi + 1e-4) {
      return malformed();
    }
    raw_.accuracy = acc;
    accuracy_known_ = true;
    return FeedResult::kConsumed;
  }
  if (f.id == ids.ekf_quat) {
    if (f.dlc < 8) return malformed();
    const std::array<std::int16_t, 4> q{get_i16(f, 0), get_i16(f, 2), get_i16(f, 4), get_i16(f, 6)};
    const std::array<double, 4> qd{q[0] * kQuatScale, q[1] * kQuatScale, q[2] * kQuatScale,
                                   q[3] * kQuatScale};
    const double norm = std::sqrt(qd[0] * qd[0] + qd[1] * qd[1] + qd[2] * qd[2] + qd[3] * qd[3]);
    if (std::fabs(norm - 1.0) > config_.max_quat_norm_error) return malformed();
    raw_.quat = q;
    if (config_.source != AttitudeMessage::kQuaternion) return FeedResult::kConsumed;
    if (!time_fresh_) {
      ++counters_.missing_time;
      return FeedResult::kMissingTime;
    }
    if (epoch_already_sampled()) return FeedResult::kDuplicate;
    emit(r_bn_from_sbg_quat(qd), f.t_us);
    return FeedResult::kSample;
  }
  // EKF_EULER
  if (f.dlc < 6) return malformed();
  const std::array<std::int16_t, 3> e{get_i16(f, 0), get_i16(f, 2), get_i16(f, 4)};
  const double roll = e[0] * kAngleScale, pitch = e[1] * kAngleScale, yaw = e[2] * kAngleScale;
  // int16 * 1e-4 reaches +/-3.2767 rad: values beyond the documented ranges are corrupt.
  if (std::fabs(roll) > kPi + 1e-4 || std::fabs(pitch) > kPi / 2 + 1e-4 ||
      std::fabs(yaw) > kPi + 1e-4) {
    return malformed();
  }
  raw_.euler = e;
  if (config_.source != AttitudeMessage::kEuler) return FeedResult::kConsumed;
  if (!time_fresh_) {
    ++counters_.missing_time;
    return FeedResult::kMissingTime;
  }
  if (epoch_already_sampled()) return FeedResult::kDuplicate;
  emit(core::r_bn_from_ypr(core::YawPitchRoll<double>{yaw, pitch, roll}), f.t_us);
  return FeedResult::kSample;
}

hal::CanFrame encode_status_01(std::uint32_t time_us, std::uint16_t general_status,
                               std::uint16_t clock_status, const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.status_01, 8);
  put_u32(f, 0, time_us);
  put_u16(f, 4, general_status);
  put_u16(f, 6, clock_status);
  return f;
}
hal::CanFrame encode_status_03(std::uint32_t solution_status, std::uint16_t heave_status,
                               const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.status_03, 6);
  put_u32(f, 0, solution_status);
  put_u16(f, 4, heave_status);
  return f;
}
hal::CanFrame encode_ekf_info(std::uint32_t time_us, const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.ekf_info, 4);
  put_u32(f, 0, time_us);
  return f;
}
hal::CanFrame encode_ekf_quat(const std::array<double, 4>& q, const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.ekf_quat, 8);
  for (std::size_t i = 0; i < 4; ++i) {
    put_u16(f, 2 * i, static_cast<std::uint16_t>(to_i16(q[i] * 32767.0)));
  }
  return f;
}
hal::CanFrame encode_ekf_euler(double roll_rad, double pitch_rad, double yaw_rad,
                               const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.ekf_euler, 6);
  put_u16(f, 0, static_cast<std::uint16_t>(to_i16(roll_rad / kAngleScale)));
  put_u16(f, 2, static_cast<std::uint16_t>(to_i16(pitch_rad / kAngleScale)));
  put_u16(f, 4, static_cast<std::uint16_t>(to_i16(yaw_rad / kAngleScale)));
  return f;
}
hal::CanFrame encode_orientation_acc(double roll_acc_rad, double pitch_acc_rad, double yaw_acc_rad,
                                     const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.ekf_orientation_acc, 6);
  put_u16(f, 0, to_u16(roll_acc_rad / kAngleScale));
  put_u16(f, 2, to_u16(pitch_acc_rad / kAngleScale));
  put_u16(f, 4, to_u16(yaw_acc_rad / kAngleScale));
  return f;
}

hal::CanFrame encode_ekf_pos(double lat_deg, double lon_deg, const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.ekf_pos, 8);
  put_u32(f, 0, static_cast<std::uint32_t>(to_i32(lat_deg / kLatLonScale)));
  put_u32(f, 4, static_cast<std::uint32_t>(to_i32(lon_deg / kLatLonScale)));
  return f;
}
hal::CanFrame encode_ekf_altitude(double altitude_m, double undulation_m,
                                  const CanIds& ids) noexcept {
  hal::CanFrame f = make_frame(ids.ekf_altitude, 6);
  put_u32(f, 0, static_cast<std::uint32_t>(to_i32(altitude_m / kAltitudeScale)));
  put_u16(f, 4, static_cast<std::uint16_t>(to_i16(undulation_m / kUndulationScale)));
  return f;
}

void CanAttitudeSource::queue_position() noexcept {
  if (position_count_ == kPositionQueue) {
    position_head_ = (position_head_ + 1) % kPositionQueue;  // the oldest goes
    --position_count_;
    ++decoder_.position_counters().overflows;
  }
  position_queue_[(position_head_ + position_count_) % kPositionQueue] = decoder_.position();
  ++position_count_;
}

hal::Status CanAttitudeSource::Positions::read(hal::PositionSample& out,
                                               std::uint32_t /*timeout_us*/) noexcept {
  if (owner_.position_count_ == 0) return hal::Status::kNoData;
  out = owner_.position_queue_[owner_.position_head_];
  owner_.position_head_ = (owner_.position_head_ + 1) % kPositionQueue;
  --owner_.position_count_;
  return hal::Status::kOk;
}

hal::Status CanAttitudeSource::read(hal::AttitudeSample& out, std::uint32_t timeout_us) noexcept {
  // Bounded: at most 64 frames per call so a flooded bus cannot starve the caller. The timeout
  // applies to every frame, not only the first: the frames of one epoch arrive one after another
  // on a real bus, and a momentarily empty queue mid-epoch is not the end of the sample.
  for (int i = 0; i < 64; ++i) {
    hal::CanFrame f;
    const hal::Status s = bus_.receive(f, timeout_us);
    if (s == hal::Status::kTimeout || s == hal::Status::kNoData) return hal::Status::kTimeout;
    if (s != hal::Status::kOk) {
      ++decoder_.counters().bus_errors;
      return s;
    }
    const FeedResult r = decoder_.feed(f);
    if (r == FeedResult::kPosition) queue_position();
    if (r == FeedResult::kSample) {
      out = decoder_.sample();
      return hal::Status::kOk;
    }
  }
  return hal::Status::kNoData;
}

}  // namespace magvec::drivers::sbg
