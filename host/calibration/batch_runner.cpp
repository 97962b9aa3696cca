// Batch calibration over a recording (see batch_runner.hpp).
#include "calibration/batch_runner.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>
#include <cstdlib>
#include <memory>
#include <string>
#include <utility>
#include <vector>

namespace magvec::host {
namespace {

using Calibrator = core::BatchCalibrator<double, core::kDynamicCapacity>;
using Fit = core::OneStepFit<double>;

std::string f2(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}
std::string g3(double v) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.3g", v);
  return buf;
}

std::vector<double> deg3(const core::Vec3<double>& rad) {
  const core::Vec3<double> d = rad * (180.0 / core::kPi<double>);
  return {d(0), d(1), d(2)};
}
std::vector<double> v3(const core::Vec3<double>& v) {
  return {v(0), v(1), v(2)};
}

// One kept row of the recording.
struct Row {
  double t_s;
  core::Vec3<double> m;
  double f;              // NaN: none
  core::Quat<double> q;  // R_bn as a quaternion, when has_att
  bool has_att;
};

double median_of(std::vector<double> v) {
  if (v.empty()) return std::nan("");
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// Attitude at any time from the rows' attitudes: slerp between the bracketing rows, refused
// across gaps (optical dropouts, missing rows) longer than max_gap_s.
class AttitudeSeries {
 public:
  AttitudeSeries(const std::vector<Row>& rows, double max_gap_s) : max_gap_s_(max_gap_s) {
    for (const Row& r : rows) {
      if (!r.has_att) continue;
      if (!t_.empty() && !(r.t_s > t_.back())) continue;  // non-increasing time: skip
      t_.push_back(r.t_s);
      q_.push_back(r.q);
    }
  }
  // *att_var: the noise variance of the interpolated attitude relative to one record,
  // (1-u)^2 + u^2 (independent record noise).
  bool at(double t, core::Mat3<double>* r_bn, double* att_var = nullptr) const {
    const auto it = std::upper_bound(t_.begin(), t_.end(), t);
    if (att_var != nullptr) *att_var = 1;
    if (it == t_.begin() || it == t_.end()) {
      if (it != t_.begin() && t == t_.back()) {
        *r_bn = q_.back().toRotationMatrix();
        return true;
      }
      return false;
    }
    const std::size_t i1 = static_cast<std::size_t>(it - t_.begin()), i0 = i1 - 1;
    const double dt = t_[i1] - t_[i0];
    if (!(dt > 0) || dt > max_gap_s_) return false;
    const double u = (t - t_[i0]) / dt;
    *r_bn = q_[i0].slerp(u, q_[i1]).toRotationMatrix();
    if (att_var != nullptr) *att_var = (1 - u) * (1 - u) + u * u;
    return true;
  }
  std::size_t size() const { return t_.size(); }
  // Median spacing of the attitude rows.
  double median_dt() const {
    std::vector<double> d;
    for (std::size_t i = 1; i < t_.size(); ++i)
      d.push_back(t_[i] - t_[i - 1]);
    return median_of(d);
  }

 private:
  double max_gap_s_;
  std::vector<double> t_;
  std::vector<core::Quat<double>> q_;
};

// Offers the rows to the calibrator with their attitude at t - tau (only the rows in `use` when
// given; rows whose attitude cannot be interpolated go in without attitude).
void fill(Calibrator* cal, const std::vector<Row>& rows, const AttitudeSeries* series, double tau,
          const std::vector<char>* use, bool need_att) {
  cal->reset();
  for (std::size_t i = 0; i < rows.size(); ++i) {
    const Row& r = rows[i];
    if (use != nullptr && (*use)[i] == 0) continue;
    if (need_att && series != nullptr) {
      core::Mat3<double> r_bn;
      double att_var = 1;
      if (series->at(r.t_s - tau, &r_bn, &att_var)) {
        cal->add_sample(r.m, r.f, r_bn, att_var);
        continue;
      }
      cal->add_sample(r.m, r.f);
      continue;
    }
    if (need_att && r.has_att) {
      cal->add_sample(r.m, r.f, core::Mat3<double>(r.q.toRotationMatrix()));
    } else {
      cal->add_sample(r.m, r.f);
    }
  }
}

// Unweighted vector cost at a fixed calibration: sum |R(t - tau)^T Rm^T h_s - F d|^2.
double scan_cost(const std::vector<Row>& rows, const std::vector<char>& use,
                 const AttitudeSeries& series, double tau, const core::SensorModel<double>& model,
                 const core::Vec3<double>& dir, double field_nT) {
  const core::Mat3<double> rmt = model.rm_matrix().transpose();
  double c = 0;
  for (std::size_t i = 0; i < rows.size(); ++i) {
    if (use[i] == 0) continue;
    core::Mat3<double> r_bn;
    if (!series.at(rows[i].t_s - tau, &r_bn)) continue;
    const double f = std::isfinite(rows[i].f) ? rows[i].f : field_nT;
    const core::Vec3<double> e =
        r_bn.transpose() * (rmt * (model.w * (rows[i].m - model.o))) - f * dir;
    c += e.squaredNorm();
  }
  return c;
}

// Vertex of the parabola through (x-h, a), (x, b), (x+h, c); curvature in *curv.
double parabola_vertex(double x, double h, double a, double b, double c, double* curv) {
  const double den = a - 2 * b + c;
  *curv = den / (h * h);
  if (!(den > 0)) return x;
  return x + 0.5 * h * (a - c) / den;
}

}  // namespace

const char* batch_method_name(core::BatchMethod m) noexcept {
  switch (m) {
    case core::BatchMethod::kOneStep:
      return "li-ml";
    case core::BatchMethod::kPlaneCompression:
      return "li";
    case core::BatchMethod::kJoint:
      return "li-joint";
    case core::BatchMethod::kEllipsoidOnly:
      return "ellipsoid";
  }
  return "unknown";
}

std::string parameter_names(std::uint32_t bits) {
  std::string s;
  for (int k = 0; k < Fit::kParams; ++k) {
    if ((bits & (1U << static_cast<unsigned>(k))) == 0) continue;
    if (!s.empty()) s += ", ";
    s += Fit::param_name(k);
  }
  return s;
}

std::string batch_verdict_reason(const core::BatchResult<double>& r,
                                 const core::BatchConfig<double>& cfg, bool noise_given) {
  const core::BatchQuality<double>& q = r.quality;
  const core::AcceptanceEvidence<double>& e = r.evidence;
  const core::AcceptanceLimits<double>& l = cfg.limits;
  switch (r.verdict) {
    case core::Verdict::kOk:
      return "all acceptance checks passed";
    case core::Verdict::kNoData:
      return "no data rows: the file has a header but no samples; record data first";
    case core::Verdict::kUnitMismatch: {
      const double ratio = e.median_norm_nT / e.median_f_nT;
      std::string hint =
          ratio < 1
              ? "values look like uT under an nT header (median |m| " + f2(e.median_norm_nT, 3) +
                    " vs F " + f2(e.median_f_nT, 1) + "): name the columns hx_uT.."
              : "the reference F looks like uT under an nT header (median "
                "|m| " +
                    f2(e.median_norm_nT, 1) + " vs F " + f2(e.median_f_nT, 3) + "): name it F_uT";
      return hint;
    }
    case core::Verdict::kTooFewSamples:
      return std::to_string(e.usable) + " usable samples, at least " +
             std::to_string(l.min_samples) +
             " needed (rows need a finite reading, a positive F and, for attitude methods, an "
             "attitude)";
    case core::Verdict::kInsufficientCoverage: {
      std::string s = "field directions cover " + f2(100.0 * e.coverage, 1) +
                      " % of the sphere (at least " + f2(100.0 * l.min_coverage, 1) + " % needed)";
      if (q.undetermined != 0)
        s += "; the data do not determine: " + parameter_names(q.undetermined);
      return s +
             "; rotate through more headings and tilts, or give a previous calibration with "
             "--prior cal.json to update only what these data determine";
    }
    case core::Verdict::kIllConditioned:
      return "normal equations numerically singular (rcond " + g3(q.rcond) + ", ellipsoid rcond " +
             g3(q.ellipsoid_rcond) +
             "): the samples do not determine all parameters; record more varied attitudes";
    case core::Verdict::kNotAnEllipsoid:
      return "the readings do not lie on a distorted sphere (the algebraic fit is not an "
             "ellipsoid) although they cover " +
             f2(100.0 * e.coverage, 1) +
             " % of the directions: the field changed during the recording or the data are not "
             "magnetometer readings";
    case core::Verdict::kUnobservableHeadingMisalignment:
      return "pitch/roll spread " + f2(q.tilt_spread_deg, 3) + " deg (minimum " +
             f2(l.min_tilt_spread_deg, 1) +
             " deg): the misalignment about the vertical is unobservable without pitch/roll "
             "variety; record tilted attitudes or hold it with --fix-heading-misalignment-deg";
    case core::Verdict::kResidualTooLarge:
      if (noise_given) {
        return "residuals are " + f2(std::sqrt(q.chi2_per_dof), 2) + "x the given noise (" +
               f2(cfg.mag_noise_nT, 3) + " nT, " + f2(cfg.attitude_noise_deg, 4) +
               " deg): check --noise-nT/--ins-noise-deg, or leave them out to estimate them";
      }
      if (std::isfinite(e.noise_nT) && !(e.noise_nT <= l.max_noise_fraction * e.median_norm_nT)) {
        return "the estimated magnetometer noise (" + f2(e.noise_nT, 1) + " nT) exceeds " +
               f2(100 * l.max_noise_fraction, 0) +
               " % of the field: the readings are not a calibratable magnetometer signal";
      }
      return "residuals have heavy tails (RMS " + f2(q.tail_ratio, 2) +
             "x their robust scale, limit " + f2(l.max_tail_ratio, 1) +
             "): part of the data does not fit the sensor model (disturbed field, wrong "
             "attitude, unmodelled lag); trim the recording to the calibration manoeuvre";
    case core::Verdict::kFieldMismatch:
      return "scale factors " + f2(q.median_norm_nT > 0 ? r.li.ks.minCoeff() : 0, 4) + ".." +
             f2(r.li.ks.maxCoeff(), 4) + " outside [" + f2(l.min_scale, 2) + ", " +
             f2(l.max_scale, 2) + "]: the reference F does not belong to these readings";
    case core::Verdict::kNotConverged:
      return "the iterative fit did not converge in " + std::to_string(cfg.max_iterations) +
             " damped steps per noise round (" + std::to_string(q.iterations) + " taken)";
  }
  return "unknown verdict";
}

namespace {

void fill_batch_file(const io::CsvReader& reader, const BatchRunOptions& opt, BatchRun* run_ptr) {
  BatchRun& run = *run_ptr;
  const core::BatchResult<double>& r = run.result;
  CalibrationFile& c = run.cal;
  c.has_solution = r.has_model;
  c.model = r.model;
  if (r.has_h_n) c.h_n_nT = r.h_n_nT;
  const bool one_step = opt.method == core::BatchMethod::kOneStep;
  if (one_step) {
    c.sigma["ks"] = v3(r.sigma.ks);
    c.sigma["O_deg"] = deg3(r.sigma.o_rad);
    c.sigma["Kof_nT"] = v3(r.sigma.kof);
  }
  if (run.needs_attitude) c.sigma["Rm_deg"] = deg3(r.sigma.rm_rad);
  if (r.has_h_n) c.sigma["h_n_nT"] = v3(r.h_n_sigma_nT);
  c.time_offset_s = run.time_offset.offset_s;
  if (run.time_offset.estimated) c.time_offset_sigma_s = run.time_offset.sigma_s;
  c.noise.mag_nT = r.noise.mag_nT;
  c.noise.mag_estimated = r.noise.estimated;
  if (r.noise.estimated) c.noise.mag_sigma_nT = r.noise.mag_sigma_nT;
  if (r.noise.has_attitude) {
    c.noise.ins_deg = r.noise.attitude_deg;
    c.noise.ins_estimated = r.noise.estimated;
    if (r.noise.estimated) c.noise.ins_sigma_deg = r.noise.attitude_sigma_deg;
  }
  c.quality.verdict = core::verdict_name(r.verdict);
  c.quality.reason = run.reason;
  c.quality.coverage = r.quality.coverage;
  c.quality.condition = r.quality.rcond > 0 ? 1.0 / r.quality.rcond : 0.0;
  c.quality.residual_rms_before_nT = run.eval.intensity_rms_before_nT;
  c.quality.residual_rms_after_nT = run.eval.intensity_rms_after_nT;
  c.quality.extra["tilt_spread_deg"] = r.quality.tilt_spread_deg;
  c.quality.extra["chi2_per_dof"] = r.quality.chi2_per_dof;
  c.quality.extra["tail_ratio"] = r.quality.tail_ratio;
  c.quality.extra["iterations"] = r.quality.iterations;
  c.quality.extra["rows_without_attitude"] = static_cast<double>(run.rows_without_attitude);
  c.quality.extra["rows_kept"] = static_cast<double>(run.rows_kept);
  c.quality.extra["keep_stride"] = static_cast<double>(run.keep_stride);
  if (run.field_from_data) c.quality.extra["field_from_median_norm_nT"] = run.field_nT;
  if (run.eval.has_enu) {
    const char* names[3] = {"E", "N", "U"};
    for (int k = 0; k < 3; ++k) {
      c.quality.extra[std::string("spread_") + names[k] + "_before_nT"] =
          run.eval.enu_sd_before_nT(k);
      c.quality.extra[std::string("spread_") + names[k] + "_after_nT"] =
          run.eval.enu_sd_after_nT(k);
    }
  }
  if (r.heading_fixed)
    c.quality.extra["heading_misalignment_fixed_deg"] = opt.config.fixed_heading_misalignment_deg;
  c.counts.samples = run.rows;
  c.counts.used = r.counts.used;
  c.counts.skipped_nonfinite = r.counts.skipped_nonfinite;
  c.counts.rejected_outliers = r.counts.outliers;
  c.provenance.input = reader.path();
  c.provenance.method = opt.method_name;
}

// The time-offset search (see batch_runner.hpp). Leaves the calibrator filled at the estimate.
TimeOffsetEstimate estimate_time_offset(Calibrator* cal, const std::vector<Row>& rows,
                                        const BatchRunOptions& opt,
                                        core::BatchResult<double>* res) {
  TimeOffsetEstimate out;
  const core::BatchResult<double> r0 = *res;
  if (!r0.has_model || !r0.has_h_n) {
    out.note = "not estimated: no calibration at zero offset to start from";
    return out;
  }
  const double tau_max = opt.max_time_offset_s;
  AttitudeSeries probe(rows, 1e9);
  const double dt = probe.median_dt();
  if (!(dt > 0)) {
    out.note = "not estimated: the attitude rows carry no usable time stamps";
    return out;
  }
  // Interpolate only across gaps of a few attitude periods (an optical dropout is not bridged).
  AttitudeSeries series(rows, std::max(4.0 * dt, 1e-3));
  // The same samples at every tau: those interpolable over the whole search range.
  std::vector<char> use(rows.size(), 0);
  core::Mat3<double> tmp;
  for (std::size_t i = 0; i < rows.size(); ++i) {
    use[i] =
        static_cast<char>(series.at(rows[i].t_s - tau_max, &tmp) &&
                          series.at(rows[i].t_s + tau_max, &tmp) && series.at(rows[i].t_s, &tmp));
    out.samples += static_cast<std::size_t>(use[i]);
  }
  if (out.samples < 100) {
    out.note = "not estimated: only " + std::to_string(out.samples) +
               " samples have attitude on both sides within +-" + f2(tau_max * 1e3, 0) + " ms";
    return out;
  }
  // 1. Scan at the zero-offset calibration, steps of half the attitude period (at most 2 ms).
  const double step = std::min(0.5 * dt, 2e-3);
  const int n_steps = static_cast<int>(std::ceil(tau_max / step));
  const core::Vec3<double> dir = r0.h_n_nT.normalized();
  const double field = r0.h_n_nT.norm();
  double best = std::numeric_limits<double>::infinity(), best_tau = 0, worst = 0;
  for (int k = -n_steps; k <= n_steps; ++k) {
    const double tau = k * step;
    const double c = scan_cost(rows, use, series, tau, r0.model, dir, field);
    if (c < best) {
      best = c;
      best_tau = tau;
    }
    worst = std::max(worst, c);
  }
  if (!(worst > best * (1 + 1e-6))) {
    out.note = "not observable: the cost does not depend on the offset (no rotation)";
    return out;
  }
  if (std::abs(best_tau) >= tau_max - 0.5 * step) {
    out.note = "not estimated: the cost falls toward the edge of the +-" + f2(tau_max * 1e3, 0) +
               " ms search range (" + f2(best_tau * 1e3, 1) + " ms)";
    return out;
  }
  // 2. Full fit (noise re-estimated) at the scan's minimum, then the refitted profile.
  const bool one_step = opt.method == core::BatchMethod::kOneStep;
  fill(cal, rows, &series, best_tau, &use, true);
  core::BatchResult<double> rb = cal->solve(opt.method);
  if (!rb.has_model || !rb.has_h_n) {
    out.note =
        "not estimated: the fit failed at the scan minimum (" + f2(best_tau * 1e3, 1) + " ms)";
    return out;
  }
  // Profile values at the current noise figures (rb) by tau: a walk revisits two points of the
  // previous bracket, and each value is a full refit.
  std::vector<std::pair<double, double>> known;
  auto profile = [&](double tau) {
    for (const auto& [t, c] : known)
      if (t == tau) return c;
    fill(cal, rows, &series, tau, &use, true);
    // chi^2 with the interpolated attitudes' noise modelled (att_var): its expectation is flat
    // in the noise part, so its minimum sits at the true offset. (Adding log det Sigma, as in a
    // full likelihood, would reward the smaller noise of mid-record interpolation and pull the
    // estimate off a record's time.)
    const double c = one_step ? cal->refit_one_step(rb).cost
                              : scan_cost(rows, use, series, tau, rb.model, rb.h_n_nT.normalized(),
                                          rb.h_n_nT.norm());
    known.emplace_back(tau, c);
    return c;
  };
  // Parabolic steps on the profile: move to the vertex when it lies within the bracket (and
  // narrow it), else walk one bracket width downhill; stop when the vertex moves < 10 us.
  // The noise figures of the profile come from a full fit; a fit at a wrong offset mistakes the
  // lag for attitude noise, so the search repeats with the noise re-estimated at its result
  // until the offset settles.
  constexpr double kMinBracket = 2.5e-4;
  double tau_hat = best_tau, curv = 0, h_start = step;
  for (int outer = 0; outer < 4; ++outer) {
    const double tau_start = tau_hat;
    double h = h_start;
    for (int round = 0; round < 12; ++round) {
      const double a = profile(tau_hat - h), b = profile(tau_hat), c = profile(tau_hat + h);
      const double v = parabola_vertex(tau_hat, h, a, b, c, &curv);
      if (!(curv > 0)) {
        tau_hat += a < c ? -h : h;  // not convex here: walk downhill
        continue;
      }
      const double moved = v - tau_hat;
      if (std::abs(moved) <= h) {
        tau_hat = v;
        if (std::abs(moved) < 1e-5) break;
        h = std::max(0.5 * h, kMinBracket);
      } else {
        tau_hat += moved > 0 ? h : -h;
      }
    }
    if (!(curv > 0) || std::abs(tau_hat - tau_start) < 2e-5) break;
    fill(cal, rows, &series, tau_hat, &use, true);
    const core::BatchResult<double> again = cal->solve(opt.method);
    if (!again.has_model || !again.has_h_n) break;
    rb = again;
    known.clear();
    // The noise re-estimated at a better offset moves the minimum less than this search moved
    // it: the next search starts from a bracket of that size instead of the scan's step.
    h_start = std::min(step, std::max(std::abs(tau_hat - tau_start), kMinBracket));
  }
  if (!(curv > 0)) {
    out.note = "not estimated: the profile cost has no curvature at the minimum";
    return out;
  }
  // cost = chi^2 (one-step, noise-normalised): var(tau) = 2 / cost''. Unweighted scan cost:
  // divide by the residual variance per component.
  double scale = 1;
  if (!one_step) {
    const double n = static_cast<double>(rb.counts.used > 0 ? rb.counts.used : 1);
    const double s2 = profile(tau_hat) / (3 * n);
    scale = s2 > 0 ? s2 : 1;
  }
  out.estimated = true;
  out.offset_s = tau_hat;
  out.sigma_s = std::sqrt(2.0 * scale / curv);
  out.note = "estimated from " + std::to_string(out.samples) + " samples";
  fill(cal, rows, &series, tau_hat, nullptr, true);
  *res = cal->solve(opt.method);
  return out;
}

}  // namespace

BatchRun run_batch(io::CsvReader& reader, const BatchRunOptions& opt) {
  BatchRun run;
  run.needs_attitude = opt.method != core::BatchMethod::kEllipsoidOnly;
  // Stream the rows, thinning the kept set when it outgrows max_rows_kept.
  std::vector<Row> rows;
  io::CsvRecord rec;
  std::uint64_t index = 0;
  const std::size_t cap = std::max<std::size_t>(opt.max_rows_kept, 64);
  while (reader.next(&rec)) {
    ++run.rows;
    if (run.needs_attitude && !rec.r_bn && !rec.dropout) ++run.rows_without_attitude;
    if (index++ % run.keep_stride != 0) continue;
    Row r{rec.t_s, rec.m_nT, rec.f_nT ? *rec.f_nT : std::nan(""), core::Quat<double>::Identity(),
          false};
    if (rec.r_bn && rec.r_bn->allFinite()) {
      r.q = core::Quat<double>(*rec.r_bn).normalized();
      r.has_att = true;
    }
    rows.push_back(r);
    if (rows.size() >= 2 * cap) {
      std::size_t k = 0;
      for (std::size_t i = 0; i < rows.size(); i += 2)
        rows[k++] = rows[i];
      rows.resize(k);
      run.keep_stride *= 2;
    }
  }
  rows.shrink_to_fit();
  run.rows_kept = rows.size();

  core::BatchConfig<double> cfg = opt.config;
  cfg.estimate_noise = true;
  // No reference field: the median |m| of the finite readings stands for it.
  if (!std::isfinite(cfg.field_nT)) {
    bool any_f = false;
    std::vector<double> norms;
    for (const Row& r : rows) {
      any_f = any_f || std::isfinite(r.f);
      if (r.m.allFinite()) norms.push_back(r.m.norm());
    }
    if (!any_f && !norms.empty()) {
      cfg.field_nT = median_of(norms);
      run.field_from_data = true;
    }
  }
  run.field_nT = cfg.field_nT;

  auto cal = std::make_unique<Calibrator>(cfg);
  fill(cal.get(), rows, nullptr, 0, nullptr, run.needs_attitude);
  if (opt.fixed_time_offset_s && run.needs_attitude) {
    AttitudeSeries probe(rows, 1e9);
    AttitudeSeries series(rows, std::max(4.0 * probe.median_dt(), 1e-3));
    fill(cal.get(), rows, &series, *opt.fixed_time_offset_s, nullptr, true);
    run.time_offset.offset_s = *opt.fixed_time_offset_s;
    run.time_offset.note = "fixed by the user";
  }
  run.result = cal->solve(opt.method);
  if (run.needs_attitude && !opt.fixed_time_offset_s && !reader.has_time()) {
    run.time_offset.note = "not estimated: the recording has no t_s column";
  } else if (run.needs_attitude && !opt.fixed_time_offset_s) {
    run.time_offset = estimate_time_offset(cal.get(), rows, opt, &run.result);
  } else if (!run.needs_attitude) {
    run.time_offset.note = "not applicable (no attitude)";
  }
  run.data_noise = run.result.noise;

  // Given noise figures: solve with them, and say when the data disagree by more than 2x.
  if (opt.mag_noise_given || opt.ins_noise_given) {
    core::BatchConfig<double> gcfg = cfg;
    gcfg.estimate_noise = false;
    if (!opt.mag_noise_given) gcfg.mag_noise_nT = run.data_noise.mag_nT;
    if (!opt.ins_noise_given && run.data_noise.has_attitude)
      gcfg.attitude_noise_deg = run.data_noise.attitude_deg;
    cal->set_config(gcfg);
    run.result = cal->solve(opt.method);
    cfg = gcfg;
    auto check = [&](bool given, double value, double data, const char* what, const char* unit,
                     const char* flag) {
      if (!given || !(data > 0) || !(value > 0)) return;
      const double ratio = value / data;
      if (ratio > 2 || ratio < 0.5) {
        run.warnings.push_back(std::string(flag) + " " + f2(value, 4) + " " + unit +
                               " disagrees with the data's own estimate of the " + what + " (" +
                               f2(data, 4) + " " + unit + ") by a factor of " +
                               f2(ratio > 1 ? ratio : 1 / ratio, 1));
      }
    };
    check(opt.mag_noise_given, opt.config.mag_noise_nT, run.data_noise.mag_nT, "magnetometer noise",
          "nT", "--noise-nT");
    if (run.data_noise.has_attitude)
      check(opt.ins_noise_given, opt.config.attitude_noise_deg, run.data_noise.attitude_deg,
            "attitude noise", "deg", "--ins-noise-deg");
  }
  run.reason = batch_verdict_reason(run.result, cfg, opt.mag_noise_given || opt.ins_noise_given);
  if (run.result.has_model) {
    // Evaluate over the samples the fit used (outliers and, for attitude methods, rows without
    // attitude excluded).
    Evaluator ev(run.result.model, run.needs_attitude);
    const auto& store = cal->store();
    for (std::size_t i = 0; i < store.size(); ++i) {
      const auto& s = store[i];
      if (s.outlier() || (run.needs_attitude && !s.has_attitude())) continue;
      const core::Mat3<double> r_bn = s.r_bn();
      ev.add(s.raw(), run.field_from_data ? std::nan("") : s.f, s.has_attitude() ? &r_bn : nullptr);
    }
    run.eval = ev.result();
  }
  fill_batch_file(reader, opt, &run);
  return run;
}

}  // namespace magvec::host
