#include "calibration/calibration_file.hpp"

#include <nlohmann/json.hpp>

#include <cmath>
#include <ctime>
#include <fstream>
#include <sstream>

#include "magvec/host/io/csv.hpp"

namespace magvec::host {
namespace {

using nlohmann::json;
constexpr const char* kSchema = "magvec-calibration/1";
constexpr double kRad = 3.14159265358979323846 / 180.0;

template <typename Derived>
json to_array(const Eigen::MatrixBase<Derived>& m, double scale = 1.0) {
  json a = json::array();
  for (Eigen::Index r = 0; r < m.rows(); ++r) {
    for (Eigen::Index c = 0; c < m.cols(); ++c)
      a.push_back(m(r, c) * scale);
  }
  return a;
}

[[noreturn]] void fail(const std::string& source, const std::string& what) {
  throw CalibrationFileError(source + ": " + what);
}

const json& field(const json& j, const char* key, const std::string& source,
                  const std::string& path) {
  if (!j.is_object() || !j.contains(key)) fail(source, "missing field '" + path + key + "'");
  return j.at(key);
}

std::vector<double> numbers(const json& j, std::size_t n, const std::string& source,
                            const std::string& name) {
  if (!j.is_array() || j.size() != n) {
    fail(source, "field '" + name + "' must be an array of " + std::to_string(n) + " numbers");
  }
  std::vector<double> out;
  for (const json& v : j) {
    if (!v.is_number()) fail(source, "field '" + name + "' holds a non-number");
    const double d = v.get<double>();
    if (!std::isfinite(d)) fail(source, "field '" + name + "' holds a non-finite number");
    out.push_back(d);
  }
  return out;
}

double number(const json& j, const std::string& source, const std::string& name) {
  if (!j.is_number() || !std::isfinite(j.get<double>()))
    fail(source, "field '" + name + "' must be a finite number");
  return j.get<double>();
}

// Optional members: absent gives the default, present must have the right type. Every access is
// checked first, so no nlohmann type_error/out_of_range escapes without the file and field named.
const json* member(const json& obj, const char* key) {
  const auto it = obj.find(key);
  return it == obj.end() ? nullptr : &*it;
}

const json* object_member(const json& obj, const char* key, const std::string& source,
                          const std::string& name) {
  const json* v = member(obj, key);
  if (v != nullptr && !v->is_object()) fail(source, "field '" + name + "' must be an object");
  return v;
}

double number_or(const json& obj, const char* key, double fallback, const std::string& source,
                 const std::string& name) {
  const json* v = member(obj, key);
  return v == nullptr ? fallback : number(*v, source, name);
}

double non_negative(const json& j, const std::string& source, const std::string& name) {
  const double v = number(j, source, name);
  if (v < 0) fail(source, "field '" + name + "' must not be negative");
  return v;
}

std::string text_or(const json& obj, const char* key, const std::string& source,
                    const std::string& name, std::string fallback = {}) {
  const json* v = member(obj, key);
  if (v == nullptr) return fallback;
  if (!v->is_string()) fail(source, "field '" + name + "' must be a string");
  return v->get<std::string>();
}

// A count: a non-negative integer that fits 64 bits. An integral float (1000.0) is accepted; a
// float cast to an unsigned type out of its range would be undefined behaviour, so it is checked.
std::uint64_t count_or_zero(const json& obj, const char* key, const std::string& source,
                            const std::string& name) {
  const json* v = member(obj, key);
  if (v == nullptr) return 0;
  if (v->is_number_unsigned()) return v->get<std::uint64_t>();
  if (v->is_number_integer() && v->get<std::int64_t>() == 0) return 0;  // "-0"
  if (v->is_number_float()) {
    const double d = v->get<double>();
    constexpr double kTwoTo64 = 18446744073709551616.0;
    if (d >= 0 && d < kTwoTo64 && d == std::floor(d)) return static_cast<std::uint64_t>(d);
  }
  fail(source, "field '" + name + "' must be a non-negative integer below 2^64");
}

// Parses, naming the innermost key when the parser itself throws (a number overflowing a double,
// 1e474, is an out_of_range error, not a parse_error).
json parse_json(const std::string& text, const std::string& source) {
  std::vector<std::string> keys;  // key of each enclosing object, innermost last
  const json::parser_callback_t track = [&keys](int, json::parse_event_t event, json& parsed) {
    switch (event) {
      case json::parse_event_t::object_start:
        keys.emplace_back();
        break;
      case json::parse_event_t::key:
        if (!keys.empty() && parsed.is_string()) keys.back() = parsed.get<std::string>();
        break;
      case json::parse_event_t::object_end:
        if (!keys.empty()) keys.pop_back();
        break;
      default:
        break;
    }
    return true;
  };
  try {
    return json::parse(text, track);
  } catch (const json::exception& e) {
    std::string path;
    for (const std::string& k : keys)
      path += (path.empty() ? "" : ".") + k;
    fail(source, std::string("not valid JSON") + (path.empty() ? "" : " in field '" + path + "'") +
                     ": " + e.what());
  }
}

}  // namespace

std::string to_json_text(const CalibrationFile& cal) {
  json j;
  j["schema"] = kSchema;
  j["W"] = to_array(cal.model.w);
  j["o_nT"] = to_array(cal.model.o);
  const core::Quat<double> q = cal.model.rm.normalized();
  j["Rm_quat"] = {q.w(), q.x(), q.y(), q.z()};

  core::LiParams<double> li;
  if (core::to_li(cal.model, &li) == core::ConversionStatus::kOk) {
    j["li"] = {{"ks", to_array(li.ks)},
               {"O_deg", to_array(li.o_rad, 1.0 / kRad)},
               {"Kof_nT", to_array(li.kof)},
               {"Rm_deg", to_array(li.rm_rad, 1.0 / kRad)}};
  }
  const core::GeParams<double> ge = core::to_ge(cal.model);
  j["ge"] = {{"Cinv", to_array(ge.c_inv)}, {"b_nT", to_array(ge.b)}};
  if (cal.sine) {
    const core::SineParams<double>& s = cal.sine->params;
    j["sine"] = {{"k", to_array(s.k)},
                 {"alpha_deg", s.alpha_rad / kRad},
                 {"beta_deg", s.beta_rad / kRad},
                 {"gamma_deg", s.gamma_rad / kRad},
                 {"B0_nT", to_array(s.b0)},
                 {"inclination_deg", cal.sine->inclination_rad / kRad}};
  }
  if (cal.h_n_nT) j["h_n_nT"] = to_array(*cal.h_n_nT);
  if (cal.reference) {
    const ReferenceInfo& r = *cal.reference;
    json ref = {{"source", r.source}};
    if (std::isfinite(r.f_nT)) ref["F_nT"] = r.f_nT;
    if (std::isfinite(r.sigma_f_nT)) ref["sigma_F_nT"] = r.sigma_f_nT;
    if (r.model) {
      const ModelReference& m = *r.model;
      ref["model"] = {{"name", m.name},
                      {"lat_deg", m.lat_deg},
                      {"lon_deg", m.lon_deg},
                      {"height_m", m.height_m},
                      {"date", m.date},
                      {"decimal_year", m.decimal_year},
                      {"enu_nT", to_array(m.enu_nT)},
                      {"sigma_enu_nT", to_array(m.sigma_enu_nT)},
                      {"F_nT", m.f_nT},
                      {"sigma_F_nT", m.sigma_f_nT},
                      {"declination_deg", m.declination_deg},
                      {"sigma_declination_deg", m.sigma_declination_deg},
                      {"inclination_deg", m.inclination_deg},
                      {"sigma_inclination_deg", m.sigma_inclination_deg}};
    }
    j["reference"] = ref;
  }
  j["time_offset_s"] = cal.time_offset_s;
  if (cal.time_offset_sigma_s) j["time_offset_sigma_s"] = *cal.time_offset_sigma_s;
  {
    json noise = json::object();
    const NoiseFigures& nf = cal.noise;
    if (std::isfinite(nf.mag_nT)) {
      noise["mag_nT"] = nf.mag_nT;
      noise["mag_source"] = nf.mag_estimated ? "estimated" : "given";
      if (std::isfinite(nf.mag_sigma_nT)) noise["mag_sigma_nT"] = nf.mag_sigma_nT;
    }
    if (std::isfinite(nf.ins_deg)) {
      noise["ins_deg"] = nf.ins_deg;
      noise["ins_source"] = nf.ins_estimated ? "estimated" : "given";
      if (std::isfinite(nf.ins_sigma_deg)) noise["ins_sigma_deg"] = nf.ins_sigma_deg;
    }
    j["noise"] = noise;
  }
  if (cal.output) {
    json out = {{"aligned", cal.output->aligned}};
    if (std::isfinite(cal.output->sigma_f_nT)) out["sigma_f_nT"] = cal.output->sigma_f_nT;
    if (std::isfinite(cal.output->sigma_enu_nT)) out["sigma_enu_nT"] = cal.output->sigma_enu_nT;
    if (cal.output->model_reference) out["model_reference"] = true;
    j["output"] = out;
  }
  json sigma = json::object();
  for (const auto& [name, values] : cal.sigma)
    sigma[name] = values;
  j["sigma"] = sigma;
  json extra = json::object();
  for (const auto& [name, value] : cal.quality.extra)
    extra[name] = value;
  j["quality"] = {{"verdict", cal.quality.verdict},
                  {"reason", cal.quality.reason},
                  {"coverage", cal.quality.coverage},
                  {"condition", cal.quality.condition},
                  {"residual_rms_nT",
                   {{"before", cal.quality.residual_rms_before_nT},
                    {"after", cal.quality.residual_rms_after_nT}}},
                  {"counts",
                   {{"samples", cal.counts.samples},
                    {"used", cal.counts.used},
                    {"skipped_nonfinite", cal.counts.skipped_nonfinite},
                    {"rejected_outliers", cal.counts.rejected_outliers}}},
                  {"extra", extra}};
  j["provenance"] = {
      {"input", cal.provenance.input},
      {"method", cal.provenance.method},
      {"samples_used", cal.counts.used},
      {"samples_rejected", cal.counts.rejected_outliers + cal.counts.skipped_nonfinite},
      {"magvec_version", cal.provenance.magvec_version},
      {"created_utc", cal.provenance.created_utc}};
  return j.dump(2) + "\n";
}

namespace {

CalibrationFile from_json_checked(const json& j, const std::string& source) {
  if (!j.is_object()) fail(source, "top level must be a JSON object");
  const json& schema = field(j, "schema", source, "");
  if (!schema.is_string() || schema.get<std::string>() != kSchema) {
    fail(source, std::string("unsupported schema (expected '") + kSchema + "')");
  }
  CalibrationFile cal;
  const std::vector<double> w = numbers(field(j, "W", source, ""), 9, source, "W");
  const std::vector<double> o = numbers(field(j, "o_nT", source, ""), 3, source, "o_nT");
  const std::vector<double> q = numbers(field(j, "Rm_quat", source, ""), 4, source, "Rm_quat");
  for (int r = 0; r < 3; ++r) {
    for (int c = 0; c < 3; ++c)
      cal.model.w(r, c) = w[static_cast<std::size_t>(3 * r + c)];
  }
  cal.model.o = core::Vec3<double>(o[0], o[1], o[2]);
  const double qn = std::sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3]);
  if (!(std::abs(qn - 1.0) <= 1e-6)) fail(source, "field 'Rm_quat' is not a unit quaternion");
  cal.model.rm = core::Quat<double>(q[0] / qn, q[1] / qn, q[2] / qn, q[3] / qn);
  const double det = cal.model.w.determinant();
  if (!(std::abs(det) > 1e-12)) fail(source, "field 'W' is singular");
  if (!std::isfinite(det)) fail(source, "field 'W' is out of range (determinant overflows)");

  if (const json* h = member(j, "h_n_nT")) {
    const std::vector<double> v = numbers(*h, 3, source, "h_n_nT");
    cal.h_n_nT = core::Vec3<double>(v[0], v[1], v[2]);
  }
  if (const json* rj = object_member(j, "reference", source, "reference")) {
    ReferenceInfo r;
    r.source = text_or(*rj, "source", source, "reference.source");
    if (r.source != "measured" && r.source != "model" && r.source != "given" && r.source != "data")
      fail(source, "field 'reference.source' must be measured, model, given or data");
    r.f_nT = number_or(*rj, "F_nT", r.f_nT, source, "reference.F_nT");
    r.sigma_f_nT = number_or(*rj, "sigma_F_nT", r.sigma_f_nT, source, "reference.sigma_F_nT");
    if (const json* mj = object_member(*rj, "model", source, "reference.model")) {
      ModelReference m;
      const auto num = [&](const char* key) {
        return number(field(*mj, key, source, "reference.model."), source,
                      std::string("reference.model.") + key);
      };
      const auto vec = [&](const char* key) {
        const std::vector<double> v = numbers(field(*mj, key, source, "reference.model."), 3,
                                              source, std::string("reference.model.") + key);
        return core::Vec3<double>(v[0], v[1], v[2]);
      };
      m.name = text_or(*mj, "name", source, "reference.model.name");
      m.date = text_or(*mj, "date", source, "reference.model.date");
      m.lat_deg = num("lat_deg");
      m.lon_deg = num("lon_deg");
      m.height_m = num("height_m");
      m.decimal_year = num("decimal_year");
      m.enu_nT = vec("enu_nT");
      m.sigma_enu_nT = vec("sigma_enu_nT");
      m.f_nT = num("F_nT");
      m.sigma_f_nT = num("sigma_F_nT");
      m.declination_deg = num("declination_deg");
      m.sigma_declination_deg = num("sigma_declination_deg");
      m.inclination_deg = num("inclination_deg");
      m.sigma_inclination_deg = num("sigma_inclination_deg");
      r.model = m;
    }
    cal.reference = r;
  }
  if (const json* t = member(j, "time_offset_s")) {
    cal.time_offset_s = number(*t, source, "time_offset_s");
    if (std::abs(cal.time_offset_s) > 10.0)
      fail(source, "field 'time_offset_s' must be finite and within +-10 s");
  }
  if (const json* t = member(j, "time_offset_sigma_s"))
    cal.time_offset_sigma_s = non_negative(*t, source, "time_offset_sigma_s");
  if (const json* nj = object_member(j, "noise", source, "noise")) {
    if (const json* v = member(*nj, "mag_nT"))
      cal.noise.mag_nT = non_negative(*v, source, "noise.mag_nT");
    if (const json* v = member(*nj, "mag_sigma_nT"))
      cal.noise.mag_sigma_nT = non_negative(*v, source, "noise.mag_sigma_nT");
    if (const json* v = member(*nj, "ins_deg"))
      cal.noise.ins_deg = non_negative(*v, source, "noise.ins_deg");
    if (const json* v = member(*nj, "ins_sigma_deg"))
      cal.noise.ins_sigma_deg = non_negative(*v, source, "noise.ins_sigma_deg");
    auto estimated = [&](const char* key, const std::string& name) {
      const std::string v = text_or(*nj, key, source, name, "given");
      if (v != "estimated" && v != "given")
        fail(source, "field '" + name + "' must be \"estimated\" or \"given\"");
      return v == "estimated";
    };
    cal.noise.mag_estimated = estimated("mag_source", "noise.mag_source");
    cal.noise.ins_estimated = estimated("ins_source", "noise.ins_source");
  }
  if (const json* oj = object_member(j, "output", source, "output")) {
    OutputQuality out;
    if (const json* a = member(*oj, "aligned")) {
      if (!a->is_boolean()) fail(source, "field 'output.aligned' must be true or false");
      out.aligned = a->get<bool>();
    }
    if (const json* v = member(*oj, "sigma_f_nT"))
      out.sigma_f_nT = non_negative(*v, source, "output.sigma_f_nT");
    if (const json* v = member(*oj, "sigma_enu_nT"))
      out.sigma_enu_nT = non_negative(*v, source, "output.sigma_enu_nT");
    if (const json* m = member(*oj, "model_reference")) {
      if (!m->is_boolean()) fail(source, "field 'output.model_reference' must be true or false");
      out.model_reference = m->get<bool>();
    }
    cal.output = out;
  }
  if (const json* sp = object_member(j, "sine", source, "sine")) {
    const json& s = *sp;
    SineResult r;
    const std::vector<double> k = numbers(field(s, "k", source, "sine."), 3, source, "sine.k");
    const std::vector<double> b0 =
        numbers(field(s, "B0_nT", source, "sine."), 3, source, "sine.B0_nT");
    r.params.k = core::Vec3<double>(k[0], k[1], k[2]);
    r.params.b0 = core::Vec3<double>(b0[0], b0[1], b0[2]);
    r.params.alpha_rad =
        number(field(s, "alpha_deg", source, "sine."), source, "sine.alpha_deg") * kRad;
    r.params.beta_rad =
        number(field(s, "beta_deg", source, "sine."), source, "sine.beta_deg") * kRad;
    r.params.gamma_rad =
        number(field(s, "gamma_deg", source, "sine."), source, "sine.gamma_deg") * kRad;
    r.inclination_rad =
        number(field(s, "inclination_deg", source, "sine."), source, "sine.inclination_deg") * kRad;
    cal.sine = r;
  }
  if (const json* s = object_member(j, "sigma", source, "sigma")) {
    for (const auto& [name, values] : s->items()) {
      if (!values.is_array()) fail(source, "field 'sigma." + name + "' must be an array");
      cal.sigma[name] = numbers(values, values.size(), source, "sigma." + name);
    }
  }
  if (const json* qp = object_member(j, "quality", source, "quality")) {
    const json& qj = *qp;
    cal.quality.verdict = text_or(qj, "verdict", source, "quality.verdict", "ok");
    cal.quality.reason = text_or(qj, "reason", source, "quality.reason");
    cal.quality.coverage = number_or(qj, "coverage", 0.0, source, "quality.coverage");
    cal.quality.condition = number_or(qj, "condition", 0.0, source, "quality.condition");
    if (const json* rms = object_member(qj, "residual_rms_nT", source, "quality.residual_rms_nT")) {
      cal.quality.residual_rms_before_nT =
          number_or(*rms, "before", 0.0, source, "quality.residual_rms_nT.before");
      cal.quality.residual_rms_after_nT =
          number_or(*rms, "after", 0.0, source, "quality.residual_rms_nT.after");
    }
    if (const json* c = object_member(qj, "counts", source, "quality.counts")) {
      cal.counts.samples = count_or_zero(*c, "samples", source, "quality.counts.samples");
      cal.counts.used = count_or_zero(*c, "used", source, "quality.counts.used");
      cal.counts.skipped_nonfinite =
          count_or_zero(*c, "skipped_nonfinite", source, "quality.counts.skipped_nonfinite");
      cal.counts.rejected_outliers =
          count_or_zero(*c, "rejected_outliers", source, "quality.counts.rejected_outliers");
    }
    if (const json* extra = member(qj, "extra"); extra != nullptr && extra->is_object()) {
      for (const auto& [name, value] : extra->items()) {
        if (value.is_number()) cal.quality.extra[name] = value.get<double>();
      }
    }
  }
  if (const json* p = object_member(j, "provenance", source, "provenance")) {
    cal.provenance.input = text_or(*p, "input", source, "provenance.input");
    cal.provenance.method = text_or(*p, "method", source, "provenance.method");
    cal.provenance.magvec_version =
        text_or(*p, "magvec_version", source, "provenance.magvec_version");
    cal.provenance.created_utc = text_or(*p, "created_utc", source, "provenance.created_utc");
  }
  // The paper forms are derived data: if present they must agree with the canonical model.
  if (const json* gj = object_member(j, "ge", source, "ge")) {
    const std::vector<double> cinv =
        numbers(field(*gj, "Cinv", source, "ge."), 9, source, "ge.Cinv");
    const core::GeParams<double> ge = core::to_ge(cal.model);
    for (int i = 0; i < 9; ++i) {
      if (!(std::abs(cinv[static_cast<std::size_t>(i)] - ge.c_inv(i / 3, i % 3)) <=
            1e-9 * (1 + ge.c_inv.norm()))) {
        fail(source, "field 'ge.Cinv' disagrees with W and Rm_quat (edited by hand?)");
      }
    }
  }
  return cal;
}

}  // namespace

CalibrationFile from_json_text(const std::string& text, const std::string& source) {
  try {
    return from_json_checked(parse_json(text, source), source);
  } catch (const json::exception& e) {
    // Not expected (every access above is checked); kept so that no nlohmann exception can leave
    // this function without the file named.
    fail(source, std::string("malformed calibration file: ") + e.what());
  }
}

void write_calibration_file(const std::string& path, const CalibrationFile& cal) {
  io::AtomicFile file(path);
  file.write(to_json_text(cal));
  file.commit();
}

CalibrationFile read_calibration_file(const std::string& path) {
  std::ifstream in(path, std::ios::binary);
  if (!in) throw CalibrationFileError(path + ": cannot open calibration file");
  std::ostringstream ss;
  ss << in.rdbuf();
  return from_json_text(ss.str(), path);
}

std::string utc_now_iso8601() {
  const std::time_t now = std::time(nullptr);
  std::tm tm{};
  gmtime_r(&now, &tm);
  char buf[32];
  std::strftime(buf, sizeof buf, "%Y-%m-%dT%H:%M:%SZ", &tm);
  return buf;
}

}  // namespace magvec::host
