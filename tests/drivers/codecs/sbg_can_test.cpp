#include "magvec/drivers/sbg_can.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <random>
#include <vector>

#include "support/alloc_counter.hpp"

namespace magvec::drivers::sbg {
namespace {

using core::Mat3;
constexpr double kDeg = core::kPi<double> / 180.0;

hal::CanFrame frame(std::uint32_t id, std::initializer_list<std::uint8_t> bytes,
                    std::uint64_t t = 0) {
  hal::CanFrame f;
  f.id = id;
  f.dlc = static_cast<std::uint8_t>(bytes.size());
  std::size_t i = 0;
  for (auto b : bytes)
    f.data[i++] = b;
  f.t_us = t;
  return f;
}

Mat3<double> r_bn_of(const hal::AttitudeSample& s) {
  return core::r_bn_from_quat(core::Quat<double>(s.q_nb[0], s.q_nb[1], s.q_nb[2], s.q_nb[3]));
}

TEST(SbgCan, HandAssembledEpochWithQuaternion) {
  CanDecoder dec;
  // STATUS_03: mode 4 (NAV_POSITION) | ATTITUDE_VALID | HEADING_VALID = 0x34.
  EXPECT_EQ(dec.feed(frame(0x102, {0x34, 0x00, 0x00, 0x00, 0x00, 0x00})), FeedResult::kConsumed);
  // ORIENTATION_ACC: 17, 17, 87 (x1e-4 rad).
  EXPECT_EQ(dec.feed(frame(0x133, {0x11, 0x00, 0x11, 0x00, 0x57, 0x00})), FeedResult::kConsumed);
  // EKF_INFO: time stamp 12345678h us, little endian.
  EXPECT_EQ(dec.feed(frame(0x130, {0x78, 0x56, 0x34, 0x12})), FeedResult::kConsumed);
  EXPECT_EQ(dec.raw().ekf_time_us, 0x12345678u);
  // EKF_QUAT: q0 = 32767 (identity): FRD aligned with NED, i.e. RFU aligned with ENU.
  ASSERT_EQ(dec.feed(frame(0x131, {0xFF, 0x7F, 0, 0, 0, 0, 0, 0}, 999)), FeedResult::kSample);
  const hal::AttitudeSample& s = dec.sample();
  EXPECT_EQ(s.t_us, 999u);
  EXPECT_EQ(s.t_ins_us, 0x12345678u);
  EXPECT_NEAR((r_bn_of(s) - Mat3<double>::Identity()).norm(), 0, 1e-12);
  EXPECT_EQ(s.solution_mode, 4);
  EXPECT_EQ(s.flags, hal::kAttAttitudeValid | hal::kAttHeadingValid | hal::kAttStatusKnown |
                         hal::kAttAccuracyKnown);
  EXPECT_DOUBLE_EQ(s.sigma_rad[0], 17e-4);
  EXPECT_DOUBLE_EQ(s.sigma_rad[2], 87e-4);

  // Heading East: q = (cos 45, 0, 0, sin 45) -> round(0.70710678 * 32767) = 23170 = 5A82h.
  EXPECT_EQ(dec.feed(frame(0x130, {0x10, 0, 0, 0})), FeedResult::kConsumed);
  ASSERT_EQ(dec.feed(frame(0x131, {0x82, 0x5A, 0, 0, 0, 0, 0x82, 0x5A})), FeedResult::kSample);
  const Mat3<double> expected = core::r_bn_from_ypr(core::YawPitchRoll<double>{90 * kDeg, 0, 0});
  EXPECT_NEAR((r_bn_of(dec.sample()) - expected).norm(), 0, 1e-9);
  // Vehicle heading East: the Forward (body y) axis sees the East component.
  EXPECT_NEAR((r_bn_of(dec.sample()) * core::Vec3<double>(1, 0, 0)).y(), 1, 1e-9);
}

TEST(SbgCan, HandAssembledEuler) {
  DecoderConfig cfg;
  cfg.source = AttitudeMessage::kEuler;
  CanDecoder dec(cfg);
  EXPECT_EQ(dec.feed(frame(0x130, {0x01, 0x00, 0x00, 0x00})), FeedResult::kConsumed);
  // roll 0.1 rad = 1000 = 03E8h, pitch -0.2 rad = -2000 = F830h, yaw 3.1415 rad = 31415 = 7AB7h.
  ASSERT_EQ(dec.feed(frame(0x132, {0xE8, 0x03, 0x30, 0xF8, 0xB7, 0x7A})), FeedResult::kSample);
  EXPECT_EQ(dec.raw().euler[1], -2000);
  const Mat3<double> expected = core::r_bn_from_ypr(core::YawPitchRoll<double>{3.1415, -0.2, 0.1});
  EXPECT_NEAR((r_bn_of(dec.sample()) - expected).norm(), 0, 1e-12);
  EXPECT_EQ(dec.sample().flags, 0u);  // no status or accuracy received yet: validity unknown
  // The quaternion is decoded (checked) but does not produce a sample in Euler mode.
  EXPECT_EQ(dec.feed(frame(0x131, {0xFF, 0x7F, 0, 0, 0, 0, 0, 0})), FeedResult::kConsumed);
}

// The SBG quaternion for aerospace (roll, pitch, yaw) is the textbook body->NED quaternion;
// both message paths must give the same R_bn.
TEST(SbgCan, QuaternionAndEulerPathsAgree) {
  std::mt19937_64 rng(5);
  std::uniform_real_distribution<double> ang(-170, 170), tilt(-80, 80);
  for (int i = 0; i < 300; ++i) {
    const double r = ang(rng) * kDeg, p = tilt(rng) * kDeg, y = ang(rng) * kDeg;
    const double cr = std::cos(r / 2), sr = std::sin(r / 2), cp = std::cos(p / 2),
                 sp = std::sin(p / 2), cy = std::cos(y / 2), sy = std::sin(y / 2);
    const std::array<double, 4> q{cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
                                  cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy};
    const Mat3<double> from_q = r_bn_from_sbg_quat(q);
    const Mat3<double> from_e = core::r_bn_from_ypr(core::YawPitchRoll<double>{y, p, r});
    ASSERT_NEAR((from_q - from_e).norm(), 0, 1e-12);
    const std::array<double, 4> back = sbg_quat_from_r_bn(from_e);
    const double sign = q[0] < 0 ? -1 : 1;
    for (std::size_t k = 0; k < 4; ++k)
      ASSERT_NEAR(back[k], sign * q[k], 1e-12);
  }
}

TEST(SbgCan, EncodersProduceTheDocumentedBytes) {
  const hal::CanFrame info = encode_ekf_info(0x12345678u);
  EXPECT_EQ(info.id, 0x130u);
  EXPECT_EQ(info.dlc, 4);
  EXPECT_EQ(info.data[0], 0x78);
  EXPECT_EQ(info.data[3], 0x12);
  const hal::CanFrame e = encode_ekf_euler(0.1, -0.2, 3.1415);
  const std::array<std::uint8_t, 6> eb{0xE8, 0x03, 0x30, 0xF8, 0xB7, 0x7A};
  for (std::size_t i = 0; i < 6; ++i)
    EXPECT_EQ(e.data[i], eb[i]);
  const hal::CanFrame q = encode_ekf_quat({std::sqrt(0.5), 0, 0, std::sqrt(0.5)});
  EXPECT_EQ(q.data[0], 0x82);
  EXPECT_EQ(q.data[1], 0x5A);
  const hal::CanFrame a = encode_orientation_acc(17e-4, 17e-4, 87e-4);
  EXPECT_EQ(a.data[4], 0x57);
  const hal::CanFrame st = encode_status_03(0x34, 0);
  EXPECT_EQ(st.id, 0x102u);
  EXPECT_EQ(st.dlc, 6);
  EXPECT_EQ(st.data[0], 0x34);
  const hal::CanFrame s1 = encode_status_01(1, 0x00FF, 0x0102);
  EXPECT_EQ(s1.id, 0x100u);
  EXPECT_EQ(s1.data[4], 0xFF);
  EXPECT_EQ(s1.data[7], 0x01);
  // Saturation instead of wrap-around.
  const hal::CanFrame big = encode_ekf_euler(10.0, -10.0, 0);
  EXPECT_EQ(big.data[0] | (big.data[1] << 8), 0x7FFF);
  EXPECT_EQ(big.data[2] | (big.data[3] << 8), 0x8000);
  // Round trip through the decoder, with configurable IDs.
  CanIds ids;
  ids.ekf_info = 0x530;
  ids.ekf_quat = 0x531;
  DecoderConfig cfg;
  cfg.ids = ids;
  CanDecoder dec(cfg);
  EXPECT_EQ(dec.feed(encode_ekf_info(7)), FeedResult::kIgnored);  // default ID, not configured
  EXPECT_EQ(dec.feed(encode_ekf_info(7, ids)), FeedResult::kConsumed);
  const Mat3<double> r = core::r_bn_from_ypr(core::YawPitchRoll<double>{0.5, 0.2, -0.3});
  ASSERT_EQ(dec.feed(encode_ekf_quat(sbg_quat_from_r_bn(r), ids)), FeedResult::kSample);
  // int16 quantisation of the quaternion: ~1.5e-5 per component.
  EXPECT_LT(core::rotation_angle_between(r_bn_of(dec.sample()), r), 1e-4);
}

TEST(SbgCan, CorruptTruncatedAndOutOfOrderFrames) {
  CanDecoder dec;
  // Attitude without a time stamp: dropped and counted.
  EXPECT_EQ(dec.feed(frame(0x131, {0xFF, 0x7F, 0, 0, 0, 0, 0, 0})), FeedResult::kMissingTime);
  EXPECT_EQ(dec.counters().missing_time, 1u);
  // Truncated frames.
  EXPECT_EQ(dec.feed(frame(0x130, {0x01, 0x02, 0x03})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x131, {0xFF, 0x7F, 0, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x132, {0, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x133, {0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x102, {0x34, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x100, {0, 0, 0, 0, 0, 0})), FeedResult::kMalformed);
  // Impossible content: |q| = 0, yaw 3.2767 rad, pitch 1.6 rad, solution mode 9, accuracy > pi.
  EXPECT_EQ(dec.feed(frame(0x131, {0, 0, 0, 0, 0, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x131, {0xFF, 0x7F, 0xFF, 0x7F, 0, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x132, {0, 0, 0, 0, 0xFF, 0x7F})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x132, {0, 0, 0x80, 0x3E, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x102, {0x09, 0, 0, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x133, {0xFF, 0xFF, 0, 0, 0, 0})), FeedResult::kMalformed);
  EXPECT_EQ(dec.counters().malformed, 12u);
  EXPECT_EQ(dec.counters().samples, 0u);
  // Extended ID with a matching number is not ours.
  hal::CanFrame ext = frame(0x130, {1, 2, 3, 4});
  ext.extended = true;
  EXPECT_EQ(dec.feed(ext), FeedResult::kIgnored);
  // Invalid solution status is passed on as flags (the loop decides), not dropped.
  EXPECT_EQ(dec.feed(encode_status_03(0x02, 0)), FeedResult::kConsumed);  // AHRS, nothing valid
  EXPECT_EQ(dec.feed(encode_ekf_info(5)), FeedResult::kConsumed);
  ASSERT_EQ(dec.feed(encode_ekf_quat({1, 0, 0, 0})), FeedResult::kSample);
  EXPECT_EQ(dec.sample().flags & (hal::kAttAttitudeValid | hal::kAttHeadingValid), 0u);
  EXPECT_TRUE(dec.sample().flags & hal::kAttStatusKnown);
  // One EKF_INFO serves one sample only (the same quaternion frame again would be a duplicate).
  EXPECT_EQ(dec.feed(encode_ekf_quat({0, 1, 0, 0})), FeedResult::kMissingTime);
  EXPECT_EQ(dec.counters().duplicates, 0u);
}

// The four frames of INS epoch i (10 ms apart): status, time, accuracy, quaternion.
void put_epoch(hal::CanFrame* out, std::size_t i, double yaw_rad) {
  out[0] = encode_status_03(0x34, 0);
  out[1] = encode_ekf_info(static_cast<std::uint32_t>(10000 * i));
  out[2] = encode_orientation_acc(1e-3, 1e-3, 3e-3);
  out[3] = encode_ekf_quat(
      sbg_quat_from_r_bn(core::r_bn_from_ypr(core::YawPitchRoll<double>{yaw_rad, 0.1, 0.2})));
}

class FakeCan final : public hal::CanBus {
 public:
  hal::Status receive(hal::CanFrame& out, std::uint32_t) noexcept override {
    if (next >= frames.size()) return hal::Status::kTimeout;
    out = frames[next++];
    return hal::Status::kOk;
  }
  hal::Status send(const hal::CanFrame&) noexcept override { return hal::Status::kOk; }
  std::array<hal::CanFrame, 400> frames{};
  std::size_t next{0};
};

// CAN double reception (a frame received twice back to back) and a gateway repeating a whole
// epoch: each copy is dropped and counted, never a second sample of the epoch.
TEST(SbgCan, DuplicateFramesAndRepeatedEpochsAreDroppedAndCounted) {
  for (const AttitudeMessage source : {AttitudeMessage::kQuaternion, AttitudeMessage::kEuler}) {
    DecoderConfig cfg;
    cfg.source = source;
    CanDecoder dec(cfg);
    const hal::CanFrame status = encode_status_03(0x34, 0);
    const hal::CanFrame info = encode_ekf_info(1000);
    const hal::CanFrame quat = encode_ekf_quat({1, 0, 0, 0});
    const hal::CanFrame euler = encode_ekf_euler(0.1, 0.2, 0.3);
    const hal::CanFrame& attitude = source == AttitudeMessage::kQuaternion ? quat : euler;
    const hal::CanFrame& other = source == AttitudeMessage::kQuaternion ? euler : quat;
    EXPECT_EQ(dec.feed(status), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(status), FeedResult::kDuplicate);  // every configured ID is checked
    EXPECT_EQ(dec.feed(info), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(info), FeedResult::kDuplicate);
    EXPECT_EQ(dec.feed(other), FeedResult::kConsumed);
    ASSERT_EQ(dec.feed(attitude), FeedResult::kSample);
    // The attitude frame received twice: before this rule, a missing time.
    EXPECT_EQ(dec.feed(attitude), FeedResult::kDuplicate);
    EXPECT_EQ(dec.counters().duplicates, 3u);
    EXPECT_EQ(dec.counters().missing_time, 0u);

    // The whole epoch again, later (a gateway): the EKF_INFO time is the last sample's.
    hal::CanFrame late = attitude;
    late.t_us = 5000;
    EXPECT_EQ(dec.feed(status), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(info), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(other), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(late), FeedResult::kDuplicate);
    EXPECT_EQ(dec.counters().duplicates, 4u);
    EXPECT_EQ(dec.counters().samples, 1u);
    // The repeated epoch ended there: its time does not serve the next attitude frame.
    EXPECT_EQ(dec.feed(other), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(attitude), FeedResult::kMissingTime);

    // A malformed frame received twice: one malformed, one duplicate.
    const hal::CanFrame short_info = frame(0x130, {1, 2, 3});
    EXPECT_EQ(dec.feed(short_info), FeedResult::kMalformed);
    EXPECT_EQ(dec.feed(short_info), FeedResult::kDuplicate);
    EXPECT_EQ(dec.counters().malformed, 1u);
    EXPECT_EQ(dec.counters().duplicates, 5u);

    // The next epoch, with the same attitude as before, is a new sample: only the time decides.
    EXPECT_EQ(dec.feed(encode_ekf_info(11000)), FeedResult::kConsumed);
    ASSERT_EQ(dec.feed(attitude), FeedResult::kSample);
    EXPECT_EQ(dec.sample().t_ins_us, 11000u);
    // A frame of another ID in between makes the same frame again a legitimate one.
    EXPECT_EQ(dec.feed(encode_ekf_info(21000)), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(other), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(attitude), FeedResult::kSample);
    EXPECT_EQ(dec.counters().samples, 3u);
    EXPECT_EQ(dec.counters().duplicates, 5u);
    // Frames of IDs the decoder does not use neither count nor separate two copies.
    EXPECT_EQ(dec.feed(encode_ekf_info(31000)), FeedResult::kConsumed);
    EXPECT_EQ(dec.feed(frame(0x7FF, {1})), FeedResult::kIgnored);
    EXPECT_EQ(dec.feed(encode_ekf_info(31000)), FeedResult::kDuplicate);
  }
}

TEST(SbgCan, AttitudeSourceOverCanBusWithoutAllocations) {
  FakeCan bus;
  for (std::size_t i = 0; i < 100; ++i)
    put_epoch(&bus.frames[4 * i], i, 0.01 * static_cast<double>(i));
  CanAttitudeSource src(bus);
  hal::AttitudeSample s;
  magvec::test::AllocationScope scope;
  for (std::size_t i = 0; i < 100; ++i) {
    ASSERT_EQ(src.read(s, 1000), hal::Status::kOk);
    EXPECT_EQ(s.t_ins_us, 10000 * i);
  }
  EXPECT_EQ(src.read(s, 1000), hal::Status::kTimeout);
  EXPECT_EQ(scope.count(), 0u);
  EXPECT_EQ(src.counters().samples, 100u);
}

// A real bus delivers the frames of one epoch one after another: a poll between two of them finds
// the queue empty. The source must keep waiting (within the caller's timeout) instead of
// reporting a timeout mid-epoch.
class TricklingCan final : public hal::CanBus {
 public:
  hal::Status receive(hal::CanFrame& out, std::uint32_t timeout_us) noexcept override {
    if (next >= count) return hal::Status::kTimeout;
    if (timeout_us == 0 && next % 4 != 0) return hal::Status::kTimeout;  // not arrived yet
    out = frames[next++];
    return hal::Status::kOk;
  }
  hal::Status send(const hal::CanFrame&) noexcept override { return hal::Status::kOk; }
  std::array<hal::CanFrame, 8> frames{};
  std::size_t count{0};
  std::size_t next{0};
};

TEST(SbgCan, AttitudeSourceWaitsForTheRestOfAnEpoch) {
  TricklingCan bus;
  for (std::size_t i = 0; i < 2; ++i)
    put_epoch(&bus.frames[4 * i], i, 0.1);
  bus.count = 8;
  CanAttitudeSource src(bus);
  hal::AttitudeSample s;
  ASSERT_EQ(src.read(s, 1000), hal::Status::kOk);
  EXPECT_EQ(s.t_ins_us, 0u);
  ASSERT_EQ(src.read(s, 1000), hal::Status::kOk);
  EXPECT_EQ(s.t_ins_us, 10000u);
  EXPECT_EQ(src.read(s, 1000), hal::Status::kTimeout);
}

// EKF_POS (0x134) and EKF_ALTITUDE (0x135), sbgECom CAN specification, "EKF messages": latitude
// and longitude int32 x 1e-7 deg, altitude int32 x 1e-3 m above MSL, undulation int16 x 0.005 m.
TEST(SbgCanPosition, HandAssembledFix) {
  CanDecoder dec;
  // STATUS_03: NAV_POSITION | ATTITUDE, HEADING, VELOCITY, POSITION valid = 0xF4.
  EXPECT_EQ(dec.feed(frame(0x102, {0xF4, 0, 0, 0, 0, 0})), FeedResult::kConsumed);
  EXPECT_EQ(dec.feed(frame(0x130, {0x40, 0x42, 0x0F, 0x00})), FeedResult::kConsumed);  // 1 s
  // 48.1372000 N, 11.5756000 E.
  EXPECT_EQ(dec.feed(frame(0x134, {0x60, 0x27, 0xB1, 0x1C, 0xE0, 0x4B, 0xE6, 0x06}, 10)),
            FeedResult::kConsumed);
  // 519.500 m above MSL, undulation 9500 x 0.005 = 47.5 m.
  ASSERT_EQ(dec.feed(frame(0x135, {0x4C, 0xED, 0x07, 0x00, 0x1C, 0x25}, 20)),
            FeedResult::kPosition);
  const hal::PositionSample& p = dec.position();
  EXPECT_EQ(p.t_us, 20u);
  EXPECT_EQ(p.t_ins_us, 1'000'000u);
  EXPECT_NEAR(p.lat_deg, 48.1372, 1e-12);
  EXPECT_NEAR(p.lon_deg, 11.5756, 1e-12);
  EXPECT_NEAR(p.altitude_m, 519.5, 1e-12);
  EXPECT_NEAR(p.undulation_m, 47.5, 1e-12);
  EXPECT_NEAR(p.height_m(), 567.0, 1e-12);
  EXPECT_EQ(p.flags, hal::kPosValid | hal::kPosStatusKnown);
  EXPECT_EQ(dec.position_counters().samples, 1u);
  // Position frames are not the attitude's business: nothing counted there.
  EXPECT_EQ(dec.counters().ignored, 0u);
  EXPECT_EQ(dec.counters().malformed, 0u);

  // Altitude first, then a southern/western position; -6000 x 0.005 = -30 m undulation.
  EXPECT_EQ(dec.feed(frame(0x102, {0x34, 0, 0, 0, 0, 0})), FeedResult::kConsumed);  // no POS_VALID
  EXPECT_EQ(dec.feed(frame(0x135, {0x4C, 0xED, 0x07, 0x00, 0x90, 0xE8}, 30)),
            FeedResult::kConsumed);
  ASSERT_EQ(dec.feed(frame(0x134, {0x87, 0x2F, 0xD1, 0xEB, 0x87, 0x2F, 0xD1, 0xEB}, 40)),
            FeedResult::kPosition);
  EXPECT_NEAR(dec.position().lat_deg, -33.8612345, 1e-12);
  EXPECT_NEAR(dec.position().lon_deg, -33.8612345, 1e-12);
  EXPECT_NEAR(dec.position().undulation_m, -30.0, 1e-12);
  EXPECT_EQ(dec.position().flags, hal::kPosStatusKnown);  // status known, position not valid
  EXPECT_EQ(dec.position_counters().samples, 2u);
}

TEST(SbgCanPosition, WithoutStatusTheValidityIsUnknown) {
  CanDecoder dec;
  EXPECT_EQ(dec.feed(frame(0x134, {0x60, 0x27, 0xB1, 0x1C, 0xE0, 0x4B, 0xE6, 0x06})),
            FeedResult::kConsumed);
  ASSERT_EQ(dec.feed(frame(0x135, {0x4C, 0xED, 0x07, 0x00, 0x1C, 0x25})), FeedResult::kPosition);
  EXPECT_EQ(dec.position().flags, 0u);
  EXPECT_EQ(dec.position().t_ins_us, 0u);
}

TEST(SbgCanPosition, WrongLengthsAndOutOfRangeValuesAreCountedRejections) {
  CanDecoder dec;
  // Wrong lengths: EKF_POS needs exactly 8 bytes, EKF_ALTITUDE 6 (up to 8).
  EXPECT_EQ(dec.feed(frame(0x134, {0x60, 0x27, 0xB1, 0x1C, 0xE0, 0x4B, 0xE6})),
            FeedResult::kMalformed);
  EXPECT_EQ(dec.feed(frame(0x135, {0x4C, 0xED, 0x07, 0x00, 0x1C})), FeedResult::kMalformed);
  hal::CanFrame long_frame = frame(0x135, {0x4C, 0xED, 0x07, 0x00, 0x1C, 0x25, 0, 0});
  long_frame.dlc = 9;
  EXPECT_EQ(dec.feed(long_frame), FeedResult::kMalformed);
  EXPECT_EQ(dec.position_counters().malformed, 3u);
  // Latitude 90.0000001 deg, longitude 180.0000001 deg: beyond what a position can be.
  EXPECT_EQ(dec.feed(frame(0x134, {0x01, 0xE9, 0xA4, 0x35, 0, 0, 0, 0})), FeedResult::kOutOfRange);
  EXPECT_EQ(dec.feed(frame(0x134, {0, 0, 0, 0, 0x01, 0xD2, 0x49, 0x6B})), FeedResult::kOutOfRange);
  // Altitude -12000.001 m; undulation 30001 x 0.005 = 150.005 m.
  EXPECT_EQ(dec.feed(frame(0x135, {0xFF, 0xE4, 0x48, 0xFF, 0, 0})), FeedResult::kOutOfRange);
  EXPECT_EQ(dec.feed(frame(0x135, {0, 0, 0, 0, 0x31, 0x75})), FeedResult::kOutOfRange);
  EXPECT_EQ(dec.position_counters().out_of_range, 4u);
  EXPECT_EQ(dec.position_counters().samples, 0u);
  // The extreme legal values pass: 90 S, 180 W (-900000000, -1800000000).
  EXPECT_EQ(dec.feed(frame(0x134, {0x00, 0x17, 0x5B, 0xCA, 0x00, 0x2E, 0xB6, 0x94})),
            FeedResult::kConsumed);
  // A rejected half ends the pair: a good altitude after a bad latitude makes no fix.
  EXPECT_EQ(dec.feed(frame(0x134, {0x01, 0xE9, 0xA4, 0x35, 0, 0, 0, 0})), FeedResult::kOutOfRange);
  EXPECT_EQ(dec.feed(frame(0x135, {0x4C, 0xED, 0x07, 0x00, 0x1C, 0x25})), FeedResult::kConsumed);
  EXPECT_EQ(dec.position_counters().samples, 0u);
  EXPECT_EQ(dec.feed(frame(0x134, {0x00, 0x17, 0x5B, 0xCA, 0x00, 0x2E, 0xB6, 0x94})),
            FeedResult::kPosition);
  EXPECT_DOUBLE_EQ(dec.position().lat_deg, -90.0);
  EXPECT_DOUBLE_EQ(dec.position().lon_deg, -180.0);
  // A frame received twice back to back: a counted duplicate, in the position counters.
  EXPECT_EQ(dec.feed(frame(0x134, {0x00, 0x17, 0x5B, 0xCA, 0x00, 0x2E, 0xB6, 0x94})),
            FeedResult::kDuplicate);
  EXPECT_EQ(dec.position_counters().duplicates, 1u);
  EXPECT_EQ(dec.counters().duplicates, 0u);
  // Nothing of this reached the attitude counters.
  EXPECT_EQ(dec.counters().malformed, 0u);
  EXPECT_EQ(dec.counters().samples, 0u);
}

TEST(SbgCanPosition, EncodersRoundTripAndConfiguredIds) {
  CanIds ids;
  ids.ekf_pos = 0x234;
  ids.ekf_altitude = 0x235;
  const hal::CanFrame p = encode_ekf_pos(48.1372, 11.5756, ids);
  const hal::CanFrame a = encode_ekf_altitude(519.5, 47.5, ids);
  EXPECT_EQ(p.id, 0x234u);
  EXPECT_EQ(p.dlc, 8);
  EXPECT_EQ(p.data, (std::array<std::uint8_t, 8>{0x60, 0x27, 0xB1, 0x1C, 0xE0, 0x4B, 0xE6, 0x06}));
  EXPECT_EQ(a.id, 0x235u);
  EXPECT_EQ(a.dlc, 6);
  EXPECT_EQ(a.data, (std::array<std::uint8_t, 8>{0x4C, 0xED, 0x07, 0x00, 0x1C, 0x25, 0, 0}));
  // The default IDs are not position messages any more for this decoder: ignored.
  DecoderConfig cfg;
  cfg.ids = ids;
  CanDecoder dec(cfg);
  EXPECT_EQ(dec.feed(encode_ekf_pos(1, 2)), FeedResult::kIgnored);
  EXPECT_EQ(dec.feed(p), FeedResult::kConsumed);
  ASSERT_EQ(dec.feed(a), FeedResult::kPosition);
  EXPECT_NEAR(dec.position().lat_deg, 48.1372, 1e-12);
}

// A bus carrying attitude epochs with a position fix in each: the attitude reader gets every
// attitude sample and the fixes wait for positions() (the oldest dropped, counted, beyond 8).
struct ScriptedCan final : hal::CanBus {
  hal::Status receive(hal::CanFrame& out, std::uint32_t) noexcept override {
    if (next >= frames.size()) return hal::Status::kTimeout;
    out = frames[next++];
    return hal::Status::kOk;
  }
  hal::Status send(const hal::CanFrame&) noexcept override { return hal::Status::kOk; }
  std::vector<hal::CanFrame> frames;
  std::size_t next{0};
};

TEST(SbgCanPosition, AttitudeSourceQueuesTheFixesForItsPositionSource) {
  ScriptedCan bus;
  const std::size_t epochs = 10;
  for (std::size_t k = 0; k < epochs; ++k) {
    bus.frames.push_back(encode_status_03(0xF4, 0));
    bus.frames.push_back(encode_ekf_info(static_cast<std::uint32_t>(1000 * k)));
    bus.frames.push_back(encode_ekf_pos(48.0 + 1e-5 * static_cast<double>(k), 11.0));
    bus.frames.push_back(encode_ekf_altitude(500.0, 47.0));
    bus.frames.push_back(encode_ekf_quat({1, 0, 0, 0}));
  }
  CanAttitudeSource src(bus);
  hal::PositionSource& pos = src.positions();
  hal::PositionSample p;
  EXPECT_EQ(pos.read(p, 1000), hal::Status::kNoData);  // never reads the bus itself
  EXPECT_EQ(bus.next, 0u);
  hal::AttitudeSample a;
  ASSERT_EQ(src.read(a, 0), hal::Status::kOk);
  ASSERT_EQ(pos.read(p, 0), hal::Status::kOk);
  EXPECT_NEAR(p.lat_deg, 48.0, 1e-9);
  EXPECT_EQ(pos.read(p, 0), hal::Status::kNoData);
  std::size_t attitudes = 1;
  while (src.read(a, 0) == hal::Status::kOk)
    ++attitudes;
  EXPECT_EQ(attitudes, epochs);
  // 9 fixes queued, 8 kept: the oldest of them went.
  EXPECT_EQ(pos.counters().overflows, 1u);
  std::size_t fixes = 0;
  while (pos.read(p, 0) == hal::Status::kOk) {
    EXPECT_NEAR(p.lat_deg, 48.0 + 1e-5 * static_cast<double>(fixes + 2), 1e-9);
    ++fixes;
  }
  EXPECT_EQ(fixes, 8u);
  EXPECT_EQ(pos.counters().samples, epochs);
}

}  // namespace
}  // namespace magvec::drivers::sbg
