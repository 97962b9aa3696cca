// magvecd's TOML configuration (host/daemon/config.hpp): numbers that have no exact double and
// text toml++ must never see (invalid UTF-8, non-ASCII outside comments) are configuration errors
// naming the file, the key or the line and column; lcm.raw_batch and its channel and sim.faults
// are checked; so are the model reference's keys.
#include "magvec/host/daemon/config.hpp"

#include <gtest/gtest.h>

#include <string>

namespace magvec::host::daemon {
namespace {

std::string error_of(const std::string& text) {
  try {
    (void)parse_config(text, "cfg.toml");
  } catch (const ConfigError& e) {
    return e.what();
  }
  return "no error";
}

// Regression: value<double>() of an integer beyond 2^53 is an empty optional; it was dereferenced.
TEST(DaemonConfigNumbers, IntegersWithoutAnExactDoubleAreRejected) {
  const std::string nt =
      error_of("[devices.magnetometer]\nnT_per_volt = [9007199254740993, 1e5, 1e5]\n");
  EXPECT_NE(nt.find("cfg.toml: devices.magnetometer.nT_per_volt: integer beyond 2^53"),
            std::string::npos)
      << nt;
  for (const char* text : {"[daemon]\nhealth_period_s = 9007199254740993\n",
                           "[daemon]\nstatus_period_s = -9223372036854775808\n",
                           "[calibration]\nreference_field_nT = 9223372036854775807\n",
                           "[devices.ins]\nrate_hz = 18014398509481985\n"}) {
    SCOPED_TRACE(text);
    EXPECT_NE(error_of(text).find("integer beyond 2^53"), std::string::npos) << error_of(text);
  }
  // 2^53 itself is exact: an ordinary range error.
  EXPECT_NE(error_of("[daemon]\nhealth_period_s = 9007199254740992\n").find("out of range"),
            std::string::npos);
  // Integers are fine where they are exact.
  EXPECT_EQ(
      parse_config("[devices.magnetometer]\nnT_per_volt = [100000, -20000, 5e4]\n", "cfg.toml")
          .magnetometer.adc.nT_per_volt,
      (std::array<double, 3>{1e5, -2e4, 5e4}));
}

TEST(DaemonConfigNumbers, TransferFactorsAreBounded) {
  for (const char* v : {"1e10", "-1e10", "0", "0.0", "inf", "nan", "9007199254740992.0"}) {
    SCOPED_TRACE(v);
    const std::string msg =
        error_of(std::string("[devices.magnetometer]\nnT_per_volt = [1e5, ") + v + ", 1e5]\n");
    EXPECT_NE(msg.find("nT_per_volt: expected non-zero numbers within +-1e9"), std::string::npos)
        << msg;
  }
  EXPECT_NE(error_of("[devices.magnetometer]\nnT_per_volt = [1e5, \"1e5\", 1e5]\n")
                .find("expected numbers"),
            std::string::npos);
}

// toml++ 3.3.0 reaches TOML_UNREACHABLE (undefined behaviour) on some non-ASCII text; such text is
// rejected before it is parsed.
TEST(DaemonConfigText, NonAsciiOutsideCommentsIsRejectedWithLineAndColumn) {
  // The upstream report's document: a line-ending backslash in a multi-line string, then U+00A7.
  EXPECT_EQ(error_of("s = \"\"\"\\\n\xC2\xA7\"\"\"\n"),
            "cfg.toml:2:1: non-ASCII character outside a comment (keys and values must be ASCII)");
  // A combining mark (U+032A) where a key is expected.
  EXPECT_NE(error_of("\xCC\xAA").find("cfg.toml:1:1: non-ASCII character"), std::string::npos);
  EXPECT_NE(error_of("[daemon]\nstate_dir = \"/var/lib/m\xC3\xA4gvec\"\n")
                .find("cfg.toml:2:24: non-ASCII"),
            std::string::npos);
  // A '#' inside a string does not start a comment.
  EXPECT_NE(error_of("[lcm]\nurl = \"udpm://#\xC3\xA4\"\n").find("cfg.toml:2:16: non-ASCII"),
            std::string::npos);
  EXPECT_NE(error_of("[lcm]\nurl = 'a#\xC3\xA4'\n").find("cfg.toml:2:10: non-ASCII"),
            std::string::npos);
  EXPECT_NE(error_of("[lcm]\nurl = '''a\n#\xC3\xA4'''\n").find("cfg.toml:3:2: non-ASCII"),
            std::string::npos);
  EXPECT_NE(error_of("[lcm]\nurl = \"a\\\"#\xC3\xA4\"\n").find("cfg.toml:2:12: non-ASCII"),
            std::string::npos);
}

TEST(DaemonConfigText, InvalidUtf8IsRejectedEvenInComments) {
  for (const char* bad : {"\xFF", "\xC0\xAF", "\xE0\x80\xAF", "\xED\xA0\x80", "\xF4\x90\x80\x80",
                          "\xC3", "\xE2\x82", "\x80"}) {
    SCOPED_TRACE(testing::PrintToString(std::string(bad)));
    EXPECT_EQ(error_of(std::string("# ok\n# x") + bad + "\n"), "cfg.toml:2:4: invalid UTF-8");
  }
}

TEST(DaemonConfigText, NonAsciiCommentsAreAllowed) {
  const Config c = parse_config(
      "# Stra\xC3\x9F"
      "e, 20 \xC2\xB5T, \xE2\x80\x83 \xF0\x9F\xA7\xAD\n"
      "[lcm]  # \xC3\xA4\n"
      "url = '''udpm://a#b'''  # \xC3\xB6 after a multi-line literal\n"
      "[lcm.channels]\n"
      "raw_mag = \"\"\"M\"\"\"\"  # \xC3\xBC after a closing quote inside the delimiter\n"
      "output = \"a\\\\\"  # \xC3\xA9 after an escaped backslash\n",
      "cfg.toml");
  EXPECT_EQ(c.lcm.url, "udpm://a#b");
  EXPECT_EQ(c.lcm.channels.raw_mag, "M\"");
  EXPECT_EQ(c.lcm.channels.output, "a\\");
}

// lcm.raw_batch: 1 (default, per-sample messages) to kMaxRawBatch; anything else is an error
// naming the key, as --check-config prints it.
TEST(DaemonConfigLcm, RawBatchIsAnIntegerInItsRange) {
  EXPECT_EQ(parse_config("", "cfg.toml").lcm.raw_batch, 1u);
  EXPECT_EQ(parse_config("[lcm]\nraw_batch = 1\n", "cfg.toml").lcm.raw_batch, 1u);
  EXPECT_EQ(parse_config("[lcm]\nraw_batch = 10\n", "cfg.toml").lcm.raw_batch, 10u);
  EXPECT_EQ(parse_config("[lcm]\nraw_batch = 1000\n", "cfg.toml").lcm.raw_batch, kMaxRawBatch);
  for (const char* bad : {"0", "-1", "1001", "4294967297", "-9223372036854775808"}) {
    SCOPED_TRACE(bad);
    EXPECT_EQ(error_of(std::string("[lcm]\nraw_batch = ") + bad + "\n"),
              "cfg.toml: lcm.raw_batch: out of range [1, 1000]");
  }
  for (const char* bad : {"2.5", "10.0", "\"10\"", "true", "nan", "[10]"}) {
    SCOPED_TRACE(bad);
    EXPECT_EQ(error_of(std::string("[lcm]\nraw_batch = ") + bad + "\n"),
              "cfg.toml: lcm.raw_batch: expected an integer");
  }
  EXPECT_EQ(error_of("[lcm]\nraw_batc = 10\n"), "cfg.toml: lcm.raw_batc: unknown key");
}

TEST(DaemonConfigSim, WakePeriodIsBounded) {
  EXPECT_EQ(parse_config("", "cfg.toml").sim.wake_period_us, 0u);
  EXPECT_EQ(parse_config("[sim]\nwake_period_us = 10000\n", "cfg.toml").sim.wake_period_us,
            10'000u);
  EXPECT_EQ(error_of("[sim]\nwake_period_us = -1\n"),
            "cfg.toml: sim.wake_period_us: out of range [0, 1000000]");
  EXPECT_EQ(error_of("[sim]\nwake_period_us = 1.5\n"),
            "cfg.toml: sim.wake_period_us: expected an integer");
}

// sim.faults takes `magvec run --faults` (one parser: host/hil/fault_spec.hpp); a bad item is a
// configuration error naming the key, never a failure when the rig starts.
TEST(DaemonConfigSim, FaultsUseTheRunSyntaxAndAreCheckedAtLoad) {
  EXPECT_EQ(parse_config("", "cfg.toml").sim.faults, "");
  EXPECT_EQ(parse_config("[sim]\nfaults = \"crc=1,ins-gap=5:1\"\n", "cfg.toml").sim.faults,
            "crc=1,ins-gap=5:1");
  EXPECT_EQ(error_of("[sim]\nfaults = \"bogus=1\"\n"),
            "cfg.toml: sim.faults: unknown fault 'bogus'");
  EXPECT_EQ(error_of("[sim]\nfaults = \"crc=2\"\n"),
            "cfg.toml: sim.faults: crc: probability must be in [0, 1]");
  EXPECT_EQ(error_of("[sim]\nfaults = 1\n"), "cfg.toml: sim.faults: expected a string");
}

// calibration.mode names the calibrator of the one factory (host/hil/calibrators.hpp); anything
// else is refused with the key and the list of modes.
TEST(DaemonConfigCalibration, ModeIsOneOfTheCalibrators) {
  EXPECT_EQ(parse_config("", "cfg.toml").calibration.mode, "li");
  for (const char* mode : {"li", "ekf", "vector-ekf", "none"}) {
    SCOPED_TRACE(mode);
    EXPECT_EQ(parse_config(std::string("[calibration]\nmode = \"") + mode + "\"\n", "cfg.toml")
                  .calibration.mode,
              mode);
  }
  EXPECT_EQ(error_of("[calibration]\nmode = \"vector_ekf\"\n"),
            "cfg.toml: calibration.mode: 'vector_ekf' is not one of ekf, li, none, vector-ekf");
  EXPECT_EQ(error_of("[calibration]\nmode = 3\n"), "cfg.toml: calibration.mode: expected a string");
}

// The fluxgate's temperature channel (ADC channel 3): off by default; its transfer and range are
// read; an axis on channel 3 while it is the temperature channel, a zero scale or an empty range
// are refused at load with the key named.
TEST(DaemonConfigMagnetometer, TemperatureChannelIsReadAndChecked) {
  const auto off = parse_config("", "cfg.toml").magnetometer.adc.temperature;
  EXPECT_FALSE(off.enabled);
  const std::string section = "[devices.magnetometer]\n";
  const auto on = parse_config(section +
                                   "temperature_channel = true\n"
                                   "temperature_degC_per_volt = 50.0\n"
                                   "temperature_offset_degC = -10.0\n"
                                   "temperature_min_degC = -20.0\n"
                                   "temperature_max_degC = 60.0\n",
                               "cfg.toml")
                      .magnetometer.adc.temperature;
  EXPECT_TRUE(on.enabled);
  EXPECT_EQ(on.degC_per_volt, 50.0);
  EXPECT_EQ(on.offset_degC, -10.0);
  EXPECT_EQ(on.min_degC, -20.0);
  EXPECT_EQ(on.max_degC, 60.0);
  EXPECT_EQ(error_of(section + "temperature_channel = true\nchannel_of_axis = [0, 3, 2]\n"),
            "cfg.toml: devices.magnetometer.channel_of_axis: an axis uses channel 3, the "
            "temperature channel");
  EXPECT_EQ(error_of(section + "temperature_channel = true\ntemperature_degC_per_volt = 0.0\n"),
            "cfg.toml: devices.magnetometer.temperature_channel: temperature scale (degC per "
            "volt) must be finite and non-zero, offset finite");
  EXPECT_EQ(error_of(section + "temperature_channel = true\ntemperature_min_degC = 50.0\n"
                               "temperature_max_degC = 50.0\n"),
            "cfg.toml: devices.magnetometer.temperature_channel: temperature range must be finite "
            "with min < max");
  // Disabled, channel 3 may carry an axis as before.
  EXPECT_EQ(parse_config(section + "channel_of_axis = [0, 3, 2]\n", "cfg.toml")
                .magnetometer.adc.channel_of_axis[1],
            3);
}

// The batch has its own channel: a reader decodes a channel as one type.
TEST(DaemonConfigLcm, RawBatchChannelDiffersFromTheSampleChannel) {
  EXPECT_EQ(parse_config("", "cfg.toml").lcm.channels.raw_mag_batch, "MAGVEC_RAW_MAG_BATCH");
  EXPECT_EQ(
      error_of("[lcm.channels]\nraw_mag_batch = \"MAGVEC_RAW_MAG\"\n"),
      "cfg.toml: lcm.channels.raw_mag_batch: must differ from raw_mag (another message type)");
  EXPECT_EQ(
      error_of("[lcm.channels]\nraw_mag = \"R\"\nraw_mag_batch = \"R\"\n"),
      "cfg.toml: lcm.channels.raw_mag_batch: must differ from raw_mag (another message type)");
  EXPECT_EQ(parse_config("[lcm.channels]\nraw_mag_batch = \"B\"\n", "cfg.toml")
                .lcm.channels.raw_mag_batch,
            "B");
}

// The model reference's keys: a model magvecd does not ship, an ID beyond 11 bits; and when the
// model is used at all (no scalar magnetometer, no reference_field_nT, not "none").
TEST(DaemonConfigReference, ModelAndPositionIdsAreChecked) {
  EXPECT_NE(error_of("[calibration]\nreference_model = \"igrf13\"\n")
                .find("cfg.toml: calibration.reference_model: 'igrf13' is not one of"),
            std::string::npos)
      << error_of("[calibration]\nreference_model = \"igrf13\"\n");
  EXPECT_NE(error_of("[devices.ins.can_ids]\nekf_pos = 2048\n").find("devices.ins.can_ids.ekf_pos"),
            std::string::npos);
  EXPECT_NE(error_of("[devices.ins.can_ids]\nekf_altitude = -1\n")
                .find("devices.ins.can_ids.ekf_altitude"),
            std::string::npos);
  EXPECT_TRUE(uses_model_reference(parse_config("", "t")));
  EXPECT_FALSE(
      uses_model_reference(parse_config("[calibration]\nreference_model = \"none\"\n", "t")));
  EXPECT_FALSE(
      uses_model_reference(parse_config("[calibration]\nreference_field_nT = 49000.0\n", "t")));
  EXPECT_FALSE(uses_model_reference(parse_config("[devices.scalar]\nenabled = true\n", "t")));
}

}  // namespace
}  // namespace magvec::host::daemon
