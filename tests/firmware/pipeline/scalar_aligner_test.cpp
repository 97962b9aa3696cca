// ScalarAligner (firmware/pipeline scalar_aligner.hpp): a magnetometer sample waits for the
// scalar reading after it and gets F interpolated at its own time; the horizon, a full queue and
// the end release it with the nearest reading or the fallback; bad readings are counted.
#include "magvec/pipeline/scalar_aligner.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <vector>

namespace magvec::pipeline {
namespace {

struct Out {
  std::vector<std::uint64_t> t_us;
  std::vector<double> f_nT;
  void operator()(const hal::MagnetometerSample& s, double f) {
    t_us.push_back(s.t_us);
    f_nT.push_back(f);
  }
};

hal::MagnetometerSample mag(std::uint64_t t_us) {
  hal::MagnetometerSample s;
  s.t_us = t_us;
  return s;
}

hal::ScalarSample scalar(std::uint64_t t_us, double f_nT, std::uint32_t flags = 0) {
  hal::ScalarSample r;
  r.t_us = t_us;
  r.f_nT = f_nT;
  r.flags = flags;
  return r;
}

TEST(ScalarAligner, SamplesWaitForTheReadingAfterThemAndAreInterpolated) {
  ScalarAligner<8, 64> a;
  Out out;
  a.on_scalar(scalar(1'000'000, 50000.0), out);
  // 10 ms magnetometer samples between two 100-ms readings: nothing out before the second one.
  for (std::uint64_t t = 1'000'000; t < 1'100'000; t += 10'000)
    a.on_magnetometer(mag(t), out);
  EXPECT_EQ(out.t_us.size(), 1u);  // the sample at the reading's own time
  a.on_scalar(scalar(1'100'000, 50010.0), out);
  ASSERT_EQ(out.t_us.size(), 10u);
  for (std::size_t i = 0; i < out.t_us.size(); ++i) {
    EXPECT_EQ(out.t_us[i], 1'000'000u + 10'000u * i);  // in order
    EXPECT_NEAR(out.f_nT[i], 50000.0 + static_cast<double>(i), 1e-9);
  }
  EXPECT_EQ(a.counters().interpolated, 9u);
  EXPECT_EQ(a.counters().nearest, 1u);
  EXPECT_EQ(a.counters().expired, 0u);
}

TEST(ScalarAligner, HorizonReleasesWithTheNearestReadingOrTheFallback) {
  ScalarAlignerConfig c;
  c.horizon_us = 50'000;
  c.max_distance_us = 30'000;
  c.fallback_nT = 48000.0;
  ScalarAligner<8, 64> a(c);
  Out out;
  a.on_scalar(scalar(1'000'000, 50000.0), out);
  for (std::uint64_t t = 1'010'000; t <= 1'100'000; t += 10'000)
    a.on_magnetometer(mag(t), out);
  // The scalar stopped: samples more than 50 ms behind the newest leave (1.01-1.04 s), those
  // within 30 ms of the last reading take it, the later ones the fallback.
  ASSERT_EQ(out.t_us.size(), 4u);
  EXPECT_DOUBLE_EQ(out.f_nT[0], 50000.0);
  EXPECT_DOUBLE_EQ(out.f_nT[2], 50000.0);
  EXPECT_DOUBLE_EQ(out.f_nT[3], 48000.0);
  EXPECT_EQ(a.counters().expired, 4u);
  a.flush(out);
  EXPECT_EQ(out.t_us.size(), 10u);
  EXPECT_EQ(a.counters().fallback, 7u);
  EXPECT_EQ(a.queued(), 0u);
}

TEST(ScalarAligner, WideGapsAreNotInterpolatedAndAFullQueueReleasesTheOldest) {
  ScalarAlignerConfig c;
  c.max_gap_us = 100'000;
  c.max_distance_us = 20'000;
  ScalarAligner<4, 3> a(c);
  Out out;
  a.on_scalar(scalar(0, 50000.0), out);
  a.on_scalar(scalar(500'000, 50100.0), out);  // 0.5 s gap: no interpolation across it
  a.on_magnetometer(mag(10'000), out);
  a.on_magnetometer(mag(250'000), out);
  a.on_magnetometer(mag(490'000), out);
  ASSERT_EQ(out.f_nT.size(), 3u);
  EXPECT_DOUBLE_EQ(out.f_nT[0], 50000.0);  // nearest within 20 ms
  EXPECT_TRUE(std::isnan(out.f_nT[1]));    // no fallback configured
  EXPECT_DOUBLE_EQ(out.f_nT[2], 50100.0);
  // No reading after them: the queue (3) fills and its oldest leaves.
  for (std::uint64_t t = 510'000; t < 550'000; t += 10'000)
    a.on_magnetometer(mag(t), out);
  EXPECT_EQ(out.f_nT.size(), 4u);
  EXPECT_EQ(a.queued(), 3u);
  EXPECT_EQ(a.counters().expired, 1u);
}

TEST(ScalarAligner, BadReadingsAreCountedAndNotUsed) {
  ScalarAligner<4, 16> a;
  Out out;
  a.on_scalar(scalar(100'000, 50000.0), out);
  a.on_scalar(scalar(200'000, 99999.0, hal::kScalarLowSignal), out);
  a.on_scalar(scalar(200'000, std::nan("")), out);
  a.on_scalar(scalar(200'000, std::numeric_limits<double>::infinity()), out);
  a.on_scalar(scalar(50'000, 40000.0), out);   // older than the newest
  a.on_scalar(scalar(100'000, 40000.0), out);  // as old as the newest
  a.on_scalar(scalar(200'000, 50010.0), out);
  EXPECT_EQ(a.counters().readings, 2u);
  EXPECT_EQ(a.counters().invalid, 3u);
  EXPECT_EQ(a.counters().reordered, 2u);
  EXPECT_NEAR(a.f_at(150'000), 50005.0, 1e-9);
  // The ring keeps the newest ReadingCapacity readings.
  for (std::uint64_t t = 300'000; t <= 600'000; t += 100'000)
    a.on_scalar(scalar(t, 50000.0 + static_cast<double>(t) / 10'000.0), out);
  EXPECT_NEAR(a.f_at(550'000), 50055.0, 1e-9);
  EXPECT_TRUE(std::isnan(a.f_at(100'000)));  // dropped from the ring, 200 ms from the rest
}

}  // namespace
}  // namespace magvec::pipeline
