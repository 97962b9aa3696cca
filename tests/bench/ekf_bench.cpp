// Per-update cost of the scalar EKF (Ge et al. 2017, docs/equations.md E-Ge), float and double, and
// of the predicted-intensity sigma. Samples are pre-generated; the filter is initialised before
// timing.
#include <benchmark/benchmark.h>

#include <random>
#include <vector>

#include "magvec/core/scalar_ekf.hpp"

namespace {

using magvec::core::EkfConfig;
using magvec::core::Mat3;
using magvec::core::ScalarEkf;
using magvec::core::Vec3;

constexpr double kF = 45306.0;

template <typename Scalar>
std::vector<Vec3<Scalar>> samples(int n) {
  Mat3<double> c;
  c << 1.362, 0.002, 0.001, 0.001, 0.861, 0.002, 0.002, 0.001, 1.046;
  const Vec3<double> b(600, 700, 750);
  std::mt19937_64 rng(1);
  std::normal_distribution<double> nd(0.0, 1.0);
  std::vector<Vec3<Scalar>> out;
  for (int i = 0; i < n; ++i) {
    Vec3<double> u(nd(rng), nd(rng), nd(rng));
    u.normalize();
    out.push_back(
        (c * (kF * u) + b + 200.0 * Vec3<double>(nd(rng), nd(rng), nd(rng))).cast<Scalar>());
  }
  return out;
}

template <typename Scalar>
void BM_EkfUpdate(benchmark::State& state) {
  const auto data = samples<Scalar>(4096);
  EkfConfig<Scalar> cfg;
  cfg.noise_sigma_nT = Scalar(200);
  cfg.iterations = static_cast<int>(state.range(0));
  cfg.divergence_detection = false;  // a long benchmark may otherwise restart on the repeated data
  ScalarEkf<Scalar> ekf(cfg);
  for (int i = 0; i < 128; ++i)
    ekf.update(data[static_cast<std::size_t>(i)], Scalar(kF));
  std::size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(ekf.update(data[i], Scalar(kF)));
    i = (i + 1) & 4095u;
  }
  state.SetItemsProcessed(static_cast<std::int64_t>(state.iterations()));
}

template <typename Scalar>
void BM_IntensitySigma(benchmark::State& state) {
  const auto data = samples<Scalar>(4096);
  EkfConfig<Scalar> cfg;
  cfg.noise_sigma_nT = Scalar(200);
  ScalarEkf<Scalar> ekf(cfg);
  for (const auto& m : data)
    ekf.update(m, Scalar(kF));
  std::size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(ekf.intensity_sigma_nT(data[i]));
    i = (i + 1) & 4095u;
  }
}

// One-off cost of the start: buffering init_samples samples and the quadric + Gauss-Newton fit.
template <typename Scalar>
void BM_InitialFit(benchmark::State& state) {
  const auto data = samples<Scalar>(64);
  EkfConfig<Scalar> cfg;
  cfg.noise_sigma_nT = Scalar(200);
  for (auto _ : state) {
    ScalarEkf<Scalar> ekf(cfg);
    for (const auto& m : data)
      ekf.update(m, Scalar(kF));
    benchmark::DoNotOptimize(ekf.initialised());
  }
  state.counters["filter_bytes"] = static_cast<double>(sizeof(ScalarEkf<Scalar>));
}

BENCHMARK_TEMPLATE(BM_InitialFit, float);
BENCHMARK_TEMPLATE(BM_InitialFit, double);
BENCHMARK_TEMPLATE(BM_EkfUpdate, float)->Arg(1)->Arg(2);
BENCHMARK_TEMPLATE(BM_EkfUpdate, double)->Arg(1)->Arg(2);
BENCHMARK_TEMPLATE(BM_IntensitySigma, float);
BENCHMARK_TEMPLATE(BM_IntensitySigma, double);

}  // namespace
