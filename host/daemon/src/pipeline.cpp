// magvecd Pipeline; see pipeline.hpp.
#include "magvec/host/daemon/pipeline.hpp"

#include <algorithm>
#include <cmath>
#include <cstdio>

#include "magvec/core/calibration_guidance.hpp"
#include "magvec/core/coverage.hpp"
#include "magvec/host/daemon/guidance_text.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/calibrators.hpp"

namespace magvec::host::daemon {
namespace {

using LiCal = hil::LiCalibrator;
using EkfCal = hil::EkfLoopCalibrator;
using VecCal = hil::VectorLoopCalibrator;

std::string solver_reason(const hil::NullCalibrator&, std::uint8_t) {
  return "none";
}
std::string solver_reason(const LiCal&, std::uint8_t code) {
  return core::verdict_name(static_cast<core::Verdict>(code));
}
std::string solver_reason(const EkfCal&, std::uint8_t code) {
  return core::ekf_cal_code_name(code);
}
std::string solver_reason(const VecCal&, std::uint8_t code) {
  return core::vec_cal_code_name(code);
}

// The figures behind a refused candidate ("" for the failures without figures).
template <typename Loop>
std::string validation_reason(const Loop& lp) {
  char buf[240];
  const double noise = lp.candidate_noise_nT();
  switch (lp.failure()) {
    case core::CalFailure::kValidationFailed: {
      const double rms = lp.last_validation_rms_nT();
      const double bound = lp.last_validation_bound_nT();
      if (rms <= bound) {  // within the bound, but worse than the active calibration
        std::snprintf(buf, sizeof buf,
                      "held-out |h| - F %.3g nT, worse than the active calibration's %.3g nT", rms,
                      lp.last_validation_active_rms_nT());
      } else {
        std::snprintf(buf, sizeof buf,
                      "held-out |h| - F %.3g nT above the bound %.3g nT (noise %.3g nT)", rms,
                      bound, noise);
      }
      return buf;
    }
    case core::CalFailure::kVectorValidationFailed:
      std::snprintf(buf, sizeof buf,
                    "held-out E/N/U scatter %.3g nT above the bound %.3g nT (noise %.3g nT and "
                    "the attitude noise)",
                    lp.last_validation_vector_rms_nT(), lp.last_validation_vector_bound_nT(),
                    noise);
      return buf;
    case core::CalFailure::kReferenceMismatch:
      std::snprintf(buf, sizeof buf,
                    "held-out mean |h| - F %.4g nT, too far for the model's 1-sigma %.3g nT (a "
                    "local anomaly, a wrong position, or a wrong scale)",
                    lp.last_validation_mean_nT(), lp.reference_sigma_nT());
      return buf;
    default:
      return "";
  }
}

// What each calibrator has and needs before a solve can be tried (calibration_guidance.hpp).
void guidance_needs(const hil::NullCalibrator&, core::GuidanceInput<double>*) {}

void guidance_needs(const LiCal& c, core::GuidanceInput<double>* in) {
  in->cells = c.coverage_cells();
  // ready() waits for the calibrator's coverage; the acceptance policy's is not above it.
  const double cover = std::max(c.config().min_coverage, c.config().batch.limits.min_coverage);
  in->cells_needed = static_cast<int>(std::ceil(cover * core::kCoverageCells - 1e-9));
  in->samples = c.stored();
  in->samples_needed = c.samples_needed();
  in->need_reference = !std::isfinite(c.config().batch.field_nT);
  in->need_attitude = c.config().method != core::BatchMethod::kEllipsoidOnly;
}

void guidance_needs(const EkfCal& c, core::GuidanceInput<double>* in) {
  // No coverage rule: the cells of the alignment store's readings are shown and aimed at (more
  // directions, faster convergence). The samples are the alignment store's (when it aligns),
  // the rest the filter's start-up set, then its updates and predicted intensity 1-sigma.
  core::CoverageGrid grid;
  const auto& store = c.alignment_store();
  for (std::size_t i = 0; i < store.size(); ++i)
    grid.add(store[i].raw());
  in->cells = grid.cells();
  in->cells_needed = 0;
  if (c.config().align) {
    in->samples = c.align_samples();
    in->samples_needed = c.align_samples_needed();
  }
  in->need_attitude = c.config().align;
  // The start-up set is the first tenth of the filter's need (a second or so), so that progress
  // does not fall back when the filter starts counting its updates.
  constexpr double kStartupShare = 0.1;
  const auto& f = c.filter();
  if (!f.initialised()) {
    const int need = std::max(f.config().init_samples, 1);
    in->other_fraction =
        kStartupShare * std::min(1.0, static_cast<double>(f.startup_samples()) / need);
  } else {
    const double pu = static_cast<double>(c.updates()) /
                      static_cast<double>(std::max<std::uint32_t>(c.config().min_updates, 1U));
    const double sig = c.sigma_f_nT();
    const double ps = sig > 0 ? c.config().max_sigma_f_nT / sig : 1.0;
    in->other_fraction =
        kStartupShare + (1 - kStartupShare) * std::clamp(std::min(pu, ps), 0.0, 1.0);
  }
}

void guidance_needs(const VecCal& c, core::GuidanceInput<double>* in) {
  // No coverage rule (the filter decides by its covariance). The samples are the start-up set
  // (the noise estimate's, then the filter's start); afterwards progress is the calibrator's
  // (the parameter 1-sigmas against their readiness limit).
  const VecCal::Diagnostics d = c.diagnostics();
  in->cells_needed = 0;
  in->need_attitude = true;
  in->need_reference = d.needs_reference;
  in->samples_needed = static_cast<std::size_t>(std::max(d.samples_needed, 1));
  in->samples = d.initialised
                    ? in->samples_needed
                    : static_cast<std::size_t>(d.noise_known ? d.startup_samples : d.noise_samples);
  in->other_fraction = c.progress();
}

// Readings the residual average spans (exponential, weight 1/kResidualSpan per reading).
constexpr double kResidualSpan = 100;

template <typename Calibrator>
class PipelineImpl final : public Pipeline {
 public:
  PipelineImpl(std::string name, std::unique_ptr<Calibrator> cal, hal::RecordSink& sink,
               const hil::HilConfig& hc, double mag_rate_hz, double ins_rate_hz, bool offset_fixed)
      : name_(std::move(name)),
        cal_(std::move(cal)),
        core_(*cal_, sink, hc, mag_rate_hz, ins_rate_hz),
        offset_fixed_(offset_fixed) {}

  void on_attitude(const hal::AttitudeSample& a) noexcept override { core_.on_attitude(a); }
  void on_magnetometer(const hal::MagnetometerSample& s, double f_ref_nT) noexcept override {
    core_.on_magnetometer(s, f_ref_nT);
    note_reading(s, f_ref_nT);
  }
  void on_read_error() noexcept override { core_.on_read_error(); }
  void flush() noexcept override { core_.flush(); }
  void set_time_offset_s(double offset_s) noexcept override {
    if (!offset_fixed_ && std::isfinite(offset_s))
      core_.set_time_offset_us(hil::offset_us_from_s(offset_s));
  }
  void override_time_offset_s(double offset_s) noexcept override {
    if (!std::isfinite(offset_s)) return;
    core_.set_time_offset_us(hil::offset_us_from_s(offset_s));
    core_.set_adopt_calibration_time_offset(false);
    offset_fixed_ = true;
  }
  double time_offset_s() const noexcept override {
    return 1e-6 * static_cast<double>(core_.pipeline().time_offset_us());
  }
  void start_calibration() noexcept override { core_.loop().start_calibration(); }
  void set_reference_sigma_nT(double sigma_nT) noexcept override {
    if (!(std::isfinite(sigma_nT) && sigma_nT > 0)) return;
    auto& lp = core_.loop();
    lp.set_reference_sigma_nT(sigma_nT);
    const core::CalState st = lp.state();
    if (st == core::CalState::kCollecting || st == core::CalState::kSolving ||
        st == core::CalState::kValidating)
      lp.start_calibration();
  }
  void set_active(const core::SensorModel<double>& model, std::uint32_t cal_id,
                  const OutputQuality& output) noexcept override {
    core_.loop().set_active(model, cal_id, output.aligned, output.sigma_f_nT, output.sigma_enu_nT,
                            output.model_reference);
  }
  void set_external_solve(bool on) noexcept override { core_.loop().set_external_solve(on); }
  SolveJob take_solve_job() override {
    const auto& lp = core_.loop();
    if (lp.state() != core::CalState::kSolving || lp.solve_ticket() == handed_ticket_) return {};
    handed_ticket_ = lp.solve_ticket();
    // The calibrator is frozen while the loop is solving, but a restart (begin()) or the end of
    // the session may come before the job ran: the job solves on its own copy.
    auto snapshot = std::make_shared<Calibrator>(*cal_);
    const std::uint32_t ticket = handed_ticket_;
    return [snapshot, ticket] {
      SolveResult r;
      r.ticket = ticket;
      const core::CalibratorSolve s = snapshot->solve(&r.model);
      r.ok = s.ok;
      r.code = s.code;
      r.aligned = s.aligned;
      r.attitude_noise_deg = s.attitude_noise_deg;
      r.mag_noise_nT = s.mag_noise_nT;
      return r;
    };
  }
  bool install_solve(const SolveResult& r) noexcept override {
    core::CalibratorSolve solve{r.ok, r.code, r.aligned};
    solve.attitude_noise_deg = r.attitude_noise_deg;
    solve.mag_noise_nT = r.mag_noise_nT;
    return core_.loop().install_solve(r.ticket, solve, r.model);
  }
  CalibrationStatus status() const override {
    const auto& lp = core_.loop();
    CalibrationStatus s;
    s.calibrator = name_;
    s.state = lp.state();
    s.failure = lp.failure();
    if (lp.state() == core::CalState::kFailed) {
      s.solver_reason = lp.failure() == core::CalFailure::kSolverRejected
                            ? solver_reason(*cal_, lp.solver_code())
                            : validation_reason(lp);
    }
    s.progress = lp.progress();
    s.validation_rms_nT = lp.last_validation_rms_nT();
    s.cal_id = lp.cal_id();
    s.active = lp.active_model();
    s.output = OutputQuality{lp.active_aligned(), lp.active_sigma_f_nT(), lp.active_sigma_enu_nT(),
                             lp.active_model_reference()};
    s.residual_nT = residual_n_ > 0 ? std::sqrt(residual_ms_) : std::nan("");
    core::GuidanceInput<double> in;
    in.collecting = lp.state() == core::CalState::kCollecting;
    guidance_needs(*cal_, &in);
    in.have_reference = have_reference_;
    in.have_field = have_field_;
    in.m_nT = last_m_;
    in.have_attitude = attitude_now(&in.r_bn);
    s.guidance = core::calibration_guidance(in);
    s.samples = in.samples;
    s.samples_needed = in.samples_needed;
    s.hint = guidance_text(s.guidance);
    if (in.collecting) s.progress = s.guidance.progress;
    // Solving and validating: everything needed was in (the loop's progress says 0 there).
    if (lp.state() == core::CalState::kSolving || lp.state() == core::CalState::kValidating)
      s.progress = 1;
    return s;
  }
  core::CalState state() const noexcept override { return core_.loop().state(); }
  const hil::HilCounters& counters() const noexcept override { return core_.counters(); }
  const core::LoopHealth& health() const noexcept override { return core_.loop().health(); }

 private:
  std::string name_;
  std::unique_ptr<Calibrator> cal_;
  hil::LoopCore<Calibrator> core_;
  bool offset_fixed_;
  std::uint32_t handed_ticket_{0};
  // The latest reading and the residual average (display only: never fed back into the records).
  bool have_field_{false};
  bool have_reference_{false};
  core::Vec3<double> last_m_ = core::Vec3<double>::Zero();
  std::uint64_t last_t_us_{0};
  double residual_ms_{0};
  double residual_n_{0};
  std::uint32_t residual_cal_id_{0};

  void note_reading(const hal::MagnetometerSample& s, double f_ref_nT) noexcept {
    const core::Vec3<double> m(s.m_nT[0], s.m_nT[1], s.m_nT[2]);
    if (!m.allFinite() || (s.flags & (hal::kMagInvalidMask | hal::kMagNotFresh)) != 0) return;
    have_field_ = true;
    last_m_ = m;
    last_t_us_ = s.t_us;
    have_reference_ = std::isfinite(f_ref_nT) && f_ref_nT > 0;
    if (!have_reference_) return;
    if (core_.loop().cal_id() != residual_cal_id_) {  // a new calibration: a new average
      residual_cal_id_ = core_.loop().cal_id();
      residual_n_ = 0;
      residual_ms_ = 0;
    }
    const auto& model = core_.loop().active_model();
    const double r = (model.w * (m - model.o)).norm() - f_ref_nT;
    residual_n_ = std::min(residual_n_ + 1, kResidualSpan);
    residual_ms_ += (r * r - residual_ms_) / residual_n_;
  }

  // The attitude at the latest reading's time, when the INS has one near it.
  bool attitude_now(core::Mat3<double>* r_bn) const noexcept {
    const auto& buf = core_.buffer();
    if (buf.size() == 0 || !have_field_) return false;
    const std::uint64_t newest = buf.newest_us();
    const std::uint64_t t = std::min(newest, last_t_us_);
    if (last_t_us_ > newest + kAttitudeStaleUs) return false;
    const core::AttitudeQuery<double> q = buf.at(t);
    if (!core::attitude_usable(q.status)) return false;
    *r_bn = core::r_bn_from_quat(q.q_nb);
    return true;
  }
  // An INS silent for longer than this is "attitude missing" to the operator.
  static constexpr std::uint64_t kAttitudeStaleUs = 500'000;
};

}  // namespace

std::unique_ptr<Pipeline> Pipeline::create(const Config& config, hal::RecordSink& sink) {
  const CalibrationConfig& cc = config.calibration;
  hil::HilConfig hc = hil_config(config);
  const double mag_rate = config.magnetometer.rate_hz;
  const double ins_rate = config.ins.rate_hz;
  const bool fixed = std::isfinite(config.ins.time_offset_s);
  hc.adopt_calibration_time_offset = !fixed;
  if (!hil::is_calibrator_mode(cc.mode))
    throw ConfigError("calibration.mode: unknown calibrator '" + cc.mode + "'");
  hil::CalibratorSpec spec;
  spec.mode = cc.mode;
  spec.noise_nT = cc.noise_nT;
  spec.attitude_noise_deg = cc.attitude_noise_deg;
  spec.li_min_samples = cc.li_min_samples;
  spec.ekf_align = cc.ekf_align;
  return hil::with_calibrator(spec, [&](auto cal) -> std::unique_ptr<Pipeline> {
    using Cal = typename decltype(cal)::element_type;
    return std::make_unique<PipelineImpl<Cal>>(cc.mode, std::move(cal), sink, hc, mag_rate,
                                               ins_rate, fixed);
  });
}

}  // namespace magvec::host::daemon
