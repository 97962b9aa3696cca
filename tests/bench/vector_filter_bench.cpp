// Per-sample cost of the online vector calibration filter (vector_calibration_filter.hpp,
// docs/equations.md E-VF), float and double: one update (vector sample, with and without the scalar
// reference) while it runs, started from a stored calibration so that the start's replays are not
// timed. The samples (a turning, pitching and rolling platform at 100 Hz, 0.3 nT and 0.015 deg
// noise) are pre-generated and repeated; divergence detection is off so that a long run over the
// repeated data cannot restart the filter. Counters: the filter's size (its RAM), updates applied.
#include <benchmark/benchmark.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <vector>

#include <Eigen/Geometry>

#include "magvec/core/frames.hpp"
#include "magvec/core/sensor_model.hpp"
#include "magvec/core/vector_calibration_filter.hpp"

namespace {

using namespace magvec::core;

constexpr int kSamples = 4096;  // 41 s at 100 Hz
constexpr double kRate_hz = 100;

// Li 2023's example sensor errors and misalignment.
SensorModel<double> truth() {
  LiParams<double> li;
  li.ks = {1.08, 1.02, 1.033};
  li.o_rad = Vec3<double>(1.7, 3.5, 2.1) * (kPi<double> / 180);
  li.kof = {5, 3.5, 0.4};
  li.rm_rad = Vec3<double>(5.7, 2.1, 3.5) * (kPi<double> / 180);
  return from_li(li);
}

Mat3<double> attitude(double t) {
  return r_bn_from_li(LiEuler<double>{1.0 * t + 0.8 * std::sin(0.37 * t), 0.7 * std::sin(1.3 * t),
                                      0.6 * std::sin(1.1 * t + 1.0)});
}

template <typename Scalar>
std::vector<VfSample<Scalar>> samples(bool with_reference) {
  const SensorModel<double> m = truth();
  const Vec3<double> h_n(-4053, 25022, -47374);
  std::mt19937_64 rng(1);
  std::normal_distribution<double> nd(0.0, 1.0);
  std::vector<VfSample<Scalar>> out;
  const double dt = 1 / kRate_hz;
  for (int i = 0; i < kSamples; ++i) {
    const double t = i * dt;
    const Mat3<double> r = attitude(t);
    const Vec3<double> e = Vec3<double>(nd(rng), nd(rng), nd(rng)) * (0.015 * kPi<double> / 180);
    VfSample<Scalar> s;
    s.m_nT = (m.predict_raw(r, h_n) + 0.3 * Vec3<double>(nd(rng), nd(rng), nd(rng))).cast<Scalar>();
    s.r_bn =
        (r * Eigen::AngleAxis<double>(e.norm(), e / e.norm()).toRotationMatrix()).cast<Scalar>();
    s.omega_n_rad_s =
        rate_n_from_attitudes(attitude(t - dt), attitude(t + dt), 2 * dt).cast<Scalar>();
    s.f_nT =
        with_reference ? static_cast<Scalar>(h_n.norm()) : std::numeric_limits<Scalar>::quiet_NaN();
    s.temperature_degC = Scalar(20);
    s.interval_s = static_cast<Scalar>(dt);
    out.push_back(s);
  }
  return out;
}

template <typename Scalar>
void BM_VectorFilterUpdate(benchmark::State& state) {
  const auto data = samples<Scalar>(state.range(0) != 0);
  VfConfig<Scalar> cfg;
  cfg.mag_noise_nT = Scalar(0.3);
  cfg.attitude_noise_rad = deg_to_rad(Scalar(0.015));
  cfg.divergence_detection = false;
  cfg.fold_samples = static_cast<int>(state.range(1));
  VectorCalibrationFilter<Scalar> filter(cfg);
  VfStart<Scalar> start;
  start.model = truth().template cast<Scalar>();
  start.sigma.ks.setConstant(Scalar(1e-3));
  start.sigma.o_rad.setConstant(deg_to_rad(Scalar(0.05)));
  start.sigma.kof.setConstant(Scalar(5));
  start.sigma.rm_rad.setConstant(deg_to_rad(Scalar(0.1)));
  start.h_n_nT = Vec3<Scalar>(Scalar(-4053), Scalar(25022), Scalar(-47374));
  start.h_n_sigma_nT.setConstant(Scalar(50));
  start.time_offset_sigma_s = Scalar(0.01);
  start.tc_sigma_nT_per_degC.setConstant(Scalar(1));
  start.temperature_ref_degC = Scalar(20);
  filter.start(start);
  // Past the stored start's settling passes (the first replay-store's worth of samples).
  for (int i = 0; i < 1024; ++i)
    (void)filter.update(data[static_cast<std::size_t>(i)]);
  if (!filter.initialised()) state.SkipWithError("the filter did not start");
  std::size_t i = 1024;
  for (auto _ : state) {
    benchmark::DoNotOptimize(filter.update(data[i]));
    i = (i + 1) % static_cast<std::size_t>(kSamples);
  }
  state.SetItemsProcessed(static_cast<std::int64_t>(state.iterations()));
  state.counters["filter_bytes"] = static_cast<double>(sizeof(filter));
  state.counters["updates"] = static_cast<double>(filter.counters().updates);
}

}  // namespace

// Args: 1 with the scalar reference (one more scalar update per sample), 0 without; the samples
// per information fold (docs/equations.md E-VF-B; 1: sequential updates per sample).
BENCHMARK_TEMPLATE(BM_VectorFilterUpdate, float)->ArgsProduct({{0, 1}, {1, 16}});
BENCHMARK_TEMPLATE(BM_VectorFilterUpdate, double)->ArgsProduct({{0, 1}, {1, 16}});
