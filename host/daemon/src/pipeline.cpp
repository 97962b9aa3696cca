// magvecd Pipeline; see pipeline.hpp.
#include "magvec/host/daemon/pipeline.hpp"

#include <cmath>

#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec/host/hil/calibrators.hpp"

namespace magvec::host::daemon {
namespace {

using LiCal = hil::LiCalibrator;
using EkfCal = hil::EkfLoopCalibrator;

std::string solver_reason(const hil::NullCalibrator&, std::uint8_t) {
  return "none";
}
std::string solver_reason(const LiCal&, std::uint8_t code) {
  return core::verdict_name(static_cast<core::Verdict>(code));
}
std::string solver_reason(const EkfCal&, std::uint8_t code) {
  return core::ekf_cal_code_name(code);
}

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
    offset_fixed_ = true;
  }
  double time_offset_s() const noexcept override {
    return 1e-6 * static_cast<double>(core_.pipeline().time_offset_us());
  }
  void start_calibration() noexcept override { core_.loop().start_calibration(); }
  void set_active(const core::SensorModel<double>& model, std::uint32_t cal_id,
                  const OutputQuality& output) noexcept override {
    core_.loop().set_active(model, cal_id, output.aligned, output.sigma_f_nT, output.sigma_enu_nT);
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
    if (lp.state() == core::CalState::kFailed &&
        lp.failure() == core::CalFailure::kSolverRejected) {
      s.solver_reason = solver_reason(*cal_, lp.solver_code());
    }
    s.progress = lp.progress();
    s.validation_rms_nT = lp.last_validation_rms_nT();
    s.cal_id = lp.cal_id();
    s.active = lp.active_model();
    s.output = OutputQuality{lp.active_aligned(), lp.active_sigma_f_nT(), lp.active_sigma_enu_nT()};
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
};

}  // namespace

std::unique_ptr<Pipeline> Pipeline::create(const Config& config, hal::RecordSink& sink) {
  const CalibrationConfig& cc = config.calibration;
  const hil::HilConfig hc = hil_config(config);
  const double mag_rate = config.magnetometer.rate_hz;
  const double ins_rate = config.ins.rate_hz;
  const bool fixed = std::isfinite(config.ins.time_offset_s);
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
