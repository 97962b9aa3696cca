// The online vector calibration filter over a recording (see vector_ekf_runner.hpp).
#include "calibration/vector_ekf_runner.hpp"

#include <Eigen/SVD>
#include <algorithm>
#include <cmath>
#include <cstdio>
#include <deque>
#include <limits>
#include <memory>
#include <stdexcept>
#include <vector>

#include "calibration/batch_runner.hpp"
#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/misalignment.hpp"

namespace magvec::host {
namespace {

constexpr double kDeg = 180.0 / core::kPi<double>;
constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
// Neighbouring rows further apart than this do not give a rotation rate (a gap in the attitude).
constexpr double kMaxRateSpanS = 0.25;
// How far around a row the stream keeps attitudes for attitude_at(): five times the filter's prior
// 1-sigma of the time offset.
constexpr double kAttitudeWindowS = 0.25;
// Half the span of the rate the filter is given (RowStream::rate_at).
constexpr double kRateHalfSpanS = 0.02;
// The temperature column the recording may carry.
constexpr const char* kTemperatureColumn = "temperature_degC";

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

double median_of(std::vector<double> v) {
  if (v.empty()) return kNaN;
  const auto mid = v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2);
  std::nth_element(v.begin(), mid, v.end());
  return *mid;
}

// Exp([v x]) (active rotation by the rotation vector v).
core::Mat3<double> exp_so3(const core::Vec3<double>& v) {
  const double a = v.norm();
  if (!(a > 0)) return core::Mat3<double>::Identity();
  return Eigen::AngleAxis<double>(a, v / a).toRotationMatrix();
}

// One data row with what the filter needs from its neighbours.
struct Item {
  io::CsvRecord rec;
  double temperature_degC = kNaN;
  core::Vec3<double> omega_n = core::Vec3<double>::Zero();  // rad/s, n-frame axes
  double interval_s = kNaN;                                 // since the previous row
  std::uint64_t index = 0;                                  // 0-based data row
};

// Streams the rows, read ahead by kAttitudeWindowS: the rate of R_bn^T at a row comes from the
// attitudes of the rows before and after it (central difference), or from the row and one
// neighbour at the ends and next to attitude gaps; attitude_at(t) interpolates the attitude at any
// time within kAttitudeWindowS of the current row (E-VF-5: the filter and the evaluation take the
// attitude at t - dt from the INS samples, as the pipeline does, instead of rotating by dt times a
// differenced rate, whose noise dt multiplies).
class RowStream {
 public:
  RowStream(const std::string& path, const io::CsvReaderOptions& ropt) : reader_(path, ropt) {
    temp_col_ = reader_.column_index(kTemperatureColumn);
  }
  bool next(Item* out) {
    if (ahead_.empty() && !read_one()) return false;
    Item cur = std::move(ahead_.front());
    ahead_.pop_front();
    cur.index = index_++;
    while (!eof_ && (ahead_.empty() || ahead_.back().rec.t_s < cur.rec.t_s + kAttitudeWindowS)) {
      if (!read_one()) break;
    }
    const Item* nxt = ahead_.empty() ? nullptr : &ahead_.front();
    const bool cur_att = cur.rec.r_bn.has_value();
    const bool prev_ok =
        have_prev_ && prev_att_ && cur.rec.t_s - prev_t_ <= kMaxRateSpanS && cur.rec.t_s > prev_t_;
    const bool next_ok = nxt != nullptr && nxt->rec.r_bn &&
                         nxt->rec.t_s - cur.rec.t_s <= kMaxRateSpanS && nxt->rec.t_s > cur.rec.t_s;
    if (cur_att) {
      const core::Mat3<double>& ra = prev_ok ? prev_r_ : *cur.rec.r_bn;
      const double ta = prev_ok ? prev_t_ : cur.rec.t_s;
      const core::Mat3<double>& rb = next_ok ? *nxt->rec.r_bn : *cur.rec.r_bn;
      const double tb = next_ok ? nxt->rec.t_s : cur.rec.t_s;
      cur.omega_n = core::rate_n_from_attitudes<double>(ra, rb, tb - ta);
    }
    if (have_prev_ && cur.rec.t_s > prev_t_) cur.interval_s = cur.rec.t_s - prev_t_;
    have_prev_ = true;
    prev_t_ = cur.rec.t_s;
    prev_att_ = cur_att;
    if (cur_att) prev_r_ = *cur.rec.r_bn;
    // The window: attitudes from kAttitudeWindowS before the current row to the rows read ahead.
    if (!fut_.empty() && fut_.front().index == cur.index) {
      push(&past_, fut_.front());
      fut_.pop_front();
    }
    while (!past_.empty() && past_.front().t_s < cur.rec.t_s - kAttitudeWindowS)
      past_.pop_front();
    *out = std::move(cur);
    return true;
  }
  // R_bn at time t, interpolated between the two attitudes in the window that bracket t (at most
  // kMaxRateSpanS apart); none outside the window or across a gap.
  std::optional<core::Mat3<double>> attitude_at(double t) const {
    const std::size_t n = past_.size() + fut_.size();
    const auto at = [&](std::size_t k) -> const Att& {
      return k < past_.size() ? past_[k] : fut_[k - past_.size()];
    };
    std::size_t lo = 0, hi = n;  // first entry with t_s >= t
    while (lo < hi) {
      const std::size_t mid = (lo + hi) / 2;
      if (at(mid).t_s < t)
        lo = mid + 1;
      else
        hi = mid;
    }
    if (lo == n) return std::nullopt;
    const Att& b = at(lo);
    if (b.t_s == t) return b.q.toRotationMatrix();
    if (lo == 0) return std::nullopt;
    const Att& a = at(lo - 1);
    if (!(b.t_s > a.t_s) || b.t_s - a.t_s > kMaxRateSpanS) return std::nullopt;
    return core::slerp_unit(a.q, b.q, (t - a.t_s) / (b.t_s - a.t_s)).toRotationMatrix();
  }
  // The rate of R_bn^T at time t from the attitudes at t -+ w, w = max(kRateHalfSpanS, 2.5 x the
  // row interval): a span that shares no INS sample with the attitude at t, so its noise is
  // independent of the residual's (a rate from the rows next to the ones interpolated at t - dt
  // biased the offset by 2 %: measured -9.89 ms for -10), and 4x less noisy than the neighbours'
  // (whose noise still pulled the offset 0.2 % towards the start's zero). None outside the window.
  std::optional<core::Vec3<double>> rate_at(double t, double interval_s) const {
    const double w =
        std::max(kRateHalfSpanS, std::isfinite(interval_s) ? 2.5 * interval_s : kRateHalfSpanS);
    if (2 * w > kMaxRateSpanS) return std::nullopt;
    const auto ra = attitude_at(t - w), rb = attitude_at(t + w);
    if (!ra || !rb) return std::nullopt;
    return core::rate_n_from_attitudes<double>(*ra, *rb, 2 * w);
  }
  const io::CsvReader& reader() const { return reader_; }

 private:
  struct Att {
    double t_s;
    core::Quat<double> q;  // R_bn
    std::uint64_t index;   // data row
  };
  // Appends keeping the times increasing: a step back in time starts the window anew.
  static void push(std::deque<Att>* d, const Att& a) {
    if (!d->empty() && !(a.t_s > d->back().t_s)) d->clear();
    d->push_back(a);
  }
  bool read_one() {
    Item it;
    if (!reader_.next(&it.rec)) {
      eof_ = true;
      return false;
    }
    it.temperature_degC = temp_col_ ? reader_.value(*temp_col_) : kNaN;
    if (it.rec.r_bn) {
      const std::uint64_t row = index_ + ahead_.size();
      push(&fut_, Att{it.rec.t_s, core::Quat<double>(*it.rec.r_bn).normalized(), row});
    }
    ahead_.push_back(std::move(it));
    return true;
  }
  io::CsvReader reader_;
  std::optional<std::size_t> temp_col_;
  std::deque<Item> ahead_;
  std::deque<Att> past_, fut_;
  bool eof_ = false;
  bool have_prev_ = false, prev_att_ = false;
  double prev_t_ = 0;
  core::Mat3<double> prev_r_ = core::Mat3<double>::Identity();
  std::uint64_t index_ = 0;
};

const std::array<const char*, kVfTraceStates> kStateNames = {"W00",
                                                             "W10",
                                                             "W11",
                                                             "W12",
                                                             "W20",
                                                             "W22",
                                                             "o_x_nT",
                                                             "o_y_nT",
                                                             "o_z_nT",
                                                             "am_deg",
                                                             "bm_deg",
                                                             "gm_deg",
                                                             "hE_nT",
                                                             "hN_nT",
                                                             "hU_nT",
                                                             "dt_s",
                                                             "c_x_nT_per_degC",
                                                             "c_y_nT_per_degC",
                                                             "c_z_nT_per_degC"};

std::vector<std::string> trace_columns() {
  std::vector<std::string> c = {"row", "t_s", "status", "initialised"};
  for (const char* s : kStateNames)
    c.emplace_back(s);
  for (const char* s : kStateNames)
    c.push_back(std::string("sigma_") + s);
  for (const char* s : {"nis", "innov_E_nT", "innov_N_nT", "innov_U_nT", "innov_F_nT"})
    c.emplace_back(s);
  return c;
}

// The filter's outputs in double, interface units, with the Li misalignment angles.
struct Snapshot {
  core::SensorModel<double> model;  // offset at T0
  core::Mat<double, 19, 19> cov = core::Mat<double, 19, 19>::Zero();
  core::Vec3<double> h_n = core::Vec3<double>::Zero();
  core::Vec3<double> tc = core::Vec3<double>::Zero();
  double dt{0}, t0{kNaN};
};

template <typename Filter>
Snapshot snapshot(const Filter& f) {
  Snapshot s;
  s.model.w = f.w().template cast<double>();
  s.model.o = f.offset_ref_nT().template cast<double>();
  s.model.rm = f.rm().template cast<double>();
  s.cov = f.covariance().template cast<double>();
  s.h_n = f.h_n_nT().template cast<double>();
  s.tc = f.temperature_coefficients_nT_per_degC().template cast<double>();
  s.dt = static_cast<double>(f.time_offset_s());
  s.t0 = static_cast<double>(f.temperature_ref_degC());
  return s;
}

double sd(const core::Mat<double, 19, 19>& p, int k) {
  return std::sqrt(std::max(p(k, k), 0.0));
}

// Li angles (alpha_m, beta_m, gamma_m) and their covariance from the filter's body-axis errors:
// phi = axes * d(li angles) (li_rm_axes_body, E-VF-A).
bool li_angles(const Snapshot& s, core::Vec3<double>* ang, core::Mat3<double>* cov) {
  core::LiParams<double> li;
  if (core::to_li(s.model, &li) != core::ConversionStatus::kOk) return false;
  *ang = li.rm_rad;
  const core::Mat3<double> axes = core::li_rm_axes_body(li.rm_rad);
  const core::Mat3<double> inv = axes.inverse();
  *cov = inv * s.cov.block<3, 3>(9, 9) * inv.transpose();
  return ang->allFinite() && cov->allFinite();
}

// ks and O of the Li form as functions of the six free W entries (central differences), and the
// sigmas they get from the W block of the covariance.
bool li_w_sigmas(const Snapshot& s, core::Vec3<double>* ks_sigma, core::Vec3<double>* o_sigma) {
  using F = core::VectorCalibrationFilter<double>;
  auto li_of = [&](const core::Mat3<double>& w, core::Vec<double, 6>* out) {
    core::SensorModel<double> m = s.model;
    m.w = w;
    core::LiParams<double> li;
    if (core::to_li(m, &li) != core::ConversionStatus::kOk) return false;
    *out << li.ks, li.o_rad;
    return out->allFinite();
  };
  core::Mat<double, 6, 6> j;
  for (int k = 0; k < F::kWEntries; ++k) {
    const double h = 1e-7;
    core::Mat3<double> wp = s.model.w, wm = s.model.w;
    const int r = F::kWRow[static_cast<std::size_t>(k)];
    const int c = F::kWCol[static_cast<std::size_t>(k)];
    wp(r, c) += h;
    wm(r, c) -= h;
    core::Vec<double, 6> pp, pm;
    if (!li_of(wp, &pp) || !li_of(wm, &pm)) return false;
    j.col(k) = (pp - pm) / (2 * h);
  }
  const core::Vec<double, 6> var = (j * s.cov.block<6, 6>(0, 0) * j.transpose()).diagonal();
  const core::Vec<double, 6> sdv = var.cwiseMax(0.0).cwiseSqrt();
  *ks_sigma = sdv.head<3>();
  *o_sigma = sdv.tail<3>();
  return true;
}

// The 19 trace values (Rm as Li angles, degrees) and their 1-sigmas.
void trace_states(const Snapshot& s, double* x, double* sx) {
  using F = core::VectorCalibrationFilter<double>;
  for (int k = 0; k < F::kWEntries; ++k) {
    x[k] = s.model.w(F::kWRow[static_cast<std::size_t>(k)], F::kWCol[static_cast<std::size_t>(k)]);
    sx[k] = sd(s.cov, k);
  }
  for (int i = 0; i < 3; ++i) {
    x[6 + i] = s.model.o(i);
    sx[6 + i] = sd(s.cov, 6 + i);
    x[12 + i] = s.h_n(i);
    sx[12 + i] = sd(s.cov, 12 + i);
    x[16 + i] = s.tc(i);
    sx[16 + i] = sd(s.cov, 16 + i);
  }
  core::Vec3<double> ang;
  core::Mat3<double> ac;
  const bool ok = li_angles(s, &ang, &ac);
  for (int i = 0; i < 3; ++i) {
    x[9 + i] = ok ? ang(i) * kDeg : kNaN;
    sx[9 + i] = ok ? std::sqrt(std::max(ac(i, i), 0.0)) * kDeg : kNaN;
  }
  x[15] = s.dt;
  sx[15] = sd(s.cov, 15);
}

// The model's attitude at t - dt (E-VF-5): R_bn(t - dt) = R_bn(t) Exp(dt [Omega x]).
core::Mat3<double> delayed(const core::Mat3<double>& r, const core::Vec3<double>& omega,
                           double dt) {
  return r * exp_so3(omega * dt);
}

struct PassResult {
  Snapshot snap;
  bool initialised{false};
  bool heading_held{false};
  double tilt_spread_deg{0};
  core::VfCounters counters;
  std::string last_reset{"none"};
  std::uint64_t last_reset_row{0};
  std::string init_verdict;
  int startup_samples{0};
  std::uint64_t rows{0}, dropouts{0}, no_att{0}, with_temp{0}, no_ref{0}, accepted{0}, gated{0};
  std::uint64_t trace_rows{0};
};

template <typename Scalar>
PassResult run_filter(const std::string& path, const io::CsvReaderOptions& ropt,
                      const core::VfConfig<Scalar>& cfg, const std::string& trace_path,
                      std::uint64_t stride, std::uint64_t total_rows) {
  using Filter = core::VectorCalibrationFilter<Scalar>;
  auto filter = std::make_unique<Filter>(cfg);
  std::unique_ptr<io::CsvWriter> trace;
  if (!trace_path.empty()) {
    trace = std::make_unique<io::CsvWriter>(
        trace_path, trace_columns(),
        std::vector<std::string>{
            "magvec calibrate --method vector-ekf trace of " + path + ": every " +
                std::to_string(stride) +
                "th data row (row: 0-based) and the last, after the "
                "filter saw it",
            "status: 0 accepted, 1 collecting, 2 initialised, 3 init_failed, 4 gated, "
            "5 field_reopened, 6 rejected_nonfinite, 7 rejected_no_reference, 8 reset, "
            "9 no attitude or dropout (not fed)",
            "states while initialised (else nan): W entries, offset at the reference temperature "
            "(nT), misalignment as Li angles am/bm/gm (deg), h_n E/N/U (nT), time offset dt_s "
            "(s, magnetometer lags when > 0), offset temperature coefficients; sigma_*: "
            "1-sigma from the filter's covariance",
            "nis: largest whitened NIS of the row's vector update; innov_*: innovation at the "
            "estimate before the row, h_n - Exp(-dt [Omega x]) R_bn^T Rm^T W (m - o(T)) and "
            "F - |h_n| (nT)"});
  }
  std::vector<double> row(trace ? trace->column_count() : 0);
  PassResult pr;
  RowStream stream(path, ropt);
  Item it;
  double last_temp = kNaN;
  while (stream.next(&it)) {
    ++pr.rows;
    const io::CsvRecord& rec = it.rec;
    if (std::isfinite(it.temperature_degC)) {
      ++pr.with_temp;
      last_temp = it.temperature_degC;
    }
    const bool traced = trace && (it.index % stride == 0 || it.index + 1 == total_rows);
    const bool was_running = filter->initialised();
    core::Vec3<double> innov = core::Vec3<double>::Constant(kNaN);
    double innov_f = kNaN;
    const double f = rec.f_nT ? *rec.f_nT : kNaN;
    int status = 9;
    if (rec.dropout) {
      ++pr.dropouts;
    } else if (!rec.r_bn) {
      ++pr.no_att;
    } else {
      // The attitude at t - dt for the filter's current dt, interpolated from the INS samples
      // around the row; the filter rotates only by what its dt moves from this (E-VF-5).
      core::Mat3<double> r_att = *rec.r_bn;
      core::Vec3<double> omega = it.omega_n;
      double applied_s = 0;
      const double dt_now = static_cast<double>(filter->time_offset_s());
      if (std::isfinite(dt_now) && dt_now != 0 && std::abs(dt_now) < kAttitudeWindowS) {
        if (const auto r = stream.attitude_at(rec.t_s - dt_now)) {
          r_att = *r;
          applied_s = dt_now;
        }
      }
      if (const auto w = stream.rate_at(rec.t_s - applied_s, it.interval_s)) omega = *w;
      if (traced && was_running) {
        const Snapshot s = snapshot(*filter);
        const double dtemp =
            std::isfinite(last_temp) && std::isfinite(s.t0) ? last_temp - s.t0 : 0.0;
        const core::Vec3<double> hs = s.model.w * (rec.m_nT - s.model.o - s.tc * dtemp);
        const core::Vec3<double> g = delayed(r_att, omega, s.dt - applied_s).transpose() *
                                     (s.model.rm_matrix().transpose() * hs);
        innov = s.h_n - g;
        if (std::isfinite(f)) innov_f = f - s.h_n.norm();
      }
      core::VfSample<Scalar> in;
      in.m_nT = rec.m_nT.template cast<Scalar>();
      in.r_bn = r_att.template cast<Scalar>();
      in.attitude_offset_s = static_cast<Scalar>(applied_s);
      in.omega_n_rad_s = omega.template cast<Scalar>();
      in.f_nT = static_cast<Scalar>(f);
      in.temperature_degC = static_cast<Scalar>(it.temperature_degC);
      in.interval_s = static_cast<Scalar>(it.interval_s);
      const core::VfStatus st = filter->update(in);
      status = static_cast<int>(st);
      switch (st) {
        case core::VfStatus::kAccepted:
        case core::VfStatus::kFieldReopened:
          ++pr.accepted;
          break;
        case core::VfStatus::kGated:
          ++pr.gated;
          break;
        case core::VfStatus::kRejectedNoReference:
          ++pr.no_ref;
          break;
        case core::VfStatus::kReset:
          pr.last_reset_row = it.index + 1;
          break;
        default:
          break;
      }
    }
    if (traced) {
      std::size_t k = 0;
      row[k++] = static_cast<double>(it.index);
      row[k++] = rec.t_s;
      row[k++] = status;
      row[k++] = filter->initialised() ? 1.0 : 0.0;
      double x[kVfTraceStates], sx[kVfTraceStates];
      if (filter->initialised()) {
        trace_states(snapshot(*filter), x, sx);
      } else {
        std::fill(std::begin(x), std::end(x), kNaN);
        std::fill(std::begin(sx), std::end(sx), kNaN);
      }
      for (double v : x)
        row[k++] = std::isfinite(v) ? v : kNaN;
      for (double v : sx)
        row[k++] = std::isfinite(v) ? v : kNaN;
      const double nis = static_cast<double>(filter->last_nis());
      row[k++] = was_running && std::isfinite(nis) ? nis : kNaN;
      for (int i = 0; i < 3; ++i)
        row[k++] = std::isfinite(innov(i)) ? innov(i) : kNaN;
      row[k++] = std::isfinite(innov_f) ? innov_f : kNaN;
      trace->write_row(row);
    }
  }
  if (trace) {
    trace->commit();
    pr.trace_rows = trace->rows();
  }
  pr.snap = snapshot(*filter);
  pr.initialised = filter->initialised();
  pr.heading_held = filter->heading_held();
  pr.tilt_spread_deg = static_cast<double>(filter->tilt_spread_deg());
  pr.counters = filter->counters();
  pr.last_reset = core::vf_reset_reason_name(filter->last_reset_reason());
  pr.init_verdict = core::verdict_name(filter->last_init_verdict());
  pr.startup_samples = filter->startup_samples();
  return pr;
}

template <typename Scalar>
core::VfConfig<Scalar> make_config(double noise_nT, double ins_deg, bool isotropic, double field_nT,
                                   const VectorEkfRunOptions& opt) {
  core::VfConfig<Scalar> c;
  c.mag_noise_nT = static_cast<Scalar>(noise_nT);
  c.attitude_noise_rad = static_cast<Scalar>(ins_deg / kDeg);
  c.attitude_model =
      isotropic ? core::AttitudeNoiseModel::kIsotropic : core::AttitudeNoiseModel::kLiEuler;
  c.reference_field_nT = static_cast<Scalar>(field_nT);
  c.min_tilt_spread_deg = static_cast<Scalar>(opt.limits.min_tilt_spread_deg);
  if (opt.time_offset_s) {
    c.estimate_time_offset = false;
    c.time_offset0_s = static_cast<Scalar>(*opt.time_offset_s);
  }
  return c;
}

// Bits of the twelve Li parameters: ks 0-2, O 3-5, Kof 6-8, Rm 9-11.
std::string li_param_name(int k) {
  static const char* kGroup[4] = {"ks", "O", "Kof", "Rm"};
  static const char* kAxis[3] = {"1", "2", "3"};
  return std::string(kGroup[k / 3]) + kAxis[k % 3];
}

}  // namespace

const std::array<const char*, kVfTraceStates>& vf_trace_state_names() noexcept {
  return kStateNames;
}

const char* vf_status_name(core::VfStatus s) noexcept {
  switch (s) {
    case core::VfStatus::kAccepted:
      return "accepted";
    case core::VfStatus::kCollecting:
      return "collecting";
    case core::VfStatus::kInitialised:
      return "initialised";
    case core::VfStatus::kInitFailed:
      return "init_failed";
    case core::VfStatus::kGated:
      return "gated";
    case core::VfStatus::kFieldReopened:
      return "field_reopened";
    case core::VfStatus::kRejectedNonFinite:
      return "rejected_nonfinite";
    case core::VfStatus::kRejectedNoReference:
      return "rejected_no_reference";
    case core::VfStatus::kReset:
      return "reset";
  }
  return "unknown";
}

VectorEkfRun run_vector_ekf(const std::string& path, const io::CsvReaderOptions& reader_options,
                            const VectorEkfRunOptions& opt) {
  if (opt.noise_nT && !(*opt.noise_nT > 0))
    throw std::invalid_argument("--noise-nT must be positive");
  if (opt.ins_noise_deg && !(*opt.ins_noise_deg > 0))
    throw std::invalid_argument("--ins-noise-deg must be positive");
  if (opt.trace_max_rows < 2) throw std::invalid_argument("the trace needs at least 2 rows");
  io::CsvReaderOptions ropt = reader_options;
  ropt.require_time = true;  // the rate and the time offset need t_s
  VectorEkfRun run;
  bool isotropic = false;
  // Pre-pass: rows, the medians of |m| and F (unit check, the field of a recording without F).
  std::vector<double> norms, fs;
  {
    io::CsvReader reader(path, ropt);
    if (reader.attitude_columns() == io::AttitudeColumns::kNone) {
      throw std::invalid_argument(
          path +
          ": no attitude columns (alpha/beta/gamma_deg, yaw/pitch/roll_deg or qw..qz): --method "
          "vector-ekf needs the INS attitude; use --method ellipsoid or ekf");
    }
    isotropic = reader.attitude_columns() == io::AttitudeColumns::kQuaternion;
    io::CsvRecord rec;
    while (reader.next(&rec)) {
      ++run.rows;
      if (rec.m_nT.allFinite()) norms.push_back(rec.m_nT.norm());
      if (rec.f_nT && std::isfinite(*rec.f_nT) && *rec.f_nT > 0) fs.push_back(*rec.f_nT);
    }
  }
  const double median_norm = median_of(norms);
  const double median_f = median_of(fs);
  norms = {};
  // The field for rows without F: given, else the recording's F (median), else the median |m|.
  double field = opt.field_nT ? *opt.field_nT : median_f;
  if (!std::isfinite(field)) {
    field = median_norm;
    run.field_from_data = std::isfinite(field);
    if (run.field_from_data) ropt.f_nT = field;  // every row: the batch methods' convention
  }
  run.field_nT = field;

  // Noise: given, or the one-step fit's variance components on a bounded subset.
  run.noise_nT = opt.noise_nT.value_or(core::VfConfig<double>{}.mag_noise_nT);
  run.ins_noise_deg = opt.ins_noise_deg.value_or(0.015);
  if (run.rows > 0 && (!opt.noise_nT || !opt.ins_noise_deg)) {
    io::CsvReaderOptions bopt = ropt;
    io::CsvReader reader(path, bopt);
    BatchRunOptions bo;
    bo.method = core::BatchMethod::kOneStep;
    bo.config.field_nT = field;
    bo.config.attitude_model =
        isotropic ? core::AttitudeNoiseModel::kIsotropic : core::AttitudeNoiseModel::kLiEuler;
    bo.max_rows_kept = opt.noise_rows;
    if (opt.time_offset_s) bo.fixed_time_offset_s = *opt.time_offset_s;
    const BatchRun br = run_batch(reader, bo);
    const core::BatchNoise<double>& nz = br.data_noise;
    if (!opt.noise_nT) {
      if (nz.estimated && std::isfinite(nz.mag_nT) && nz.mag_nT > 0) {
        run.noise_nT = nz.mag_nT;
        run.noise_sigma_nT = nz.mag_sigma_nT;
        run.noise_estimated = true;
      } else {
        run.warnings.push_back(
            "the data did not give a magnetometer noise estimate (one-step fit: " +
            std::string(core::verdict_name(br.result.verdict)) + "); using " + f2(run.noise_nT, 3) +
            " nT: give --noise-nT");
      }
    }
    if (!opt.ins_noise_deg) {
      if (nz.estimated && nz.has_attitude && std::isfinite(nz.attitude_deg) &&
          nz.attitude_deg > 0) {
        run.ins_noise_deg = nz.attitude_deg;
        run.ins_noise_sigma_deg = nz.attitude_sigma_deg;
        run.ins_noise_estimated = true;
      } else {
        run.warnings.push_back("the data did not give an INS noise estimate; using " +
                               f2(run.ins_noise_deg, 4) + " deg: give --ins-noise-deg");
      }
    }
  }

  const std::uint64_t stride =
      std::max<std::uint64_t>(1, (run.rows + opt.trace_max_rows - 2) / (opt.trace_max_rows - 1));
  run.trace_stride = stride;
  const double field_cfg = std::isfinite(field) ? field : 0.0;
  PassResult pr =
      opt.float32
          ? run_filter<float>(
                path, ropt,
                make_config<float>(run.noise_nT, run.ins_noise_deg, isotropic, field_cfg, opt),
                opt.trace_path, stride, run.rows)
          : run_filter<double>(
                path, ropt,
                make_config<double>(run.noise_nT, run.ins_noise_deg, isotropic, field_cfg, opt),
                opt.trace_path, stride, run.rows);
  run.initialised = pr.initialised;
  run.model = pr.snap.model;
  run.h_n_nT = pr.snap.h_n;
  run.time_offset_s = pr.snap.dt;
  run.tc_nT_per_degC = pr.snap.tc;
  run.temperature_ref_degC = pr.snap.t0;
  const core::Mat<double, 19, 19>& p = pr.snap.cov;
  for (int i = 0; i < 3; ++i) {
    run.h_n_sigma_nT(i) = sd(p, 12 + i);
    run.tc_sigma_nT_per_degC(i) = sd(p, 16 + i);
  }
  run.time_offset_sigma_s = sd(p, 15);
  run.heading_held = pr.heading_held;
  run.tilt_spread_deg = pr.tilt_spread_deg;
  run.counters = pr.counters;
  run.last_reset = pr.last_reset;
  run.last_reset_row = pr.last_reset_row;
  run.last_init_verdict = pr.init_verdict;
  run.startup_samples = pr.startup_samples;
  run.dropouts = pr.dropouts;
  run.rows_without_attitude = pr.no_att;
  run.rows_with_temperature = pr.with_temp;
  run.rows_without_reference = pr.no_ref;
  run.accepted = pr.accepted;
  run.gated = pr.gated;
  run.trace_rows = pr.trace_rows;

  // Li form and its 1-sigmas from the covariance.
  const bool model_finite = run.model.w.allFinite() && run.model.o.allFinite();
  if (run.initialised && model_finite &&
      core::to_li(run.model, &run.li) == core::ConversionStatus::kOk) {
    core::Vec3<double> ang;
    core::Mat3<double> ac;
    run.li_ok = li_w_sigmas(pr.snap, &run.li_sigma.ks, &run.li_sigma.o_rad) &&
                li_angles(pr.snap, &ang, &ac);
    if (run.li_ok) {
      for (int i = 0; i < 3; ++i) {
        run.li_sigma.kof(i) = sd(p, 6 + i);
        run.li_sigma.rm_rad(i) = std::sqrt(std::max(ac(i, i), 0.0));
      }
    }
  }

  // Evaluation pass at the final estimate: attitude moved back by the time offset, offset at each
  // row's temperature.
  Evaluator ev(run.model, true);
  std::uint64_t usable = 0;
  if (run.initialised && model_finite) {
    RowStream stream(path, ropt);
    Item it;
    double last_temp = kNaN;
    while (stream.next(&it)) {
      if (std::isfinite(it.temperature_degC)) last_temp = it.temperature_degC;
      if (it.rec.dropout || !it.rec.r_bn) continue;
      ++usable;
      const double dtemp = std::isfinite(last_temp) && std::isfinite(run.temperature_ref_degC)
                               ? last_temp - run.temperature_ref_degC
                               : 0.0;
      // The attitude at t - dt from the INS samples around the row; outside the stream's window
      // (or across a gap) rotated by dt at the row's rate.
      const std::optional<core::Mat3<double>> ri =
          stream.attitude_at(it.rec.t_s - run.time_offset_s);
      const core::Mat3<double> r = ri ? *ri : delayed(*it.rec.r_bn, it.omega_n, run.time_offset_s);
      const double f = run.field_from_data ? kNaN : (it.rec.f_nT ? *it.rec.f_nT : kNaN);
      ev.add(it.rec.m_nT - run.tc_nT_per_degC * dtemp, f, &r);
    }
  } else {
    usable = run.rows - run.dropouts - run.rows_without_attitude;
  }
  run.eval = ev.result();

  // Evidence for the one acceptance policy.
  core::AcceptanceEvidence<double>& e = run.evidence;
  core::AcceptanceLimits<double> limits = opt.limits;
  limits.min_samples = std::max<std::size_t>(
      limits.min_samples, static_cast<std::size_t>(core::VfConfig<double>{}.init_samples));
  e.rows = run.rows;
  e.usable = usable;
  e.median_norm_nT = median_norm;
  e.median_f_nT = median_f;
  std::uint32_t undetermined = 0;
  core::Vec<double, 12> rel = core::Vec<double, 12>::Constant(kNaN);
  if (run.initialised) {
    e.coverage = run.eval.coverage;
    e.tilt_spread_deg = run.tilt_spread_deg;
    if (run.li_ok) {
      const double fref = std::isfinite(field) && field > 0 ? field : 1.0;
      for (int i = 0; i < 3; ++i) {
        rel(i) = run.li_sigma.ks(i);
        rel(3 + i) = run.li_sigma.o_rad(i);
        rel(6 + i) = run.li_sigma.kof(i) / fref;
        rel(9 + i) = run.li_sigma.rm_rad(i);
      }
      for (int k = 0; k < 12; ++k)
        if (!(rel(k) <= limits.max_relative_sigma)) undetermined |= 1U << static_cast<unsigned>(k);
    }
  }
  e.undetermined = undetermined;
  e.converged = run.initialised && model_finite && run.li_ok && run.h_n_nT.allFinite() &&
                std::isfinite(run.time_offset_s);
  e.noise_given = opt.noise_nT.has_value();
  e.noise_nT = run.noise_nT;
  if (run.initialised && model_finite && std::abs(run.model.w.determinant()) > 0) {
    const Eigen::JacobiSVD<core::Mat3<double>> svd(run.model.w);
    e.min_scale = 1.0 / svd.singularValues()(0);
    e.max_scale = 1.0 / svd.singularValues()(2);
  }
  run.verdict_code = core::judge(e, limits);
  run.verdict = core::verdict_name(run.verdict_code);

  // The reason, naming the cause and what to do.
  const core::VfCounters& k = run.counters;
  const int need = core::VfConfig<double>{}.init_samples;
  auto not_running = [&]() -> std::string {
    if (k.resets > 0) {
      return "the filter ran, then detected a divergence and restarted (" + run.last_reset + ", " +
             std::to_string(k.resets) + " reset" + (k.resets == 1 ? "" : "s") +
             ", the last at row " + std::to_string(run.last_reset_row) +
             ") and had not started again by the end of the data (" +
             std::to_string(run.startup_samples) + " of " + std::to_string(need) +
             " start-up samples kept): check the noise figures (--noise-nT, --ins-noise-deg) and "
             "for disturbed or out-of-model stretches, or record longer";
    }
    if (k.init_attempts == 0) {
      if (run.rows_without_reference > 0 && run.startup_samples == 0)
        return "the filter never started: no scalar reference for its start (no F_nT, no "
               "--field-nT); give --field-nT or --site/--date";
      return "the filter never started: it kept " + std::to_string(run.startup_samples) + " of " +
             std::to_string(need) +
             " start-up samples (each a few degrees of attitude change from the last): the "
             "recording does not turn enough; rotate through more headings and tilts";
    }
    // The start fits the one-step model to a small set kept by attitude change (E-VF-1); say what
    // its refusal means for that set, which can differ from the recording as a whole.
    std::string why;
    if (run.last_init_verdict == "unobservable_heading_misalignment") {
      why =
          "the kept set does not determine the misalignment about the vertical (too little tilt "
          "among its samples, or noise too large for so few)";
    } else if (run.last_init_verdict == "insufficient_coverage") {
      why = "the kept set does not determine every parameter (too few directions for the noise)";
    } else {
      why = "the kept set's fit was refused";
    }
    return "the filter never started: " + std::to_string(k.init_attempts) + " start" +
           (k.init_attempts == 1 ? "" : "s") + " from data tried on " + std::to_string(need) +
           " samples kept by attitude change, all refused by the start's batch fit (the last: " +
           run.last_init_verdict + ": " + why + "; the whole recording's tilt spread is " +
           f2(run.tilt_spread_deg, 2) + " deg, magnetometer noise " + f2(run.noise_nT, 1) +
           " nT); rotate through more tilts early in the recording, or use --method li-ml, which "
           "fits every sample at once";
  };
  switch (run.verdict_code) {
    case core::Verdict::kOk:
      run.reason = "all acceptance checks passed";
      break;
    case core::Verdict::kNoData:
      run.reason = "no data rows: the file has a header but no samples";
      break;
    case core::Verdict::kUnitMismatch: {
      const double ratio = e.median_norm_nT / e.median_f_nT;
      run.reason = (ratio < 1 ? "values look like uT under an nT header"
                              : "the reference F looks like uT under an nT header") +
                   std::string(" (median |m| ") + g3(e.median_norm_nT) + " vs F " +
                   g3(e.median_f_nT) + ")";
      break;
    }
    case core::Verdict::kTooFewSamples:
      run.reason = std::to_string(usable) + " usable samples (a finite reading with attitude), " +
                   "at least " + std::to_string(limits.min_samples) + " needed";
      if (!run.initialised) run.reason += "; " + not_running();
      break;
    case core::Verdict::kUnobservableHeadingMisalignment:
      run.reason = "pitch/roll spread " + f2(run.tilt_spread_deg, 2) + " deg (at least " +
                   f2(limits.min_tilt_spread_deg, 1) +
                   " needed): the misalignment about the vertical stayed held at the start's "
                   "value (docs/equations.md E-VF-7); tilt the platform";
      break;
    case core::Verdict::kInsufficientCoverage: {
      std::string s = "field directions cover " + f2(100.0 * e.coverage, 1) + " % of the sphere";
      if (undetermined != 0) {
        s += "; the filter's covariance leaves undetermined:";
        bool first = true;
        for (int i = 0; i < 12; ++i) {
          if ((undetermined & (1U << static_cast<unsigned>(i))) == 0) continue;
          s += std::string(first ? " " : ", ") + li_param_name(i) + " (1-sigma " + g3(rel(i)) +
               (i >= 6 && i < 9 ? " of F)" : ")");
          first = false;
        }
        s += " (limit " + g3(limits.max_relative_sigma) + ")";
      }
      run.reason = s + "; rotate through more headings and tilts";
      break;
    }
    case core::Verdict::kNotConverged:
      run.reason = run.initialised ? "the state or its covariance is not finite" : not_running();
      break;
    case core::Verdict::kResidualTooLarge:
      run.reason = "the magnetometer noise (" + f2(e.noise_nT, 1) + " nT) exceeds " +
                   f2(100 * limits.max_noise_fraction, 0) + " % of the field";
      break;
    case core::Verdict::kFieldMismatch:
      run.reason = "scale factors " + f2(e.min_scale, 4) + ".." + f2(e.max_scale, 4) +
                   " outside [" + f2(limits.min_scale, 2) + ", " + f2(limits.max_scale, 2) +
                   "]: the reference field does not match the readings";
      break;
    default:
      run.reason = "see the verdict";
      break;
  }
  if (run.verdict_code == core::Verdict::kOk && k.resets > 0) {
    run.warnings.push_back("the filter restarted " + std::to_string(k.resets) +
                           " time(s) on a detected divergence (last: " + run.last_reset +
                           " at row " + std::to_string(run.last_reset_row) +
                           "): the result rests on the data after the last restart");
  }

  CalibrationFile& c = run.cal;
  c.has_solution = run.initialised && model_finite;
  c.model = run.model;
  if (run.initialised) {
    c.h_n_nT = run.h_n_nT;
    c.time_offset_s = run.time_offset_s;
    if (!opt.time_offset_s) c.time_offset_sigma_s = run.time_offset_sigma_s;
    c.sigma["h_n_nT"] = {run.h_n_sigma_nT(0), run.h_n_sigma_nT(1), run.h_n_sigma_nT(2)};
  }
  if (run.li_ok) {
    c.sigma["ks"] = {run.li_sigma.ks(0), run.li_sigma.ks(1), run.li_sigma.ks(2)};
    c.sigma["O_deg"] = {run.li_sigma.o_rad(0) * kDeg, run.li_sigma.o_rad(1) * kDeg,
                        run.li_sigma.o_rad(2) * kDeg};
    c.sigma["Kof_nT"] = {run.li_sigma.kof(0), run.li_sigma.kof(1), run.li_sigma.kof(2)};
    c.sigma["Rm_deg"] = {run.li_sigma.rm_rad(0) * kDeg, run.li_sigma.rm_rad(1) * kDeg,
                         run.li_sigma.rm_rad(2) * kDeg};
  }
  c.noise.mag_nT = run.noise_nT;
  c.noise.mag_estimated = run.noise_estimated;
  if (run.noise_estimated) c.noise.mag_sigma_nT = run.noise_sigma_nT;
  c.noise.ins_deg = run.ins_noise_deg;
  c.noise.ins_estimated = run.ins_noise_estimated;
  if (run.ins_noise_estimated) c.noise.ins_sigma_deg = run.ins_noise_sigma_deg;
  // Aligned: the misalignment about the vertical was estimated, not held (E-VF-7).
  OutputQuality out;
  out.aligned = run.initialised && !run.heading_held;
  c.output = out;
  c.quality.verdict = run.verdict;
  c.quality.reason = run.reason;
  c.quality.coverage = run.eval.coverage;
  c.quality.residual_rms_before_nT = run.eval.intensity_rms_before_nT;
  c.quality.residual_rms_after_nT = run.eval.intensity_rms_after_nT;
  auto& x = c.quality.extra;
  x["updates"] = k.updates;
  x["reference_updates"] = k.reference_updates;
  x["gated"] = k.gated;
  x["gated_reference"] = k.gated_reference;
  x["resets"] = k.resets;
  x["field_reopens"] = k.field_reopens;
  x["init_attempts"] = k.init_attempts;
  x["init_failures"] = k.init_failures;
  x["heading_held_updates"] = k.heading_held;
  x["tilt_spread_deg"] = run.tilt_spread_deg;
  x["float32"] = opt.float32 ? 1.0 : 0.0;
  x["aligned"] = out.aligned ? 1.0 : 0.0;
  if (run.initialised) {
    x["tc_x_nT_per_degC"] = run.tc_nT_per_degC(0);
    x["tc_y_nT_per_degC"] = run.tc_nT_per_degC(1);
    x["tc_z_nT_per_degC"] = run.tc_nT_per_degC(2);
    x["tc_sigma_x_nT_per_degC"] = run.tc_sigma_nT_per_degC(0);
    x["tc_sigma_y_nT_per_degC"] = run.tc_sigma_nT_per_degC(1);
    x["tc_sigma_z_nT_per_degC"] = run.tc_sigma_nT_per_degC(2);
    if (std::isfinite(run.temperature_ref_degC))
      x["temperature_ref_degC"] = run.temperature_ref_degC;
  }
  x["rows_with_temperature"] = static_cast<double>(run.rows_with_temperature);
  if (run.eval.has_enu) {
    x["spread_E_after_nT"] = run.eval.enu_sd_after_nT(0);
    x["spread_N_after_nT"] = run.eval.enu_sd_after_nT(1);
    x["spread_U_after_nT"] = run.eval.enu_sd_after_nT(2);
  }
  c.counts.samples = run.rows;
  c.counts.used = run.accepted;
  c.counts.skipped_nonfinite = run.dropouts + run.rows_without_attitude;
  c.counts.rejected_outliers = run.gated;
  c.provenance.input = path;
  c.provenance.method = "vector-ekf";
  return run;
}

}  // namespace magvec::host
