// magvecd TOML configuration; see config.hpp.
#include "magvec/host/daemon/config.hpp"

#include "magvec/host/daemon/default_config_text.hpp"
#include "magvec/host/hil/fault_spec.hpp"

#include <toml++/toml.h>
#include <cmath>
#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <optional>
#include <set>
#include <sstream>

namespace magvec::host::daemon {
namespace {

// Exact double value of an integer or floating-point node. toml++'s value<double>() is an empty
// optional for an integer beyond 2^53 (no exact double), so that case is reported, never
// dereferenced.
std::optional<double> exact_double(const toml::node& n) {
  if (const auto* f = n.as_floating_point()) return f->get();
  if (const auto* i = n.as_integer()) {
    constexpr std::int64_t kExact = std::int64_t{1} << 53;
    if (i->get() > kExact || i->get() < -kExact) return std::nullopt;
    return static_cast<double>(i->get());
  }
  return std::nullopt;
}

constexpr const char* kInexactInteger =
    "integer beyond 2^53 is not exactly representable as a number; write it as a float (1e16)";

// toml++ 3.3.0 (Debian 12) has undefined behaviour on some non-ASCII input: valid UTF-8 in
// certain positions reaches TOML_UNREACHABLE in its Unicode classification (fixed upstream after
// 3.3.0; newer releases still have open reports of the same kind). Pinning a newer copy would
// replace the distribution package for a format whose values are all ASCII, so the text is
// guarded instead: it must be valid UTF-8 and non-ASCII characters may appear only in comments,
// where toml++ merely checks for control characters and surrogates (which valid UTF-8 excludes).
// The scan tracks strings only to tell a comment's '#' from one inside a string; where it
// disagrees with TOML on invalid documents, the result is a rejection, never unguarded text.
void check_text(const std::string& text, const std::string& source) {
  enum class In : std::uint8_t { kCode, kComment, kBasic, kLiteral, kMlBasic, kMlLiteral };
  In in = In::kCode;
  std::size_t line = 1;
  std::size_t line_start = 0;
  const auto at = [&text](std::size_t i) -> unsigned char {
    return i < text.size() ? static_cast<unsigned char>(text[i]) : 0;
  };
  const auto starts = [&text](std::size_t i, const char* three) {
    return text.compare(i, 3, three) == 0;
  };
  for (std::size_t i = 0; i < text.size();) {
    const unsigned char c = at(i);
    if (c >= 0x80) {
      // One UTF-8 sequence, strictly: no overlongs, surrogates or values above U+10FFFF.
      std::size_t n = 0;
      std::uint32_t cp = 0;
      if (c >= 0xC2 && c <= 0xDF) {
        n = 2;
        cp = c & 0x1Fu;
      } else if (c >= 0xE0 && c <= 0xEF) {
        n = 3;
        cp = c & 0x0Fu;
      } else if (c >= 0xF0 && c <= 0xF4) {
        n = 4;
        cp = c & 0x07u;
      }
      bool ok = n != 0;
      for (std::size_t k = 1; ok && k < n; ++k) {
        ok = (at(i + k) & 0xC0u) == 0x80u;
        cp = (cp << 6) | (at(i + k) & 0x3Fu);
      }
      ok = ok && !(n == 3 && cp < 0x800) && !(n == 4 && (cp < 0x10000 || cp > 0x10FFFF)) &&
           !(cp >= 0xD800 && cp <= 0xDFFF);
      const std::string where =
          source + ":" + std::to_string(line) + ":" + std::to_string(i - line_start + 1) + ": ";
      if (!ok) throw ConfigError(where + "invalid UTF-8");
      if (in != In::kComment) {
        throw ConfigError(where +
                          "non-ASCII character outside a comment (keys and values must be ASCII)");
      }
      i += n;
      continue;
    }
    if (c == '\n') {
      ++line;
      line_start = i + 1;
      if (in == In::kComment || in == In::kBasic || in == In::kLiteral) in = In::kCode;
      ++i;
      continue;
    }
    switch (in) {
      case In::kCode:
        if (c == '#') {
          in = In::kComment;
        } else if (starts(i, R"(""")")) {
          in = In::kMlBasic;
          i += 2;
        } else if (starts(i, "'''")) {
          in = In::kMlLiteral;
          i += 2;
        } else if (c == '"') {
          in = In::kBasic;
        } else if (c == '\'') {
          in = In::kLiteral;
        }
        break;
      case In::kComment:
        break;
      case In::kBasic:
        if (c == '\\' && at(i + 1) != 0 && at(i + 1) < 0x80 && at(i + 1) != '\n') {
          ++i;  // the escaped character cannot end the string
        } else if (c == '"') {
          in = In::kCode;
        }
        break;
      case In::kLiteral:
        if (c == '\'') in = In::kCode;
        break;
      case In::kMlBasic:
      case In::kMlLiteral: {
        const char quote = in == In::kMlBasic ? '"' : '\'';
        if (in == In::kMlBasic && c == '\\' && at(i + 1) != 0 && at(i + 1) < 0x80 &&
            at(i + 1) != '\n') {
          ++i;
        } else if (c == static_cast<unsigned char>(quote)) {
          // A run of 3 to 5 quotes closes the string (up to two belong to its content).
          std::size_t run = 1;
          while (at(i + run) == static_cast<unsigned char>(quote))
            ++run;
          if (run >= 3) in = In::kCode;
          i += run - 1;
        }
        break;
      }
    }
    ++i;
  }
}

// Typed access to one table; remembers which keys were read so unknown keys can be reported.
class Table {
 public:
  Table(const toml::table* t, std::string path, const std::string& source)
      : t_(t), path_(std::move(path)), source_(source) {}

  [[noreturn]] void fail(const std::string& key, const std::string& what) const {
    throw ConfigError(source_ + ": " + path_ + (path_.empty() ? "" : ".") + key + ": " + what);
  }

  const toml::node* get(const std::string& key) {
    used_.insert(key);
    return t_ == nullptr ? nullptr : t_->get(key);
  }

  void str(const std::string& key, std::string* out) {
    const toml::node* n = get(key);
    if (n == nullptr) return;
    if (!n->is_string()) fail(key, "expected a string");
    *out = n->as_string()->get();
  }
  void boolean(const std::string& key, bool* out) {
    const toml::node* n = get(key);
    if (n == nullptr) return;
    if (!n->is_boolean()) fail(key, "expected true or false");
    *out = n->as_boolean()->get();
  }
  void number(const std::string& key, double* out, double lo, double hi) {
    const toml::node* n = get(key);
    if (n == nullptr) return;
    if (!n->is_number()) fail(key, "expected a number");
    const std::optional<double> exact = exact_double(*n);
    if (!exact) fail(key, kInexactInteger);
    const double v = *exact;
    if (!(v >= lo && v <= hi))  // also rejects nan
      fail(key, "out of range [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
    *out = v;
  }
  // A number that may be nan (explicitly "no value").
  void number_or_nan(const std::string& key, double* out, double lo, double hi) {
    const toml::node* n = get(key);
    if (n == nullptr) return;
    if (!n->is_number()) fail(key, "expected a number (or nan)");
    const std::optional<double> exact = exact_double(*n);
    if (!exact) fail(key, kInexactInteger);
    const double v = *exact;
    if (std::isnan(v)) {
      *out = v;
      return;
    }
    if (!(v >= lo && v <= hi))
      fail(key, "out of range [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
    *out = v;
  }
  template <typename Int>
  void integer(const std::string& key, Int* out, std::int64_t lo, std::int64_t hi) {
    const toml::node* n = get(key);
    if (n == nullptr) return;
    if (!n->is_integer()) fail(key, "expected an integer");
    const std::int64_t v = n->as_integer()->get();
    if (v < lo || v > hi)
      fail(key, "out of range [" + std::to_string(lo) + ", " + std::to_string(hi) + "]");
    *out = static_cast<Int>(v);
  }
  template <typename T, std::size_t N, typename Read>
  void array(const std::string& key, std::array<T, N>* out, Read read_one) {
    const toml::node* n = get(key);
    if (n == nullptr) return;
    const toml::array* a = n->as_array();
    if (a == nullptr || a->size() != N) fail(key, "expected an array of " + std::to_string(N));
    for (std::size_t i = 0; i < N; ++i)
      (*out)[i] = read_one(a->get(i), key);
  }
  void one_of(const std::string& key, std::string* out, const std::set<std::string>& allowed) {
    str(key, out);
    if (allowed.count(*out) == 0) {
      std::string list;
      for (const auto& a : allowed)
        list += (list.empty() ? "" : ", ") + a;
      fail(key, "'" + *out + "' is not one of " + list);
    }
  }
  Table sub(const std::string& key) {
    const toml::node* n = get(key);
    if (n != nullptr && !n->is_table()) fail(key, "expected a table");
    return Table(n == nullptr ? nullptr : n->as_table(), path_.empty() ? key : path_ + "." + key,
                 source_);
  }
  void check_unknown() const {
    if (t_ == nullptr) return;
    for (const auto& [k, v] : *t_) {
      const std::string key(k.str());
      if (used_.count(key) == 0) fail(key, "unknown key");
    }
  }

 private:
  const toml::table* t_;
  std::string path_;
  const std::string& source_;
  std::set<std::string> used_;
};

}  // namespace

Config parse_config(const std::string& text, const std::string& source) {
  check_text(text, source);
  toml::table root;
  try {
    root = toml::parse(text, source);
  } catch (const toml::parse_error& e) {
    std::ostringstream os;
    os << source << ":" << e.source().begin.line << ":" << e.source().begin.column << ": "
       << e.description();
    throw ConfigError(os.str());
  }
  Config c;
  Table top(&root, "", source);

  Table d = top.sub("daemon");
  d.str("state_dir", &c.daemon.state_dir);
  if (c.daemon.state_dir.empty()) d.fail("state_dir", "must not be empty");
  d.one_of("log_level", &c.daemon.log_level, {"trace", "debug", "info", "warn", "error"});
  d.boolean("realtime", &c.daemon.realtime);
  d.integer("rt_priority", &c.daemon.rt_priority, 1, 99);
  d.number("health_period_s", &c.daemon.health_period_s, 0.01, 3600);
  d.number("status_period_s", &c.daemon.status_period_s, 0.01, 3600);
  d.check_unknown();

  Table l = top.sub("lcm");
  l.str("url", &c.lcm.url);
  l.str("command_url", &c.lcm.command_url);
  if (!c.lcm.command_url.empty() && c.lcm.command_url == c.lcm.url)
    l.fail("command_url", "must differ from url (the daemon must not receive its own data)");
  l.integer("raw_batch", &c.lcm.raw_batch, 1, kMaxRawBatch);
  Table ch = l.sub("channels");
  ch.str("raw_mag", &c.lcm.channels.raw_mag);
  ch.str("raw_mag_batch", &c.lcm.channels.raw_mag_batch);
  // One type per channel: a reader decodes by channel name.
  if (c.lcm.channels.raw_mag_batch == c.lcm.channels.raw_mag)
    ch.fail("raw_mag_batch", "must differ from raw_mag (another message type)");
  ch.str("attitude", &c.lcm.channels.attitude);
  ch.str("pipeline", &c.lcm.channels.pipeline);
  ch.str("output", &c.lcm.channels.output);
  ch.str("cal_state", &c.lcm.channels.cal_state);
  ch.str("health", &c.lcm.channels.health);
  ch.str("command", &c.lcm.channels.command);
  ch.str("reply", &c.lcm.channels.reply);
  ch.check_unknown();
  l.check_unknown();

  Table dev = top.sub("devices");
  Table m = dev.sub("magnetometer");
  auto& mc = c.magnetometer;
  m.one_of("link", &mc.link, {"spi", "serial"});
  m.number("rate_hz", &mc.rate_hz, 0.1, 10000);
  m.str("spi_device", &mc.spi_device);
  m.integer("spi_speed_hz", &mc.spi_speed_hz, 1000, 50'000'000);
  m.str("drdy_chip", &mc.drdy_chip);
  m.integer("drdy_line", &mc.drdy_line, 0, 1023);
  m.str("serial_device", &mc.serial_device);
  m.integer("serial_baud", &mc.serial_baud, 300, 4'000'000);
  m.integer("serial_reconnect_ms", &mc.serial_reconnect_ms, 10, 600'000);
  m.integer("serial_latency_us", &mc.serial_latency_us, 0, 1'000'000);
  // |nT_per_volt| up to 1e9 (1 T per volt) covers any fluxgate electronics by orders of magnitude.
  auto as_nT_per_volt = [&m](const toml::node* n, const std::string& key) {
    if (n == nullptr || !n->is_number()) m.fail(key, "expected numbers");
    const std::optional<double> exact = exact_double(*n);
    if (!exact) m.fail(key, kInexactInteger);
    const double v = *exact;
    if (!(std::abs(v) <= 1e9) || v == 0) m.fail(key, "expected non-zero numbers within +-1e9");
    return v;
  };
  auto as_u8 = [&m](std::int64_t hi) {
    return [&m, hi](const toml::node* n, const std::string& key) {
      if (n == nullptr || !n->is_integer()) m.fail(key, "expected integers");
      const std::int64_t v = n->as_integer()->get();
      if (v < 0 || v > hi) m.fail(key, "values must be in [0, " + std::to_string(hi) + "]");
      return static_cast<std::uint8_t>(v);
    };
  };
  m.array("nT_per_volt", &mc.adc.nT_per_volt, as_nT_per_volt);
  m.array("channel_of_axis", &mc.adc.channel_of_axis, as_u8(3));
  m.array("gain_code", &mc.adc.gain_code, as_u8(7));
  m.integer("stuck_count", &mc.adc.stuck_count, 0, 1'000'000);
  // The fluxgate's temperature on ADC channel 3 (ads131_fluxgate.hpp): T = offset + V * scale.
  auto& tc = mc.adc.temperature;
  m.boolean("temperature_channel", &tc.enabled);
  m.number("temperature_degC_per_volt", &tc.degC_per_volt, -1e6, 1e6);
  m.number("temperature_offset_degC", &tc.offset_degC, -1e4, 1e4);
  m.number("temperature_min_degC", &tc.min_degC, -273.15, 1000);
  m.number("temperature_max_degC", &tc.max_degC, -273.15, 1000);
  if (const drivers::Ads131ConfigError e = drivers::check_config(mc.adc);
      e != drivers::Ads131ConfigError::kNone) {
    m.fail(e == drivers::Ads131ConfigError::kAxisOnTemperatureChannel ? "channel_of_axis"
                                                                      : "temperature_channel",
           drivers::to_string(e));
  }
  m.check_unknown();

  Table ins = dev.sub("ins");
  ins.str("can_interface", &c.ins.can_interface);
  ins.number("rate_hz", &c.ins.rate_hz, 1, 1000);
  ins.integer("latency_comp_us", &c.ins.latency_comp_us, 0, 1'000'000);
  ins.integer("fusion_horizon_us", &c.ins.fusion_horizon_us, 0, 1'000'000);
  ins.number_or_nan("time_offset_s", &c.ins.time_offset_s, -10, 10);
  ins.boolean("require_attitude_valid", &c.ins.require_attitude_valid);
  Table ids = ins.sub("can_ids");
  ids.integer("status_01", &c.ins.ids.status_01, 0, 0x7FF);
  ids.integer("status_03", &c.ins.ids.status_03, 0, 0x7FF);
  ids.integer("ekf_info", &c.ins.ids.ekf_info, 0, 0x7FF);
  ids.integer("ekf_quat", &c.ins.ids.ekf_quat, 0, 0x7FF);
  ids.integer("ekf_euler", &c.ins.ids.ekf_euler, 0, 0x7FF);
  ids.integer("ekf_orientation_acc", &c.ins.ids.ekf_orientation_acc, 0, 0x7FF);
  ids.integer("ekf_pos", &c.ins.ids.ekf_pos, 0, 0x7FF);
  ids.integer("ekf_altitude", &c.ins.ids.ekf_altitude, 0, 0x7FF);
  ids.check_unknown();
  ins.check_unknown();

  Table st = dev.sub("scalar");
  auto& so = c.scalar;
  st.boolean("enabled", &so.enabled);
  st.one_of("format", &so.format, {"g882"});
  st.str("device", &so.device);
  if (so.device.empty()) st.fail("device", "must not be empty");
  st.integer("baud", &so.baud, 300, 4'000'000);
  st.integer("reconnect_ms", &so.reconnect_ms, 10, 600'000);
  st.integer("latency_us", &so.latency_us, 0, 1'000'000);
  std::string preamble(1, so.line.preamble);
  st.str("preamble", &preamble);
  // One printable character that cannot occur inside a line (digits, blank, '.', ',', the
  // Julian clock's letters) or a line end.
  if (preamble.size() != 1 || preamble[0] < 0x21 || preamble[0] > 0x7E ||
      std::string("0123456789.,DHMS_").find(preamble[0]) != std::string::npos)
    st.fail("preamble",
            "'" + preamble +
                "' must be one printable character other than a digit, '.', ',', D, H, M, S, _");
  so.line.preamble = preamble[0];
  st.integer("analog_channels", &so.line.analog_channels, 0,
             drivers::G882LineDecoder::kMaxAnalogChannels);
  st.boolean("julian_time", &so.line.julian_time);
  st.number("min_field_nT", &so.line.min_field_nT, 0, 199999.999);
  st.number("max_field_nT", &so.line.max_field_nT, 0, 199999.999);
  if (!(so.line.min_field_nT < so.line.max_field_nT))
    st.fail("max_field_nT", "must be above min_field_nT");
  st.integer("min_signal", &so.line.min_signal, 0, 9999);
  st.integer("max_gap_us", &so.align.max_gap_us, 1000, 10'000'000);
  st.integer("max_distance_us", &so.align.max_distance_us, 0, 10'000'000);
  st.integer("horizon_us", &so.align.horizon_us, 0, 10'000'000);
  // A sample waits up to horizon_us in the aligner before the core's pipeline sees it: the INS
  // epochs around it must still be in the attitude buffer (64 epochs, hil::LoopCore) by then, and
  // the aligner's queue must hold horizon_us of magnetometer samples.
  const double buffer_us = (64.0 - 4.0) / c.ins.rate_hz * 1e6 - c.ins.fusion_horizon_us;
  if (so.enabled && static_cast<double>(so.align.horizon_us) > buffer_us)
    st.fail("horizon_us", std::to_string(so.align.horizon_us) +
                              " is longer than the INS attitude buffer holds with devices.ins "
                              "rate_hz and fusion_horizon_us (at most " +
                              std::to_string(static_cast<std::int64_t>(buffer_us)) + ")");
  if (so.enabled && c.magnetometer.rate_hz * so.align.horizon_us * 1e-6 > kScalarQueueSamples)
    st.fail("horizon_us", "holds more than " + std::to_string(kScalarQueueSamples) +
                              " magnetometer samples at devices.magnetometer.rate_hz");
  st.check_unknown();
  dev.check_unknown();

  Table cal = top.sub("calibration");
  auto& cc = c.calibration;
  cal.one_of("mode", &cc.mode, {"li", "ekf", "vector-ekf", "none"});
  cal.boolean("start_on_boot", &cc.start_on_boot);
  cal.boolean("auto_accept", &cc.auto_accept);
  cal.number_or_nan("noise_nT", &cc.noise_nT, 1e-6, 1e5);
  cal.number_or_nan("attitude_noise_deg", &cc.attitude_noise_deg, 1e-6, 10);
  cal.integer("validation_samples", &cc.validation_samples, 1, 1'000'000);
  cal.number("validation_max_rms_factor", &cc.validation_max_rms_factor, 0.1, 1000);
  cal.number("validation_min_rms_nT", &cc.validation_min_rms_nT, 0, 1e5);
  cal.boolean("validate_against_active", &cc.validate_against_active);
  cal.boolean("ekf_align", &cc.ekf_align);
  cal.integer("li_min_samples", &cc.li_min_samples, 16, 512);
  cal.number_or_nan("reference_field_nT", &cc.reference_field_nT, 1000, 200000);
  cal.one_of("reference_model", &cc.reference_model, {"wmm2025", "none"});
  cal.boolean("solve_on_worker", &cc.solve_on_worker);
  cal.check_unknown();
  c.scalar.align.fallback_nT = cc.reference_field_nT;

  Table sim = top.sub("sim");
  sim.one_of("scenario", &c.sim.scenario, {"li2023", "survey"});
  sim.integer("seed", &c.sim.seed, 0, std::numeric_limits<std::int64_t>::max());
  sim.integer("samples_per_attitude", &c.sim.samples_per_attitude, 1, 1'000'000);
  sim.integer("wake_period_us", &c.sim.wake_period_us, 0, 1'000'000);
  sim.str("faults", &c.sim.faults);
  try {  // checked here, so a bad item is a configuration error and not a failure at start
    drivers::sim::ScenarioConfig sc;
    drivers::sim::SimRigConfig rc;
    hil::apply_faults(c.sim.faults, &sc, &rc);
  } catch (const hil::FaultSpecError& e) {
    sim.fail("faults", e.what());
  }
  sim.check_unknown();

  top.check_unknown();
  return c;
}

std::string read_config_text(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw ConfigError(path + ": cannot read the configuration file");
  std::ostringstream os;
  os << in.rdbuf();
  if (in.bad()) throw ConfigError(path + ": read error");
  return os.str();
}

std::string command_url_for(const std::string& url) {
  // udpm://GROUP:PORT?OPTIONS (GROUP:PORT optional: LCM's default 239.255.76.67:7667).
  const std::string scheme = "udpm://";
  if (url.rfind(scheme, 0) != 0) return url;
  const std::size_t q = url.find('?');
  const std::string address =
      url.substr(scheme.size(), q == std::string::npos ? q : q - scheme.size());
  const std::string options = q == std::string::npos ? "" : url.substr(q);
  std::string group = "239.255.76.67";
  long port = 7667;
  if (!address.empty()) {
    const std::size_t colon = address.rfind(':');
    group = address.substr(0, colon);
    if (colon != std::string::npos) {
      char* end = nullptr;
      port = std::strtol(address.c_str() + colon + 1, &end, 10);
      if (end == address.c_str() + colon + 1 || *end != '\0' || port < 1 || port > 65535)
        return url;  // not understood: LCM will report it
    }
  }
  return scheme + group + ":" + std::to_string(port == 65535 ? 65534 : port + 1) + options;
}

std::string command_url(const LcmConfig& c) {
  return c.command_url.empty() ? command_url_for(c.url) : c.command_url;
}

const std::string& default_config_text() {
  static const std::string kText = kDefaultConfigToml;
  return kText;
}

}  // namespace magvec::host::daemon
