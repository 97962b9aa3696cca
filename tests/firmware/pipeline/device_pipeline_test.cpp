// DevicePipeline (firmware/pipeline/.../device_pipeline.hpp): HAL samples in, one record per
// magnetometer sample out, with the HAL record's NaN conventions, failed reads and sink refusals
// counted, float and double alike, no heap per event. The timing rules themselves are the core's
// SamplePipeline; here they are exercised through HAL samples as a driver delivers them.
#include "magvec/pipeline/device_pipeline.hpp"

#include <gtest/gtest.h>

#include <cmath>
#include <cstdint>
#include <limits>
#include <random>
#include <set>
#include <vector>

#include "support/alloc_counter.hpp"

namespace magvec {
namespace {

// The loop outputs with the active (identity) model.
template <typename Scalar>
using IdleCalibrator = pipeline::NullCalibrator<Scalar>;

constexpr std::uint32_t kLatencyUs = 15'000;
const core::Vec3<double> kField(-4053.0, 25022.0, -47374.0);

core::Quat<double> attitude_at(std::uint64_t t_us) {
  const double angle = 0.5 * 1e-6 * static_cast<double>(t_us);  // 29 deg/s about a fixed axis
  return core::Quat<double>(
      Eigen::AngleAxis<double>(angle, core::Vec3<double>(0.3, -0.4, 0.866).normalized()));
}

hal::AttitudeSample ins_sample(std::uint64_t epoch_us) {
  hal::AttitudeSample a;
  const core::Quat<double> q = attitude_at(epoch_us);
  a.t_us = epoch_us + kLatencyUs;  // CAN receive time
  a.q_nb = {q.w(), q.x(), q.y(), q.z()};
  a.flags = hal::kAttAttitudeValid | hal::kAttHeadingValid;
  return a;
}

hal::MagnetometerSample mag_sample(std::uint64_t t_us) {
  hal::MagnetometerSample s;
  s.t_us = t_us;
  const core::Vec3<double> m = core::r_bn_from_quat(attitude_at(t_us)) * kField;
  s.m_nT = {m(0), m(1), m(2)};
  return s;
}

template <typename Scalar>
core::PipelineConfig<Scalar> config() {
  core::PipelineConfig<Scalar> c;
  c.ins_latency_us = kLatencyUs;
  c.horizon_us = 100'000;
  c.mag_period_us = 5'000;
  c.ins_period_us = 10'000;
  return c;
}

template <typename Scalar>
using Pipe = pipeline::DevicePipeline<Scalar, IdleCalibrator<Scalar>, 64, 64>;

// 200 Hz magnetometer, 100 Hz INS received kLatencyUs after its epoch, fed in arrival order;
// modify(i, sample) may change each magnetometer sample before it is fed (noise, spikes, steps).
template <typename Scalar, typename Emit, typename Modify>
void feed_stream(Pipe<Scalar>& p, int samples, Emit&& emit, Modify&& modify) {
  std::uint64_t next_ins = 0;
  for (int i = 0; i < samples; ++i) {
    const std::uint64_t t = 100'000 + 5'000 * static_cast<std::uint64_t>(i);
    while (next_ins + kLatencyUs <= t) {
      p.on_attitude(ins_sample(next_ins), emit);
      next_ins += 10'000;
    }
    hal::MagnetometerSample s = mag_sample(t);
    modify(i, s);
    p.on_magnetometer(s, static_cast<Scalar>(kField.norm()), emit);
  }
  for (int k = 0; k < 20; ++k, next_ins += 10'000)
    p.on_attitude(ins_sample(next_ins), emit);
  p.flush(emit);
}

template <typename Scalar, typename Emit>
void feed_stream(Pipe<Scalar>& p, int samples, Emit&& emit) {
  feed_stream(p, samples, emit, [](int, hal::MagnetometerSample&) {});
}

TEST(DevicePipeline, LateInsFramesAreWaitedForAndInterpolated) {
  IdleCalibrator<double> cal;
  Pipe<double> p(cal, config<double>());
  std::vector<hal::OutputRecord> out;
  feed_stream(p, 400, [&](const core::OutputRecord<double>& r) {
    out.push_back(pipeline::to_hal_record(r));
  });
  ASSERT_EQ(out.size(), 400u);
  for (std::size_t i = 0; i < out.size(); ++i) {
    const hal::OutputRecord& r = out[i];
    EXPECT_EQ(r.t_us, 100'000 + 5'000 * i);  // in sample order
    ASSERT_EQ(r.flags & (core::kOutNoAttitude | core::kOutAttExtrapolated), 0u) << i;
    const core::Vec3<double> h(r.h_n_nT[0], r.h_n_nT[1], r.h_n_nT[2]);
    EXPECT_LT((h - kField).norm(), 1e-6);  // slerp is exact for a fixed-axis rotation
  }
  EXPECT_EQ(p.counters().records, 400u);
  EXPECT_EQ(p.counters().horizon_expired, 0u);
  EXPECT_EQ(p.counters().mag_missing, 0u);
  EXPECT_EQ(p.counters().att_gaps, 0u);
}

TEST(DevicePipeline, FloatFollowsDouble) {
  IdleCalibrator<float> calf;
  IdleCalibrator<double> cald;
  Pipe<float> pf(calf, config<float>());
  Pipe<double> pd(cald, config<double>());
  std::vector<hal::OutputRecord> of, od;
  feed_stream(pf, 200, [&](const core::OutputRecord<float>& r) {
    of.push_back(pipeline::to_hal_record(r));
  });
  feed_stream(pd, 200, [&](const core::OutputRecord<double>& r) {
    od.push_back(pipeline::to_hal_record(r));
  });
  ASSERT_EQ(of.size(), od.size());
  for (std::size_t i = 0; i < of.size(); ++i) {
    EXPECT_EQ(of[i].t_us, od[i].t_us);
    EXPECT_EQ(of[i].flags, od[i].flags);
    for (std::size_t k = 0; k < 3; ++k)
      EXPECT_NEAR(of[i].h_n_nT[k], od[i].h_n_nT[k], 0.05);  // float: ~1e-6 of 54 uT
  }
}

TEST(DevicePipeline, HalRecordsCarryNaNForValuesTheyDoNotHave) {
  IdleCalibrator<double> cal;
  Pipe<double> p(cal, config<double>());
  std::vector<hal::OutputRecord> out;
  auto emit = [&](const core::OutputRecord<double>& r) {
    out.push_back(pipeline::to_hal_record(r));
  };
  // No INS at all: records without attitude once the horizon expires.
  p.on_magnetometer(mag_sample(100'000), 50'000.0, emit);
  hal::MagnetometerSample stale = mag_sample(105'000);
  stale.flags = hal::kMagNotFresh;
  p.on_magnetometer(stale, 50'000.0, emit);
  hal::MagnetometerSample saturated = mag_sample(110'000);
  saturated.flags = hal::kMagSaturated;
  p.on_magnetometer(saturated, 50'000.0, emit);
  p.on_read_error();
  p.flush(emit);
  ASSERT_EQ(out.size(), 3u);
  // Sample without attitude: h_s and F exist, h_n does not.
  EXPECT_NE(out[0].flags & core::kOutNoAttitude, 0u);
  EXPECT_TRUE(std::isfinite(out[0].f_nT));
  EXPECT_TRUE(std::isfinite(out[0].h_s_nT[0]));
  EXPECT_TRUE(std::isnan(out[0].h_n_nT[0]));
  // Not fresh: a dropout, no output value at all.
  EXPECT_NE(out[1].flags & core::kOutDropout, 0u);
  EXPECT_EQ(out[1].flags & core::kOutDeviceError, 0u);
  EXPECT_TRUE(std::isnan(out[1].f_nT));
  EXPECT_TRUE(std::isnan(out[1].sigma_f_nT));
  EXPECT_TRUE(std::isnan(out[1].h_s_nT[2]));
  EXPECT_TRUE(std::isnan(out[1].h_n_nT[1]));
  // Saturated: passed on as a device error.
  EXPECT_NE(out[2].flags & core::kOutDeviceError, 0u);
  const pipeline::DeviceCounters& c = p.counters();
  EXPECT_EQ(c.mag_samples, 3u);
  EXPECT_EQ(c.mag_not_fresh, 1u);
  EXPECT_EQ(c.mag_read_errors, 1u);
  EXPECT_EQ(c.records, 3u);
}

// NaN and inf at every input of the pipeline: a non-finite magnetometer value is a counted
// dropout with NaN outputs; a non-finite attitude is refused by the buffer (att_rejected) and
// never reaches a record; a non-finite scalar reference is no reference. No number of any record
// is made from a non-finite input.
TEST(DevicePipeline, NonFiniteInputsAreCountedAndNeverPropagated) {
  constexpr double kInf = std::numeric_limits<double>::infinity();
  constexpr double kNaN = std::numeric_limits<double>::quiet_NaN();
  IdleCalibrator<double> cal;
  Pipe<double> p(cal, config<double>());
  std::vector<hal::OutputRecord> out;
  auto emit = [&](const core::OutputRecord<double>& r) {
    out.push_back(pipeline::to_hal_record(r));
  };
  std::set<std::uint64_t> bad_mag;
  std::uint64_t bad_att = 0;
  std::uint64_t next_ins = 0;
  for (int i = 0; i < 400; ++i) {
    const std::uint64_t t = 100'000 + 5'000 * static_cast<std::uint64_t>(i);
    while (next_ins + kLatencyUs <= t) {
      hal::AttitudeSample a = ins_sample(next_ins);
      if ((next_ins / 10'000) % 37 == 5) {
        a.q_nb[(next_ins / 10'000) % 4] = (next_ins / 10'000) % 2 != 0 ? kNaN : kInf;
        ++bad_att;
      }
      p.on_attitude(a, emit);
      next_ins += 10'000;
    }
    hal::MagnetometerSample s = mag_sample(t);
    if (i % 23 == 7) {
      s.m_nT[static_cast<std::size_t>(i % 3)] = i % 2 != 0 ? kNaN : -kInf;
      bad_mag.insert(t);
    }
    p.on_magnetometer(s, i % 19 == 3 ? kInf : kField.norm(), emit);
  }
  for (int k = 0; k < 20; ++k, next_ins += 10'000)
    p.on_attitude(ins_sample(next_ins), emit);
  p.flush(emit);
  ASSERT_EQ(out.size(), 400u);
  ASSERT_GT(bad_att, 5u);
  for (const hal::OutputRecord& r : out) {
    if (bad_mag.count(r.t_us) == 1) {
      EXPECT_NE(r.flags & core::kOutDropout, 0u) << r.t_us;
      EXPECT_TRUE(std::isnan(r.f_nT) && std::isnan(r.h_s_nT[0]) && std::isnan(r.h_n_nT[0]));
      continue;
    }
    EXPECT_EQ(r.flags & core::kOutDropout, 0u) << r.t_us;
    EXPECT_TRUE(std::isfinite(r.f_nT));
    // Interpolated across the refused epoch (20 ms apart, within the buffer's gap limit).
    ASSERT_EQ(r.flags & core::kOutNoAttitude, 0u) << r.t_us;
    for (const double v : r.h_n_nT)
      EXPECT_TRUE(std::isfinite(v));
  }
  EXPECT_EQ(p.loop().health().dropouts, bad_mag.size());
  EXPECT_EQ(p.counters().att_rejected, bad_att);
}

struct RefusingSink final : hal::RecordSink {
  std::uint32_t calls{0};
  hal::Status emit(const hal::OutputRecord&) noexcept override {
    ++calls;
    return calls % 2 == 0 ? hal::Status::kBusError : hal::Status::kOk;
  }
};

TEST(DevicePipeline, SinkRefusalsAreCounted) {
  IdleCalibrator<double> cal;
  Pipe<double> p(cal, config<double>());
  RefusingSink sink;
  feed_stream(p, 10, p.emit_to(sink));
  EXPECT_EQ(sink.calls, 10u);
  EXPECT_EQ(p.counters().sink_errors, 5u);
}

// INS frames swapped in transit are reordering; a step back beyond the longest interpolation gap
// is a clock jump that restarts the attitude buffer.
TEST(DevicePipeline, InsReorderingIsNotAClockJump) {
  IdleCalibrator<double> cal;
  Pipe<double> p(cal, config<double>());
  auto none = [](const core::OutputRecord<double>&) {};
  p.on_attitude(ins_sample(0), none);
  p.on_attitude(ins_sample(20'000), none);
  p.on_attitude(ins_sample(10'000), none);  // 10 ms back: reordered
  EXPECT_EQ(p.counters().att_reordered, 1u);
  EXPECT_EQ(p.counters().att_time_jumps, 0u);
  EXPECT_EQ(p.core().buffer().size(), 3u);
  p.on_attitude(ins_sample(30'000), none);
  EXPECT_EQ(p.counters().att_gaps, 1u);  // 0 -> 20 ms was a gap when it arrived
  p.on_attitude(ins_sample(0), none);    // 30 ms back: still within the 50 ms gap, reordered
  EXPECT_EQ(p.counters().att_reordered, 2u);
  EXPECT_EQ(p.counters().att_rejected, 1u);  // a duplicate of the first epoch
  // 200 ms back: a new time base.
  p.on_attitude(ins_sample(1'000'000), none);
  p.on_attitude(ins_sample(800'000), none);
  EXPECT_EQ(p.counters().att_time_jumps, 1u);
  EXPECT_EQ(p.core().buffer().size(), 1u);
}

// The spike screen (core SamplePipeline, docs/equations.md E-Spike) on a rotating stream with
// sensor noise: every injected spike (one axis, 200 nT to 2 uT, either sign) is flagged and
// counted, nothing else is; the flagged records keep their values.
template <typename Scalar>
void spikes_flagged_exactly(double noise_nT) {
  IdleCalibrator<Scalar> cal;
  Pipe<Scalar> p(cal, config<Scalar>());
  std::vector<hal::OutputRecord> out;
  auto emit = [&](const core::OutputRecord<Scalar>& r) {
    out.push_back(pipeline::to_hal_record(r));
  };
  std::mt19937_64 rng(5);
  std::normal_distribution<double> noise(0, noise_nT);
  std::uniform_real_distribution<double> u(0, 1);
  std::set<std::uint64_t> spiked;
  feed_stream(p, 4000, emit, [&](int i, hal::MagnetometerSample& s) {
    for (double& v : s.m_nT)
      v += noise(rng);
    if (i > 40 && u(rng) < 0.01) {
      const auto axis = static_cast<std::size_t>(u(rng) * 3) % 3;
      s.m_nT[axis] += (u(rng) < 0.5 ? -1 : 1) * (200 + 1800 * u(rng));
      spiked.insert(s.t_us);
    }
  });
  ASSERT_EQ(out.size(), 4000u);
  ASSERT_GT(spiked.size(), 20u);
  std::size_t flagged = 0;
  for (const hal::OutputRecord& r : out) {
    const bool spike = (r.flags & core::kOutSpike) != 0;
    EXPECT_EQ(spike, spiked.count(r.t_us) == 1) << r.t_us;
    if (spike) {
      ++flagged;
      EXPECT_TRUE(std::isfinite(r.f_nT));  // kept, flagged
    }
  }
  EXPECT_EQ(flagged, spiked.size());
  EXPECT_EQ(p.counters().spikes, spiked.size());
  EXPECT_GT(p.counters().spike_screened, 3900u);
}

TEST(DevicePipeline, SpikesAreFlaggedAndCountedExactly) {
  spikes_flagged_exactly<double>(0.3);  // fluxgate-class noise
  spikes_flagged_exactly<double>(5.0);  // MEMS-class noise: the screen learns it
  spikes_flagged_exactly<float>(0.3);
}

// A step of the field (a real jump, or the next attitude of a piecewise-constant run) moves every
// later sample: it is not a spike. Noise-free data (RMS near zero) flag nothing either.
TEST(DevicePipeline, StepsAndNoiseFreeDataAreNotSpikes) {
  IdleCalibrator<double> cal;
  Pipe<double> p(cal, config<double>());
  std::size_t spikes = 0;
  auto emit = [&](const core::OutputRecord<double>& r) {
    spikes += (r.flags & core::kOutSpike) != 0 ? 1u : 0u;
  };
  feed_stream(p, 2000, emit, [](int i, hal::MagnetometerSample& s) {
    // Steps of 1 uT every 100 samples, in alternating directions, on top of the rotation.
    s.m_nT[1] += 1000.0 * static_cast<double>((i / 100) % 2);
  });
  EXPECT_EQ(spikes, 0u);
  EXPECT_EQ(p.counters().spikes, 0u);
  EXPECT_GT(p.counters().spike_screened, 1900u);
}

// Off (spike_factor 0), or without a horizon (no next sample to judge against): nothing screened.
TEST(DevicePipeline, SpikeScreenNeedsTheNextSample) {
  for (const bool off : {true, false}) {
    core::PipelineConfig<double> c = config<double>();
    if (off) {
      c.spike_factor = 0;
    } else {
      c.horizon_us = 0;
    }
    IdleCalibrator<double> cal;
    Pipe<double> p(cal, c);
    std::size_t n = 0;
    feed_stream(p, 400, [&](const core::OutputRecord<double>&) { ++n; });
    EXPECT_EQ(n, 400u);
    EXPECT_EQ(p.counters().spike_screened, 0u) << off;
  }
}

TEST(DevicePipeline, NoHeapAllocationPerEvent) {
  IdleCalibrator<float> cal;
  Pipe<float> p(cal, config<float>());
  RefusingSink sink;
  auto emit = p.emit_to(sink);
  feed_stream(p, 50, emit);  // warm-up
  const test::AllocationScope scope;
  feed_stream(p, 400, emit);
  EXPECT_EQ(scope.count(), 0u);
}

}  // namespace
}  // namespace magvec
