// Sine-fitting calibration over two sweep recordings (see sine_runner.hpp).
#include "calibration/sine_runner.hpp"

#include <cmath>
#include <limits>
#include <stdexcept>
#include <vector>

namespace magvec::host {
namespace {

constexpr double kDeg = 180.0 / core::kPi<double>;
// Above this many readings the O(N^2) numerical propagation is skipped.
constexpr std::size_t kMaxSigmaSamples = 5000;

struct SweepSample {
  double theta_rad;
  core::Vec3<double> m;
  double f;
};

std::vector<SweepSample> read_sweep(io::CsvReader& r, std::uint64_t* rows, std::uint64_t* skipped) {
  if (!r.has_theta()) {
    throw std::invalid_argument(r.path() +
                                ": no theta_deg column (a turntable sweep needs the table angle)");
  }
  std::vector<SweepSample> out;
  io::CsvRecord rec;
  while (r.next(&rec)) {
    ++*rows;
    const double th = rec.theta_deg ? *rec.theta_deg : std::nan("");
    if (rec.dropout || !std::isfinite(th) || !rec.m_nT.allFinite()) {
      ++*skipped;
      continue;
    }
    out.push_back({core::deg_to_rad(th), rec.m_nT, rec.f_nT ? *rec.f_nT : std::nan("")});
  }
  return out;
}

core::SineSolution<double> solve(const std::vector<SweepSample>& xy,
                                 const std::vector<SweepSample>& xz,
                                 const core::SineFitOptions<double>& o) {
  core::SineSweep<double> a, b;
  for (const SweepSample& s : xy)
    a.add(s.theta_rad, s.m);
  for (const SweepSample& s : xz)
    b.add(s.theta_rad, s.m);
  return core::solve_sine(a, b, o);
}

core::Vec<double, 10> params(const core::SineSolution<double>& s) {
  core::Vec<double, 10> p;
  p << s.params.k, s.params.alpha_rad, s.params.beta_rad, s.params.gamma_rad, s.params.b0,
      s.inclination_rad;
  return p;
}

// Var(p) = sum over readings and axes of (dp/dm)^2 * rms^2 (residual RMS of that axis and sweep).
SineParamSigmas propagate(std::vector<SweepSample> xy, std::vector<SweepSample> xz,
                          const core::SineFitOptions<double>& o,
                          const core::SineSolution<double>& sol) {
  SineParamSigmas out;
  if (xy.size() + xz.size() > kMaxSigmaSamples) return out;
  core::Vec<double, 10> var = core::Vec<double, 10>::Zero();
  constexpr double kStep = 1e-3;  // nT: the problem is smooth, readings are O(1e4)
  for (int sweep = 0; sweep < 2; ++sweep) {
    std::vector<SweepSample>& v = sweep == 0 ? xy : xz;
    const core::Vec3<double>& rms = sweep == 0 ? sol.xy.rms : sol.xz.rms;
    for (SweepSample& s : v) {
      for (int k = 0; k < 3; ++k) {
        const double keep = s.m(k);
        s.m(k) = keep + kStep;
        const core::SineSolution<double> sp = solve(xy, xz, o);
        s.m(k) = keep - kStep;
        const core::SineSolution<double> sm = solve(xy, xz, o);
        s.m(k) = keep;
        if (sp.status != core::SineStatus::kOk || sm.status != core::SineStatus::kOk) return out;
        core::Vec<double, 10> d = (params(sp) - params(sm)) / (2 * kStep);
        d(3) = std::remainder(d(3) * 2 * kStep, 2 * core::kPi<double>) / (2 * kStep);
        var += d.cwiseProduct(d) * (rms(k) * rms(k));
      }
    }
  }
  const core::Vec<double, 10> sd = var.cwiseSqrt();
  out.available = sd.allFinite();
  out.k = sd.segment<3>(0);
  out.alpha_rad = sd(3);
  out.beta_rad = sd(4);
  out.gamma_rad = sd(5);
  out.b0 = sd.segment<3>(6);
  out.inclination_rad = sd(9);
  return out;
}

std::string f2(double v, int decimals) {
  char buf[64];
  std::snprintf(buf, sizeof(buf), "%.*f", decimals, v);
  return buf;
}

}  // namespace

const char* sine_status_name(core::SineStatus s) noexcept {
  switch (s) {
    case core::SineStatus::kOk:
      return "ok";
    case core::SineStatus::kTooFewSamples:
      return "too_few_samples";
    case core::SineStatus::kDegenerateSweep:
      return "degenerate_sweep";
    case core::SineStatus::kNoField:
      return "field_mismatch";
    case core::SineStatus::kInconsistent:
      return "inconsistent_sweeps";
  }
  return "unknown";
}

SineRun run_sine(io::CsvReader& xy_reader, io::CsvReader& xz_reader, const SineRunOptions& opt) {
  SineRun run;
  const std::vector<SweepSample> xy = read_sweep(xy_reader, &run.rows_xy, &run.skipped_xy);
  const std::vector<SweepSample> xz = read_sweep(xz_reader, &run.rows_xz, &run.skipped_xz);
  double fsum = 0;
  std::size_t fn = 0;
  for (const auto* v : {&xy, &xz}) {
    for (const SweepSample& s : *v) {
      if (std::isfinite(s.f)) {
        fsum += s.f;
        ++fn;
      }
    }
  }
  run.field_nT = opt.field_nT ? *opt.field_nT
                              : (fn > 0 ? fsum / static_cast<double>(fn)
                                        : std::numeric_limits<double>::quiet_NaN());
  core::SineFitOptions<double> o;
  o.xz_fixture = opt.fixture;
  o.field_nT = std::isfinite(run.field_nT) ? run.field_nT : 0.0;
  run.solution = solve(xy, xz, o);
  const core::SineSolution<double>& sol = run.solution;
  const bool ok = sol.status == core::SineStatus::kOk;
  if (ok) run.sigma = propagate(xy, xz, o, sol);

  Evaluator ev(ok ? sol.model() : core::SensorModel<double>{}, false);
  for (const auto* v : {&xy, &xz}) {
    for (const SweepSample& s : *v)
      ev.add(s.m, std::isfinite(s.f) ? s.f : run.field_nT, nullptr);
  }
  run.eval = ev.result();

  const double max_rms = 3.0 * opt.noise_nT + 1.0;
  const double fit_rms = std::fmax(sol.xy.rms.maxCoeff(), sol.xz.rms.maxCoeff());
  run.verdict = sine_status_name(sol.status);
  switch (sol.status) {
    case core::SineStatus::kOk:
      if (!(fit_rms <= max_rms)) {
        run.verdict = "residual_too_large";
        run.reason = "sine-fit residual RMS " + f2(fit_rms, 2) + " nT above 3x the stated noise " +
                     "+ 1 nT (" + f2(max_rms, 2) +
                     " nT): check --noise-nT, the fixture or the data";
      } else {
        run.reason = "all acceptance checks passed";
      }
      break;
    case core::SineStatus::kTooFewSamples:
      run.reason = "a sweep has fewer than 4 usable readings (XY " + std::to_string(xy.size()) +
                   ", XZ " + std::to_string(xz.size()) + ")";
      break;
    case core::SineStatus::kDegenerateSweep:
      run.reason = "a sweep does not span enough turntable angles for a sine fit";
      break;
    case core::SineStatus::kNoField:
      run.reason = "no total field |B|: the sweeps have no F_nT; give --field-nT";
      break;
    case core::SineStatus::kInconsistent:
      run.reason =
          "the sweeps give out-of-range formulas (|cos(phi)/cos(beta)| > 1 or similar): "
          "wrong --fixture or sweeps swapped?";
      break;
  }

  CalibrationFile& c = run.cal;
  c.model = ok ? sol.model() : core::SensorModel<double>{};
  if (ok) c.sine = SineResult{sol.params, sol.inclination_rad};
  if (run.sigma.available) {
    const SineParamSigmas& s = run.sigma;
    c.sigma["k"] = {s.k(0), s.k(1), s.k(2)};
    c.sigma["alpha_deg"] = {s.alpha_rad * kDeg};
    c.sigma["beta_deg"] = {s.beta_rad * kDeg};
    c.sigma["gamma_deg"] = {s.gamma_rad * kDeg};
    c.sigma["B0_nT"] = {s.b0(0), s.b0(1), s.b0(2)};
    c.sigma["inclination_deg"] = {s.inclination_rad * kDeg};
  }
  c.quality.verdict = run.verdict;
  c.quality.reason = run.reason;
  c.quality.coverage = run.eval.coverage;
  c.quality.condition = 0;
  c.quality.residual_rms_before_nT = run.eval.intensity_rms_before_nT;
  c.quality.residual_rms_after_nT = run.eval.intensity_rms_after_nT;
  c.quality.extra["field_nT"] = std::isfinite(run.field_nT) ? run.field_nT : 0.0;
  c.quality.extra["fit_rms_max_nT"] = fit_rms;
  c.quality.extra["rows_xy"] = static_cast<double>(run.rows_xy);
  c.quality.extra["rows_xz"] = static_cast<double>(run.rows_xz);
  c.counts.samples = run.rows_xy + run.rows_xz;
  c.counts.used = xy.size() + xz.size();
  c.counts.skipped_nonfinite = run.skipped_xy + run.skipped_xz;
  c.counts.rejected_outliers = 0;
  c.provenance.input = xy_reader.path() + " + " + xz_reader.path();
  c.provenance.method =
      std::string("sine-") +
      (opt.fixture == core::SineFixture::kPlaneNormal ? "plane-normal" : "housing-y");
  return run;
}

}  // namespace magvec::host
