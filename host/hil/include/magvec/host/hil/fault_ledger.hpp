// FaultLedger: what the simulated devices injected, sample by sample, turned into the exact counts
// the pipeline must show for it; counter_checks() puts every counter next to its expectation.
// Used by `magvec soak` (host/cli/cmd_soak.cpp) and the fault-matrix test
// (tests/host/hil/fault_matrix_test.cpp).
//
// Why sample by sample: the aggregate injection counters do not say how faults combine. A CRC
// error on a frame that also carried a dropout is a read error, not a dropout; two adjacent lost
// samples are one step of three periods (two missing), ten or more are a time jump; a lost INS
// epoch next to an INS gap is part of the same gap. The ledger reads the rig's injection counters
// after every step (at most one INS epoch per magnetometer sample, i.e. mag rate > INS rate;
// otherwise the epoch's category is ambiguous and counted in ambiguous_steps) and applies the
// pipeline's documented rules (core/sample_pipeline.hpp: missing, jumps, gaps, reordering) to the
// host times of what the devices actually delivered. It never looks at the pipeline's own state.
#pragma once

#include <cstdint>
#include <string>
#include <vector>

#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/host/hil/loop_core.hpp"
#include "magvec/pipeline/device_pipeline.hpp"

namespace magvec::host::hil {

struct ExpectedCounts {
  std::uint64_t steps{0};
  std::uint64_t mag_delivered{0};  // samples the driver delivers: one record each
  std::uint64_t mag_rejected{0};   // frames/lines the driver rejects (CRC, checksum): read errors
  std::uint64_t mag_not_fresh{0};  // delivered samples of a simulator dropout (SPI)
  std::uint64_t mag_saturated{0};  // delivered samples with a full-scale code
  std::uint64_t mag_stuck{0};      // delivered samples the stuck detector flags
  std::uint64_t mag_device_resets{0};  // delivered samples reporting a device reset
  // Saturated, stuck or reset samples that are not dropouts (a dropout is never an error).
  std::uint64_t mag_device_errors{0};
  std::uint64_t mag_missing{0};     // samples missing from the delivered sequence
  std::uint64_t mag_time_jumps{0};  // steps of the delivered sequence that are clock jumps
  std::uint64_t garbage_bytes{0};
  std::uint64_t att_delivered{0};  // INS epochs the decoder turns into a sample
  std::uint64_t att_invalid{0};    // of those, with attitude invalid
  std::uint64_t att_gaps{0};
  std::uint64_t att_time_jumps{0};
  std::uint64_t att_reordered{0};
  std::uint64_t att_malformed{0};     // corrupted CAN frames
  std::uint64_t att_missing_time{0};  // epochs whose time frame was corrupted, attitude intact
  // Frames received twice and repeats of epochs the decoder had sampled: dropped by the decoder.
  std::uint64_t att_duplicates{0};
  // Spikes the pipeline's screen must flag: on a screenable sample (delivered, not a dropout or
  // a device error) between two screenable, unspiked neighbours on one time base. A spike
  // next to another spike, an unscreenable neighbour or a time jump, or among the screen's
  // first samples, may or may not be flagged: spikes_ambiguous.
  std::uint64_t spikes{0};
  std::uint64_t spikes_ambiguous{0};
  std::uint64_t ambiguous_steps{0};  // steps with more than one INS epoch of mixed categories
};

class FaultLedger {
 public:
  FaultLedger(const drivers::sim::SimRigConfig& rig_config, double mag_rate_hz,
              const HilConfig& config) noexcept
      : link_(rig_config.link),
        ins_rate_hz_(rig_config.ins.rate_hz),
        can_latency_us_(rig_config.ins.can_latency_us),
        latency_comp_us_(config.ins_latency_comp_us),
        max_gap_us_(config.buffer.max_gap_us),
        mag_period_us_(pipeline::period_us_from_hz(mag_rate_hz)),
        ins_period_us_(pipeline::period_us_from_hz(rig_config.ins.rate_hz)) {}

  // After every rig step that produced a sample (HilSession::step() returned true).
  void observe(drivers::sim::SimRig& rig) noexcept {
    ++e_.steps;
    observe_mag(rig);
    observe_ins(rig);
  }

  const ExpectedCounts& expected() const noexcept { return e_; }

 private:
  void observe_mag(drivers::sim::SimRig& rig) noexcept {
    bool delivered = false;
    bool screenable = true;
    if (link_ == drivers::sim::MagLink::kSpi) {
      const drivers::sim::SimAds131Injected& a = rig.adc().injected();
      const bool rejected = a.crc_corrupted != adc_.crc_corrupted;
      delivered = !rejected;
      if (rejected) ++e_.mag_rejected;
      const bool not_fresh = a.not_fresh != adc_.not_fresh;
      // Counted by the sim on the intact frames the driver decodes only.
      const bool saturated = a.saturated_frames != adc_.saturated_frames;
      const bool stuck = a.stuck_frames != adc_.stuck_frames;
      const bool reset = a.reset_frames != adc_.reset_frames;
      const bool invalid = saturated || stuck || reset;
      screenable = !not_fresh && !invalid;
      if (delivered && not_fresh) ++e_.mag_not_fresh;
      if (saturated) ++e_.mag_saturated;
      if (stuck) ++e_.mag_stuck;
      if (reset) ++e_.mag_device_resets;
      if (invalid && !not_fresh) ++e_.mag_device_errors;
      adc_ = a;
    } else {
      const drivers::sim::SimSerialInjected& s = rig.serial().injected();
      const std::uint32_t lines = s.lines - serial_.lines;
      const std::uint32_t bad = s.bad_checksums - serial_.bad_checksums;
      e_.mag_rejected += bad;
      delivered = lines > bad;
      e_.garbage_bytes += s.garbage_bytes - serial_.garbage_bytes;
      serial_ = s;
    }
    if (!delivered) return;
    ++e_.mag_delivered;
    const std::uint64_t t = rig.host_us(rig.last().t_s);
    bool jump = false;
    if (have_mag_) {
      // sample_pipeline.hpp: a step of k periods, < 0.5 or > 10, is a jump; 1.5 < k <= 10 means
      // round(k) - 1 samples are missing.
      const std::uint64_t p = mag_period_us_ > 0 ? mag_period_us_ : 1;
      if (t < mag_us_ || 2 * (t - mag_us_) < p || t - mag_us_ > 10 * p) {
        ++e_.mag_time_jumps;
        jump = true;
      } else if (2 * (t - mag_us_) > 3 * p) {
        e_.mag_missing += (t - mag_us_ + p / 2) / p - 1;
      }
    }
    have_mag_ = true;
    mag_us_ = t;
    const bool spiked = (rig.last().flags & drivers::sim::kFlagSpike) != 0 && screenable;
    observe_spike_screen(t, screenable, spiked, jump);
  }

  // sample_pipeline.hpp's spike screen, one delivered sample late: the sample before this one
  // (pending_) is judged now that its successor is known.
  void observe_spike_screen(std::uint64_t t, bool screenable, bool spiked, bool jump) noexcept {
    const std::uint64_t p = mag_period_us_ > 0 ? mag_period_us_ : 1;
    if (have_pending_ && pending_.screenable) {
      const bool judged = !jump && have_prev_ && screenable && t - prev_us_ <= 10 * p;
      const bool warm = screened_ >= kSpikeWarmup;  // the screen's start-up samples are past
      if (judged && !warm) ++screened_;
      if (pending_.spiked) {
        const bool certain = judged && warm && !spiked && !pending_.after_spike;
        if (certain) {
          ++e_.spikes;
        } else {
          ++e_.spikes_ambiguous;
        }
      }
      // The screen's previous sample: the last one that passed (a spike the screen may have let
      // through makes the next judgement ambiguous: after_spike).
      if (!pending_.spiked) {
        prev_us_ = pending_.t_us;
        have_prev_ = true;
      }
    }
    if (jump) have_prev_ = false;
    const bool after = have_pending_ && pending_.spiked;
    pending_ = {t, screenable, spiked, after};
    have_pending_ = true;
  }

  void observe_ins(drivers::sim::SimRig& rig) noexcept {
    const drivers::sim::SimSbgInjected& i = rig.ins().injected();
    const std::uint32_t sent = i.epochs - ins_.epochs;
    const std::uint32_t gap = i.gap_epochs - ins_.gap_epochs;
    const std::uint32_t lost = i.corrupted_epochs - ins_.corrupted_epochs;
    const std::uint32_t invalid = i.invalid_epochs - ins_.invalid_epochs;
    e_.att_malformed += i.corrupted_frames - ins_.corrupted_frames;
    e_.att_missing_time += i.untimed_epochs - ins_.untimed_epochs;
    e_.att_duplicates += (i.duplicated_frames - ins_.duplicated_frames) +
                         (i.repeated_sampled_epochs - ins_.repeated_sampled_epochs);
    ins_ = i;
    const std::uint32_t n = sent + gap;
    if (n == 0) return;
    // With several epochs in one step, which of them was lost or invalid is unknown unless they
    // all share one category.
    const bool mixed =
        (gap != 0 && gap != n) || (lost != 0 && lost != sent) || (invalid != 0 && invalid != sent);
    if (n > 1 && mixed) ++e_.ambiguous_steps;
    for (std::uint32_t j = 0; j < n; ++j) {
      const std::uint64_t k = epoch_++;
      const bool is_gap = j < gap;
      const bool is_lost = !is_gap && lost != 0;
      if (is_gap || is_lost) continue;
      ++e_.att_delivered;
      if (invalid != 0) ++e_.att_invalid;
      on_ins_time(rig.host_us(static_cast<double>(k) / ins_rate_hz_) + can_latency_us_);
    }
  }

  // sample_pipeline.hpp: backwards by more than max_gap_us is a clock jump, by less a reordering;
  // a spacing above 1.5 INS periods is a gap.
  void on_ins_time(std::uint64_t t_rx_us) noexcept {
    const std::uint64_t t = t_rx_us > latency_comp_us_ ? t_rx_us - latency_comp_us_ : 0;
    if (!have_ins_) {
      ins_us_ = t;
    } else if (t < ins_us_ && ins_us_ - t > max_gap_us_) {
      ++e_.att_time_jumps;
      ins_us_ = t;
    } else if (t < ins_us_) {
      ++e_.att_reordered;
    } else {
      if (2 * (t - ins_us_) > 3 * std::uint64_t{ins_period_us_}) ++e_.att_gaps;
      ins_us_ = t;
    }
    have_ins_ = true;
  }

  drivers::sim::MagLink link_;
  double ins_rate_hz_;
  std::uint32_t can_latency_us_;
  std::uint32_t latency_comp_us_;
  std::uint64_t max_gap_us_;
  std::uint32_t mag_period_us_;
  std::uint32_t ins_period_us_;
  ExpectedCounts e_{};
  drivers::sim::SimAds131Injected adc_{};
  drivers::sim::SimSerialInjected serial_{};
  drivers::sim::SimSbgInjected ins_{};
  std::uint64_t epoch_{0};
  std::uint64_t mag_us_{0};
  std::uint64_t ins_us_{0};
  bool have_mag_{false};
  bool have_ins_{false};
  // Spike screen mirror.
  static constexpr std::uint32_t kSpikeWarmup = 16;  // SamplePipeline::kSpikeWarmup
  struct Pending {
    std::uint64_t t_us{0};
    bool screenable{false};
    bool spiked{false};
    bool after_spike{false};
  };
  Pending pending_{};
  bool have_pending_{false};
  std::uint64_t prev_us_{0};
  bool have_prev_{false};
  std::uint32_t screened_{0};
};

// One counter next to what the injection says it must be.
struct CounterCheck {
  std::string counter;     // where it is counted
  std::string fault;       // what it counts
  std::uint64_t counted;   // the pipeline's value
  std::uint64_t expected;  // from the ledger
  std::uint64_t slack{0};  // cases the ledger cannot decide: counted within expected + slack
  bool ok() const noexcept { return counted >= expected && counted <= expected + slack; }
};

// Every counter of a session (HilSession or anything with the same accessors) next to the
// ledger's expectation. Counters no injected fault may move are expected at 0. Consequences
// without an exact injection count (horizon_expired, extrapolated, no_attitude) are not listed.
template <typename Session>
std::vector<CounterCheck> counter_checks(Session& session, const ExpectedCounts& e) {
  const auto& mc = session.mag_counters();
  const auto& ac = session.attitude_counters();
  const auto& c = session.counters();
  const auto& h = session.loop().health();
  const bool spi = session.rig().config().link == drivers::sim::MagLink::kSpi;
  std::vector<CounterCheck> v;
  auto add = [&v](std::string counter, std::string fault, std::uint64_t counted,
                  std::uint64_t expected) {
    v.push_back({std::move(counter), std::move(fault), counted, expected});
  };
  add("steps", "magnetometer samples simulated", c.steps, e.steps);
  add("records", "one per delivered sample", c.records, e.mag_delivered);
  add("loop.samples", "one per delivered sample", h.samples, e.mag_delivered);
  add("mag.crc_errors", spi ? "ADC frame CRC corrupted" : "serial line checksum wrong",
      mc.crc_errors, e.mag_rejected);
  // Both sources return the rejection from read() (kCrcError for an ADC frame or a serial line).
  add("mag_read_errors",
      spi ? "rejected ADC frames (no record)" : "rejected serial lines (no record)",
      c.mag_read_errors, e.mag_rejected);
  add("mag.samples", "delivered samples", mc.samples, e.mag_delivered);
  add("mag_not_fresh", "simulator dropout (ADC DRDY bits clear)", c.mag_not_fresh, e.mag_not_fresh);
  add("loop.dropouts", "simulator dropout (NaN record, kOutDropout)", h.dropouts, e.mag_not_fresh);
  add("mag.saturated", "full-scale code in a delivered frame", mc.saturated, e.mag_saturated);
  add("mag.stuck", "ADC channel repeating one code (stuck detector)", mc.stuck, e.mag_stuck);
  add("mag.device_resets", "ADC reset mid-stream (STATUS.RESET, re-initialised)", mc.device_resets,
      e.mag_device_resets);
  add("loop.device_errors", "saturated, stuck or reset samples (kOutDeviceError)", h.device_errors,
      e.mag_device_errors);
  add("mag.garbage_bytes", "garbage bytes before a serial line", mc.garbage_bytes, e.garbage_bytes);
  add("mag_missing", "samples absent from the delivered sequence", c.mag_missing, e.mag_missing);
  add("mag_time_jumps", "clock jump (magnetometer stamps)", c.mag_time_jumps, e.mag_time_jumps);
  add("mag.malformed", "(no fault)", mc.malformed, 0);
  add("mag.overflows", "(no fault)", mc.overflows, 0);
  add("mag.timeouts", "(no fault)", mc.timeouts, 0);
  add("mag.bus_errors", "(no fault)", mc.bus_errors, 0);
  add("att.malformed", "CAN frame truncated", ac.malformed, e.att_malformed);
  add("att.missing_time", "EKF_INFO truncated, attitude frame intact", ac.missing_time,
      e.att_missing_time);
  add("att.duplicates", "CAN frame received twice, sampled epoch repeated", ac.duplicates,
      e.att_duplicates);
  add("att.samples", "INS epochs decoded", ac.samples, e.att_delivered);
  add("att_samples", "INS epochs decoded", c.att_samples, e.att_delivered);
  add("att_invalid", "INS attitude-invalid window", c.att_invalid, e.att_invalid);
  add("att_gaps", "INS gap, lost epochs, forward clock jump", c.att_gaps, e.att_gaps);
  add("att_time_jumps", "backward clock jump (INS stamps)", c.att_time_jumps, e.att_time_jumps);
  add("att_reordered", "(no fault)", c.att_reordered, e.att_reordered);
  add("att_rejected", "(no fault)", c.att_rejected, 0);
  add("att.bus_errors", "(no fault)", ac.bus_errors, 0);
  add("queue_full", "(no fault)", c.queue_full, 0);
  add("sink_errors", "(no fault)", c.sink_errors, 0);
  add("ledger.ambiguous_steps", "INS epochs the ledger cannot attribute", e.ambiguous_steps, 0);
  v.push_back({"spikes", "spikes between two clean neighbours (kOutSpike)", c.spikes, e.spikes,
               e.spikes_ambiguous});
  return v;
}

inline bool all_ok(const std::vector<CounterCheck>& checks) noexcept {
  for (const CounterCheck& c : checks)
    if (!c.ok()) return false;
  return true;
}

}  // namespace magvec::host::hil
