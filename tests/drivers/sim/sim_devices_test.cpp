// Simulated devices (drivers/sim/sim_devices.hpp) under the REAL drivers: round trips within the
// quantisation of each format, and every injected fault detected and counted by the driver.
#include "magvec/drivers/sim/sim_devices.hpp"

#include <gtest/gtest.h>

#include <cmath>

#include "magvec/core/frames.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/serial_fluxgate.hpp"

namespace {

using namespace magvec;
using drivers::sim::MagLink;
using drivers::sim::ScenarioConfig;
using drivers::sim::SimRig;
using drivers::sim::SimRigConfig;
using drivers::sim::Simulator;

ScenarioConfig short_survey(std::uint32_t samples) {
  ScenarioConfig c = drivers::sim::scenario_survey();  // 200 Hz, Li truth, |h| = 53729 nT
  c.num_samples = samples;
  return c;
}

SimRigConfig spi_rig() {
  SimRigConfig r;
  r.link = MagLink::kSpi;
  r.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};  // +/-120 uT range at gain 1
  return r;
}

constexpr double kLsbNt = 1.2 / 8388608.0 * 1e5;  // one ADC code at 1e5 nT/V, gain 1

TEST(SimAds131Device, CodeFromNtInvertsTheDriverTransfer) {
  for (const std::uint8_t gain : {std::uint8_t{0}, std::uint8_t{3}}) {
    for (const double nT : {0.0, 1.0, -14999.3, 12345.6, -1e-3}) {  // inside +/-15 uT (gain 8)
      const std::int32_t code = drivers::sim::SimAds131Device::code_from_nT(nT, 1e5, gain);
      const double back = drivers::ads131::code_to_volts(code, gain) * 1e5;
      EXPECT_LE(std::fabs(back - nT), 0.5 * kLsbNt / drivers::ads131::gain_from_code(gain) + 1e-12);
    }
  }
  bool clipped = false;
  EXPECT_EQ(drivers::sim::SimAds131Device::code_from_nT(2e5, 1e5, 0, &clipped),
            drivers::ads131::kCodePositiveFullScale);
  EXPECT_TRUE(clipped);
  EXPECT_EQ(drivers::sim::SimAds131Device::code_from_nT(-2e5, 1e5, 0, &clipped),
            drivers::ads131::kCodeNegativeFullScale);
  EXPECT_TRUE(clipped);
}

TEST(SimAds131Device, RealDriverReadsBackTheSimulatorWithinHalfAnLsb) {
  Simulator sim(short_survey(2000), 7);
  SimRigConfig rc = spi_rig();
  rc.adc.transfer.gain_code = {1, 1, 1, 0};  // gain 2 on the used channels: checks GAIN1 path
  rc.adc.transfer.nT_per_volt = {2e5, 2e5, 2e5};
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  EXPECT_EQ(rig.adc().gain1(), drivers::ads131::gain1_register(rc.adc.transfer.gain_code));
  double worst = 0;
  std::uint32_t n = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    EXPECT_EQ(s.t_us, rig.host_us(rig.last().t_s));
    EXPECT_EQ(s.flags, 0u);
    for (int i = 0; i < 3; ++i)
      worst = std::fmax(worst, std::fabs(s.m_nT[static_cast<std::size_t>(i)] - rig.last().m_nT[i]));
    ++n;
    hal::MagnetometerSample none;
    EXPECT_EQ(fg.read(none, 0), hal::Status::kTimeout);  // one DRDY edge per conversion
  }
  EXPECT_EQ(n, 2000u);
  // 1 LSB = 1.2 V / 2 / 2^23 * 2e5 nT/V = 0.0143 nT.
  EXPECT_LE(worst, 0.5 * kLsbNt + 1e-9);
  EXPECT_GT(worst, 0.2 * kLsbNt);  // it is quantised (not a pass-through)
  EXPECT_EQ(fg.counters().samples, 2000u);
  EXPECT_EQ(fg.counters().crc_errors, 0u);
  EXPECT_EQ(rig.adc().injected().bad_commands, 0u);
}

TEST(SimAds131Device, CrcErrorsAreAllDetectedAndCounted) {
  Simulator sim(short_survey(4000), 11);
  SimRigConfig rc = spi_rig();
  rc.adc.faults.crc_error_probability = 0.05;
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  std::uint32_t ok = 0, crc = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    const hal::Status st = fg.read(s, 0);
    if (st == hal::Status::kOk) {
      ++ok;
      for (int i = 0; i < 3; ++i)
        EXPECT_NEAR(s.m_nT[static_cast<std::size_t>(i)], rig.last().m_nT[i], 0.5 * kLsbNt + 1e-9);
    } else {
      EXPECT_EQ(st, hal::Status::kCrcError);
      ++crc;
    }
  }
  const auto& inj = rig.adc().injected();
  EXPECT_GT(inj.crc_corrupted, 150u);  // ~5 % of 4000
  EXPECT_LT(inj.crc_corrupted, 260u);
  EXPECT_EQ(fg.counters().crc_errors, inj.crc_corrupted);
  EXPECT_EQ(crc, inj.crc_corrupted);
  EXPECT_EQ(ok + crc, 4000u);
  EXPECT_EQ(fg.counters().samples, ok);
}

TEST(SimAds131Device, SaturationAndDropoutsAreFlaggedAndCounted) {
  ScenarioConfig c = short_survey(4000);
  c.dropout_probability = 0.03;
  Simulator sim(c, 12);
  SimRigConfig rc = spi_rig();
  rc.adc.faults.saturation_probability = 0.02;
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  std::uint32_t not_fresh = 0, sim_dropouts = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    const bool dropout = !rig.last().m_nT.allFinite();
    sim_dropouts += dropout ? 1u : 0u;
    EXPECT_EQ((s.flags & hal::kMagNotFresh) != 0, dropout);
    not_fresh += (s.flags & hal::kMagNotFresh) != 0 ? 1u : 0u;
  }
  const auto& inj = rig.adc().injected();
  EXPECT_GT(inj.saturated, 50u);
  EXPECT_GT(sim_dropouts, 80u);
  EXPECT_EQ(not_fresh, inj.not_fresh);
  EXPECT_EQ(not_fresh, sim_dropouts);
  // Every frame with a full-scale code (forced, or held through a dropout) is counted.
  EXPECT_GE(inj.saturated_frames, inj.saturated);
  EXPECT_EQ(fg.counters().saturated, inj.saturated_frames);
  EXPECT_EQ(inj.range_clipped, 0u);
  EXPECT_EQ(fg.counters().stuck, 0u);
}

// Device resets mid-stream and a stuck channel, at gain 2 (a reset puts the device back at gain
// 1): the real driver flags and counts each reset, configures the device again, and every sample
// it does not flag reads back within half an LSB; the stuck detector flags the stuck window from
// its 64th equal code on.
TEST(SimAds131Device, ResetsMidStreamAndAStuckChannelAreFlaggedAndCounted) {
  Simulator sim(short_survey(4000), 13);  // 20 s at 200 Hz
  SimRigConfig rc = spi_rig();
  rc.adc.transfer.gain_code = {1, 1, 1, 0};
  rc.adc.transfer.nT_per_volt = {2e5, 2e5, 2e5};
  rc.adc.faults.reset_probability = 0.005;
  rc.adc.faults.stuck_start_s = 10;
  rc.adc.faults.stuck_length_s = 2;  // 400 conversions
  rc.adc.faults.stuck_axis = 1;
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  std::uint32_t resets = 0, stuck = 0, good = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    resets += (s.flags & hal::kMagDeviceReset) != 0 ? 1u : 0u;
    stuck += (s.flags & hal::kMagStuck) != 0 ? 1u : 0u;
    const bool in_window = rig.last().t_s >= 10 && rig.last().t_s < 12;
    if ((s.flags & hal::kMagInvalidMask) != 0 || in_window) continue;
    ++good;
    for (int i = 0; i < 3; ++i)
      EXPECT_NEAR(s.m_nT[static_cast<std::size_t>(i)], rig.last().m_nT[i], 0.5 * kLsbNt + 1e-9);
  }
  const auto& inj = rig.adc().injected();
  EXPECT_GT(inj.resets, 10u);
  EXPECT_EQ(resets, inj.resets);
  EXPECT_EQ(fg.counters().device_resets, inj.resets);
  EXPECT_EQ(inj.reset_frames, inj.resets);
  EXPECT_EQ(inj.stuck_conversions, 400u);
  // A reset in the window restarts the detector: at most 400 - 62 flagged.
  EXPECT_EQ(fg.counters().stuck, stuck);
  EXPECT_EQ(inj.stuck_frames, stuck);
  EXPECT_GT(stuck, 100u);
  EXPECT_LE(stuck, 400u - (rc.adc.transfer.stuck_count - 2));
  EXPECT_GT(good, 3500u);
  EXPECT_TRUE(fg.initialised());
}

// Channel 3 as the fluxgate's temperature: the real driver reads back the simulator's
// temperature ramp within half a code of the temperature transfer; while the sensor is open
// (full scale) the samples come without a temperature, counted, with their field values intact.
TEST(SimAds131Device, TemperatureChannelReadsBackTheRampAndAnOpenSensorIsCounted) {
  ScenarioConfig sc = short_survey(4000);  // 20 s at 200 Hz
  sc.temp_start_c = 5.0;
  sc.temp_rate_c_per_s = 1.0;  // 5 .. 25 degC
  Simulator sim(sc, 17);
  SimRigConfig rc = spi_rig();
  rc.adc.transfer.temperature.enabled = true;  // 100 degC/V, 0 degC at 0 V (the defaults)
  rc.adc.faults.temperature_open_start_s = 12;
  rc.adc.faults.temperature_open_length_s = 1;  // 200 conversions
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  // One code of the temperature channel at gain 1: 1.2 V / 2^23 * 100 degC/V.
  constexpr double kLsbDegC = 1.2 / 8388608.0 * 100.0;
  double worst = 0;
  std::uint32_t with_t = 0, without_t = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    EXPECT_EQ(s.flags, 0u);  // an open temperature sensor does not invalidate the field
    for (int i = 0; i < 3; ++i)
      EXPECT_NEAR(s.m_nT[static_cast<std::size_t>(i)], rig.last().m_nT[i], 0.5 * kLsbNt + 1e-9);
    const double t = rig.last().t_s;
    if (t >= 12 && t < 13) {
      EXPECT_TRUE(std::isnan(s.temperature_degC)) << t;
      ++without_t;
      continue;
    }
    ASSERT_TRUE(std::isfinite(s.temperature_degC)) << t;
    worst = std::fmax(worst, std::fabs(s.temperature_degC - rig.last().temperature_c));
    ++with_t;
  }
  EXPECT_EQ(with_t, 3800u);
  EXPECT_EQ(without_t, 200u);
  EXPECT_LE(worst, 0.5 * kLsbDegC + 1e-9);
  EXPECT_EQ(rig.adc().injected().temperature_open, 200u);
  EXPECT_EQ(fg.counters().temperature_rejected, 200u);
  EXPECT_EQ(fg.counters().samples, 4000u);
}

// Disabled (the default), channel 3 is not read as a temperature: NaN, nothing counted.
TEST(SimAds131Device, TemperatureChannelOffGivesNoTemperature) {
  Simulator sim(short_survey(200), 5);
  SimRigConfig rc = spi_rig();
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    EXPECT_TRUE(std::isnan(s.temperature_degC));
  }
  EXPECT_EQ(fg.counters().temperature_rejected, 0u);
  EXPECT_EQ(rig.adc().injected().temperature_open, 0u);
}

TEST(SimAds131Device, ClockJumpShiftsDrdyTimestamps) {
  Simulator sim(short_survey(400), 3);
  SimRigConfig rc = spi_rig();
  rc.time.jump_at_s = 1.0;
  rc.time.jump_us = -400'000;  // backwards: the fault under test
  SimRig rig(sim, rc);
  drivers::Ads131Fluxgate fg(rig.adc(), rig.adc(), rc.adc.transfer);
  ASSERT_EQ(fg.init(), hal::Status::kOk);
  std::uint64_t prev = 0;
  int backwards = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    if (prev != 0 && s.t_us < prev) {
      ++backwards;
      EXPECT_EQ(prev - s.t_us, 400'000u - 5'000u);
    }
    prev = s.t_us;
  }
  EXPECT_EQ(backwards, 1);
  EXPECT_EQ(rig.clock_jumps_injected(), 1u);
}

TEST(SimAds131Device, MissedEdgesWhenTheHostDoesNotRead) {
  Simulator sim(short_survey(20), 3);
  SimRig rig(sim, spi_rig());
  while (rig.step()) {
  }
  EXPECT_EQ(rig.adc().missed_edges(), 20u - drivers::sim::SimAds131Device::kEdgeQueue);
}

// ---------------------------------------------------------------- serial

SimRigConfig serial_rig() {
  SimRigConfig r;
  r.link = MagLink::kSerial;
  r.serial.line.checksum = drivers::ChecksumMode::kRequired;
  return r;
}

using SerialAscii = drivers::SerialFluxgate<drivers::AsciiLineDecoder>;

TEST(SimSerialFluxgate, RealDriverReadsBackLinesWithinTheirResolution) {
  Simulator sim(short_survey(1000), 5);
  const SimRigConfig rc = serial_rig();
  SimRig rig(sim, rc);
  SerialAscii fg(rig.serial(), rig.clock(), drivers::AsciiLineDecoder(rc.serial.line));
  std::uint32_t n = 0;
  while (rig.step()) {
    hal::MagnetometerSample s;
    ASSERT_EQ(fg.read(s, 0), hal::Status::kOk);
    EXPECT_EQ(s.t_us, rig.host_us(rig.last().t_s));
    for (int i = 0; i < 3; ++i)
      EXPECT_NEAR(s.m_nT[static_cast<std::size_t>(i)], rig.last().m_nT[i], 0.0005 + 1e-9);
    ++n;
  }
  EXPECT_EQ(n, 1000u);
  EXPECT_EQ(fg.counters().garbage_bytes, 0u);
}

TEST(SimSerialFluxgate, GarbageBadChecksumsAndDropoutsAreCounted) {
  ScenarioConfig c = short_survey(4000);
  c.dropout_probability = 0.02;
  Simulator sim(c, 6);
  SimRigConfig rc = serial_rig();
  rc.serial.faults.garbage_probability = 0.05;
  rc.serial.faults.bad_checksum_probability = 0.03;
  SimRig rig(sim, rc);
  SerialAscii fg(rig.serial(), rig.clock(), drivers::AsciiLineDecoder(rc.serial.line));
  std::uint32_t ok = 0;
  std::uint32_t crc_errors = 0;  // returned by read(), as the ADC source returns a bad frame
  while (rig.step()) {
    hal::MagnetometerSample s;
    for (;;) {
      const hal::Status st = fg.read(s, 0);
      if (st == hal::Status::kNoData || st == hal::Status::kTimeout) break;
      if (st == hal::Status::kCrcError) {
        ++crc_errors;
        continue;
      }
      ASSERT_EQ(st, hal::Status::kOk);
      ++ok;
      for (int i = 0; i < 3; ++i)
        EXPECT_NEAR(s.m_nT[static_cast<std::size_t>(i)], rig.last().m_nT[i], 0.0005 + 1e-9);
    }
  }
  EXPECT_EQ(crc_errors, rig.serial().injected().bad_checksums);
  const auto& inj = rig.serial().injected();
  EXPECT_GT(inj.garbage_bytes, 500u);
  EXPECT_GT(inj.bad_checksums, 60u);
  EXPECT_GT(inj.dropouts, 40u);
  EXPECT_EQ(fg.counters().garbage_bytes, inj.garbage_bytes);
  EXPECT_EQ(fg.counters().crc_errors, inj.bad_checksums);
  EXPECT_EQ(fg.counters().malformed, 0u);
  EXPECT_EQ(ok, inj.lines - inj.bad_checksums);
  EXPECT_EQ(inj.lines + inj.dropouts, 4000u);
  EXPECT_EQ(inj.overflow_bytes, 0u);
}

// ---------------------------------------------------------------- SBG INS

TEST(SimSbgIns, RealDecoderReadsBackAttitudeWithinInt16Quantisation) {
  ScenarioConfig c = short_survey(2000);  // 10 s
  c.ins_noise_deg = 0.0;
  Simulator sim(c, 9);
  SimRigConfig rc = spi_rig();
  SimRig rig(sim, rc);
  drivers::sbg::CanAttitudeSource ins(rig.ins());
  std::uint32_t n = 0;
  double worst = 0;
  while (rig.step()) {
    hal::AttitudeSample a;
    while (ins.read(a, 0) == hal::Status::kOk) {
      const double t = static_cast<double>(n) / 100.0;  // epoch k at k / 100 Hz
      EXPECT_EQ(a.t_us, rig.host_us(t) + rc.ins.can_latency_us);
      EXPECT_EQ(a.t_ins_us,
                static_cast<std::uint64_t>(std::llround(t * 1e6)) + rc.ins.ins_clock_offset_us);
      EXPECT_EQ(a.flags, hal::kAttAttitudeValid | hal::kAttHeadingValid | hal::kAttStatusKnown |
                             hal::kAttAccuracyKnown);
      const core::Quat<double> q(a.q_nb[0], a.q_nb[1], a.q_nb[2], a.q_nb[3]);
      const double err =
          core::rotation_angle_between(core::r_bn_from_quat(q), sim.true_attitude_at(t));
      worst = std::fmax(worst, err);
      EXPECT_NEAR(a.sigma_rad[0], rc.ins.accuracy_rad, 0.5e-4);
      ++n;
    }
  }
  EXPECT_EQ(n, rig.ins().injected().epochs);
  EXPECT_GE(n, 1000u);
  // int16/32767 per component: a rounding error of 0.5/32767 on each of 4 components moves the
  // rotation by at most 2 * |dq| = 2 * sqrt(4) * 0.5 / 32767 = 6.1e-5 rad.
  EXPECT_LE(worst, 6.2e-5);
  EXPECT_EQ(ins.counters().malformed, 0u);
  EXPECT_EQ(ins.counters().missing_time, 0u);
}

TEST(SimSbgIns, CorruptedFramesAreCountedAsMalformed) {
  Simulator sim(short_survey(6000), 10);
  SimRigConfig rc = spi_rig();
  rc.ins.faults.corrupt_probability = 0.03;
  SimRig rig(sim, rc);
  drivers::sbg::CanAttitudeSource ins(rig.ins());
  std::uint32_t n = 0;
  while (rig.step()) {
    hal::AttitudeSample a;
    while (ins.read(a, 0) == hal::Status::kOk)
      ++n;
  }
  const auto& inj = rig.ins().injected();
  EXPECT_GT(inj.corrupted_frames, 40u);
  EXPECT_EQ(ins.counters().malformed, inj.corrupted_frames);
  EXPECT_EQ(n, inj.epochs - inj.corrupted_epochs);
  EXPECT_LE(ins.counters().missing_time, inj.corrupted_epochs);
  EXPECT_EQ(inj.overflow_frames, 0u);
}

// Duplicates alone and next to truncated frames: the real decoder drops every copy (a frame
// received twice, the repeat of an epoch it had sampled) and re-counts what a repeated corrupt
// epoch loses; no epoch gives two samples.
TEST(SimSbgIns, DuplicatedFramesAndRepeatedEpochsAreDroppedAndCounted) {
  for (const double corrupt : {0.0, 0.03}) {
    Simulator sim(short_survey(6000), 10);
    SimRigConfig rc = spi_rig();
    rc.ins.faults.duplicate_probability = 0.1;
    rc.ins.faults.corrupt_probability = corrupt;
    SimRig rig(sim, rc);
    drivers::sbg::CanAttitudeSource ins(rig.ins());
    std::uint32_t n = 0;
    std::uint64_t last_ins_us = 0;
    while (rig.step()) {
      hal::AttitudeSample a;
      while (ins.read(a, 0) == hal::Status::kOk) {
        EXPECT_TRUE(n == 0 || a.t_ins_us > last_ins_us) << "an epoch sampled twice";
        last_ins_us = a.t_ins_us;
        ++n;
      }
    }
    const auto& inj = rig.ins().injected();
    EXPECT_GT(inj.duplicated_frames, 30u);
    EXPECT_GT(inj.repeated_epochs, 30u);
    EXPECT_EQ(ins.counters().duplicates, inj.duplicated_frames + inj.repeated_sampled_epochs);
    EXPECT_EQ(ins.counters().malformed, inj.corrupted_frames);
    EXPECT_EQ(ins.counters().missing_time, inj.untimed_epochs);
    EXPECT_EQ(n, inj.epochs - inj.corrupted_epochs);
    EXPECT_EQ(inj.overflow_frames, 0u);
    if (corrupt > 0) {
      EXPECT_LT(inj.repeated_sampled_epochs, inj.repeated_epochs);  // some repeats fail again
    } else {
      EXPECT_EQ(inj.repeated_sampled_epochs, inj.repeated_epochs);
    }
  }
}

TEST(SimSbgIns, GapAndInvalidStatusWindows) {
  Simulator sim(short_survey(4000), 10);  // 20 s
  SimRigConfig rc = spi_rig();
  rc.ins.faults.gap_start_s = 5.0;
  rc.ins.faults.gap_length_s = 1.0;
  rc.ins.faults.invalid_start_s = 10.0;
  rc.ins.faults.invalid_length_s = 2.0;
  SimRig rig(sim, rc);
  drivers::sbg::CanAttitudeSource ins(rig.ins());
  std::uint32_t n = 0, invalid = 0, in_gap = 0;
  while (rig.step()) {
    hal::AttitudeSample a;
    while (ins.read(a, 0) == hal::Status::kOk) {
      ++n;
      const double t = static_cast<double>(a.t_ins_us - rc.ins.ins_clock_offset_us) * 1e-6;
      if (t >= 5.0 && t < 6.0) ++in_gap;
      if ((a.flags & hal::kAttAttitudeValid) == 0) {
        ++invalid;
        EXPECT_GE(t, 10.0);
        EXPECT_LT(t, 12.0);
      }
    }
  }
  const auto& inj = rig.ins().injected();
  EXPECT_EQ(inj.gap_epochs, 100u);
  EXPECT_EQ(inj.invalid_epochs, 200u);
  EXPECT_EQ(in_gap, 0u);
  EXPECT_EQ(invalid, inj.invalid_epochs);
  EXPECT_EQ(n, inj.epochs);
}

}  // namespace
