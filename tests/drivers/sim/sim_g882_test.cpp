// SimG882 (drivers/sim sim_g882.hpp): one line per cycle carrying the simulator's true |h_n|
// (plus the configured noise), decoded by the real G-882 codec; injected faults equal the
// decoder's counters.
#include "magvec/drivers/sim/sim_g882.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

namespace magvec::drivers::sim {
namespace {

struct Decoded {
  std::vector<hal::ScalarSample> samples;
  std::vector<double> truth;  // |h_n| at the sample of each written line
  std::vector<double> sent;   // the reading written (before rounding)
};

Decoded run(const SimG882Config& cfg, std::uint32_t samples, G882LineDecoder& dec) {
  ScenarioConfig sc = scenario_survey();
  sc.num_samples = samples;
  Simulator sim(sc, 5);
  SimG882 dev(cfg);
  Decoded d;
  SimSample s{};
  while (sim.next(&s)) {
    double f = 0;
    const bool wrote = dev.transmit(s, &f);
    if (wrote) {
      d.truth.push_back(s.h_n_true_nT.norm());
      d.sent.push_back(f);
    }
    std::array<std::uint8_t, 64> buf{};
    std::size_t n = 0;
    while (dev.read(buf, n, 0) == hal::Status::kOk) {
      hal::ScalarSample out;
      for (std::size_t i = 0; i < n; ++i)
        if (dec.push(buf[i], static_cast<std::uint64_t>(s.t_s * 1e6), out) == hal::Status::kOk)
          d.samples.push_back(out);
    }
  }
  return d;
}

TEST(SimG882, OneLinePerCycleWithTheTrueFieldAndItsNoise) {
  SimG882Config cfg;
  cfg.noise_nT = 0;
  G882LineDecoder dec(cfg.line);
  const ScenarioConfig sc = scenario_survey();
  const std::uint32_t n = 2000;
  const Decoded d = run(cfg, n, dec);
  const double duration_s = n / sc.rate_hz;
  EXPECT_NEAR(static_cast<double>(d.samples.size()), duration_s * cfg.rate_hz, 1.0);
  ASSERT_EQ(d.samples.size(), d.truth.size());
  for (std::size_t i = 0; i < d.samples.size(); ++i) {
    EXPECT_NEAR(d.samples[i].f_nT, d.truth[i], 0.0005 + 1e-9);  // the format's 1 pT resolution
    EXPECT_DOUBLE_EQ(d.samples[i].quality, 1500.0 / 9999.0);
  }
  EXPECT_EQ(dec.counters().malformed + dec.counters().garbage_bytes, 0u);

  // With noise: the scatter of reading - truth is the configured sigma.
  cfg.noise_nT = 0.5;
  G882LineDecoder noisy(cfg.line);
  const Decoded e = run(cfg, 20000, noisy);
  double ss = 0;
  for (std::size_t i = 0; i < e.samples.size(); ++i)
    ss += (e.samples[i].f_nT - e.truth[i]) * (e.samples[i].f_nT - e.truth[i]);
  const double rms = std::sqrt(ss / static_cast<double>(e.samples.size()));
  EXPECT_NEAR(rms, 0.5, 0.5 * 4 / std::sqrt(2.0 * static_cast<double>(e.samples.size())));
}

TEST(SimG882, InjectedGarbageAndTruncatedLinesEqualTheDecoderCounters) {
  SimG882Config cfg;
  cfg.faults.garbage_probability = 0.2;
  G882LineDecoder dec(cfg.line);
  const Decoded d = run(cfg, 4000, dec);
  EXPECT_GT(dec.counters().garbage_bytes, 50u);
  EXPECT_EQ(d.samples.size(), d.truth.size());

  SimG882Config t;
  t.faults.truncate_probability = 0.1;
  G882LineDecoder dect(t.line);
  const Decoded e = run(t, 4000, dect);
  // Each cut line is restarted by the next line's preamble (unless it is the very last one).
  EXPECT_GT(dect.counters().malformed, 5u);
  EXPECT_LE(dect.counters().malformed, static_cast<std::uint32_t>(e.truth.size()));
  EXPECT_EQ(e.samples.size(), e.truth.size());
  for (std::size_t i = 0; i < e.samples.size(); ++i)
    EXPECT_NEAR(e.samples[i].f_nT, e.sent[i], 0.0005 + 1e-9);
}

TEST(SimG882, GarbageCountEqualsInjectedAndRateIsConfigurable) {
  SimG882Config cfg;
  cfg.rate_hz = 20;
  cfg.faults.garbage_probability = 0.3;
  ScenarioConfig sc = scenario_survey();
  sc.num_samples = 1000;
  Simulator sim(sc, 9);
  SimG882 dev(cfg);
  G882LineDecoder dec(cfg.line);
  SimSample s{};
  std::uint32_t lines = 0;
  while (sim.next(&s)) {
    lines += dev.transmit(s) ? 1u : 0u;
    std::array<std::uint8_t, 64> buf{};
    std::size_t n = 0;
    hal::ScalarSample out;
    while (dev.read(buf, n, 0) == hal::Status::kOk)
      for (std::size_t i = 0; i < n; ++i)
        (void)dec.push(buf[i], 0, out);
  }
  EXPECT_NEAR(lines, 1000 / sc.rate_hz * 20, 1.0);
  EXPECT_EQ(dec.counters().garbage_bytes, dev.injected().garbage_bytes);
  EXPECT_EQ(dec.counters().samples, dev.injected().lines);
  EXPECT_EQ(dev.injected().overflow_bytes, 0u);
}

}  // namespace
}  // namespace magvec::drivers::sim
