// Throughput of the simulated fluxgate + INS (drivers/sim/simulator.hpp): one Simulator::next().
#include <benchmark/benchmark.h>

#include "magvec/drivers/sim/simulator.hpp"

namespace {

using magvec::drivers::sim::ScenarioConfig;
using magvec::drivers::sim::SimSample;
using magvec::drivers::sim::Simulator;

void run(benchmark::State& state, ScenarioConfig cfg) {
  cfg.num_samples = 1U << 30;
  cfg.spike_probability = 0.01;
  cfg.spike_amplitude_nT = 100;
  cfg.dropout_probability = 0.01;
  Simulator sim(cfg, 1);
  SimSample s;
  for (auto _ : state) {
    benchmark::DoNotOptimize(sim.next(&s));
    benchmark::DoNotOptimize(s);
  }
  state.SetItemsProcessed(state.iterations());
}

void BM_SimNextLi2023(benchmark::State& state) {
  run(state, magvec::drivers::sim::scenario_li2023());
}
void BM_SimNextSurvey(benchmark::State& state) {
  run(state, magvec::drivers::sim::scenario_survey());
}
BENCHMARK(BM_SimNextLi2023);
BENCHMARK(BM_SimNextSurvey);

}  // namespace
