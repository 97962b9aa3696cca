// One sensor-loop iteration, as it runs on the device: decode the ADS131M04 output frame
// (CRC, codes -> nT), decode the SBG CAN frames that arrived since the last sample and insert the
// attitude into the AttitudeBuffer, align (slerp to the sample time), SensorLoop::process with the
// EKF calibrator collecting (one EKF measurement update) and compensation. The bytes are recorded
// beforehand from the simulated devices (drivers/sim), so the simulation is not timed.
// BM_LoopIteration/ekf: with the EkfCalibrator updating every sample (never "ready").
// BM_LoopIteration/none: the same without a calibration running (decode + align + compensate).
// BM_HilStep: a whole HilSession step including the device simulation, for scale.
#include <benchmark/benchmark.h>

#include <array>
#include <memory>
#include <vector>

#include "magvec/core/attitude_buffer.hpp"
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/host/hil/hil_session.hpp"

namespace {

using namespace magvec;

struct Recorded {
  std::vector<drivers::ads131::Frame> adc;
  std::vector<std::uint64_t> t_us;
  std::vector<std::vector<hal::CanFrame>> can;  // frames received before each sample
  drivers::Ads131FluxgateConfig transfer{};
};

const Recorded& recording() {
  static const Recorded rec = [] {
    Recorded r;
    drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
    sc.num_samples = 8192;
    drivers::sim::Simulator sim(sc, 1);
    drivers::sim::SimRigConfig rc;
    rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
    r.transfer = rc.adc.transfer;
    auto rig = std::make_unique<drivers::sim::SimRig>(sim, rc);
    drivers::Ads131Fluxgate init_driver(rig->adc(), rig->adc(), rc.adc.transfer);
    if (init_driver.init() != hal::Status::kOk) std::abort();
    while (rig->step()) {
      std::vector<hal::CanFrame> frames;
      hal::CanFrame f;
      while (rig->ins().receive(f, 0) == hal::Status::kOk)
        frames.push_back(f);
      hal::EdgeEvent ev;
      while (rig->adc().wait_edge(ev, 0) == hal::Status::kOk && ev.edge != hal::Edge::kFalling) {
      }
      drivers::ads131::Frame tx{}, rx{};
      drivers::ads131::build_command_frame(drivers::ads131::kCmdNull, {}, false, tx);
      rig->adc().transfer(tx, rx);
      r.adc.push_back(rx);
      r.t_us.push_back(ev.t_us);
      r.can.push_back(std::move(frames));
    }
    return r;
  }();
  return rec;
}

template <typename Calibrator>
void run_loop(benchmark::State& state, Calibrator& cal, bool calibrate) {
  const Recorded& rec = recording();
  drivers::Ads131FrameDecoder adc(rec.transfer);
  drivers::sbg::CanDecoder can;
  core::AttitudeBuffer<double, 64> buffer;
  core::LoopConfig<double> lc;
  lc.noise_nT = 0.3;
  core::SensorLoop<double, Calibrator> loop(cal, lc);
  if (calibrate) loop.start_calibration();
  const std::size_t n = rec.adc.size();
  std::size_t i = 0;
  for (auto _ : state) {
    for (const hal::CanFrame& f : rec.can[i]) {
      if (can.feed(f) == drivers::sbg::FeedResult::kSample) {
        const hal::AttitudeSample& a = can.sample();
        buffer.insert(a.t_us - 500, core::Quat<double>(a.q_nb[0], a.q_nb[1], a.q_nb[2], a.q_nb[3]));
      }
    }
    hal::MagnetometerSample s;
    adc.decode(rec.adc[i], rec.t_us[i], s);
    core::MagSample<double> m;
    m.t_us = s.t_us;
    m.m_nT = core::Vec3<double>(s.m_nT[0], s.m_nT[1], s.m_nT[2]);
    m.f_ref_nT = 53729.0;
    const core::AttitudeQuery<double> q = buffer.at(s.t_us);
    core::Mat3<double> r_bn;
    const bool ok = core::attitude_usable(q.status);
    if (ok) r_bn = core::r_bn_from_quat(q.q_nb);
    benchmark::DoNotOptimize(loop.process(m, ok ? &r_bn : nullptr));
    if (++i == n) {
      // Wrap around: restart the time base (the buffer would otherwise see a clock reset).
      state.PauseTiming();
      i = 0;
      buffer.clear();
      can = drivers::sbg::CanDecoder{};
      state.ResumeTiming();
    }
  }
  state.counters["ekf_updates"] = static_cast<double>(loop.health().cal_used);
}

void BM_LoopIteration_Ekf(benchmark::State& state) {
  core::EkfCalibratorConfig<double> cfg;
  cfg.ekf.noise_sigma_nT = 0.3;
  cfg.ekf.divergence_detection = false;  // the recording repeats
  cfg.min_updates = 0xFFFFFFFFu;         // never ready: an EKF update on every iteration
  auto cal = std::make_unique<core::EkfCalibrator<double, 256>>(cfg);
  run_loop(state, *cal, true);
}
BENCHMARK(BM_LoopIteration_Ekf)->Name("BM_LoopIteration/ekf");

void BM_LoopIteration_None(benchmark::State& state) {
  host::hil::NullCalibrator cal;
  run_loop(state, cal, false);
}
BENCHMARK(BM_LoopIteration_None)->Name("BM_LoopIteration/none");

struct NullSink final : hal::RecordSink {
  hal::Status emit(const hal::OutputRecord&) noexcept override { return hal::Status::kOk; }
};

void BM_HilStep(benchmark::State& state) {
  drivers::sim::ScenarioConfig sc = drivers::sim::scenario_survey();
  sc.num_samples = 0xFFFFFFFFu;
  drivers::sim::Simulator sim(sc, 1);
  drivers::sim::SimRigConfig rc;
  rc.adc.transfer.nT_per_volt = {1e5, 1e5, 1e5};
  core::EkfCalibratorConfig<double> cfg;
  cfg.ekf.noise_sigma_nT = 0.3;
  cfg.min_updates = 0xFFFFFFFFu;
  auto cal = std::make_unique<core::EkfCalibrator<double, 256>>(cfg);
  NullSink sink;
  host::hil::HilConfig hc;
  hc.loop.noise_nT = 0.3;
  auto hil = std::make_unique<host::hil::HilSession<core::EkfCalibrator<double, 256>>>(
      sim, rc, *cal, sink, hc);
  if (hil->init() != hal::Status::kOk) std::abort();
  for (auto _ : state)
    benchmark::DoNotOptimize(hil->step());
}
BENCHMARK(BM_HilStep);

}  // namespace
