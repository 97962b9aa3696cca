// `magvec demo`: the real pipeline end to end, in simulated time (docs/architecture.md#simulation).
// A survey (drivers/sim scenario_survey: Li et al. 2023 sensor and field, 60 s calibration
// manoeuvre, then survey lines) is played through simulated devices speaking the real bytes
// (ADS131M04 on SPI + DRDY, SBG INS on CAN, with a few injected faults) -> the real codecs ->
// AttitudeBuffer -> SensorLoop with the Li batch calibrator (core::BatchLiCalibrator: collects
// during the manoeuvre, solves the one-step fit, validates on held-out samples, applies; or, with
// --calibrator vector-ekf, the online vector calibration filter, core::VectorCalibrator)
// -> DIR/records.csv. The calibration is written to DIR/cal.json. The before/after table is over
// the survey lines after the calibration was applied: "before" is the raw reading (|m|, and m
// rotated by R_bn^T), "after" the loop's output, "floor" the TRUE parameters applied to the same
// records and attitudes (what a perfect calibration would give: the noise).
#include <CLI/CLI.hpp>
#include <cmath>
#include <deque>
#include <filesystem>
#include <iostream>
#include <limits>
#include <memory>
#include <string>

#include "calibration/calibration_file.hpp"
#include "commands.hpp"
#include "magvec/core/batch_li_calibrator.hpp"
#include "magvec/core/compensator.hpp"
#include "magvec/core/vector_calibrator.hpp"
#include "magvec/host/hil/calibrators.hpp"
#include "magvec/host/hil/csv_record_sink.hpp"
#include "magvec/host/hil/hil_session.hpp"
#include "magvec/version.hpp"
#include "stats.hpp"

namespace magvec::host::cli {
namespace {

using LiCal = hil::LiCalibrator;
using VecCal = hil::VectorLoopCalibrator;

struct DemoOptions {
  std::string out_dir;
  std::uint64_t seed = 1;
  std::string calibrator = "li";
  double noise_nT = 0.3;
  double ins_noise_deg = 0.015;
  double dropout_rate = 0.002;
  double crc_rate = 0.01;
  double ins_corrupt_rate = 0.01;
};

// Forwards every record to the CSV sink and scores the calibrated survey-line records against the
// simulation truth (the session's current simulated sample and the attitude the loop used).
template <typename Session>
class ScoringSink final : public hal::RecordSink {
 public:
  ScoringSink(hil::CsvRecordSink& csv, const drivers::sim::ScenarioConfig& sc)
      : csv_(csv), truth_(sc.truth), survey_(sc.survey) {}
  void attach(Session* s) { session_ = s; }

  // The truth of every simulated sample, kept until its record is emitted: the pipeline emits a
  // record only when the fusion horizon lets it, after later samples were simulated.
  void remember(const drivers::sim::SimSample& s) {
    pending_.push_back({session_->rig().host_us(s.t_s), s});
  }

  hal::Status emit(const hal::OutputRecord& r) noexcept override {
    const hal::Status st = csv_.emit(r);
    while (!pending_.empty() && pending_.front().t_us < r.t_us)
      pending_.pop_front();
    drivers::sim::SimSample s;
    if (!pending_.empty() && pending_.front().t_us == r.t_us) {
      s = pending_.front().sample;
    } else if (session_->rig().host_us(session_->rig().last().t_s) == r.t_us) {
      s = session_->rig().last();  // emitted within the step that simulated it
    } else {
      return st;
    }
    if (r.cal_id == 0 || !on_line(s.t_s) ||
        (r.flags & (core::kOutDropout | core::kOutDeviceError | core::kOutNoAttitude)) != 0) {
      return st;
    }
    const core::AttitudeQuery<double> q = session_->buffer().at(r.t_us);
    if (!core::attitude_usable(q.status)) return st;
    const core::Mat3<double> r_bn = core::r_bn_from_quat(q.q_nb);
    const core::Vec3<double> raw(r.raw_nT[0], r.raw_nT[1], r.raw_nT[2]);
    core::Compensated<double> c;
    if (!truth_.compensate(raw, &c)) return st;
    const double f = s.f_nT;
    f_before.add(raw.norm() - f);
    f_after.add(r.f_nT - f);
    f_floor.add(c.intensity - f);
    const core::Vec3<double> before = r_bn.transpose() * raw;
    const core::Vec3<double> floor = r_bn.transpose() * c.h_b;
    for (int k = 0; k < 3; ++k) {
      const auto kk = static_cast<std::size_t>(k);
      comp_before[k].add(before(k));
      comp_after[k].add(r.h_n_nT[kk]);
      err_before[k].add(before(k) - s.h_n_true_nT(k));
      err_after[k].add(r.h_n_nT[kk] - s.h_n_true_nT(k));
      err_floor[k].add(floor(k) - s.h_n_true_nT(k));
    }
    return st;
  }

  Stats f_before, f_after, f_floor, comp_before[3], comp_after[3], err_before[3], err_after[3],
      err_floor[3];

 private:
  // Straight parts of the survey lines (not the turns, not the manoeuvre).
  bool on_line(double t_s) const noexcept {
    const double tau = t_s - survey_.manoeuvre_s;
    if (tau < 0) return false;
    return std::fmod(tau, survey_.line_s + survey_.turn_s) < survey_.line_s;
  }

  struct Pending {
    std::uint64_t t_us;
    drivers::sim::SimSample sample;
  };
  std::deque<Pending> pending_;
  hil::CsvRecordSink& csv_;
  core::Compensator<double> truth_;
  drivers::sim::SurveyConfig survey_;
  Session* session_{nullptr};
};

void write_cal(const std::string& path, const LiCal& cal, double validation_rms_nT,
               const OutputQuality& output, const DemoOptions& o) {
  const core::BatchResult<double>& r = cal.last_result();
  const double deg = 180.0 / core::kPi<double>;
  CalibrationFile f;
  f.model = r.model;
  f.h_n_nT = r.h_n_nT;
  const auto v3 = [](const core::Vec3<double>& v, double k) {
    return std::vector<double>{v(0) * k, v(1) * k, v(2) * k};
  };
  f.sigma["ks"] = v3(r.sigma.ks, 1.0);
  f.sigma["O_deg"] = v3(r.sigma.o_rad, deg);
  f.sigma["Kof_nT"] = v3(r.sigma.kof, 1.0);
  f.sigma["Rm_deg"] = v3(r.sigma.rm_rad, deg);
  f.quality.verdict = core::verdict_name(r.verdict);
  f.quality.reason = "Li one-step fit in the sensor loop; validated on held-out samples (RMS " +
                     fixed(validation_rms_nT, 3) + " nT)";
  f.quality.coverage = r.quality.coverage;
  f.quality.condition = r.quality.rcond > 0 ? 1.0 / r.quality.rcond : 0.0;
  f.quality.residual_rms_before_nT = r.quality.intensity_rms_raw_nT;
  f.quality.residual_rms_after_nT = r.quality.intensity_rms_nT;
  f.quality.extra["chi2_per_dof"] = r.quality.chi2_per_dof;
  f.quality.extra["enu_rms_E_nT"] = r.quality.enu_rms_nT(0);
  f.quality.extra["enu_rms_N_nT"] = r.quality.enu_rms_nT(1);
  f.quality.extra["enu_rms_U_nT"] = r.quality.enu_rms_nT(2);
  f.output = output;
  f.noise.mag_nT = r.noise.mag_nT;
  f.noise.mag_sigma_nT = r.noise.mag_sigma_nT;
  f.noise.mag_estimated = r.noise.estimated;
  if (r.noise.has_attitude) {
    f.noise.ins_deg = r.noise.attitude_deg;
    f.noise.ins_sigma_deg = r.noise.attitude_sigma_deg;
    f.noise.ins_estimated = r.noise.estimated;
  }
  f.counts.samples = cal.counts().seen;
  f.counts.used = r.counts.used;
  f.counts.skipped_nonfinite = cal.counts().rejected;
  f.counts.rejected_outliers = r.counts.outliers;
  f.provenance.input = "magvec demo: simulated survey, seed " + std::to_string(o.seed);
  f.provenance.method = "li_one_step_in_loop";
  f.provenance.magvec_version = kVersion;
  f.provenance.created_utc = utc_now_iso8601();
  write_calibration_file(path, f);
}

// The calibrator's part of the report: the calibration line, its noise figures, cal.json and the
// recovered parameters against the truth. Throws when no calibration was applied.
void report_calibration(const core::SensorLoop<double, LiCal>& loop, const LiCal& calr,
                        const DemoOptions& o, const drivers::sim::ScenarioConfig& sc,
                        std::uint64_t applied_at, const std::string& cal_path) {
  const LiCal* cal = &calr;
  const auto& res = cal->last_result();
  std::cout << "Calibration: state " << core::cal_state_name(loop.state()) << ", cal_id "
            << loop.cal_id();
  if (applied_at > 0)
    std::cout << ", applied at t = " << fixed(static_cast<double>(applied_at) / sc.rate_hz, 2)
              << " s";
  std::cout << "; kept " << cal->counts().kept << " of " << cal->counts().seen
            << " samples (motion-decimated), coverage " << fixed(cal->coverage(), 2) << "; verdict "
            << core::verdict_name(res.verdict) << "; validation intensity RMS "
            << fixed(loop.last_validation_rms_nT(), 3) << " nT\n";
  if (res.noise.estimated) {
    std::cout << "  noise estimated from the data: magnetometer " << fixed(res.noise.mag_nT, 3)
              << " +- " << fixed(res.noise.mag_sigma_nT, 3) << " nT/axis (simulated " << o.noise_nT
              << "), INS " << fixed(res.noise.attitude_deg, 4) << " +- "
              << fixed(res.noise.attitude_sigma_deg, 4) << " deg/angle (simulated "
              << o.ins_noise_deg << ")\n";
  }
  if (loop.state() != core::CalState::kApplied || !res.ok()) {
    throw std::runtime_error("the in-loop calibration did not apply (state " +
                             std::string(core::cal_state_name(loop.state())) + ", verdict " +
                             core::verdict_name(res.verdict) + ")");
  }
  write_cal(cal_path, *cal, loop.last_validation_rms_nT(),
            OutputQuality{loop.active_aligned(), loop.active_sigma_f_nT(),
                          loop.active_sigma_enu_nT(), loop.active_model_reference()},
            o);

  // Recovered parameters vs truth.
  core::LiParams<double> truth;
  core::to_li(sc.truth, &truth);
  const double deg = 180.0 / core::kPi<double>;
  std::cout << "\nParameter          truth       recovered    1-sigma\n";
  const auto row = [](const std::string& name, double t, double v, double s, int d) {
    std::cout << "  " << name << std::string(name.size() < 10 ? 10 - name.size() : 0, ' ')
              << num(t, d) << " " << num(v, d) << " " << num(s, d) << "\n";
  };
  const char* ax[3] = {"x", "y", "z"};
  for (int k = 0; k < 3; ++k)
    row(std::string("Ks") + ax[k], truth.ks(k), res.li.ks(k), res.sigma.ks(k), 6);
  for (int k = 0; k < 3; ++k)
    row("O" + std::to_string(k + 1) + " deg", truth.o_rad(k) * deg, res.li.o_rad(k) * deg,
        res.sigma.o_rad(k) * deg, 5);
  for (int k = 0; k < 3; ++k)
    row(std::string("Kof") + ax[k] + " nT", truth.kof(k), res.li.kof(k), res.sigma.kof(k), 3);
  const char* rmn[3] = {"am", "bm", "gm"};
  for (int k = 0; k < 3; ++k)
    row(std::string(rmn[k]) + " deg", truth.rm_rad(k) * deg, res.li.rm_rad(k) * deg,
        res.sigma.rm_rad(k) * deg, 5);
  for (int k = 0; k < 3; ++k)
    row(std::string("h_n ") + "ENU"[k] + " nT", sc.h_n_nT(k), res.h_n_nT(k), res.h_n_sigma_nT(k),
        2);
}

void report_calibration(const core::SensorLoop<double, VecCal>& loop, const VecCal& cal,
                        const DemoOptions& o, const drivers::sim::ScenarioConfig& sc,
                        std::uint64_t applied_at, const std::string& cal_path) {
  const VecCal::Diagnostics dg = cal.diagnostics();
  std::cout << "Calibration: state " << core::cal_state_name(loop.state()) << ", cal_id "
            << loop.cal_id();
  if (applied_at > 0)
    std::cout << ", applied at t = " << fixed(static_cast<double>(applied_at) / sc.rate_hz, 2)
              << " s";
  std::cout << "; vector-ekf: filter updates " << dg.filter_counters.updates << ", gated "
            << dg.counts.gated << ", resets " << dg.filter_counters.resets
            << "; validation intensity RMS " << fixed(loop.last_validation_rms_nT(), 3) << " nT\n";
  if (dg.noise_known && dg.noise.estimated) {
    const auto& n = dg.noise;
    std::cout << "  noise estimated from the data: magnetometer " << fixed(n.mag_nT, 3) << " +- "
              << fixed(n.mag_sigma_nT, 3) << " nT/axis (simulated " << o.noise_nT << "), INS "
              << fixed(n.attitude_deg, 4) << " +- " << fixed(n.attitude_sigma_deg, 4)
              << " deg/angle (simulated " << o.ins_noise_deg << ")\n";
  }
  if (loop.state() != core::CalState::kApplied) {
    std::string why = std::string(core::cal_state_name(loop.state()));
    if (loop.state() == core::CalState::kFailed) {
      why += std::string(", ") + core::cal_failure_name(loop.failure());
      if (loop.failure() == core::CalFailure::kSolverRejected)
        why += std::string(" ") + core::vec_cal_code_name(loop.solver_code());
    }
    throw std::runtime_error("the in-loop calibration did not apply (state " + why + ")");
  }
  // The applied candidate is the filter's model at the solve; the filter paused there (the loop
  // stops feeding it), so its covariance is the candidate's.
  const core::SensorModel<double>& model = loop.active_model();
  const core::VfSigmas<double>& sg = dg.sigmas;
  const double deg = 180.0 / core::kPi<double>;
  CalibrationFile file;
  file.model = model;
  file.h_n_nT = dg.h_n_nT;
  const auto v3 = [](const core::Vec3<double>& v, double k) {
    return std::vector<double>{v(0) * k, v(1) * k, v(2) * k};
  };
  file.sigma["o_nT"] = v3(sg.o_nT, 1.0);
  file.sigma["Rm_body_deg"] = v3(sg.rm_rad, deg);
  file.sigma["h_n_nT"] = v3(sg.h_n_nT, 1.0);
  file.time_offset_s = 0;  // the filter's estimate is reported, not applied by the pipeline
  file.quality.verdict = "ok";
  file.quality.reason =
      "online vector calibration filter in the sensor loop; validated on held-out samples (RMS " +
      fixed(loop.last_validation_rms_nT(), 3) + " nT)";
  file.quality.extra["time_offset_estimate_ms"] = dg.time_offset_s * 1e3;
  file.quality.extra["time_offset_sigma_ms"] = sg.dt_s * 1e3;
  file.output = OutputQuality{loop.active_aligned(), loop.active_sigma_f_nT(),
                              loop.active_sigma_enu_nT(), loop.active_model_reference()};
  const auto& n = dg.noise;
  file.noise.mag_nT = n.mag_nT;
  file.noise.mag_sigma_nT = n.mag_sigma_nT;
  file.noise.mag_estimated = n.estimated;
  file.noise.ins_deg = n.attitude_deg;
  file.noise.ins_sigma_deg = n.attitude_sigma_deg;
  file.noise.ins_estimated = n.estimated;
  file.counts.samples = dg.counts.seen;
  file.counts.used = dg.filter_counters.updates;
  file.counts.skipped_nonfinite = dg.counts.nonfinite;
  file.provenance.input = "magvec demo: simulated survey, seed " + std::to_string(o.seed);
  file.provenance.method = "vector_ekf_in_loop";
  file.provenance.magvec_version = kVersion;
  file.provenance.created_utc = utc_now_iso8601();
  write_calibration_file(cal_path, file);

  // Recovered parameters vs truth (the filter's 1-sigmas are of W, o and a body-frame rotation,
  // not of the Li angles: the offsets' are shown, the others are in cal.json's sigma).
  core::LiParams<double> truth, got;
  core::to_li(sc.truth, &truth);
  if (core::to_li(model, &got) != core::ConversionStatus::kOk)
    throw std::runtime_error("the applied calibration is not in Li form");
  std::cout << "\nParameter          truth       recovered    1-sigma\n";
  const auto row = [](const std::string& name, double t, double v, double s, int d) {
    std::cout << "  " << name << std::string(name.size() < 10 ? 10 - name.size() : 0, ' ')
              << num(t, d) << " " << num(v, d) << " " << num(s, d) << "\n";
  };
  const double nan = std::numeric_limits<double>::quiet_NaN();
  const char* ax[3] = {"x", "y", "z"};
  for (int k = 0; k < 3; ++k)
    row(std::string("Ks") + ax[k], truth.ks(k), got.ks(k), nan, 6);
  for (int k = 0; k < 3; ++k)
    row("O" + std::to_string(k + 1) + " deg", truth.o_rad(k) * deg, got.o_rad(k) * deg, nan, 5);
  for (int k = 0; k < 3; ++k)
    row(std::string("Kof") + ax[k] + " nT", truth.kof(k), got.kof(k), sg.o_nT(k), 3);
  const char* rmn[3] = {"am", "bm", "gm"};
  for (int k = 0; k < 3; ++k)
    row(std::string(rmn[k]) + " deg", truth.rm_rad(k) * deg, got.rm_rad(k) * deg, nan, 5);
  for (int k = 0; k < 3; ++k)
    row(std::string("h_n ") + "ENU"[k] + " nT", sc.h_n_nT(k), dg.h_n_nT(k), sg.h_n_nT(k), 2);
  std::cout << "  time offset " << fixed(dg.time_offset_s * 1e3, 3) << " +- "
            << fixed(sg.dt_s * 1e3, 3) << " ms (simulated 0; estimated, not applied)\n";
}

template <typename Cal>
void run_with(const DemoOptions& o, std::unique_ptr<Cal> cal) {
  using DemoSession = hil::HilSession<Cal>;
  namespace fs = std::filesystem;
  fs::create_directories(o.out_dir);
  const std::string records_path = (fs::path(o.out_dir) / "records.csv").string();
  const std::string cal_path = (fs::path(o.out_dir) / "cal.json").string();

  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.mag_noise_nT = o.noise_nT;
  sc.ins_noise_deg = o.ins_noise_deg;
  sc.dropout_probability = o.dropout_rate;
  drivers::sim::Simulator sim(sc, o.seed);
  drivers::sim::SimRigConfig rc;
  rc.link = drivers::sim::MagLink::kSpi;
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};  // 100 uT/V at gain 1: 0.014 nT per code
  rc.adc.faults.crc_error_probability = o.crc_rate;
  rc.ins.faults.corrupt_probability = o.ins_corrupt_rate;
  rc.adc.seed = o.seed ^ 0xA1;
  rc.ins.seed = o.seed ^ 0xC3;
  hil::HilConfig hc;
  // The simulated noise is not told to the loop: the calibration estimates it, as in the field.
  hc.loop.noise_nT = std::numeric_limits<double>::quiet_NaN();
  hc.loop.attitude_noise_deg = std::numeric_limits<double>::quiet_NaN();
  hil::CsvRecordSink csv(
      records_path, {std::string("magvec ") + kVersion + " demo: survey seed " +
                     std::to_string(o.seed) + ", " + o.calibrator + " calibrator in the loop"});
  ScoringSink<DemoSession> sink(csv, sc);
  auto session = std::make_unique<DemoSession>(sim, rc, *cal, sink, hc);
  sink.attach(session.get());
  if (const hal::Status s = session->init(); s != hal::Status::kOk)
    throw std::runtime_error(std::string("device initialisation failed: ") + hal::to_string(s));
  std::uint64_t applied_at = 0;
  while (session->step()) {
    sink.remember(session->rig().last());
    if (applied_at == 0 && session->loop().cal_id() > 0) applied_at = session->counters().steps;
  }
  if (session->counters().sink_errors != 0)
    throw std::runtime_error("writing " + records_path + " failed: " + csv.last_error());
  csv.commit();

  const auto& loop = session->loop();
  std::cout << "magvec demo: simulated survey (seed " << o.seed << "), " << sc.num_samples
            << " samples at " << sc.rate_hz << " Hz: " << sc.survey.manoeuvre_s
            << " s calibration manoeuvre (+-30 deg pitch/roll, 3 heading turns) + 4 survey lines\n"
            << "  pipeline: simulated ADS131M04 (SPI) + SBG INS (CAN) -> real codecs -> "
               "AttitudeBuffer -> SensorLoop + "
            << (o.calibrator == "li" ? "Li one-step calibrator"
                                     : "online vector calibration filter")
            << " (in the loop)\n"
            << "  noise: magnetometer " << o.noise_nT << " nT/axis, INS " << o.ins_noise_deg
            << " deg/angle; faults: ADC CRC " << o.crc_rate << ", dropouts " << o.dropout_rate
            << ", INS corrupt frames " << o.ins_corrupt_rate << "\n\n";
  report_calibration(loop, *cal, o, sc, applied_at, cal_path);

  std::cout << "\nSurvey lines after the calibration was applied: " << sink.f_after.count()
            << " records (turns, dropouts, device errors, no-attitude records excluded)\n"
            << "Total field vs reference F [nT]   before (raw |m|)   after (loop)   floor (true "
               "params)\n"
            << "  mean error                   " << num(sink.f_before.mean(), 3) << " "
            << num(sink.f_after.mean(), 3) << " " << num(sink.f_floor.mean(), 3) << "\n"
            << "  RMS error                    " << num(sink.f_before.rms(), 3) << " "
            << num(sink.f_after.rms(), 3) << " " << num(sink.f_floor.rms(), 3) << "\n\n";
  const char* names[3] = {"East ", "North", "Up   "};
  std::cout << "ENU components [nT]   SD before   SD after  RMS err before  RMS err after  RMS err "
               "floor\n";
  for (int k = 0; k < 3; ++k) {
    std::cout << "  " << names[k] << "    " << num(sink.comp_before[k].sd(), 3) << " "
              << num(sink.comp_after[k].sd(), 3) << " " << num(sink.err_before[k].rms(), 3) << " "
              << num(sink.err_after[k].rms(), 3) << " " << num(sink.err_floor[k].rms(), 3) << "\n";
  }
  std::cout << "  ('before' = raw reading rotated by R_bn^T without calibration; 'floor' = the "
               "TRUE parameters on the same records: the INS and magnetometer noise)\n";

  const auto& c = session->counters();
  const auto& h = loop.health();
  const auto& mc = session->mag_counters();
  const auto& ac = session->attitude_counters();
  const auto& adc = session->rig().adc().injected();
  const auto& ins = session->rig().ins().injected();
  std::cout << "\nHealth (counted / injected): ADC CRC errors " << mc.crc_errors << " / "
            << adc.crc_corrupted << ", dropouts " << h.dropouts << " / " << adc.not_fresh
            << " (a dropout frame can itself be lost to a CRC error)"
            << ", INS malformed frames " << ac.malformed << " / " << ins.corrupted_frames
            << ", records without attitude " << h.no_attitude << ", INS gaps " << c.att_gaps
            << ", missing samples " << c.mag_missing << "\n"
            << "Wrote " << csv.rows() << " records to " << records_path
            << " and the calibration to " << cal_path << "\n";
}

void run(const DemoOptions& o) {
  // The simulated noise is not told to the calibrator either: default spec (estimated).
  hil::CalibratorSpec spec;
  spec.mode = o.calibrator;
  if (o.calibrator == "li") return run_with(o, std::make_unique<LiCal>(hil::li_config(spec)));
  if (o.calibrator == "vector-ekf")
    return run_with(o, std::make_unique<VecCal>(hil::vector_config(spec)));
  throw std::invalid_argument("demo: unknown calibrator '" + o.calibrator + "'");
}

}  // namespace

void register_demo(CLI::App& app) {
  auto opt = std::make_shared<DemoOptions>();
  CLI::App* sub = app.add_subcommand(
      "demo",
      "Simulated survey through the real pipeline: devices -> codecs -> sensor loop with the Li "
      "calibrator (or --calibrator vector-ekf) in the loop; writes records.csv and cal.json; "
      "before/after table");
  sub->add_option("--out-dir", opt->out_dir, "Output directory (records.csv, cal.json)")
      ->required();
  sub->add_option("--seed", opt->seed, "Random seed")->capture_default_str();
  sub->add_option("--calibrator", opt->calibrator,
                  "In-loop calibrator: li (batch one-step fit) or vector-ekf (online vector "
                  "calibration filter); neither is told the simulated noise")
      ->check(CLI::IsMember({"li", "vector-ekf"}))
      ->capture_default_str();
  sub->add_option("--noise-nT", opt->noise_nT, "Magnetometer noise SD per axis")
      ->check(CLI::Range(0.0, 1e6))
      ->capture_default_str();
  sub->add_option("--ins-noise-deg", opt->ins_noise_deg, "INS noise SD per Euler angle")
      ->check(CLI::Range(0.0, 90.0))
      ->capture_default_str();
  sub->add_option("--dropout-rate", opt->dropout_rate, "Dropout probability per sample")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  sub->add_option("--crc-rate", opt->crc_rate, "ADC output-frame corruption probability")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  sub->add_option("--ins-corrupt-rate", opt->ins_corrupt_rate,
                  "INS CAN frame corruption probability")
      ->check(CLI::Range(0.0, 1.0))
      ->capture_default_str();
  sub->callback([opt] { run(*opt); });
}

}  // namespace magvec::host::cli
