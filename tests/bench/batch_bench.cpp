// Google Benchmark of the batch calibration: per-sample accumulation, the algebraic
// ellipsoid solve, and the full one-step refinement at N = 60, 6000 and 10^6 samples.
#include <benchmark/benchmark.h>

#include <memory>
#include <random>
#include <vector>

#include "magvec/core/batch_calibrator.hpp"
#include "magvec/core/ellipsoid_fit.hpp"
#include "magvec/core/one_step.hpp"

namespace {

using namespace magvec::core;
constexpr double kDeg = kPi<double> / 180.0;

struct Data {
  std::vector<Vec3<double>> m;
  std::vector<Mat3<double>> r;
  double f;
};

Data make_data(std::size_t n) {
  LiParams<double> p;
  p.ks = {1.08, 1.02, 1.033};
  p.o_rad = Vec3<double>(1.7, 3.5, 2.1) * kDeg;
  p.kof = {4.9, 3.4, 0.7};
  p.rm_rad = Vec3<double>(5.7, 2.1, 3.5) * kDeg;
  const SensorModel<double> model = from_li(p);
  const Vec3<double> h(-4053, 25022, -47374);
  std::mt19937_64 rng(42);
  std::normal_distribution<double> g(0, 1);
  Data d;
  d.f = h.norm();
  for (std::size_t i = 0; i < n; ++i) {
    Quat<double> q(g(rng), g(rng), g(rng), g(rng));
    q.normalize();
    const Mat3<double> r = q.toRotationMatrix();
    d.r.push_back(r);
    d.m.push_back(model.predict_raw(r, h) + 0.3 * Vec3<double>(g(rng), g(rng), g(rng)));
  }
  return d;
}

void BM_EllipsoidAccumulate(benchmark::State& state) {
  const Data d = make_data(1024);
  EllipsoidFit<double> fit;
  std::size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(fit.add(d.m[i & 1023U], d.f));
    ++i;
  }
  state.SetItemsProcessed(static_cast<std::int64_t>(state.iterations()));
}
BENCHMARK(BM_EllipsoidAccumulate);

void BM_EllipsoidAccumulateFloat(benchmark::State& state) {
  const Data d = make_data(1024);
  std::vector<Vec3<float>> mf;
  for (const auto& m : d.m)
    mf.push_back(m.cast<float>());
  EllipsoidFit<float> fit;
  std::size_t i = 0;
  for (auto _ : state) {
    benchmark::DoNotOptimize(fit.add(mf[i & 1023U], static_cast<float>(d.f)));
    ++i;
  }
}
BENCHMARK(BM_EllipsoidAccumulateFloat);

void BM_EllipsoidAlgebraicSolve(benchmark::State& state) {
  const Data d = make_data(60);
  EllipsoidFit<double> fit;
  for (const auto& m : d.m)
    fit.add(m, d.f);
  for (auto _ : state)
    benchmark::DoNotOptimize(fit.solve());
}
BENCHMARK(BM_EllipsoidAlgebraicSolve);

// The batch calibrator with the growing store `magvec calibrate` uses (compiled once in
// magvec::core_batch_double; a fixed capacity per size would compile the whole solver again for
// each), N samples from the argument.
void BM_OneStep(benchmark::State& state) {
  const auto n = static_cast<std::size_t>(state.range(0));
  const Data d = make_data(n);
  auto cal = std::make_unique<BatchCalibrator<double, kDynamicCapacity>>();
  for (std::size_t i = 0; i < n; ++i)
    cal->add_sample(d.m[i], d.f, d.r[i]);
  for (auto _ : state) {
    const BatchResult<double> r = cal->solve(BatchMethod::kOneStep);
    benchmark::DoNotOptimize(r);
    state.counters["iterations"] = r.quality.iterations;
  }
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(n));
}
BENCHMARK(BM_OneStep)->Arg(60)->Unit(benchmark::kMicrosecond);
BENCHMARK(BM_OneStep)->Arg(6000)->Unit(benchmark::kMillisecond);
BENCHMARK(BM_OneStep)->Arg(1000000)->Unit(benchmark::kMillisecond)->Iterations(1);

// One Gauss-Newton pass of the one-step fit (the per-iteration cost, linear in N).
void BM_OneStepPass(benchmark::State& state) {
  constexpr std::size_t kN = 6000;
  const Data d = make_data(kN);
  auto st = std::make_unique<SampleStore<double, kN>>();
  for (std::size_t i = 0; i < kN; ++i)
    st->push(d.m[i], d.f, &d.r[i]);
  Normalization<double> norm;
  norm.scale = d.f;
  const OneStepFit<double>::Params p{Vec3<double>::Ones(), Vec3<double>::Zero(),
                                     Vec3<double>::Zero(), Vec3<double>::Zero(),
                                     Vec3<double>(-4053, 25022, -47374).normalized()};
  for (auto _ : state) {
    const auto sums =
        OneStepFit<double>::pass(*st, norm, p, p, 0.3 / d.f, 4.5e-8, AttitudeNoiseModel::kLiEuler);
    benchmark::DoNotOptimize(sums.chi2);
  }
  state.SetItemsProcessed(state.iterations() * static_cast<std::int64_t>(kN));
}
BENCHMARK(BM_OneStepPass)->Unit(benchmark::kMicrosecond);

}  // namespace
