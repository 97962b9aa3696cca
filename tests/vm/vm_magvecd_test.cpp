// VM system test: magvecd end to end on real Linux drivers inside the guest.
// A "rig" in this process plays the simulator's continuous-rotation scenario (drivers/sim
// scenario_rotation, rates set below, fixed seed) in real time through the guest kernel's devices,
// as the hardware would deliver it:
//   - INS: SimSbgIns's SBG CAN frames of each 100 Hz epoch, sent on vcan0 through a SocketCAN
//     socket kInsLatencyUs after the epoch's time (the INS's output latency; the daemon's
//     latency_comp_us is set to it), so the epochs that bracket a magnetometer sample arrive after
//     it and the daemon interpolates within its fusion horizon;
//   - ADC: SimAds131Device's channel codes of each conversion (read back from a simulated frame, so
//     the encoding is the simulator's, inverse of the daemon's transfer coefficients), written to
//     /dev/magvec_adc_feed, whose FIFO the virtual ADS131M04 (toolchain/vm/magvec_vspi.c) serves
//     on /dev/spidev0.0, one conversion per data frame;
//   - DRDY: a falling edge on the gpio-sim line (its `pull` attribute) once the codes are queued.
// The rig thread runs SCHED_FIFO above the daemon (as hardware events do not wait for software).
// magvecd runs in real mode (spidev + libgpiod + SocketCAN, realtime on, the li solve on its
// worker thread) and publishes on LCM udpm over the guest's loopback; this process subscribes.
// Checks: each conversion has exactly one output (matched by its DRDY time stamp and its raw
// reading) and no conversion was read after the next one was queued (what a real ADC's single
// result latch would have lost), also while the solve ran; the calibrated E/N/U against the
// simulator's TRUE attitude and field within 1.3x the floor computed from the true attitude and
// the configured noise (tests/host/hil/enu_floor.hpp, the HIL tests' floor), |h| within the
// magnetometer noise of the true model's own intensity error. Latencies are printed, never
// asserted.
// Reference field: none is configured (no scalar magnetometer, no reference_field_nT), so the
// daemon takes F from WMM2025 at the position the INS reports in its EKF_POS/EKF_ALTITUDE frames
// on vcan0 (SimSbgIns sends them every 10th epoch, of its default site). The rig's field is the
// model's at that site and date, without an anomaly: the accuracy claims keep their floors, and
// what is checked beyond them is that the position frames reached the model through the bus and
// the outputs say so (model-reference flag, sigma_f with the model's 1-sigma). The model's data
// files are in the guest's /share/magvec/geomag (run-suite --file), where an installed magvecd
// looks for them.
// Each check is its own test case; the run happens once, in SetUpTestSuite.
#include <fcntl.h>
#include <gtest/gtest.h>
#include <pthread.h>
#include <sched.h>
#include <signal.h>
#include <sys/stat.h>
#include <sys/wait.h>
#include <time.h>
#include <unistd.h>

#include <algorithm>
#include <array>
#include <atomic>
#include <cerrno>
#include <cmath>
#include <cstdint>
#include <cstdio>
#include <cstring>
#include <deque>
#include <fstream>
#include <lcm/lcm-cpp.hpp>
#include <limits>
#include <memory>
#include <mutex>
#include <sstream>
#include <string>
#include <thread>
#include <utility>
#include <vector>

#include "host/hil/enu_floor.hpp"
#include "magvec/core/compensator.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/drivers/ads131m04.hpp"
#include "magvec/drivers/linux/socketcan_bus.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/host/daemon/config.hpp"
#include "magvec/host/daemon/position_reference.hpp"
#include "magvec/host/daemon/sim_setup.hpp"
#include "magvec_lcm/attitude.hpp"
#include "magvec_lcm/calibrated_vector.hpp"
#include "magvec_lcm/calibration_state.hpp"
#include "magvec_lcm/health.hpp"
#include "magvec_lcm/mag_sample.hpp"
#include "magvec_lcm/pipeline_event.hpp"
#include "vm_env.hpp"

namespace {

using magvec::vmtest::env;
using magvec::vmtest::read_sysfs_number;

constexpr double kRateHz = 45.0;  // magnetometer: not a divisor of the INS rate, so the samples
                                  // fall at varying fractions between INS epochs
constexpr double kInsRateHz = 100.0;
constexpr std::uint32_t kInsLatencyUs = 10'000;  // INS epoch time -> its frames on the bus
constexpr std::uint32_t kHorizonUs = 50'000;     // >= INS period + latency + guest jitter
constexpr std::uint32_t kSamples = 900;          // 20 s of scenario
constexpr double kStartS = 0.1;                  // scenario time of the first sample
constexpr std::uint64_t kSeed = 7;
// Rotation like a calibration manoeuvre: heading 30 deg/s, pitch +-40 deg and roll +-35 deg both
// peaking at 60 deg/s. The tilts take the field's direction in the sensor frame (inclination 62
// deg) across the li calibrator's coverage threshold (10 of 32 cells) after ~5 s; the simulator's
// default +-30/+-20 deg never do.
constexpr double kHeadingRateDegS = 30.0;
constexpr double kPitchAmpDeg = 40.0;
constexpr double kRollAmpDeg = 35.0;
constexpr double kPeakTiltRateDegS = 60.0;
// A rig event later than this restarts the schedule from now (counted): a VM stall must not send
// the missed events as a burst (the conversions whose INS epochs and edge it put on two time
// bases are not scored: see rig_time_error_us).
constexpr std::uint64_t kLateNs = 2'000'000;
// The rig sleeps until this long before an event, does what is not time-critical (queues the
// conversion's codes, sends the epoch's frames but its attitude frame), then spins to the due
// time and makes the one time-stamped write: a wake-up under emulation is a few hundred us late,
// and at 60 deg/s 100 us of stamp error is an attitude error of 0.006 deg (the INS noise is
// 0.015 deg).
constexpr std::uint64_t kSpinNs = 1'000'000;
constexpr const char* kUrl = "udpm://239.255.76.67:7667?ttl=0";
constexpr const char* kWork = "/tmp/magvecd_vm";
constexpr double kPi = 3.14159265358979323846;

std::uint64_t mono_ns() {
  timespec ts{};
  clock_gettime(CLOCK_MONOTONIC, &ts);
  return static_cast<std::uint64_t>(ts.tv_sec) * 1'000'000'000ull +
         static_cast<std::uint64_t>(ts.tv_nsec);
}

void sleep_until_ns(std::uint64_t t_ns) {
  timespec ts{};
  ts.tv_sec = static_cast<time_t>(t_ns / 1'000'000'000ull);
  ts.tv_nsec = static_cast<long>(t_ns % 1'000'000'000ull);
  while (clock_nanosleep(CLOCK_MONOTONIC, TIMER_ABSTIME, &ts, nullptr) == EINTR) {
  }
}

std::string read_file(const std::string& path) {
  std::ifstream f(path);
  std::stringstream ss;
  ss << f.rdbuf();
  return ss.str();
}

// WMM2025 at the position SimSbgIns reports (its default site) today: the field the rig's
// magnetometer sees. Evaluated once, so the run and the scoring use the same field; the daemon
// evaluates the model when the first fix arrives, seconds later (secular variation ~1e-4 nT).
const magvec::host::geomag::ReferenceField& site_field() {
  static const magvec::host::geomag::ReferenceField field = [] {
    const magvec::drivers::sim::SimSite sim_site{};
    magvec::host::geomag::Site site;
    site.lat_deg = sim_site.lat_deg;
    site.lon_deg = sim_site.lon_deg;
    site.height_m = sim_site.altitude_m + sim_site.undulation_m;  // above the WGS84 ellipsoid
    return magvec::host::geomag::MagneticModel::wmm2025().field(
        site, magvec::host::daemon::PositionReference::utc_decimal_year_now());
  }();
  return field;
}

magvec::drivers::sim::ScenarioConfig scenario() {
  magvec::drivers::sim::ScenarioConfig sc = magvec::drivers::sim::scenario_rotation();
  sc.h_n_nT = site_field().enu_nT;
  sc.rate_hz = kRateHz;
  sc.num_samples = kSamples;
  // The INS epochs run from t = 0: the first samples have epochs before them to interpolate from.
  sc.start_time_s = kStartS;
  sc.rotation.heading_rate_deg_s = kHeadingRateDegS;
  sc.rotation.pitch_amp_deg = kPitchAmpDeg;
  sc.rotation.pitch_period_s = 2 * kPi * kPitchAmpDeg / kPeakTiltRateDegS;
  sc.rotation.roll_amp_deg = kRollAmpDeg;
  sc.rotation.roll_period_s = 2 * kPi * kRollAmpDeg / kPeakTiltRateDegS;
  return sc;
}

// li_min_samples: 100 samples of this rotation (2-3 s) pass the coverage rule but leave
// directions the held-out samples visit; validation refused 13 of 30 seeds there, and most of
// them when a stalled guest stamps samples late (docs/equations.md E-TO-3). 150: none of 30
// seeds refused, 2 of 30 with late stamps; applied by sample 423 (and the worker's solve time).
std::string config_text() {
  char buf[2048];
  std::snprintf(buf, sizeof buf,
                "[daemon]\nstate_dir = \"%s/state\"\nrealtime = true\nhealth_period_s = 1.0\n"
                "status_period_s = 0.5\n[lcm]\nurl = \"%s\"\n"
                "[devices.magnetometer]\nlink = \"spi\"\nrate_hz = %.1f\nspi_device = \"%s\"\n"
                "drdy_chip = \"%s\"\ndrdy_line = %s\n"
                "[devices.ins]\ncan_interface = \"%s\"\nrate_hz = %.1f\nlatency_comp_us = %u\n"
                "fusion_horizon_us = %u\n"
                "[calibration]\nmode = \"li\"\nli_min_samples = 150\nvalidation_samples = 100\n"
                "reference_model = \"wmm2025\"\nsolve_on_worker = true\n",
                kWork, kUrl, kRateHz, env("MAGVEC_TEST_SPIDEV", "/dev/spidev0.0").c_str(),
                env("MAGVEC_TEST_GPIOCHIP").c_str(), env("MAGVEC_TEST_GPIO_LINE", "0").c_str(),
                env("MAGVEC_TEST_CAN", "vcan0").c_str(), kInsRateHz, kInsLatencyUs, kHorizonUs);
  return buf;
}

struct OutputSample {
  std::array<double, 3> raw{};
  std::array<double, 3> enu{};
  double f{0};
  double sigma_f{0};
  std::uint32_t flags{0};
  std::int32_t cal_id{0};
  std::int64_t t_us{0};
  std::uint64_t rx_us{0};  // when this process received it (guest monotonic)
};

struct RawSample {
  std::int64_t t_us{0};
  std::uint64_t rx_us{0};
};

// What the rig did for one conversion.
struct RigSample {
  double t_s{0};                      // scenario time
  magvec::core::Vec3<double> m_nT{};  // the reading the codes carry
  std::uint64_t due_us{0};            // DRDY edge due (guest monotonic)
  std::uint64_t pull_us{0};           // just before the falling edge was written
  // The rig's wake before writing this conversion, later than it asked for (guest monotonic): a
  // guest that did not run (the emulator's host thread descheduled: qemu TCG, one vCPU) wakes late.
  std::uint64_t wake_late_us{0};
  long long overruns_after{0};  // the emulated ADC's overrun count just after the edge was written
};

struct VmRun {
  bool ran{false};
  std::string setup_error;
  std::string daemon_stderr;
  int exit_status{-1};
  double stop_ms{-1};
  bool cal_file{false};
  bool rig_realtime{false};
  // DRDY path: the kernel stamps of the daemon's raw samples less the rig's writes of their
  // edges, median of the last 31 (the subscriber computes it; the rig reads it).
  std::mutex pull_mu;
  std::deque<std::uint64_t> pulls;  // rig's DRDY writes not yet matched (guest monotonic us)
  std::deque<double> drdy_paths;
  std::atomic<double> drdy_path_us{0};
  double rig_seconds{0};
  std::vector<double> restarts_s;  // scenario times where the rig restarted its schedule
  // Guest stalls seen by the watchdog (StallWatch): [from, to] guest monotonic us.
  std::vector<std::pair<std::uint64_t, std::uint64_t>> stalls;
  std::uint32_t late_events{0};  // time-stamped writes more than 50 us late (no restart)
  std::uint64_t can_frames{0};
  std::uint32_t epochs{0};
  std::uint64_t can_looped{0};  // CAN frames the rig's listener received
  // Per INS epoch number: when its attitude frame was due on the bus and the kernel's receive
  // stamp of it (guest monotonic us; 0 when not seen).
  struct EpochSent {
    std::uint64_t due_us{0};
    std::uint64_t stamp_us{0};
    std::uint64_t send_us{0};  // just before its attitude frame was sent
  };
  std::vector<EpochSent> epochs_sent;
  std::uint32_t fed{0};
  long long vspi_fed{-1}, vspi_frames{-1}, vspi_overruns{-1}, vspi_max_queued{-1};
  long long vspi_overruns0{0};  // the count before the run
  std::vector<RigSample> samples;
  std::vector<OutputSample> outputs;
  std::vector<RawSample> raws;
  std::vector<magvec_lcm::calibration_state> states;
  std::vector<std::pair<std::uint64_t, std::uint64_t>> solves;  // [solving seen, result seen] us
  std::uint64_t applied_rx_us{0};  // the first "applied" state received (guest monotonic)
  std::size_t attitudes{0};
  magvec_lcm::health health{};
  bool have_health{false};
};

VmRun g_run;

class Subscriber {
 public:
  explicit Subscriber(VmRun& run) : run_(run), lcm_(kUrl) {}
  bool good() { return lcm_.good(); }
  void start() {
    lcm_.subscribe("MAGVEC_OUTPUT", &Subscriber::on_output, this);
    lcm_.subscribe("MAGVEC_RAW_MAG", &Subscriber::on_raw, this);
    lcm_.subscribe("MAGVEC_CAL_STATE", &Subscriber::on_state, this);
    lcm_.subscribe("MAGVEC_PIPELINE", &Subscriber::on_event, this);
    lcm_.subscribe("MAGVEC_ATTITUDE", &Subscriber::on_attitude, this);
    lcm_.subscribe("MAGVEC_HEALTH", &Subscriber::on_health, this);
    thread_ = std::thread([this] {
      while (!stop_)
        lcm_.handleTimeout(50);
    });
  }
  void stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }

 private:
  static std::uint64_t now_us() { return mono_ns() / 1000; }
  void on_output(const lcm::ReceiveBuffer*, const std::string&,
                 const magvec_lcm::calibrated_vector* m) {
    OutputSample o;
    o.rx_us = now_us();
    for (std::size_t i = 0; i < 3; ++i) {
      o.raw[i] = m->raw_nT[i];
      o.enu[i] = m->h_enu_nT[i];
    }
    o.f = m->f_nT;
    o.sigma_f = m->sigma_f_nT;
    o.flags = static_cast<std::uint32_t>(m->flags);
    o.cal_id = m->cal_id;
    o.t_us = m->t_us;
    std::lock_guard<std::mutex> lock(mu_);
    run_.outputs.push_back(o);
  }
  void on_raw(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::mag_sample* m) {
    const std::uint64_t rx = now_us();
    {
      std::lock_guard<std::mutex> lock(run_.pull_mu);
      std::uint64_t pull = 0;
      while (!run_.pulls.empty() && static_cast<std::int64_t>(run_.pulls.front()) <= m->t_us) {
        pull = run_.pulls.front();
        run_.pulls.pop_front();
      }
      const auto d = static_cast<double>(m->t_us) - static_cast<double>(pull);
      if (pull != 0 && d < 2'000) {
        run_.drdy_paths.push_back(d);
        if (run_.drdy_paths.size() > 31) run_.drdy_paths.pop_front();
        std::vector<double> v(run_.drdy_paths.begin(), run_.drdy_paths.end());
        std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
        run_.drdy_path_us = v[v.size() / 2];
      }
    }
    std::lock_guard<std::mutex> lock(mu_);
    run_.raws.push_back(RawSample{m->t_us, rx});
  }
  void on_state(const lcm::ReceiveBuffer*, const std::string&,
                const magvec_lcm::calibration_state* m) {
    const std::uint64_t rx = now_us();
    std::lock_guard<std::mutex> lock(mu_);
    // A solve window opens with the first "solving" state and closes with its SOLVE_RESULT.
    if (m->state == "solving" && (run_.solves.empty() || run_.solves.back().second != 0))
      run_.solves.emplace_back(rx, 0);
    if (m->state == "applied" && run_.applied_rx_us == 0) run_.applied_rx_us = rx;
    run_.states.push_back(*m);
  }
  void on_event(const lcm::ReceiveBuffer*, const std::string&,
                const magvec_lcm::pipeline_event* m) {
    const std::uint64_t rx = now_us();
    std::lock_guard<std::mutex> lock(mu_);
    if (m->kind == magvec_lcm::pipeline_event::SOLVE_RESULT && !run_.solves.empty() &&
        run_.solves.back().second == 0)
      run_.solves.back().second = rx;
  }
  void on_attitude(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::attitude*) {
    std::lock_guard<std::mutex> lock(mu_);
    ++run_.attitudes;
  }
  void on_health(const lcm::ReceiveBuffer*, const std::string&, const magvec_lcm::health* m) {
    std::lock_guard<std::mutex> lock(mu_);
    run_.health = *m;
    run_.have_health = true;
  }

  VmRun& run_;
  lcm::LCM lcm_;
  std::thread thread_;
  std::atomic<bool> stop_{false};
  std::mutex mu_;
};

bool write_pull(int fd, const char* value) {
  const auto n = static_cast<ssize_t>(std::strlen(value));
  return pwrite(fd, value, static_cast<std::size_t>(n), 0) == n;
}

std::string vspi_param(const char* name);

// A SCHED_FIFO thread above the rig and the daemon that wakes every kWatchPeriodNs: a wake more
// than kLateNs late means no task of the guest ran in between (qemu TCG with one vCPU: the
// emulator's host thread was descheduled, or the guest kernel was busy with interrupts off). Those
// intervals are the time the daemon could not have used.
class StallWatch {
 public:
  static constexpr std::uint64_t kWatchPeriodNs = 2'000'000;
  explicit StallWatch(VmRun& run) : run_(run) {}
  void start() {
    thread_ = std::thread([this] { loop(); });
  }
  void stop() {
    stop_ = true;
    if (thread_.joinable()) thread_.join();
  }
  ~StallWatch() { stop(); }

 private:
  void loop() {
    sched_param sp{};
    sp.sched_priority = 40;
    (void)pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp);
    std::uint64_t next = mono_ns() + kWatchPeriodNs;
    while (!stop_) {
      sleep_until_ns(next);
      const std::uint64_t now = mono_ns();
      if (now > next + kLateNs) run_.stalls.emplace_back(next / 1000, now / 1000);
      next = std::max(next + kWatchPeriodNs, now + kWatchPeriodNs / 2);
    }
  }
  VmRun& run_;
  std::atomic<bool> stop_{false};
  std::thread thread_;
};

// The real-time claims (no late read, interpolated outputs at the INS-noise floor) are judged only
// on a guest that ran: under plain emulation on a loaded host the whole guest stops for
// milliseconds at a time (seen here: 1 s of 16 s, 275 stalls), and then neither the rig's timing
// nor the daemon's can be what hardware would give. The share of the run the watchdog saw the
// guest stopped; above kMaxStalledShare those claims are reported as not judged, with the figure.
constexpr double kMaxStalledShare = 0.02;

// A claim the rig's timing cannot support is reported NOT JUDGED (ctest: skipped) on the host's
// clock. On the instruction-count clock (run-suite's default, exported to /init on the kernel
// command line) the guest is never stopped and the rig is on time by construction: there the same
// condition is a failure, so that these claims cannot pass unjudged.
bool guest_clock_counts_instructions() {
  return env("MAGVEC_VM_CLOCK") == "icount";
}
#define MAGVEC_NOT_JUDGED(why)                                                         \
  do {                                                                                 \
    if (guest_clock_counts_instructions())                                             \
      FAIL() << (why) << " -- on the instruction-count clock, where it cannot happen"; \
    GTEST_SKIP() << (why);                                                             \
  } while (0)

// Guest time [from_us, to_us] the watchdog saw the guest stopped.
double stalled_us(const VmRun& run, std::uint64_t from_us, std::uint64_t to_us) {
  double us = 0;
  for (const auto& st : run.stalls) {
    const std::uint64_t a = std::max(st.first, from_us), b = std::min(st.second, to_us);
    if (b > a) us += static_cast<double>(b - a);
  }
  return us;
}

double stalled_share(const VmRun& run) {
  // No rig run: nothing to excuse (the claims are then judged, and fail on the missing data).
  return run.rig_seconds > 0
             ? 1e-6 * stalled_us(run, 0, std::numeric_limits<std::uint64_t>::max()) /
                   run.rig_seconds
             : 0.0;
}

// The rig: plays the scenario through the guest's devices on a schedule of guest monotonic time.
class Rig {
 public:
  Rig(VmRun& run, int feed, int pull, magvec::drivers::SocketCanBus& can,
      magvec::drivers::SocketCanBus& listener)
      : run_(run), feed_(feed), pull_(pull), can_(can), listener_(listener) {}

  void play(magvec::drivers::sim::SimRig& rig) {
    attitude_id_ = rig.config().ins.ids.ekf_quat;
    t0_ns_ = mono_ns() + 100'000'000ull;
    while (rig.step()) {
      const magvec::drivers::sim::SimSample& s = rig.last();
      // The codes the simulated ADC latched: read back through its SPI frame.
      std::array<std::uint8_t, magvec::drivers::ads131::kFrameBytes> tx{}, rx{};
      rig.adc().transfer(tx, rx);
      std::array<std::int32_t, 4> codes{};
      for (std::size_t ch = 0; ch < 4; ++ch)
        codes[ch] = magvec::drivers::ads131::decode_word24(
            rx.data() + magvec::drivers::ads131::kWordBytes * (1 + ch));
      magvec::hal::EdgeEvent e;
      while (rig.adc().wait_edge(e, 0) == magvec::hal::Status::kOk) {
      }
      // INS epochs up to t - latency were emitted by step(): each goes on the bus at its own
      // time (epoch + latency), before this sample's edge.
      take_ins(rig);
      send_ins_until(s.t_s);
      const std::uint64_t wake_late_ns = wake_before(s.t_s);
      if (::write(feed_, codes.data(), sizeof codes) == static_cast<ssize_t>(sizeof codes))
        ++run_.fed;
      // The DRDY path (pull -> gpio-sim -> line event stamp) is tens of us longer than the CAN
      // path while the daemon waits on the line: the edge is written that much earlier, so that
      // both kinds of stamp fall at the same offset from their due times.
      const double lead_us = std::max(0.0, run_.drdy_path_us.load() - can_path_us());
      const auto lead_ns = static_cast<std::uint64_t>(lead_us * 1000);
      const std::uint64_t due = on_time(s.t_s, lead_ns) + lead_ns;
      RigSample r;
      r.t_s = s.t_s;
      r.m_nT = s.m_nT;
      r.due_us = due / 1000;
      r.pull_us = mono_ns() / 1000;
      r.wake_late_us = wake_late_ns / 1000;
      {
        std::lock_guard<std::mutex> lock(run_.pull_mu);
        run_.pulls.push_back(r.pull_us);
      }
      write_pull(pull_, "pull-down");
      write_pull(pull_, "pull-up");
      // The rig runs SCHED_FIFO on the guest's one CPU: the daemon cannot read between the edge
      // and this count, so a late read of the previous conversion is counted after it.
      r.overruns_after = read_sysfs_number(vspi_param("fed_overruns"));
      run_.samples.push_back(r);
      drain_listener(0);
    }
    // The epochs that bracket the last samples.
    const double t_last = run_.samples.empty() ? 0.0 : run_.samples.back().t_s;
    rig.ins().run_until(t_last + 3.0 / kInsRateHz);
    take_ins(rig);
    send_ins_until(std::numeric_limits<double>::infinity());
    run_.rig_seconds = static_cast<double>(mono_ns() - t0_ns_) * 1e-9;
    drain_listener(200'000);
  }

 private:
  struct Pending {
    std::uint64_t due_us;  // scenario time of arrival (epoch + latency)
    magvec::hal::CanFrame frame;
  };

  void take_ins(magvec::drivers::sim::SimRig& rig) {
    magvec::hal::CanFrame f;
    const std::uint64_t epoch_us = rig.config().time.epoch_us;
    while (rig.ins().receive(f, 0) == magvec::hal::Status::kOk)
      pending_.push_back(Pending{f.t_us - epoch_us, f});
  }

  std::uint64_t due_ns(double t_s) const {
    return t0_ns_ + static_cast<std::uint64_t>(std::llround(t_s * 1e9));
  }

  // Sleeps until kSpinNs before scenario time t_s; returns how much later than that it woke.
  std::uint64_t wake_before(double t_s) {
    const std::uint64_t due = due_ns(t_s);
    if (due <= kSpinNs) return 0;
    sleep_until_ns(due - kSpinNs);
    const std::uint64_t now = mono_ns();
    return now > due - kSpinNs ? now - (due - kSpinNs) : 0;
  }

  // Spins until scenario time t_s less lead_ns; a late arrival restarts the schedule. Returns the
  // time it aimed at.
  std::uint64_t on_time(double t_s, std::uint64_t lead_ns = 0) {
    const std::uint64_t due = due_ns(t_s) - lead_ns;
    std::uint64_t now = mono_ns();
    while (now < due)
      now = mono_ns();
    if (now > due + kLateNs) {
      run_.restarts_s.push_back(t_s);
      t0_ns_ += now - due;
      return now;
    }
    if (now > due + 50'000) ++run_.late_events;
    return due;
  }

  void send_ins_until(double t_s) {
    while (!pending_.empty() && static_cast<double>(pending_.front().due_us) * 1e-6 <= t_s) {
      const std::uint64_t due_us = pending_.front().due_us;
      const double t_epoch_s = static_cast<double>(due_us) * 1e-6;
      wake_before(t_epoch_s);
      // The epoch's frames in bus order, its attitude frame (whose receive time stamps the
      // epoch) on time: the frames before it go early, those after it (the position, every few
      // epochs) right behind it.
      std::size_t in_epoch = 0, attitude_at = 0;
      bool has_attitude = false;
      while (in_epoch < pending_.size() && pending_[in_epoch].due_us == due_us) {
        if (pending_[in_epoch].frame.id == attitude_id_) {
          attitude_at = in_epoch;
          has_attitude = true;
        }
        ++in_epoch;
      }
      std::uint32_t sent = 0;
      std::uint64_t due = 0, send_us = 0;
      for (std::size_t i = 0; i < in_epoch; ++i) {
        const magvec::hal::CanFrame f = pending_.front().frame;
        pending_.pop_front();
        const bool attitude = i == attitude_at;
        if (attitude) due = on_time(t_epoch_s);
        const std::uint64_t t_send_us = mono_ns() / 1000;
        if (can_.send(f) == magvec::hal::Status::kOk) ++sent;
        if (attitude) send_us = t_send_us;
      }
      run_.can_frames += sent;
      ++run_.epochs;
      const auto n = static_cast<std::size_t>(
          std::llround((static_cast<double>(due_us) - kInsLatencyUs) * 1e-6 * kInsRateHz));
      if (run_.epochs_sent.size() <= n) run_.epochs_sent.resize(n + 1);
      run_.epochs_sent[n] = VmRun::EpochSent{due / 1000, 0, send_us};
      if (has_attitude) awaiting_stamp_.push_back(n);  // the listener pairs attitude frames
      drain_listener(0);
    }
  }

  // The rig's own listener on vcan0 sees every frame the daemon's socket sees, with the same
  // kernel stamp (taken when the frame is queued, during the send): the stamp of each epoch's
  // attitude frame. Read without waiting, so that a deferred delivery (the network softirq runs
  // after the real-time tasks) never holds up the next event.
  void drain_listener(std::uint32_t timeout_us) {
    magvec::hal::CanFrame f;
    while (run_.can_looped < run_.can_frames &&
           listener_.receive(f, timeout_us) == magvec::hal::Status::kOk) {
      ++run_.can_looped;
      if (f.id == attitude_id_ && !awaiting_stamp_.empty()) {
        VmRun::EpochSent& e = run_.epochs_sent[awaiting_stamp_.front()];
        awaiting_stamp_.pop_front();
        e.stamp_us = f.t_us;
        can_path_.push_back(static_cast<double>(e.stamp_us) - static_cast<double>(e.send_us));
        if (can_path_.size() > 31) can_path_.pop_front();
      }
    }
  }

  VmRun& run_;
  int feed_;
  int pull_;
  magvec::drivers::SocketCanBus& can_;
  magvec::drivers::SocketCanBus& listener_;
  // Median (last 31 epochs) of the attitude frame's kernel stamp less its send time (us).
  double can_path_us() {
    if (can_path_.empty()) return 0;
    std::vector<double> v(can_path_.begin(), can_path_.end());
    std::nth_element(v.begin(), v.begin() + static_cast<std::ptrdiff_t>(v.size() / 2), v.end());
    return v[v.size() / 2];
  }

  std::deque<double> can_path_;
  std::uint32_t attitude_id_{0};
  std::deque<Pending> pending_;
  std::deque<std::size_t> awaiting_stamp_;  // epochs sent whose attitude frame was not read yet
  std::uint64_t t0_ns_{0};
};

std::string vspi_param(const char* name) {
  return env("MAGVEC_TEST_VSPI_PARAMS", "/sys/module/magvec_vspi/parameters") + "/" + name;
}

void run_once(VmRun& run) {
  namespace sim = magvec::drivers::sim;
  namespace daemon = magvec::host::daemon;
  run.ran = true;
  ::mkdir(kWork, 0755);
  try {
    (void)site_field();
  } catch (const magvec::host::geomag::GeomagError& e) {
    run.setup_error = std::string("the rig's field from WMM2025: ") + e.what();
    return;
  }
  const sim::ScenarioConfig sc = scenario();
  const std::string text = config_text();
  const std::string config_path = std::string(kWork) + "/magvecd.toml";
  std::ofstream(config_path) << text;
  const daemon::Config config = daemon::parse_config(text, config_path);

  // Devices of the rig.
  const int feed = ::open(env("MAGVEC_TEST_ADC_FEED", "/dev/magvec_adc_feed").c_str(), O_WRONLY);
  const int pull = ::open(env("MAGVEC_TEST_GPIO_PULL").c_str(), O_WRONLY);
  magvec::drivers::OsError err;
  magvec::drivers::SocketCanConfig cc;
  cc.interface = env("MAGVEC_TEST_CAN", "vcan0");
  cc.receive_error_frames = false;
  auto can = magvec::drivers::SocketCanBus::open(cc, &err);
  auto listener = magvec::drivers::SocketCanBus::open(cc, &err);
  if (feed < 0 || pull < 0 || !can || !listener) {
    run.setup_error = "rig devices: feed " + std::to_string(feed) + ", pull " +
                      std::to_string(pull) + ", can " + err.message + " (errno " +
                      std::to_string(errno) + ")";
    return;
  }
  write_pull(pull, "pull-up");  // DRDY idles high; a conversion is a falling edge
  const long long fed0 = read_sysfs_number(vspi_param("fed_conversions"));
  const long long frames0 = read_sysfs_number(vspi_param("fed_frames"));
  const long long overruns0 = read_sysfs_number(vspi_param("fed_overruns"));

  Subscriber sub(run);
  if (!sub.good()) {
    run.setup_error = "LCM udpm unavailable in the guest (lo multicast route?)";
    return;
  }
  sub.start();  // before the rig turns real-time: the subscriber thread stays SCHED_OTHER

  sched_param sp{};

  const std::string err_path = std::string(kWork) + "/magvecd.err";
  const pid_t pid = fork();
  if (pid == 0) {
    const int fd = ::open(err_path.c_str(), O_WRONLY | O_CREAT | O_TRUNC, 0644);
    dup2(fd, 2);
    dup2(fd, 1);
    const std::string exe = env("MAGVEC_TEST_MAGVECD", "/bin/magvecd");
    execl(exe.c_str(), exe.c_str(), "--config", config_path.c_str(), static_cast<char*>(nullptr));
    _exit(127);
  }
  // Ready once it logged its devices (opened, ADC initialised) - or it exited.
  const std::uint64_t t_start = mono_ns();
  bool ready = false;
  while (mono_ns() - t_start < 30'000'000'000ull) {
    if (read_file(err_path).find("devices: ") != std::string::npos) {
      ready = true;
      break;
    }
    int st = 0;
    if (waitpid(pid, &st, WNOHANG) == pid) {
      run.exit_status = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
      break;
    }
    usleep(50'000);
  }
  if (ready) {
    usleep(300'000);
    // The rig above the daemon's SCHED_FIFO priority (config default 20): the devices' events
    // happen on time whatever the daemon is doing, as with hardware.
    sp.sched_priority = 30;
    run.rig_realtime = pthread_setschedparam(pthread_self(), SCHED_FIFO, &sp) == 0;
    sim::Simulator s(sc, kSeed);
    sim::SimRigConfig rc = daemon::sim_rig_config(config);
    rc.ins.rate_hz = kInsRateHz;
    rc.ins.can_latency_us = kInsLatencyUs;
    rc.ins_lead_s = 0;  // each epoch arrives its latency after its time, as on the vehicle
    sim::SimRig rig(s, rc);
    Rig player(run, feed, pull, *can, *listener);
    StallWatch watch(run);
    watch.start();
    player.play(rig);
    watch.stop();
    sp.sched_priority = 0;
    pthread_setschedparam(pthread_self(), SCHED_OTHER, &sp);
    sleep(1);
    const std::uint64_t t_term = mono_ns();
    kill(pid, SIGTERM);
    int st = 0;
    while (waitpid(pid, &st, WNOHANG) != pid) {
      if (mono_ns() - t_term > 10'000'000'000ull) {
        kill(pid, SIGKILL);
        waitpid(pid, &st, 0);
        break;
      }
      usleep(10'000);
    }
    run.stop_ms = static_cast<double>(mono_ns() - t_term) * 1e-6;
    run.exit_status = WIFEXITED(st) ? WEXITSTATUS(st) : 128 + WTERMSIG(st);
  } else if (run.exit_status < 0) {
    kill(pid, SIGKILL);
    waitpid(pid, nullptr, 0);
    run.setup_error = "magvecd did not report its devices within 30 s";
  }
  usleep(200'000);
  sub.stop();
  ::close(feed);
  ::close(pull);
  run.vspi_fed = read_sysfs_number(vspi_param("fed_conversions")) - fed0;
  run.vspi_frames = read_sysfs_number(vspi_param("fed_frames")) - frames0;
  run.vspi_overruns = read_sysfs_number(vspi_param("fed_overruns")) - overruns0;
  run.vspi_overruns0 = overruns0;
  run.vspi_max_queued = read_sysfs_number(vspi_param("fed_max_queued"));
  run.daemon_stderr = read_file(err_path);
  struct stat sb {};
  run.cal_file = ::stat((std::string(kWork) + "/state/cal.json").c_str(), &sb) == 0;
}

// Index of the rig sample whose falling edge produced the DRDY stamp t_us, or -1: the stamp
// falls after the rig's write of that edge and before the next sample's.
long match_sample(const std::vector<RigSample>& s, std::int64_t t_us) {
  const auto it = std::upper_bound(
      s.begin(), s.end(), t_us,
      [](std::int64_t t, const RigSample& r) { return t < static_cast<std::int64_t>(r.pull_us); });
  if (it == s.begin()) return -1;
  const auto k = static_cast<long>(it - s.begin()) - 1;
  const double period_us = 1e6 / kRateHz;
  if (static_cast<double>(t_us - static_cast<std::int64_t>(
                                     s[static_cast<std::size_t>(k)].pull_us)) > 0.5 * period_us)
    return -1;
  return k;
}

bool in_solve(const VmRun& run, std::uint64_t t_us) {
  for (const auto& w : run.solves)
    if (t_us >= w.first && (w.second == 0 || t_us <= w.second)) return true;
  return false;
}

struct Stat {
  double worst{0};
  double sum{0};
  std::size_t n{0};
  void add(double v) {
    worst = std::max(worst, v);
    sum += v;
    ++n;
  }
  double mean() const { return n ? sum / static_cast<double>(n) : 0; }
};

class MagvecdVm : public ::testing::Test {
 protected:
  static void SetUpTestSuite() {
    if (!g_run.ran && !env("MAGVEC_IN_VM").empty()) run_once(g_run);
  }
  void SetUp() override {
    if (env("MAGVEC_IN_VM").empty()) GTEST_SKIP() << "needs the VM (toolchain/vm)";
    ASSERT_TRUE(g_run.setup_error.empty()) << g_run.setup_error << "\n" << g_run.daemon_stderr;
  }
};

TEST_F(MagvecdVm, DaemonRunsOnRealDevicesAndStopsCleanly) {
  EXPECT_NE(g_run.daemon_stderr.find("ADS131M04 on /dev/spidev"), std::string::npos)
      << g_run.daemon_stderr;
  EXPECT_EQ(g_run.exit_status, 0) << g_run.daemon_stderr;
  EXPECT_LT(g_run.stop_ms, 1000.0) << "SIGTERM -> exit";
  Stat ins;
  for (const VmRun::EpochSent& e : g_run.epochs_sent)
    if (e.stamp_us != 0) ins.add(static_cast<double>(e.stamp_us) - static_cast<double>(e.due_us));
  std::printf(
      "rig (SCHED_FIFO %s, DRDY write -> stamp at the end %.0f us): %u samples fed in %.2f s, %u "
      "INS epochs (%llu CAN frames, kernel "
      "stamp - due: mean %.0f us, worst %.0f us), %zu schedule restarts, %u writes > 50 us late; "
      "stop %.0f ms\n",
      g_run.rig_realtime ? "on" : "refused", g_run.drdy_path_us.load(), g_run.fed,
      g_run.rig_seconds, g_run.epochs, static_cast<unsigned long long>(g_run.can_frames),
      ins.mean(), ins.worst, g_run.restarts_s.size(), g_run.late_events, g_run.stop_ms);
  const auto& h = g_run.health;
  std::printf(
      "health: mag %lld (crc %lld, not fresh %lld, missing %lld, time jumps %lld, device resets "
      "%lld), att %lld (malformed %lld, invalid %lld, gaps %lld, rejected %lld, duplicates %lld), "
      "records %lld, no attitude %lld; %zu attitude messages\n",
      static_cast<long long>(h.mag_samples), static_cast<long long>(h.mag_crc_errors),
      static_cast<long long>(h.mag_not_fresh), static_cast<long long>(h.mag_missing),
      static_cast<long long>(h.mag_time_jumps), static_cast<long long>(h.mag_device_resets),
      static_cast<long long>(h.att_samples), static_cast<long long>(h.att_malformed),
      static_cast<long long>(h.att_invalid), static_cast<long long>(h.att_gaps),
      static_cast<long long>(h.att_rejected), static_cast<long long>(h.att_duplicates),
      static_cast<long long>(h.records), static_cast<long long>(h.no_attitude), g_run.attitudes);
  std::array<std::size_t, 8> flag_count{};
  for (const OutputSample& o : g_run.outputs)
    for (std::size_t b = 0; b < flag_count.size(); ++b)
      flag_count[b] += (o.flags >> b) & 1u;
  std::printf("output flags (bit: count):");
  for (std::size_t b = 0; b < flag_count.size(); ++b)
    std::printf(" %zu: %zu", b, flag_count[b]);
  std::printf("\n");
  Stat drdy;  // kernel stamp of each DRDY edge - its due time
  for (const OutputSample& o : g_run.outputs) {
    const long k = match_sample(g_run.samples, o.t_us);
    if (k >= 0)
      drdy.add(static_cast<double>(o.t_us) -
               static_cast<double>(g_run.samples[static_cast<std::size_t>(k)].due_us));
  }
  std::printf("DRDY kernel stamp - due: mean %.0f us, worst %.0f us\n", drdy.mean(), drdy.worst);
  {
    std::vector<double> spin, path;
    for (const OutputSample& o : g_run.outputs) {
      const long k = match_sample(g_run.samples, o.t_us);
      if (k < 0) continue;
      const RigSample& rs = g_run.samples[static_cast<std::size_t>(k)];
      spin.push_back(static_cast<double>(rs.pull_us) - static_cast<double>(rs.due_us));
      path.push_back(static_cast<double>(o.t_us) - static_cast<double>(rs.pull_us));
    }
    std::sort(spin.begin(), spin.end());
    std::sort(path.begin(), path.end());
    if (!spin.empty())
      std::printf(
          "DRDY edges (us, p10/p50/p90): write - due %.0f/%.0f/%.0f (written early by the "
          "path lead), kernel stamp - write %.0f/%.0f/%.0f\n",
          spin[spin.size() / 10], spin[spin.size() / 2], spin[spin.size() * 9 / 10],
          path[path.size() / 10], path[path.size() / 2], path[path.size() * 9 / 10]);
  }
  EXPECT_EQ(g_run.fed, kSamples);
  EXPECT_EQ(h.att_samples, static_cast<std::int64_t>(g_run.epochs));
  EXPECT_EQ(h.att_malformed, 0);
  EXPECT_EQ(h.att_rejected, 0);
  // An INS gap only where the rig restarted its schedule after a stall.
  EXPECT_LE(h.att_gaps, static_cast<std::int64_t>(g_run.restarts_s.size()));
  EXPECT_EQ(g_run.can_looped, g_run.can_frames) << "CAN frames not delivered on vcan0";
}

// Every conversion the emulated ADC produced has exactly one output, none was read after the next
// one was queued (a real ADC's single result latch would have lost it), also while the calibration
// solve ran on the daemon's worker thread.
TEST_F(MagvecdVm, NoConversionLostWhileTheSolveRuns) {
  const VmRun& r = g_run;
  const std::vector<OutputSample>& o = r.outputs;
  std::printf(
      "emulated ADC: %lld conversions queued, %lld read as new data, %lld read late "
      "(overrun of a single latch), at most %lld queued\n",
      r.vspi_fed, r.vspi_frames, r.vspi_overruns, r.vspi_max_queued);
  EXPECT_EQ(r.vspi_fed, static_cast<long long>(kSamples));
  EXPECT_EQ(r.vspi_frames, r.vspi_fed) << "conversions the daemon read as new data";
  std::string not_judged;  // the late-read claim on a stalling guest (see below)
  // Each late read attributed to its conversion (RigSample::overruns_after): conversion j read
  // after j+1 was queued is counted between the edges j+1 and j+2. Conversion j+1 is queued when
  // the rig wakes for it, so the daemon had from edge j to that wake to read j. A guest stall
  // (StallWatch; or the rig restarting its schedule) stops every guest task: when the stalls in
  // that window add up to more than half a period, the daemon had less than half a period of guest
  // time for the read and the late read is the emulator's. Every other late read is the daemon's
  // and fails the test.
  {
    const std::vector<RigSample>& rs = r.samples;
    const long long end = r.vspi_overruns0 + r.vspi_overruns;
    const double period_us = 1e6 / kRateHz;
    long long excused = 0, daemon = 0;
    std::printf("guest stalls seen by the watchdog: %zu, %.0f ms in all\n", r.stalls.size(),
                1e-3 * stalled_us(r, 0, std::numeric_limits<std::uint64_t>::max()));
    for (std::size_t j = 0; j + 1 < rs.size(); ++j) {
      const RigSample& next = rs[j + 1];
      const long long d =
          (j + 2 < rs.size() ? rs[j + 2].overruns_after : end) - next.overruns_after;
      if (d <= 0) continue;
      // The window: edge j to the rig's wake for j+1 (kSpinNs before its edge's due time).
      const std::uint64_t from = rs[j].pull_us;
      const std::uint64_t to = next.due_us - kSpinNs / 1000 + next.wake_late_us;
      const double window_stalled_us = stalled_us(r, from, to);
      const bool restart =
          std::find(r.restarts_s.begin(), r.restarts_s.end(), next.t_s) != r.restarts_s.end();
      const bool stalled = restart || window_stalled_us > 0.5 * period_us;
      // Where it fell in the calibration's course (which daemon work ran next to it).
      const auto since_ms = [&](std::uint64_t t0) {
        return t0 == 0 ? std::nan("")
                       : 1e-3 * (static_cast<double>(from) - static_cast<double>(t0));
      };
      std::printf(
          "late read of conversion %zu (x%lld): guest stalled %.1f ms of the %.1f ms before the "
          "next was queued%s -> %s (edge %.1f ms after the solve result, %.1f ms after "
          "'applied' was received)\n",
          j, d, 1e-3 * window_stalled_us, 1e-3 * static_cast<double>(to - from),
          restart ? ", the rig restarted its schedule" : "",
          stalled ? "the emulator's" : "the daemon's",
          since_ms(r.solves.empty() ? 0 : r.solves.back().second), since_ms(r.applied_rx_us));
      (stalled ? excused : daemon) += d;
    }
    // Counted before the edge of conversion 1: no read can be late there.
    daemon += (rs.size() > 1 ? rs[1].overruns_after : end) - r.vspi_overruns0;
    EXPECT_EQ(daemon + excused, r.vspi_overruns);
    const double share = stalled_share(r);
    if (share > kMaxStalledShare) {
      if (daemon > 0) {
        char why[200];
        std::snprintf(why, sizeof why,
                      "NOT JUDGED: %lld late reads the daemon's by the rule above, but the guest "
                      "was stopped %.1f %% of the run (limit %.0f %%)",
                      daemon, 100 * share, 100 * kMaxStalledShare);
        not_judged = why;
      }
    } else {
      EXPECT_EQ(daemon, 0) << "conversions read after the next one was queued, with the guest "
                              "running ("
                           << excused << " more next to guest stalls)";
    }
  }
  ASSERT_TRUE(r.have_health) << "no MAGVEC_HEALTH message";
  const auto& h = r.health;
  EXPECT_EQ(h.mag_samples, static_cast<std::int64_t>(kSamples));
  EXPECT_EQ(h.records, static_cast<std::int64_t>(kSamples));
  EXPECT_EQ(h.mag_crc_errors, 0);
  EXPECT_EQ(h.mag_not_fresh, 0) << "a read without new data: an edge without its conversion";
  EXPECT_EQ(h.mag_read_errors, 0);
  EXPECT_EQ(o.size(), static_cast<std::size_t>(kSamples)) << "outputs published";
  EXPECT_EQ(r.raws.size(), static_cast<std::size_t>(kSamples)) << "raw samples published";

  // Output k is conversion k: its DRDY stamp follows the rig's edge k and its raw reading is
  // the one conversion k carried (to the ADC's resolution).
  std::vector<int> outputs_of(r.samples.size(), 0);
  std::size_t unmatched = 0, wrong_raw = 0;
  for (const OutputSample& s : o) {
    const long k = match_sample(r.samples, s.t_us);
    if (k < 0) {
      ++unmatched;
      continue;
    }
    const RigSample& rs = r.samples[static_cast<std::size_t>(k)];
    ++outputs_of[static_cast<std::size_t>(k)];
    for (std::size_t i = 0; i < 3; ++i)
      if (std::abs(s.raw[i] - rs.m_nT[static_cast<int>(i)]) > 0.1) {
        ++wrong_raw;
        break;
      }
  }
  std::size_t missing = 0, duplicated = 0;
  for (int c : outputs_of) {
    missing += c == 0 ? 1 : 0;
    duplicated += c > 1 ? 1 : 0;
  }
  EXPECT_EQ(unmatched, 0u) << "outputs whose stamp follows no rig edge";
  EXPECT_EQ(missing, 0u) << "conversions without an output";
  EXPECT_EQ(duplicated, 0u) << "conversions with more than one output";
  EXPECT_EQ(wrong_raw, 0u) << "outputs whose raw reading is not their conversion's";
  // The cadence counter sees the rig's schedule restarts as gaps, nothing else.
  std::int64_t gaps = 0;
  const auto p = static_cast<std::int64_t>(std::llround(1e6 / kRateHz));
  for (std::size_t i = 1; i < o.size(); ++i) {
    const std::int64_t dt = o[i].t_us - o[i - 1].t_us;
    if (2 * dt > 3 * p && dt <= 10 * p) gaps += (dt + p / 2) / p - 1;
  }
  EXPECT_EQ(h.mag_missing, gaps) << "cadence gaps (rig restarts: " << r.restarts_s.size() << ")";

  // The solve windows (guest time from the "solving" state to the SOLVE_RESULT event) and the
  // per-sample latencies: DRDY edge -> raw sample published (the read), and -> calibrated output
  // (includes the fusion horizon's wait for the INS epoch after the sample).
  ASSERT_FALSE(r.solves.empty()) << "no solve seen";
  std::size_t in_window = 0, in_window_out = 0;
  for (std::size_t k = 0; k < r.samples.size(); ++k)
    if (in_solve(r, r.samples[k].pull_us)) {
      ++in_window;
      in_window_out += outputs_of[k] == 1 ? 1u : 0u;
    }
  Stat read_in, read_out, out_in, out_out;
  for (const RawSample& s : r.raws) {
    const double d = static_cast<double>(s.rx_us) - static_cast<double>(s.t_us);
    (in_solve(r, static_cast<std::uint64_t>(s.t_us)) ? read_in : read_out).add(d);
  }
  // The last conversion has no next one: the spike screen (core::SamplePipeline) holds it until
  // the stop's flush, so it is left out of the latencies.
  for (std::size_t i = 0; i + 1 < o.size(); ++i) {
    const OutputSample& s = o[i];
    const double d = static_cast<double>(s.rx_us) - static_cast<double>(s.t_us);
    (in_solve(r, static_cast<std::uint64_t>(s.t_us)) ? out_in : out_out).add(d);
  }
  for (const auto& w : r.solves)
    std::printf("solve window (guest, as seen by the subscriber): %.1f ms\n",
                w.second ? 1e-3 * static_cast<double>(w.second - w.first) : -1.0);
  std::printf("during the solves: %zu conversions, %zu with exactly one output\n", in_window,
              in_window_out);
  std::printf(
      "DRDY -> raw sample received: during solves worst %.1f ms (n %zu), outside worst "
      "%.1f ms mean %.1f ms (n %zu)\n",
      1e-3 * read_in.worst, read_in.n, 1e-3 * read_out.worst, 1e-3 * read_out.mean(), read_out.n);
  std::printf(
      "DRDY -> output received (the sample waits for its INS epochs and the next conversion): "
      "during solves worst %.1f ms (n %zu), outside worst %.1f ms mean %.1f ms (n %zu, the last "
      "one, flushed at the stop, left out)\n",
      1e-3 * out_in.worst, out_in.n, 1e-3 * out_out.worst, 1e-3 * out_out.mean(), out_out.n);
  const std::string& log = r.daemon_stderr;
  for (const char* what : {"solve on the worker", "persisted to"}) {
    for (std::size_t at = log.find(what); at != std::string::npos; at = log.find(what, at + 1)) {
      const std::size_t bol = log.rfind('\n', at);
      const std::size_t from = bol == std::string::npos ? 0 : bol + 1;
      std::printf("daemon: %s\n", log.substr(from, log.find('\n', at) - from).c_str());
    }
  }
  EXPECT_NE(log.find("solve on the worker"), std::string::npos) << log;
  EXPECT_EQ(in_window_out, in_window);
  // Last, after every other assertion ran (a failure above still fails the test).
  if (!not_judged.empty()) MAGVEC_NOT_JUDGED(not_judged);
}

// The rig's own timing error for a conversion (us): the scenario time at which the daemon's
// interpolation between the kernel stamps of the bracketing INS epochs (less the compensated
// latency) places the DRDY stamp, minus the conversion's true time. The VM's scheduling, not the
// daemon; NaN when an epoch was not seen.
double rig_time_error_us(const VmRun& r, const RigSample& s, std::int64_t drdy_us) {
  const auto e = static_cast<std::size_t>(std::floor(s.t_s * kInsRateHz + 1e-9));
  if (e + 1 >= r.epochs_sent.size()) return std::numeric_limits<double>::quiet_NaN();
  const VmRun::EpochSent& a = r.epochs_sent[e];
  const VmRun::EpochSent& b = r.epochs_sent[e + 1];
  if (a.stamp_us == 0 || b.stamp_us == 0 || b.stamp_us <= a.stamp_us)
    return std::numeric_limits<double>::quiet_NaN();
  // The daemon's attitude time of an epoch: its stamp less the compensated latency.
  const double a_us = static_cast<double>(a.stamp_us) - kInsLatencyUs;
  const double w =
      (static_cast<double>(drdy_us) - a_us) / static_cast<double>(b.stamp_us - a.stamp_us);
  return ((static_cast<double>(e) + w) / kInsRateHz - s.t_s) * 1e6;
}

// Whether the INS epoch a conversion waits for (the first whose attitude time, its kernel stamp
// less the compensated latency, is at or after the conversion's DRDY stamp) reached the guest's
// socket later than the fusion horizon after that stamp, or not at all. Then the pipeline's rule
// is to extrapolate and flag (docs/architecture.md, delayed fusion horizon): the rig's frame was
// late (a stalled guest), not the daemon.
bool ins_epoch_past_horizon(const VmRun& r, std::int64_t drdy_us) {
  for (const VmRun::EpochSent& e : r.epochs_sent) {
    if (e.stamp_us == 0) continue;
    if (static_cast<double>(e.stamp_us) - kInsLatencyUs < static_cast<double>(drdy_us)) continue;
    return static_cast<double>(e.stamp_us) > static_cast<double>(drdy_us) + kHorizonUs;
  }
  return true;
}

// The calibration's data: the rig's timing of the conversions before the first solve (the li
// one-step fit uses their attitudes, so a late DRDY edge there is an attitude error in the fit).
// Above kRigTimeErrorUs RMS the calibration is the emulator's.
constexpr double kRigTimeErrorUs = 100.0;  // 0.006 deg at 60 deg/s
struct CalDataTiming {
  double rms_us{0};
  std::size_t n{0};
  std::size_t off_time{0};
  bool judged() const { return rms_us <= kRigTimeErrorUs; }
  std::string not_judged() const {
    char why[240];
    std::snprintf(why, sizeof why,
                  "NOT JUDGED: the calibration's data were delivered by the rig with a time error "
                  "RMS of %.0f us (limit %.0f us; %zu of %zu off time): the calibration is the "
                  "emulator's",
                  rms_us, kRigTimeErrorUs, off_time, n);
    return why;
  }
};
CalDataTiming cal_data_timing(const VmRun& r) {
  CalDataTiming t;
  double sq = 0;
  const std::uint64_t solve_rx = r.solves.empty() ? 0 : r.solves.front().first;
  for (const OutputSample& o : r.outputs) {
    const long k = match_sample(r.samples, o.t_us);
    if (k < 0 || o.cal_id != 0 || o.rx_us >= solve_rx) continue;
    const double dt_us = rig_time_error_us(r, r.samples[static_cast<std::size_t>(k)], o.t_us);
    if (!std::isfinite(dt_us)) continue;
    sq += dt_us * dt_us;
    ++t.n;
    if (std::abs(dt_us) > kRigTimeErrorUs) ++t.off_time;
  }
  t.rms_us = t.n ? std::sqrt(sq / static_cast<double>(t.n)) : 0.0;
  return t;
}

TEST_F(MagvecdVm, CalibratesAppliesAndPersists) {
  bool applied = false;
  std::int32_t persisted = 0;
  std::string failed;  // the daemon's refusal of its candidate ("failure reason"), if any
  for (const auto& s : g_run.states) {
    applied = applied || (s.state == "applied" && s.cal_id >= 1);
    persisted = std::max(persisted, s.persisted_cal_id);
    // Refusals of the candidate itself; any other failure (no reference, ...) is judged as one.
    using magvec::core::cal_failure_name;
    using magvec::core::CalFailure;
    if (s.state == "failed" &&
        (s.failure == cal_failure_name(CalFailure::kValidationFailed) ||
         s.failure == cal_failure_name(CalFailure::kVectorValidationFailed) ||
         s.failure == cal_failure_name(CalFailure::kSolverRejected)))
      failed = s.failure + " " + s.solver_reason;
  }
  // A candidate fitted to data the rig delivered off time (late DRDY edges of a stalled guest
  // pair samples with later attitudes) may be refused by validation or the solver, which is the
  // daemon doing its job (docs/equations.md E-TO-3). Then nothing may have been applied or
  // persisted; the apply path is NOT JUDGED on that run.
  const CalDataTiming cal = cal_data_timing(g_run);
  if (!applied && !failed.empty() && !cal.judged()) {
    EXPECT_EQ(persisted, 0);
    EXPECT_FALSE(g_run.cal_file) << "state/cal.json written for a refused calibration";
    for (const OutputSample& o : g_run.outputs)
      ASSERT_EQ(o.cal_id, 0) << "an output with a calibration that was refused";
    MAGVEC_NOT_JUDGED("refused (" + failed + ") and " + cal.not_judged());
  }
  EXPECT_TRUE(applied) << g_run.states.size() << " state messages\n" << g_run.daemon_stderr;
  EXPECT_GE(persisted, 1);
  EXPECT_TRUE(g_run.cal_file) << "state/cal.json";
  std::size_t calibrated = 0;
  for (const OutputSample& o : g_run.outputs)
    calibrated += o.cal_id >= 1 ? 1 : 0;
  EXPECT_GE(calibrated, kSamples / 3) << "outputs with the calibration applied";
}

// No reference is configured: F comes from WMM2025 at the position the INS frames on vcan0 carry.
// The daemon announces the model at the fix, and every calibrated output carries the
// model-reference flag and a sigma_f that includes the model's 1-sigma (the fluxgate sees the
// model's field here, but a survey site has anomalies the model does not know).
TEST_F(MagvecdVm, ReferenceFieldFromTheModelAtTheInsPositionOnTheBus) {
  const std::string& log = g_run.daemon_stderr;
  EXPECT_NE(log.find("reference field from wmm2025 at the INS position"), std::string::npos) << log;
  const std::size_t announced = log.find("reference field: WMM2025 at 47.9000 N 11.3000 E 647 m");
  EXPECT_NE(announced, std::string::npos) << log;
  const double sigma_model = magvec::host::daemon::PositionReference::sigma_nT();
  std::size_t calibrated = 0, flagged = 0, with_sigma = 0;
  for (const OutputSample& o : g_run.outputs) {
    if (o.cal_id < 1) continue;
    ++calibrated;
    flagged += (o.flags & magvec::core::kOutModelReference) != 0 ? 1 : 0;
    with_sigma += o.sigma_f >= sigma_model ? 1 : 0;
  }
  std::printf(
      "model F %.1f nT at the site (%s, %.4f); %zu calibrated outputs, %zu flagged "
      "model-referenced, %zu with sigma_f >= %.0f nT\n",
      site_field().total_nT, site_field().model.c_str(), site_field().decimal_year, calibrated,
      flagged, with_sigma, sigma_model);
  if (calibrated == 0)
    GTEST_SKIP() << "no calibration applied (judged in CalibratesAppliesAndPersists)";
  EXPECT_EQ(flagged, calibrated);
  EXPECT_EQ(with_sigma, calibrated);
}

// The calibrated outputs against the simulator's TRUE attitude and field at each conversion's
// scenario time: E/N/U within 1.3x the floor from the true attitude and the configured noise (INS
// angle noise through the interpolation between epochs, magnetometer noise: enu_floor.hpp), the
// bound of the HIL test of an in-loop calibration; |h| within the magnetometer noise (0.3 nT) of
// what the true model makes of the same readings (the li fit from ~100 motion-decimated samples
// adds its parameter error). Scored: the conversions the rig delivered on time (its DRDY stamp
// within kRigTimeErrorUs of the true time relative to the INS epochs' stamps); the others (VM
// stalls, schedule restarts) are counted and scored separately, printed only.
// The calibration is judged by the same rule: its data are the conversions before the solve, and
// the li one-step fit estimates the misalignment from their attitudes, so a DRDY stamp off by
// 1 ms at 60 deg/s is a 0.06 deg (50 nT) error in its data. When the rig's time error RMS over
// them is above kRigTimeErrorUs, the calibration is the emulator's and the claims are NOT JUDGED
// (seen on a slow host, TCG: 0.9-1.1 ms RMS, two thirds of them off time, with the guest stalled
// under 2 %); the numbers are still printed.
TEST_F(MagvecdVm, InterpolatedOutputsWithinTheTrueFloor) {
  const VmRun& r = g_run;
  if (stalled_share(r) > kMaxStalledShare)
    MAGVEC_NOT_JUDGED(
        "NOT JUDGED: the guest was stopped " + std::to_string(100 * stalled_share(r)) +
        " % of the run (limit " + std::to_string(100 * kMaxStalledShare) + " %, " +
        std::to_string(r.stalls.size()) + " stalls, " + std::to_string(r.restarts_s.size()) +
        " rig schedule restarts): the outputs' timing is the emulator's");
  const magvec::drivers::sim::ScenarioConfig sc = scenario();
  const magvec::drivers::sim::Simulator truth(sc, kSeed);
  const magvec::core::Compensator<double> true_model(sc.truth);
  magvec::test::EnuFloorAccumulator enu, enu_all;
  double f_err = 0, f_floor = 0;
  std::size_t n_f = 0, flagged = 0, flagged_late_ins = 0, off_time = 0;
  double time_err_sq = 0;
  const CalDataTiming cal = cal_data_timing(r);
  std::printf("before the solve: %zu conversions, rig time error RMS %.0f us, %zu off time\n",
              cal.n, cal.rms_us, cal.off_time);
  std::string not_judged = cal.judged() ? std::string() : cal.not_judged();
  const bool judged = not_judged.empty();
  for (const OutputSample& o : r.outputs) {
    const long k = match_sample(r.samples, o.t_us);
    if (k < 0 || o.cal_id < 1) continue;
    const RigSample& rs = r.samples[static_cast<std::size_t>(k)];
    if ((o.flags & (magvec::core::kOutDropout | magvec::core::kOutDeviceError |
                    magvec::core::kOutNoAttitude | magvec::core::kOutAttExtrapolated)) != 0) {
      const bool only_extrapolated =
          (o.flags & (magvec::core::kOutDropout | magvec::core::kOutDeviceError |
                      magvec::core::kOutNoAttitude)) == 0;
      ++(only_extrapolated && ins_epoch_past_horizon(r, o.t_us) ? flagged_late_ins : flagged);
      continue;
    }
    const magvec::core::Vec3<double> h_true = truth.true_field_at(rs.t_s);
    const magvec::core::Vec3<double> enu_out(o.enu[0], o.enu[1], o.enu[2]);
    const magvec::core::Mat3<double> r_true = truth.true_attitude_at(rs.t_s);
    const double f = magvec::test::epoch_fraction(rs.t_s + sc.ins_latency_s, kInsRateHz);
    enu_all.add(enu_out, r_true, h_true, sc.truth, sc.mag_noise_nT, sc.ins_noise_deg, f);
    const double dt_us = rig_time_error_us(r, rs, o.t_us);
    if (!(std::abs(dt_us) <= kRigTimeErrorUs)) {
      ++off_time;
      continue;
    }
    time_err_sq += dt_us * dt_us;
    enu.add(enu_out, r_true, h_true, sc.truth, sc.mag_noise_nT, sc.ins_noise_deg, f);
    magvec::core::Compensated<double> c;
    const magvec::core::Vec3<double> raw(o.raw[0], o.raw[1], o.raw[2]);
    if (true_model.compensate(raw, &c)) {
      f_err += (o.f - h_true.norm()) * (o.f - h_true.norm());
      f_floor += (c.intensity - h_true.norm()) * (c.intensity - h_true.norm());
      ++n_f;
    }
  }
  std::printf(
      "scored %llu calibrated outputs (rig time error RMS %.0f us); left out: %zu delivered off "
      "time by the rig (> %.0f us), %zu flagged, %zu extrapolated because the rig's INS frame "
      "came after the horizon\n",
      static_cast<unsigned long long>(enu.n),
      enu.n ? std::sqrt(time_err_sq / static_cast<double>(enu.n)) : 0.0, off_time, kRigTimeErrorUs,
      flagged, flagged_late_ins);
  // Enough on-time outputs for the 1.3 margin below to be more than 4 sigma of the RMS estimate
  // (an RMS over n independent Gaussian errors has a relative 1-sigma of 1/sqrt(2 n):
  // 0.3 >= 4 / sqrt(2 n) for n >= 89). A slow emulator delivers fewer on time (the rig's own
  // timing, > kRigTimeErrorUs); below this the daemon cannot be judged.
  constexpr std::uint64_t kMinScored = 100;
  EXPECT_EQ(flagged, 0u) << "calibrated outputs without an interpolated attitude although the "
                            "INS epoch after them was in within the horizon";
  if (judged) {
    ASSERT_GE(enu.n, kMinScored) << "too few calibrated outputs to score: " << off_time
                                 << " delivered off time by the rig, " << flagged
                                 << " flagged by the daemon";
  }
  const char* names[3] = {"E", "N", "U"};
  for (int k = 0; k < 3; ++k) {
    std::printf("%s: RMS error %.2f nT, floor %.2f nT, ratio %.3f (all %llu: %.3f)\n", names[k],
                enu.error(k), enu.floor(k), enu.error(k) / enu.floor(k),
                static_cast<unsigned long long>(enu_all.n), enu_all.error(k) / enu_all.floor(k));
    if (!judged || enu.n == 0) continue;
    EXPECT_GT(enu.floor(k), 3.0) << names[k] << ": the INS noise is there";
    EXPECT_LE(enu.error(k), 1.3 * enu.floor(k)) << names[k];
  }
  if (n_f == 0) {
    if (!judged) MAGVEC_NOT_JUDGED(not_judged);
    FAIL() << "no calibrated output to score";
  }
  const double f_rms = std::sqrt(f_err / static_cast<double>(n_f));
  const double f_floor_rms = std::sqrt(f_floor / static_cast<double>(n_f));
  std::printf("|h|: RMS error %.3f nT, floor %.3f nT, ratio %.3f\n", f_rms, f_floor_rms,
              f_rms / f_floor_rms);
  if (!judged) MAGVEC_NOT_JUDGED(not_judged);
  EXPECT_LE(f_rms, f_floor_rms + sc.mag_noise_nT);
}

}  // namespace
