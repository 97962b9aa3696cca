// LCM message types of magvecd (host/lcm/*.lcm), tested for real over LCM's in-process memq
// provider: every type published and received back field for field, and the HAL <-> LCM
// conversions (lcm_codec.hpp) exact to the bit (replay depends on it).
#include <gtest/gtest.h>

#include <cmath>
#include <cstring>
#include <lcm/lcm-cpp.hpp>
#include <limits>

#include "magvec/host/daemon/lcm_codec.hpp"

namespace magvec::host::daemon {
namespace {

template <typename Msg>
struct Catcher {
  int count{0};
  Msg last{};
  std::string channel;
  void on(const lcm::ReceiveBuffer*, const std::string& ch, const Msg* m) {
    ++count;
    last = *m;
    channel = ch;
  }
};

// Publishes `m` on memq and returns what the subscriber received.
template <typename Msg>
Msg round_trip(lcm::LCM& l, const Msg& m, const std::string& channel) {
  Catcher<Msg> c;
  lcm::Subscription* s = l.subscribe(channel, &Catcher<Msg>::on, &c);
  EXPECT_EQ(l.publish(channel, &m), 0);
  EXPECT_GE(l.handleTimeout(1000), 1);
  l.unsubscribe(s);
  EXPECT_EQ(c.count, 1);
  EXPECT_EQ(c.channel, channel);
  return c.last;
}

bool same_bits(double a, double b) {
  return std::memcmp(&a, &b, sizeof a) == 0;
}

class LcmTypes : public ::testing::Test {
 protected:
  lcm::LCM lcm_{"memq://"};
};

TEST_F(LcmTypes, MemqProviderWorks) {
  ASSERT_TRUE(lcm_.good());
}

TEST_F(LcmTypes, MagSampleRoundTripIsExact) {
  hal::MagnetometerSample s;
  s.t_us = 12'345'678'901ULL;
  s.m_nT = {-4053.123456789012, 25022.000000000004, std::numeric_limits<double>::quiet_NaN()};
  s.raw = {-8388608, 8388607, 17};
  s.flags = hal::kMagNotFresh | hal::kMagSaturated;
  s.sequence = 0xFFFFFFF0u;  // above INT32_MAX: carried through the int32 field bit for bit
  const auto back = round_trip(lcm_, to_lcm(s, 53729.25), "T_MAG");
  const hal::MagnetometerSample r = from_lcm(back);
  EXPECT_EQ(r.t_us, s.t_us);
  for (std::size_t i = 0; i < 3; ++i) {
    EXPECT_TRUE(same_bits(r.m_nT[i], s.m_nT[i])) << i;
    EXPECT_EQ(r.raw[i], s.raw[i]);
  }
  EXPECT_EQ(r.flags, s.flags);
  EXPECT_EQ(r.sequence, s.sequence);
  EXPECT_EQ(back.f_ref_nT, 53729.25);
}

TEST_F(LcmTypes, AttitudeRoundTripIsExact) {
  hal::AttitudeSample a;
  a.t_us = 10'000'500;
  a.t_ins_us = 123'456;
  a.q_nb = {0.7071067811865476, 0.1, -0.2, 0.6745368781616021};
  a.sigma_rad = {2.6e-4, 2.7e-4, 1e-3};
  a.flags = hal::kAttAttitudeValid | hal::kAttHeadingValid | hal::kAttStatusKnown;
  a.solution_mode = 4;
  const hal::AttitudeSample r = from_lcm(round_trip(lcm_, to_lcm(a), "T_ATT"));
  EXPECT_EQ(r.t_us, a.t_us);
  EXPECT_EQ(r.t_ins_us, a.t_ins_us);
  for (std::size_t i = 0; i < 4; ++i)
    EXPECT_TRUE(same_bits(r.q_nb[i], a.q_nb[i]));
  for (std::size_t i = 0; i < 3; ++i)
    EXPECT_TRUE(same_bits(r.sigma_rad[i], a.sigma_rad[i]));
  EXPECT_EQ(r.flags, a.flags);
  EXPECT_EQ(r.solution_mode, a.solution_mode);
}

TEST_F(LcmTypes, CalibratedVectorRoundTripIsBitIdentical) {
  hal::OutputRecord o;
  o.t_us = 99;
  o.raw_nT = {1.5, -2.25, 3.125};
  o.h_s_nT = {1.0 / 3.0, -2.0 / 7.0, 1e-300};
  o.h_n_nT = {std::numeric_limits<double>::quiet_NaN(), 0.0, -0.0};
  o.f_nT = 53729.123;
  o.sigma_f_nT = 0.3;
  o.flags = 0x24;
  o.cal_id = 7;
  const hal::OutputRecord r = from_lcm(round_trip(lcm_, to_lcm(o), "T_OUT"));
  EXPECT_TRUE(bit_identical(r, o));
  hal::OutputRecord changed = r;
  changed.h_n_nT[2] = 0.0;  // -0.0 -> +0.0: equal as numbers, different bits
  EXPECT_FALSE(bit_identical(changed, o));
}

TEST_F(LcmTypes, CalibrationStateRoundTrip) {
  CalibrationStatus st;
  st.calibrator = "li";
  st.state = core::CalState::kFailed;
  st.failure = core::CalFailure::kSolverRejected;
  st.solver_reason = "insufficient_coverage";
  st.progress = 0.25;
  st.validation_rms_nT = 0.5;
  st.cal_id = 3;
  st.active.w = core::Mat3<double>::Identity() * 1.01;
  st.active.o = core::Vec3<double>(1, 2, 3);
  st.active.rm = core::Quat<double>(0.9, 0.1, 0.2, 0.3).normalized();
  const auto m = round_trip(lcm_, to_lcm(st, 1234, 2), "T_CAL");
  EXPECT_EQ(m.t_us, 1234);
  EXPECT_EQ(m.calibrator, "li");
  EXPECT_EQ(m.state, "failed");
  EXPECT_EQ(m.failure, "solver_rejected");
  EXPECT_EQ(m.solver_reason, "insufficient_coverage");
  EXPECT_EQ(m.progress, 0.25);
  EXPECT_EQ(m.cal_id, 3);
  EXPECT_EQ(m.persisted_cal_id, 2);
  const core::SensorModel<double> back = model_from_arrays(m.w, m.o_nT, m.rm_quat);
  EXPECT_EQ(back.w, st.active.w);
  EXPECT_EQ(back.o, st.active.o);
  EXPECT_EQ(back.rm.coeffs(), st.active.rm.coeffs());
}

TEST_F(LcmTypes, HealthRoundTrip) {
  magvec_lcm::health h{};
  h.t_us = 1;
  h.uptime_ms = 2;
  h.mag_samples = 3;
  h.mag_crc_errors = 4;
  h.att_samples = 5;
  h.records = 6;
  h.calibrations_applied = 7;
  h.publish_errors = 8;
  const auto r = round_trip(lcm_, h, "T_HEALTH");
  EXPECT_EQ(r.t_us, 1);
  EXPECT_EQ(r.uptime_ms, 2);
  EXPECT_EQ(r.mag_samples, 3);
  EXPECT_EQ(r.mag_crc_errors, 4);
  EXPECT_EQ(r.att_samples, 5);
  EXPECT_EQ(r.records, 6);
  EXPECT_EQ(r.calibrations_applied, 7);
  EXPECT_EQ(r.publish_errors, 8);
}

// The device counters of the health message: every source counter in its own field, the scalar
// part only with a scalar magnetometer.
TEST_F(LcmTypes, HealthCarriesEveryDeviceCounter) {
  hal::MagCounters mc{};
  mc.samples = 10;
  mc.crc_errors = 11;
  mc.malformed = 12;
  mc.bus_errors = 13;
  mc.timeouts = 14;
  mc.saturated = 15;
  mc.device_resets = 16;
  hal::AttitudeCounters ac{};
  ac.samples = 20;
  ac.malformed = 21;
  ac.duplicates = 22;
  magvec_lcm::health none{};
  set_device_health(none, mc, ac, nullptr);
  const auto n = round_trip(lcm_, none, "T_HEALTH");
  EXPECT_EQ(n.mag_samples, 10);
  EXPECT_EQ(n.mag_crc_errors, 11);
  EXPECT_EQ(n.mag_malformed, 12);
  EXPECT_EQ(n.mag_bus_errors, 13);
  EXPECT_EQ(n.mag_timeouts, 14);
  EXPECT_EQ(n.mag_saturated, 15);
  EXPECT_EQ(n.mag_device_resets, 16);
  EXPECT_EQ(n.att_samples, 20);
  EXPECT_EQ(n.att_malformed, 21);
  EXPECT_EQ(n.att_duplicates, 22);
  EXPECT_FALSE(n.scalar_present);
  EXPECT_EQ(n.scalar_samples, 0);

  ScalarHealth sh;
  sh.source.samples = 30;
  sh.source.malformed = 31;
  sh.source.crc_errors = 32;
  sh.source.out_of_range = 33;
  sh.source.overflows = 34;
  sh.source.garbage_bytes = 35;
  sh.source.low_signal = 36;
  sh.source.bus_errors = 37;
  sh.read_errors = 38;
  sh.timeouts = 39;
  sh.f_interpolated = 40;
  sh.f_nearest = 41;
  sh.f_fallback = 42;
  magvec_lcm::health with{};
  set_device_health(with, mc, ac, &sh);
  const auto w = round_trip(lcm_, with, "T_HEALTH");
  EXPECT_TRUE(w.scalar_present);
  EXPECT_EQ(w.mag_device_resets, 16);
  EXPECT_EQ(w.att_duplicates, 22);
  EXPECT_EQ(w.scalar_samples, 30);
  EXPECT_EQ(w.scalar_malformed, 31);
  EXPECT_EQ(w.scalar_crc_errors, 32);
  EXPECT_EQ(w.scalar_out_of_range, 33);
  EXPECT_EQ(w.scalar_overflows, 34);
  EXPECT_EQ(w.scalar_garbage_bytes, 35);
  EXPECT_EQ(w.scalar_low_signal, 36);
  EXPECT_EQ(w.scalar_bus_errors, 37);
  EXPECT_EQ(w.scalar_read_errors, 38);
  EXPECT_EQ(w.scalar_timeouts, 39);
  EXPECT_EQ(w.scalar_f_interpolated, 40);
  EXPECT_EQ(w.scalar_f_nearest, 41);
  EXPECT_EQ(w.scalar_f_fallback, 42);
}

TEST_F(LcmTypes, PipelineEventsRoundTrip) {
  const auto s = round_trip(lcm_, session_start_event(1, "[calibration]\nmode = \"ekf\"\n"), "T_P");
  EXPECT_EQ(
      s.kind,
      static_cast<std::int8_t>(
          magvec_lcm::pipeline_event::SESSION_START));  // copy: the constant has no definition
  EXPECT_EQ(s.sequence, 1);
  EXPECT_EQ(s.config_toml, "[calibration]\nmode = \"ekf\"\n");
  core::SensorModel<double> m;
  m.w << 1.1, 0.01, 0.02, 0.0, 0.9, 0.03, 0.0, 0.0, 1.05;
  m.o = core::Vec3<double>(100.5, -20.25, 3.0);
  m.rm = core::Quat<double>(0.99, 0.01, -0.02, 0.03).normalized();
  const auto a = round_trip(lcm_, set_active_event(2, m, 5), "T_P");
  EXPECT_EQ(a.kind,
            static_cast<std::int8_t>(
                magvec_lcm::pipeline_event::SET_ACTIVE));  // copy: the constant has no definition
  EXPECT_EQ(a.cal_id, 5);
  const core::SensorModel<double> back = model_from_arrays(a.w, a.o_nT, a.rm_quat);
  EXPECT_EQ(back.w, m.w);
  EXPECT_EQ(back.o, m.o);
  EXPECT_EQ(back.rm.coeffs(), m.rm.coeffs());
  const auto st = round_trip(lcm_, start_calibration_event(3), "T_P");
  EXPECT_EQ(
      st.kind,
      static_cast<std::int8_t>(
          magvec_lcm::pipeline_event::START_CALIBRATION));  // copy: the constant has no definition
  EXPECT_EQ(st.sequence, 3);
}

TEST_F(LcmTypes, CommandAndReplyRoundTrip) {
  magvec_lcm::command c;
  c.request_id = 0x123456789AB;
  c.command = "accept";
  const auto rc = round_trip(lcm_, c, "T_CMD");
  EXPECT_EQ(rc.request_id, c.request_id);
  EXPECT_EQ(rc.command, "accept");
  magvec_lcm::command_reply r{};
  r.request_id = c.request_id;
  r.ok = true;
  r.message = "calibration 2 persisted";
  CalibrationStatus st;
  st.calibrator = "ekf";
  st.cal_id = 2;
  r.state = to_lcm(st, 5, 2);
  const auto rr = round_trip(lcm_, r, "T_REPLY");
  EXPECT_EQ(rr.request_id, c.request_id);
  EXPECT_TRUE(rr.ok);
  EXPECT_EQ(rr.message, r.message);
  EXPECT_EQ(rr.state.calibrator, "ekf");
  EXPECT_EQ(rr.state.state, "idle");
  EXPECT_EQ(rr.state.cal_id, 2);
}

TEST_F(LcmTypes, TruncatedMessageFailsToDecode) {
  const magvec_lcm::mag_sample m = to_lcm(hal::MagnetometerSample{}, 1.0);
  std::vector<std::uint8_t> buf(static_cast<std::size_t>(m.getEncodedSize()));
  ASSERT_EQ(m.encode(buf.data(), 0, static_cast<int>(buf.size())), static_cast<int>(buf.size()));
  magvec_lcm::mag_sample out;
  EXPECT_LT(out.decode(buf.data(), 0, static_cast<int>(buf.size()) - 1), 0);
  buf[0] ^= 0xFF;  // fingerprint
  EXPECT_LT(out.decode(buf.data(), 0, static_cast<int>(buf.size())), 0);
}

}  // namespace
}  // namespace magvec::host::daemon
