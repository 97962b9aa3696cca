// SBG Systems INS (Ellipse, Ekinox, Apogee, Quanta) CAN output messages: decoder to
// hal::AttitudeSample and encoder (for the simulated INS and tests).
//
// Source of the format: SBG Systems "sbgECom CAN messages" documentation (CAN output message list,
// firmware ELLIPSE >= 1.7 / HPINS >= 2.1) and sbgECom's sbgEComLogEkf.h for the status bits.
// All fields little endian, classic CAN, default 11-bit IDs (configurable here and on the device):
//   0x100 STATUS_01        TIME_STAMP u32 us | GENERAL_STATUS u16 | CLOCK_STATUS u16   (8 bytes)
//   0x102 STATUS_03        SOLUTION_STATUS u32 | HEAVE_STATUS u16                      (6 bytes)
//   0x130 EKF_INFO         TIME_STAMP u32 us (time since power-on)                     (4 bytes)
//   0x131 EKF_QUAT         Q0 Q1 Q2 Q3 int16, scale 1/32767 (Q0 = scalar part)         (8 bytes)
//   0x132 EKF_EULER        ROLL PITCH YAW int16, scale 1e-4 rad                        (6 bytes)
//   0x133 EKF_ORIENTATION_ACC  ROLL_ACC PITCH_ACC YAW_ACC u16, scale 1e-4 rad, 1 sigma (6 bytes)
//   0x134 EKF_POS          LATITUDE LONGITUDE int32, scale 1e-7 deg, WGS84             (8 bytes)
//   0x135 EKF_ALTITUDE     ALTITUDE int32, scale 1e-3 m above mean sea level |
//                          UNDULATION int16, scale 0.005 m (geoid - ellipsoid)         (6 bytes)
//   (sbgECom documentation, "CAN Protocol Specifications", section "EKF messages":
//   SBG_ECAN_MSG_EKF_POS and SBG_ECAN_MSG_EKF_ALTITUDE; height above the ellipsoid =
//   ALTITUDE + UNDULATION.)
//   SOLUTION_STATUS: bits 0-3 solution mode (0 UNINITIALIZED, 1 VERTICAL_GYRO, 2 AHRS,
//   3 NAV_VELOCITY, 4 NAV_POSITION), bit 4 ATTITUDE_VALID, bit 5 HEADING_VALID,
//   bit 6 VELOCITY_VALID, bit 7 POSITION_VALID.
// Conventions: SBG Euler angles are aerospace roll/pitch/yaw, navigation NED, body X forward,
// Y right, Z down (FRD); R_bn (ENU -> RFU) = r_bn_from_ypr() of frames.hpp. The quaternion
// rotates body FRD vectors into NED, i.e. its rotation matrix is C_ned_frd, and
// R_bn = P C_ned_frd^T P with P = enu_ned_swap().
// Frames are grouped into epochs: EKF_INFO opens an epoch (INS time); the configured attitude
// message (quaternion by default, or Euler) closes it and produces one sample stamped with the
// epoch's INS time and the CAN receive time of the attitude frame. The latest accuracy and
// solution status received are attached. An attitude frame without a fresh EKF_INFO is counted
// as missing_time and dropped (no timestamp to align it with). A malformed EKF_INFO or attitude
// frame also ends the epoch, so a later attitude frame is never stamped with a stale epoch time.
// Duplicates are dropped and counted (duplicates), never turned into a second sample:
//   - a frame identical (ID, DLC, bytes) to the previous frame of a configured ID: CAN double
//     reception (the receivers took the frame, the transmitter saw an error in its last bits and
//     sent it again). No configured message repeats back to back otherwise: EKF_INFO's time stamp
//     changes every epoch and separates the others.
//   - an epoch whose EKF_INFO time equals the last sample's (a gateway repeating an epoch): its
//     attitude frame would give the same INS time a later receive time, i.e. a wrong attitude time.
// Position: an EKF_POS and an EKF_ALTITUDE frame (either order) make one hal::PositionSample,
// stamped with the receive time of the second and the INS time of the latest EKF_INFO, valid
// when the latest SOLUTION_STATUS has POSITION_VALID. Rejected and counted in the position
// counters (never the attitude's): a wrong length (malformed); a latitude beyond +-90 deg, a
// longitude beyond +-180 deg (the message's fields are int32 and reach +-214.7 deg), an altitude
// outside [-12 km, 100 km] or an undulation beyond +-150 m (the geoid departs from the ellipsoid
// by -107 to +86 m) (out_of_range; such a frame also ends the pair, so a good half is never
// combined with a stale one).
// Not verified here: the 8-byte EKF_INFO variant of newer firmware (TIME_STAMP + solution status
// bits) is accepted as long as the first 4 bytes are the time stamp; extra bytes are ignored.
#pragma once

#include <array>
#include <cstdint>

#include "magvec/core/frames.hpp"
#include "magvec/hal/attitude_source.hpp"
#include "magvec/hal/can_bus.hpp"
#include "magvec/hal/position_source.hpp"

namespace magvec::drivers::sbg {

struct CanIds {
  std::uint32_t status_01{0x100};
  std::uint32_t status_03{0x102};
  std::uint32_t ekf_info{0x130};
  std::uint32_t ekf_quat{0x131};
  std::uint32_t ekf_euler{0x132};
  std::uint32_t ekf_orientation_acc{0x133};
  std::uint32_t ekf_pos{0x134};
  std::uint32_t ekf_altitude{0x135};
};

inline constexpr std::uint32_t kSolutionModeMask = 0x0Fu;
inline constexpr std::uint32_t kSolAttitudeValid = 1u << 4;
inline constexpr std::uint32_t kSolHeadingValid = 1u << 5;
inline constexpr std::uint32_t kSolVelocityValid = 1u << 6;
inline constexpr std::uint32_t kSolPositionValid = 1u << 7;
enum class SolutionMode : std::uint8_t {
  kUninitialized = 0,
  kVerticalGyro = 1,
  kAhrs = 2,
  kNavVelocity = 3,
  kNavPosition = 4,
};

inline constexpr double kQuatScale = 1.0 / 32767.0;
inline constexpr double kAngleScale = 1e-4;       // rad per LSB
inline constexpr double kLatLonScale = 1e-7;      // deg per LSB
inline constexpr double kAltitudeScale = 1e-3;    // m per LSB
inline constexpr double kUndulationScale = 5e-3;  // m per LSB
// Plausibility bounds of a position fix (see the top).
inline constexpr double kMinAltitude_m = -12'000;
inline constexpr double kMaxAltitude_m = 100'000;
inline constexpr double kMaxUndulation_m = 150;

enum class AttitudeMessage : std::uint8_t { kQuaternion, kEuler };

struct DecoderConfig {
  CanIds ids{};
  AttitudeMessage source{AttitudeMessage::kQuaternion};
  double max_quat_norm_error{0.01};  // |q| outside 1 +/- this (after scaling) -> malformed
};

// Raw decoded content of the last frames (diagnostics and tests).
struct RawState {
  std::uint32_t ekf_time_us{0};
  std::array<std::int16_t, 4> quat{};
  std::array<std::int16_t, 3> euler{};  // roll, pitch, yaw
  std::array<std::uint16_t, 3> accuracy{};
  std::uint32_t solution_status{0};
  std::uint32_t status01_time_us{0};
  std::uint16_t general_status{0};
  std::uint16_t clock_status{0};
  std::int32_t lat{0};  // EKF_POS, 1e-7 deg
  std::int32_t lon{0};
  std::int32_t altitude{0};    // EKF_ALTITUDE, 1e-3 m
  std::int16_t undulation{0};  // 5e-3 m
};

enum class FeedResult : std::uint8_t {
  kIgnored,      // not one of the configured IDs
  kConsumed,     // valid frame, state updated, no new sample
  kSample,       // a new attitude sample is available via sample()
  kMalformed,    // wrong length / extended ID / out-of-range content (counted)
  kMissingTime,  // attitude frame without a preceding EKF_INFO (counted)
  kDuplicate,    // the previous frame again, or an epoch already sampled (counted)
  kPosition,     // a new position fix is available via position()
  kOutOfRange,   // a position frame whose values cannot be a position (counted)
};

class CanDecoder {
 public:
  explicit CanDecoder(const DecoderConfig& config = {}) noexcept : config_(config) {}

  FeedResult feed(const hal::CanFrame& frame) noexcept;
  const hal::AttitudeSample& sample() const noexcept { return sample_; }
  const RawState& raw() const noexcept { return raw_; }
  const hal::AttitudeCounters& counters() const noexcept { return counters_; }
  hal::AttitudeCounters& counters() noexcept { return counters_; }
  const hal::PositionSample& position() const noexcept { return position_; }
  const hal::PositionCounters& position_counters() const noexcept { return position_counters_; }
  hal::PositionCounters& position_counters() noexcept { return position_counters_; }

 private:
  FeedResult feed_position(const hal::CanFrame& f) noexcept;
  void emit(const core::Mat3<double>& r_bn, std::uint64_t t_rx_us) noexcept;
  // Whether `f` repeats the previous configured frame (remembers `f` either way).
  bool same_as_last(const hal::CanFrame& f) noexcept;
  // Whether the fresh EKF_INFO time is the last sample's: then the epoch ends here, counted.
  bool epoch_already_sampled() noexcept;

  DecoderConfig config_;
  RawState raw_{};
  hal::AttitudeSample sample_{};
  hal::AttitudeCounters counters_{};
  hal::PositionSample position_{};
  hal::PositionCounters position_counters_{};
  hal::CanFrame last_frame_{};  // previous frame of a configured ID (double reception)
  bool time_fresh_{false};
  bool status_known_{false};
  bool accuracy_known_{false};
  bool have_last_frame_{false};
  bool have_sample_{false};
  bool lat_lon_fresh_{false};   // EKF_POS received since the last fix
  bool altitude_fresh_{false};  // EKF_ALTITUDE received since the last fix
};

// Conversions between SBG payload conventions and the core's R_bn.
core::Mat3<double> r_bn_from_sbg_quat(const std::array<double, 4>& q_ned_frd) noexcept;
std::array<double, 4> sbg_quat_from_r_bn(const core::Mat3<double>& r_bn) noexcept;

// Encoders (standard 11-bit IDs from `ids`; values are rounded and saturated to the field range).
hal::CanFrame encode_status_01(std::uint32_t time_us, std::uint16_t general_status,
                               std::uint16_t clock_status, const CanIds& ids = {}) noexcept;
hal::CanFrame encode_status_03(std::uint32_t solution_status, std::uint16_t heave_status,
                               const CanIds& ids = {}) noexcept;
hal::CanFrame encode_ekf_info(std::uint32_t time_us, const CanIds& ids = {}) noexcept;
hal::CanFrame encode_ekf_quat(const std::array<double, 4>& q_ned_frd,
                              const CanIds& ids = {}) noexcept;
hal::CanFrame encode_ekf_euler(double roll_rad, double pitch_rad, double yaw_rad,
                               const CanIds& ids = {}) noexcept;
hal::CanFrame encode_orientation_acc(double roll_acc_rad, double pitch_acc_rad, double yaw_acc_rad,
                                     const CanIds& ids = {}) noexcept;
hal::CanFrame encode_ekf_pos(double lat_deg, double lon_deg, const CanIds& ids = {}) noexcept;
hal::CanFrame encode_ekf_altitude(double altitude_m, double undulation_m,
                                  const CanIds& ids = {}) noexcept;

// hal::AttitudeSource over a hal::CanBus; the position fixes decoded from the same frames are
// kept for positions() (a hal::PositionSource).
class CanAttitudeSource final : public hal::AttitudeSource {
 public:
  static constexpr std::size_t kPositionQueue = 8;

  CanAttitudeSource(hal::CanBus& bus, const DecoderConfig& config = {}) noexcept
      : bus_(bus), decoder_(config), positions_(*this) {}
  CanAttitudeSource(const CanAttitudeSource&) = delete;
  CanAttitudeSource& operator=(const CanAttitudeSource&) = delete;
  // Receives frames until one completes a sample or the bus has nothing within timeout_us (the
  // wait for each frame; at most 64 frames per call).
  hal::Status read(hal::AttitudeSample& out, std::uint32_t timeout_us) noexcept override;
  const hal::AttitudeCounters& counters() const noexcept override { return decoder_.counters(); }
  const CanDecoder& decoder() const noexcept { return decoder_; }
  // The INS position fixes. One bus carries both: the fixes are decoded while the attitude is
  // read, and queued (the oldest dropped and counted as an overflow when the queue is full).
  // Reading positions never takes frames from the bus, so it can never steal an attitude frame:
  // its read() hands on the queued fixes (kNoData when there are none) and does not wait.
  hal::PositionSource& positions() noexcept { return positions_; }

 private:
  class Positions final : public hal::PositionSource {
   public:
    explicit Positions(CanAttitudeSource& owner) noexcept : owner_(owner) {}
    hal::Status read(hal::PositionSample& out, std::uint32_t timeout_us) noexcept override;
    const hal::PositionCounters& counters() const noexcept override {
      return owner_.decoder_.position_counters();
    }

   private:
    CanAttitudeSource& owner_;
  };
  void queue_position() noexcept;

  hal::CanBus& bus_;
  CanDecoder decoder_;
  Positions positions_;
  std::array<hal::PositionSample, kPositionQueue> position_queue_{};
  std::size_t position_head_{0};
  std::size_t position_count_{0};
};

}  // namespace magvec::drivers::sbg
