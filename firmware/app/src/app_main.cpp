// The firmware application: a fixed, deterministic scenario run end to end on the MCU.
//   Simulator (survey scenario, Li et al. 2023 truth, 50 Hz, fixed seed) -> simulated ADS131M04
//   (SPI + DRDY) and SBG INS (CAN) speaking the real bytes -> the real codecs (Ads131Fluxgate,
//   CanAttitudeSource) -> pipeline::DevicePipeline (the one sample pipeline: AttitudeBuffer with
//   the delayed fusion horizon -> core::SensorLoop<Scalar, core::EkfCalibrator>, Scalar =
//   MAGVEC_APP_SCALAR) -> OutputRecords -> hal::RecordSink (RecordLineSink: semihosting console,
//   or the board UART) -- the same pipeline as `magvec run`, magvecd and replay, without an OS.
// The INS frames arrive as on real hardware (after the magnetometer sample they bracket, CAN
// latency included); a sample waits in the pipeline's queue until they are there.
// Acquisition and processing are split as on hardware: the board's sample clock (SysTick under
// qemu) interrupts once per magnetometer period and its handler does what the data-ready
// interrupts do (steps the simulated rig, reads the drivers) into a bounded single-producer/
// single-consumer queue; the main loop feeds the pipeline from the queue, in order. The
// calibrator's batch solve (alignment fit + Li form) is not run inside a sample: the loop
// (external_solve) freezes the calibrator and raises a solve ticket, the main loop solves when
// the queue is empty (idle time, preempted by the ticks) and installs the result when the
// pipeline has processed kSolveInstallRecords more samples, a fixed point in the sample stream,
// so the records do not depend on how long the solve took (the M7 image and the host twin stay
// bit-identical). Under qemu the clock needs -icount (virtual time = instructions) for a
// deterministic interleaving; the host twin has no clock and acquires from its main loop.
// Boot: the ParamStore (FlashParamStore over SimFlash) is read; with no stored calibration the
// loop starts calibrating (ScalarEkf: initial fit, filter, then the misalignment solve, held-out
// validation). When the loop applies the calibration it is stored in the ParamStore, a power-cut
// sweep checks that every interrupted store leaves the old or the new blob, the blob is reloaded
// from flash as after a reboot and installed as the active calibration (it must be bit-identical).
// Report: "MV <key> ..." lines; exact values as IEEE-754 double bit patterns in hex, parsed by
// tests/mcu/compare_app_runs.py. Arguments (space separated):
//   quiet      no record lines and no test statistics (instruction counting)
//   baseline   skip the core work (attitude buffer, loop): devices + codecs only
//   uart       records to the board UART (mps2: CMSDK UART0 = qemu -serial) instead of the console
//   n=<k>      stop after k magnetometer samples
//   tick_us=<k> sample clock period in microseconds (default kDefaultTickUs; boards with a clock)
// Exit code 0 when every on-target check passed (power-cut sweep, reload, calibration applied).
// MAGVEC_APP_VECTOR=1 builds the same image with the online vector calibration filter as the
// calibrator (core::VectorCalibrator, calibrator mode `vector-ekf`, docs/equations.md E-VF) in
// place of the scalar EKF; the solve is then a read of the filter, still run in idle time.
#include <algorithm>
#include <array>
#include <atomic>
#include <cstdint>
#include <cstring>
#include <limits>

#include "magvec/app/board.hpp"
#include "magvec/app/image_profile.hpp"
#include "magvec/app/line_writer.hpp"
#include "magvec/app/record_line_sink.hpp"
#include "magvec/core/ekf_calibrator.hpp"
#include "magvec/core/sensor_loop.hpp"
#include "magvec/core/vector_calibrator.hpp"
#include "magvec/drivers/ads131_fluxgate.hpp"
#include "magvec/drivers/param_store.hpp"
#include "magvec/drivers/sbg_can.hpp"
#include "magvec/drivers/sim/sim_devices.hpp"
#include "magvec/drivers/sim/simulator.hpp"
#include "magvec/drivers/sim_flash.hpp"
#include "magvec/pipeline/device_pipeline.hpp"
#include "magvec/pipeline/solve_schedule.hpp"

#ifndef MAGVEC_APP_SCALAR
#error "MAGVEC_APP_SCALAR (float or double) must be defined by the build"
#endif
#ifndef MAGVEC_APP_VECTOR
#define MAGVEC_APP_VECTOR 0
#endif

namespace magvec::app {
namespace {

using Scalar = MAGVEC_APP_SCALAR;
namespace sim = drivers::sim;

#if MAGVEC_APP_VECTOR
using Calibrator = VectorImageCalibrator<Scalar>;
#else
using Calibrator = EkfImageCalibrator<Scalar>;
#endif
using Loop = core::SensorLoop<Scalar, Calibrator>;
// 64 INS epochs (0.64 s at 100 Hz); 8 queued magnetometer samples (160 ms at 50 Hz) cover the
// 50 ms fusion horizon with room for late CAN bursts.
using Pipeline = pipeline::DevicePipeline<Scalar, Calibrator, 64, 8>;

#if MAGVEC_APP_VECTOR
core::VectorCalibratorConfig<Scalar> make_cal_config(const sim::ScenarioConfig& s) noexcept {
  return vector_calibrator_config<Scalar>(s);
}
const char* cal_code_name(std::uint8_t code) noexcept {
  return core::vec_cal_code_name(code);
}
#else
core::EkfCalibratorConfig<Scalar> make_cal_config(const sim::ScenarioConfig& s) noexcept {
  return ekf_calibrator_config<Scalar>(s);
}
const char* cal_code_name(std::uint8_t code) noexcept {
  return core::ekf_cal_code_name(code);
}
#endif

// Sample clock period under qemu -icount shift=0 (one instruction per virtual nanosecond): 500 us
// = 500 000 instructions per magnetometer sample, of which the tick handler's simulated world
// (simulator, rig, codecs: ~340 000 on the M4F, soft double) takes the larger part; the main loop
// gets roughly what a 168 MHz M4F has per sample at 1 kHz.
#if MAGVEC_APP_VECTOR
// The vector image: 3 360 us = 3.36 M instructions per sample, what a 168 MHz M4F has at the
// scenario's 50 Hz. Its calibrator starts from data inside one sample (two batch fits and the
// replay passes, ~60 M instructions, E-VF-1): at 500 us the acquisition queue would overflow
// during that sample (as it would on an M4F sampling at 300 Hz); at 50 Hz it holds.
constexpr std::uint32_t kDefaultTickUs = 3360;
#else
constexpr std::uint32_t kDefaultTickUs = 500;
#endif
// Acquisition queue: 64 events (one tick is a magnetometer sample and ~2 INS frames) hold ~20
// sample periods of main-loop stall (the EKF's start-up fit is the longest).
constexpr std::size_t kAcqQueueEvents = 64;

// Calibration blob (ParamStore payload): version, count, then W (row-major), o, Rm (w, x, y, z)
// as little-endian IEEE doubles, whatever Scalar is (float widens and narrows back exactly).
constexpr std::uint16_t kBlobVersion = 1;
constexpr std::size_t kBlobValues = 16;
constexpr std::size_t kBlobBytes = 4 + 8 * kBlobValues;

void put_f64(std::uint8_t* p, double v) noexcept {
  std::uint64_t b = 0;
  std::memcpy(&b, &v, 8);
  for (int k = 0; k < 8; ++k)
    p[k] = static_cast<std::uint8_t>(b >> (8 * k));
}
double get_f64(const std::uint8_t* p) noexcept {
  std::uint64_t b = 0;
  for (int k = 0; k < 8; ++k)
    b |= static_cast<std::uint64_t>(p[k]) << (8 * k);
  double v = 0;
  std::memcpy(&v, &b, 8);
  return v;
}

void serialise(const core::SensorModel<Scalar>& m, std::uint8_t (&blob)[kBlobBytes]) noexcept {
  blob[0] = kBlobVersion & 0xFF;
  blob[1] = kBlobVersion >> 8;
  blob[2] = kBlobValues;
  blob[3] = 0;
  std::uint8_t* p = blob + 4;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c, p += 8)
      put_f64(p, static_cast<double>(m.w(r, c)));
  for (int i = 0; i < 3; ++i, p += 8)
    put_f64(p, static_cast<double>(m.o(i)));
  const Scalar q[4] = {m.rm.w(), m.rm.x(), m.rm.y(), m.rm.z()};
  for (int i = 0; i < 4; ++i, p += 8)
    put_f64(p, static_cast<double>(q[i]));
}

bool deserialise(const std::uint8_t* blob, std::size_t n, core::SensorModel<Scalar>* m) noexcept {
  if (n != kBlobBytes || blob[0] != (kBlobVersion & 0xFF) || blob[1] != 0 || blob[2] != kBlobValues)
    return false;
  const std::uint8_t* p = blob + 4;
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c, p += 8)
      m->w(r, c) = static_cast<Scalar>(get_f64(p));
  for (int i = 0; i < 3; ++i, p += 8)
    m->o(i) = static_cast<Scalar>(get_f64(p));
  Scalar q[4];
  for (int i = 0; i < 4; ++i, p += 8)
    q[i] = static_cast<Scalar>(get_f64(p));
  m->rm = core::Quat<Scalar>(q[0], q[1], q[2], q[3]);
  return m->w.allFinite() && m->o.allFinite();
}

struct Options {
  bool records{true};
  bool core{true};
  bool uart{false};
  std::uint32_t max_samples{std::numeric_limits<std::uint32_t>::max()};
  std::uint32_t tick_us{kDefaultTickUs};
};

std::uint32_t parse_u32(const char* p, const char* end) noexcept {
  std::uint32_t v = 0;
  for (; p < end && *p >= '0' && *p <= '9'; ++p)
    v = v * 10 + static_cast<std::uint32_t>(*p - '0');
  return v;
}

Options parse_options(const char* a) noexcept {
  Options o;
  while (*a != '\0') {
    while (*a == ' ')
      ++a;
    const char* w = a;
    while (*a != '\0' && *a != ' ')
      ++a;
    const auto len = static_cast<std::size_t>(a - w);
    if (len == 5 && std::strncmp(w, "quiet", 5) == 0) o.records = false;
    if (len == 4 && std::strncmp(w, "uart", 4) == 0) o.uart = true;
    if (len == 8 && std::strncmp(w, "baseline", 8) == 0) {
      o.core = false;
      o.records = false;
    }
    if (len > 2 && w[0] == 'n' && w[1] == '=') o.max_samples = parse_u32(w + 2, a);
    if (len > 8 && std::strncmp(w, "tick_us=", 8) == 0) o.tick_us = parse_u32(w + 8, a);
  }
  return o;
}

// Everything the image owns, statically allocated (constructed by __libc_init_array).
const sim::ScenarioConfig g_scenario = make_scenario();
sim::Simulator g_sim(g_scenario, kSeed);
sim::SimRig g_rig(g_sim, make_rig_config());
drivers::Ads131Fluxgate g_adc(g_rig.adc(), g_rig.adc(), make_rig_config().adc.transfer);
drivers::sbg::CanAttitudeSource g_ins(g_rig.ins());
Calibrator g_cal(make_cal_config(g_scenario));
Pipeline g_pipeline(g_cal, pipeline_config<Scalar>(g_scenario, MAGVEC_APP_VECTOR != 0));
Loop& g_loop = g_pipeline.loop();
constexpr std::size_t kSector = 1024;
std::uint8_t g_flash_storage[4 * kSector];
drivers::SimFlash g_flash(g_flash_storage, kSector);
constexpr drivers::ParamStoreLayout kLayout{0, 2 * kSector};

struct PowerCutResult {
  std::uint32_t trials{0}, old_blob{0}, new_blob{0}, bad{0};
};

// Every interrupted store (program cut after k bytes, erase cut) must leave the old or the new
// blob loadable, never a corrupt one.
PowerCutResult power_cut_sweep(const std::uint8_t (&old_blob)[kBlobBytes],
                               const std::uint8_t (&new_blob)[kBlobBytes]) noexcept {
  PowerCutResult r;
  const std::size_t program_total = drivers::FlashParamStore::kHeaderSize + kBlobBytes;
  for (std::size_t trial = 0;; ++trial) {
    const bool erase_cut = trial < 3;
    const std::size_t k = erase_cut ? 0 : (trial - 3) * 5;
    if (!erase_cut && k > program_total + 12) break;
    g_flash.restore_power();
    std::memset(g_flash_storage, 0xFF, sizeof g_flash_storage);
    drivers::FlashParamStore store(g_flash, kLayout);
    if (store.store(old_blob) != hal::Status::kOk) {
      ++r.bad;
      continue;
    }
    if (erase_cut) {
      // During the first erase, half-way through it, and near the end of the second sector.
      static constexpr std::size_t kEraseOk[3] = {0, 0, 1};
      static constexpr std::size_t kErased[3] = {0, kSector / 2, kSector - 8};
      g_flash.cut_during_erase(kEraseOk[trial], kErased[trial]);
    } else {
      g_flash.cut_after_program_bytes(k);
    }
    (void)store.store(new_blob);
    g_flash.restore_power();  // reboot
    drivers::FlashParamStore reloaded(g_flash, kLayout);
    std::uint8_t out[kBlobBytes + 16];
    std::size_t n = 0;
    std::uint32_t seq = 0;
    ++r.trials;
    if (reloaded.load(out, n, seq) != hal::Status::kOk || n != kBlobBytes) {
      ++r.bad;
    } else if (std::memcmp(out, old_blob, kBlobBytes) == 0) {
      ++r.old_blob;
    } else if (std::memcmp(out, new_blob, kBlobBytes) == 0) {
      ++r.new_blob;
    } else {
      ++r.bad;
    }
  }
  g_flash.restore_power();
  return r;
}

// ---- acquisition: the data-ready path ------------------------------------------------------

// Bounded single-producer (tick handler) / single-consumer (main loop) ring. The consumer works
// on the front element in place and releases it afterwards; indices are free-running.
template <typename T, std::size_t N>
class SpscQueue {
  static_assert(N > 0 && (N & (N - 1)) == 0, "power of two");

 public:
  bool push(const T& v) noexcept {
    const std::uint32_t h = head_.load(std::memory_order_relaxed);
    if (h - tail_.load(std::memory_order_acquire) == N) return false;
    buf_[h % N] = v;
    head_.store(h + 1, std::memory_order_release);
    return true;
  }
  const T* front() const noexcept {
    const std::uint32_t t = tail_.load(std::memory_order_relaxed);
    return head_.load(std::memory_order_acquire) == t ? nullptr : &buf_[t % N];
  }
  void pop_front() noexcept {
    tail_.store(tail_.load(std::memory_order_relaxed) + 1, std::memory_order_release);
  }
  bool empty() const noexcept { return front() == nullptr; }

 private:
  T buf_[N];
  std::atomic<std::uint32_t> head_{0};
  std::atomic<std::uint32_t> tail_{0};
};

enum class AcqKind : std::uint8_t { kAttitude, kMagnetometer, kReadError };

// A magnetometer sample with what the test scores it against (the scenario's scalar reference,
// which also rides with it into the pipeline, and the true E/N/U field) and its acquisition time.
struct MagEntry {
  hal::MagnetometerSample s;
  double f_nT;
  double h_n_true_nT[3];
  std::uint64_t acquired_us;
};

struct AcqEvent {
  AcqKind kind{AcqKind::kReadError};
  union {
    hal::AttitudeSample att;
    MagEntry mag;
  };
  AcqEvent() noexcept : mag{} {}
};

// Written by the tick handler only (the main loop reads them after `done`), except `consumed`
// (main loop) and `solve_window` (main loop: a solve is pending, for the depth figure).
struct Acquisition {
  SpscQueue<AcqEvent, kAcqQueueEvents> queue;
  std::uint32_t max_samples{0};
  std::uint32_t samples{0}, not_fresh{0}, read_errors{0}, device_errors{0}, att_samples{0};
  std::uint32_t lost_events{0};  // queue full: an event the main loop never sees (must stay 0)
  std::uint32_t ticks{0};
  std::uint32_t max_depth{0};        // most magnetometer samples waiting at once
  std::uint32_t max_depth_solve{0};  // ... while a solve was pending
  std::atomic<std::uint32_t> consumed{0};
  std::atomic<bool> solve_window{false};
  std::atomic<bool> done{false};
};
Acquisition g_acq;

void push_event(const AcqEvent& e) noexcept {
  if (!g_acq.queue.push(e)) ++g_acq.lost_events;
}

// One sample period: the world advances one magnetometer sample (simulated rig), then every INS
// frame received by now and every magnetometer sample are read, in this order, as the interrupt
// handlers of a board would (the tick handler; on the host, called by the main loop).
void acquisition_tick() noexcept {
  if (g_acq.done.load(std::memory_order_relaxed)) return;
  ++g_acq.ticks;
  if (g_acq.samples >= g_acq.max_samples || !g_rig.step()) {
    board_stop_sample_clock();
    g_acq.done.store(true, std::memory_order_release);
    return;
  }
  AcqEvent e;
  hal::AttitudeSample a;
  for (int guard = 0; guard < 256 && g_ins.read(a, 0) == hal::Status::kOk; ++guard) {
    ++g_acq.att_samples;
    e.kind = AcqKind::kAttitude;
    e.att = a;
    push_event(e);
  }
  const sim::SimSample& truth = g_rig.last();
  for (int guard = 0; guard < 8 && g_acq.samples < g_acq.max_samples; ++guard) {
    MagEntry m{};
    const hal::Status rs = g_adc.read(m.s, 0);
    if (rs == hal::Status::kTimeout || rs == hal::Status::kNoData) break;
    if (rs != hal::Status::kOk) {
      ++g_acq.read_errors;
      e.kind = AcqKind::kReadError;
      push_event(e);
      continue;
    }
    ++g_acq.samples;
    if ((m.s.flags & hal::kMagNotFresh) != 0) ++g_acq.not_fresh;
    if ((m.s.flags & hal::kMagInvalidMask) != 0) ++g_acq.device_errors;
    m.f_nT = truth.f_nT;
    for (int i = 0; i < 3; ++i)
      m.h_n_true_nT[i] = truth.h_n_true_nT(i);
    m.acquired_us = board_time_us();
    e.kind = AcqKind::kMagnetometer;
    e.mag = m;
    push_event(e);
    const std::uint32_t depth = g_acq.samples - g_acq.consumed.load(std::memory_order_relaxed);
    g_acq.max_depth = std::max(g_acq.max_depth, depth);
    if (g_acq.solve_window.load(std::memory_order_relaxed))
      g_acq.max_depth_solve = std::max(g_acq.max_depth_solve, depth);
  }
}

// Main loop: nothing to do until the next tick.
bool acquisition_idle() noexcept {
  return g_acq.queue.empty() && !g_acq.done.load(std::memory_order_acquire);
}

// ---- the calibrator's solve, off the per-sample path ---------------------------------------

struct SolveJob {
  pipeline::SolveSchedule schedule{kSolveInstallRecords};  // ticket raised, result not installed
  bool solved{false};
  core::CalibratorSolve result{};
  core::SensorModel<Scalar> model{};
  // Figures: the solve's duration (board clock) and the samples that arrived meanwhile.
  std::uint64_t solve_us{0};
  std::uint32_t ticks_during{0};
  std::uint32_t forced{0};  // solves the deadline had to run because the queue never emptied
};

void run_solve(SolveJob& job) noexcept {
  const std::uint64_t t0 = board_time_us();
  const std::uint32_t ticks0 = g_acq.ticks;
  job.result = g_cal.solve(&job.model);
  job.solve_us = board_time_us() - t0;
  job.ticks_during = g_acq.ticks - ticks0;
  job.solved = true;
}

struct Stats {
  std::uint32_t processed{0}, uncal_samples{0}, cal_samples{0}, hn_samples{0};
  double sum_sq_f_uncal{0};  // intensity - F before a calibration is active (identity model)
  double sum_sq_f_cal{0};    // intensity - F with the stored calibration active
  double max_abs_f_cal{0};
  double sum_sq_hn_cal{0};  // |h_n - h_n true|^2 with the stored calibration active
};

// The truth of the newest samples, by time stamp: a record leaves the pipeline after later
// samples were read, and is scored against the truth of its own sample.
struct TruthRing {
  static constexpr std::size_t kSize = 16;  // > the pipeline's queue (8) + 1
  struct Entry {
    std::uint64_t t_us{0};
    double f_nT{0};
    core::Vec3<double> h_n_nT = core::Vec3<double>::Zero();
  };
  Entry e[kSize];
  std::size_t next{0};
  void put(std::uint64_t t_us, double f_nT, const core::Vec3<double>& h_n_nT) noexcept {
    e[next % kSize] = Entry{t_us, f_nT, h_n_nT};
    ++next;
  }
  const Entry* find(std::uint64_t t_us) const noexcept {
    for (std::size_t k = 0; k < kSize && k < next; ++k) {
      const Entry& x = e[(next - 1 - k) % kSize];
      if (x.t_us == t_us) return &x;
    }
    return nullptr;
  }
};

// Loop milestones (sample numbers, 1-based, as counted by n=<k>): the insn counting windows.
struct Milestones {
  std::uint32_t init_fit{0};  // the sample that completed the EKF's initial fit
  std::uint32_t solve{0};     // the sample after which the solve's result was installed
  std::uint32_t applied{0};   // the sample on which the loop applied the calibration
  std::uint32_t ready{0};     // the sample that raised the solve ticket (solved in idle time)
  // The samples whose EKF update relinearised the start-up set (docs/equations.md E-Acc-3): rare
  // events inside a sample, which the insn count measures apart from the per-sample path.
  std::array<std::uint32_t, 8> relinearised{};
  std::size_t n_relinearised{0};
};

// The scalar EKF's relinearisations of its start-up set so far; the vector filter has none.
template <typename Cal>
std::uint32_t start_relinearisations(const Cal& cal) noexcept {
#if MAGVEC_APP_VECTOR
  (void)cal;
  return 0;
#else
  return cal.filter().counters().start_relinearisations;
#endif
}

void report_vec(LineWriter& w, const char* key, const Scalar* v, int n) noexcept {
  w.str("MV ").str(key);
  for (int i = 0; i < n; ++i)
    w.sp().hex(static_cast<double>(v[i]));
  w.end();
}

// G = W^T W (upper triangle 00 01 02 11 12 22) of the filter and its 1-sigma from the EKF
// covariance of W (first-order propagation: dG = dW^T W + W^T dW).
template <typename Ekf>
void report_g(LineWriter& w, const Ekf& ekf) noexcept {
  const core::Mat3<Scalar> wm = ekf.c_inv();
  const core::Mat3<Scalar> g = wm.transpose() * wm;
  const core::Mat<Scalar, 12, 12> p = ekf.covariance();
  static constexpr int kI[6] = {0, 0, 0, 1, 1, 2};
  static constexpr int kJ[6] = {0, 1, 2, 1, 2, 2};
  Scalar gv[6];
  Scalar gs[6];
  for (int e = 0; e < 6; ++e) {
    const int i = kI[e], j = kJ[e];
    gv[e] = g(i, j);
    // G_ij = sum_r W_ri W_rj: dG_ij/dW_rc = [c == i] W_rj + [c == j] W_ri.
    core::Vec<Scalar, 9> jac = core::Vec<Scalar, 9>::Zero();
    for (int r = 0; r < 3; ++r) {
      jac(core::ekf_w_index(r, i)) += wm(r, j);
      jac(core::ekf_w_index(r, j)) += wm(r, i);
    }
    const Scalar var = jac.dot(p.template topLeftCorner<9, 9>() * jac);
    gs[e] = std::sqrt(var > 0 ? var : Scalar(0));
  }
  report_vec(w, "g", gv, 6);
  report_vec(w, "g_sigma", gs, 6);
}

void report_model(LineWriter& w, const char* key, const core::SensorModel<Scalar>& m) noexcept {
  Scalar v[16];
  for (int r = 0; r < 3; ++r)
    for (int c = 0; c < 3; ++c)
      v[3 * r + c] = m.w(r, c);
  for (int i = 0; i < 3; ++i)
    v[9 + i] = m.o(i);
  v[12] = m.rm.w();
  v[13] = m.rm.x();
  v[14] = m.rm.y();
  v[15] = m.rm.z();
  report_vec(w, key, v, 16);
}

// Power-cut sweep over storing blob_new on top of blob_old (a test of the flash store, run after
// the stream: it is not sample-path work). Returns 0 or the exit code of the failed check.
int report_power_cut_sweep(LineWriter& w, const std::uint8_t (&blob_old)[kBlobBytes],
                           const std::uint8_t (&blob_new)[kBlobBytes]) noexcept {
  const PowerCutResult pc = power_cut_sweep(blob_old, blob_new);
  w.str("MV pcut trials=").u(pc.trials).str(" old=").u(pc.old_blob).str(" new=");
  w.u(pc.new_blob).str(" bad=").u(pc.bad).end();
  return pc.bad != 0 || pc.old_blob == 0 || pc.new_blob == 0 ? 3 : 0;
}

// End of the calibration: store, reload (as after a reboot), install. Returns 0 or the exit code
// of the failed check; blob_new: what was stored.
int store_and_reload(LineWriter& w, const std::uint8_t (&blob_old)[kBlobBytes],
                     std::uint8_t (&blob_new)[kBlobBytes]) noexcept {
  int rc = 0;
  serialise(g_loop.active_model(), blob_new);
  std::memset(g_flash_storage, 0xFF, sizeof g_flash_storage);
  drivers::FlashParamStore store(g_flash, kLayout);
  const bool stored =
      store.store(blob_old) == hal::Status::kOk && store.store(blob_new) == hal::Status::kOk;
  drivers::FlashParamStore after_reboot(g_flash, kLayout);
  std::uint8_t loaded[kBlobBytes + 16];
  std::size_t n = 0;
  std::uint32_t seq = 0;
  core::SensorModel<Scalar> model;
  const bool ok = stored && after_reboot.load(loaded, n, seq) == hal::Status::kOk &&
                  deserialise(loaded, n, &model) && seq == 2 &&
                  std::memcmp(loaded, blob_new, kBlobBytes) == 0;
  w.str("MV reload ok=").u(ok ? 1 : 0).str(" seq=").u(seq).str(" bytes=").u(n).end();
  if (!ok) return 4;
  // The reloaded model replaces the loop's (bit-identical: the blob holds doubles); it keeps the
  // alignment flag and the held-out sigma_F of the calibration it is.
  std::uint8_t again[kBlobBytes];
  serialise(model, again);
  if (std::memcmp(again, blob_new, kBlobBytes) != 0) return 4;
  g_loop.set_active(model, g_loop.cal_id(), g_loop.active_aligned(), g_loop.active_sigma_f_nT());
  return rc;
}

}  // namespace

int app_main(const char* args) noexcept {
  const Options opt = parse_options(args);
  LineWriter w;
  RecordLineSink sink(board_record_port(opt.uart));
  w.str("MV begin scenario=").str(g_scenario.name).str(" seed=").u(kSeed);
  w.str(" scalar=").str(sizeof(Scalar) == 4 ? "float" : "double").str(" board=").str(board_name());
  w.str(" core=").u(opt.core ? 1 : 0).str(" records=").str(opt.uart ? "uart" : "console").end();
  w.str("MV sizeof loop=").u(sizeof(Loop)).str(" calibrator=").u(sizeof(Calibrator));
  w.str(" ekf=").u(sizeof(Calibrator::Filter)).str(" pipeline=").u(sizeof(g_pipeline));
  w.str(" rig=").u(sizeof(g_rig)).end();

  int rc = 0;
  if (g_adc.init() != hal::Status::kOk) {
    w.str("MV error adc_init").end();
    return 2;
  }
  // Boot: a stored calibration becomes the active one; without one, calibrate.
  std::uint8_t blob_old[kBlobBytes];
  {
    drivers::FlashParamStore boot(g_flash, kLayout);
    std::uint8_t loaded[kBlobBytes + 16];
    std::size_t n = 0;
    std::uint32_t seq = 0;
    core::SensorModel<Scalar> model;
    const hal::Status ls = boot.load(loaded, n, seq);
    if (ls == hal::Status::kOk && deserialise(loaded, n, &model)) {
      g_loop.set_active(model, seq);
    } else if (opt.core) {
      g_loop.start_calibration();
    }
    w.str("MV boot stored=").u(ls == hal::Status::kOk ? 1 : 0).str(" state=");
    w.str(core::cal_state_name(g_loop.state())).end();
  }
  serialise(g_loop.active_model(), blob_old);  // what the flash held before: the identity model

  Stats st;
  Milestones ms;
  TruthRing truth_ring;
  SolveJob job;
  bool stored = false;
  std::uint8_t blob_new[kBlobBytes] = {};
  bool prev_init = g_cal.filter().initialised();
  std::uint32_t prev_relin = start_relinearisations(g_cal);
  core::CalState prev_state = g_loop.state();
  // Every record, in sample order, when the pipeline processes its sample (INS epochs bracket it
  // or the fusion horizon expired). `processed` numbers the samples as n=<k> counts them.
  auto on_record = [&](const core::OutputRecord<Scalar>& rec) noexcept {
    ++st.processed;
    // Milestones and the end of the calibration.
    if (!prev_init && g_cal.filter().initialised() && ms.init_fit == 0) ms.init_fit = st.processed;
    prev_init = g_cal.filter().initialised();
    if (const std::uint32_t r = start_relinearisations(g_cal); r != prev_relin) {
      prev_relin = r;
      if (ms.n_relinearised < ms.relinearised.size())
        ms.relinearised[ms.n_relinearised++] = st.processed;
    }
    // A solve ticket: the main loop solves in idle time; the result goes in at a fixed record.
    if (job.schedule.raised(g_loop, st.processed)) {
      job.solved = false;
      if (ms.ready == 0) ms.ready = st.processed;
      g_acq.solve_window.store(true, std::memory_order_relaxed);
    }
    if (job.schedule.due(st.processed)) {
      if (!job.solved) {
        ++job.forced;
        run_solve(job);
      }
      job.schedule.installed();
      g_acq.solve_window.store(false, std::memory_order_relaxed);
      if (g_loop.install_solve(job.schedule.ticket(), job.result, job.model) && ms.solve == 0)
        ms.solve = st.processed;
    }
    const core::CalState state = g_loop.state();
    if (state != prev_state) {
      if (state == core::CalState::kApplied) ms.applied = st.processed;
      if (state == core::CalState::kFailed) {
        w.str("MV cal_failed failure=").u(static_cast<std::uint64_t>(g_loop.failure()));
        w.str(" code=").str(cal_code_name(g_loop.solver_code())).end();
        rc = rc != 0 ? rc : 6;
      }
      prev_state = state;
    }
    if (state == core::CalState::kApplied && !stored) {
      stored = true;
      const int src = store_and_reload(w, blob_old, blob_new);
      if (src != 0) rc = rc != 0 ? rc : src;
    }

    if (opt.records && st.processed % kRecordEvery == 0) {
      if (sink.emit(pipeline::to_hal_record(rec)) != hal::Status::kOk)
        g_pipeline.count_sink_error();
    }
    if (!opt.records || (rec.flags & core::kOutDropout) != 0) return;
    // Test statistics (not in quiet runs: they are not part of the per-sample firmware work).
    const TruthRing::Entry* truth = truth_ring.find(rec.t_us);
    if (truth == nullptr) return;
    const double res = static_cast<double>(rec.intensity_nT) - truth->f_nT;
    if (rec.cal_id == 0) {
      ++st.uncal_samples;
      st.sum_sq_f_uncal += res * res;
      return;
    }
    ++st.cal_samples;
    st.sum_sq_f_cal += res * res;
    st.max_abs_f_cal = std::fmax(st.max_abs_f_cal, std::fabs(res));
    if ((rec.flags & core::kOutNoAttitude) == 0) {
      ++st.hn_samples;
      st.sum_sq_hn_cal += (rec.h_n_nT.template cast<double>() - truth->h_n_nT).squaredNorm();
    }
  };

  // Latency of a magnetometer sample: from its acquisition to the end of its pipeline call
  // (queue wait + its own processing), worst overall and while a solve was pending.
  std::uint64_t max_latency_us = 0;
  std::uint64_t max_latency_solve_us = 0;
  auto consume = [&](const AcqEvent& e) noexcept {
    switch (e.kind) {
      case AcqKind::kAttitude:
        if (opt.core) g_pipeline.on_attitude(e.att, on_record);
        break;
      case AcqKind::kReadError:
        if (opt.core) g_pipeline.on_read_error();
        break;
      case AcqKind::kMagnetometer: {
        const MagEntry& m = e.mag;
        const bool solving = job.schedule.pending();
        if (opt.core) {
          if (opt.records) {
            truth_ring.put(
                m.s.t_us, m.f_nT,
                core::Vec3<double>(m.h_n_true_nT[0], m.h_n_true_nT[1], m.h_n_true_nT[2]));
          }
          // The scenario's scalar reference channel rides with the sample.
          g_pipeline.on_magnetometer(m.s, static_cast<Scalar>(m.f_nT), on_record);
        }
        g_acq.consumed.fetch_add(1, std::memory_order_relaxed);
        const std::uint64_t latency = board_time_us() - m.acquired_us;
        max_latency_us = std::max(max_latency_us, latency);
        if (solving || job.schedule.pending())
          max_latency_solve_us = std::max(max_latency_solve_us, latency);
        break;
      }
    }
  };

  g_acq.max_samples = opt.max_samples;
  const bool clocked = board_start_sample_clock(opt.tick_us, &acquisition_tick);
  for (;;) {
    for (const AcqEvent* e = g_acq.queue.front(); e != nullptr; e = g_acq.queue.front()) {
      consume(*e);
      g_acq.queue.pop_front();
    }
    // Idle time: the pending solve (preempted by the ticks; samples wait in the queue).
    if (job.schedule.pending() && !job.solved) {
      run_solve(job);
      continue;
    }
    if (g_acq.done.load(std::memory_order_acquire)) {
      if (g_acq.queue.empty()) break;
      continue;
    }
    if (clocked) {
      board_wait_for_interrupt(&acquisition_idle);
    } else {
      acquisition_tick();
    }
  }
  // End of the stream (or of n=<k>): every sample read gets its record.
  if (opt.core) g_pipeline.flush(on_record);
  // A ticket the flush raised is solved too (idle time after the stream; not installed).
  if (job.schedule.pending() && !job.solved) run_solve(job);
  if (stored) {
    const int prc = report_power_cut_sweep(w, blob_old, blob_new);
    if (prc != 0) rc = rc != 0 ? rc : prc;
  }

  const auto& ekf = g_cal.filter();
  const core::LoopHealth& lh = g_loop.health();
#if MAGVEC_APP_VECTOR
  const core::VfCounters& ec = ekf.counters();
  w.str("MV vf initialised=").u(ekf.initialised() ? 1 : 0).str(" updates=").u(ec.updates);
  w.str(" gated=").u(ec.gated).str(" resets=").u(ec.resets);
  w.str(" init_failures=").u(ec.init_failures).str(" noise_nT=");
  w.fixed(static_cast<double>(g_cal.noise().mag_nT), 4).str(" ins_deg=");
  w.fixed(static_cast<double>(g_cal.noise().attitude_deg), 5).str(" time_offset_ms=");
  w.fixed(1e3 * static_cast<double>(ekf.time_offset_s()), 4).end();
  const core::VfOutputUncertainty<Scalar>& ou = g_cal.output_uncertainty();
  w.str("MV vf_output enu_nT=").fixed(static_cast<double>(ou.vector_nT), 4);
  w.str(" enu_noise_nT=").fixed(static_cast<double>(ou.vector_noise_nT), 4);
  w.str(" intensity_nT=").fixed(static_cast<double>(ou.intensity_nT), 4);
  w.str(" intensity_noise_nT=").fixed(static_cast<double>(ou.intensity_noise_nT), 4).end();
  constexpr std::uint32_t kAlignSamples = 0;  // the vector filter has no alignment store
#else
  const core::EkfCounters& ec = ekf.counters();
  w.str("MV ekf initialised=").u(ekf.initialised() ? 1 : 0).str(" updates=").u(ec.updates);
  w.str(" gated=").u(ec.gated).str(" reinit=").u(ec.reinitialisations);
  w.str(" init_failures=").u(ec.init_failures).end();
  const auto kAlignSamples = g_cal.align_samples();
#endif
  w.str("MV loop state=").str(core::cal_state_name(g_loop.state())).str(" cal_id=");
  w.u(g_loop.cal_id()).str(" samples=").u(lh.samples).str(" used=").u(lh.cal_used);
  w.str(" gated=").u(lh.cal_gated).str(" rejected=").u(lh.cal_rejected);
  w.str(" dropouts=").u(lh.dropouts).str(" device_errors=").u(lh.device_errors);
  w.str(" no_attitude=").u(lh.no_attitude).str(" align_samples=").u(kAlignSamples).end();
  w.str("MV milestones init_fit=").u(ms.init_fit).str(" solve=").u(ms.solve);
  w.str(" applied=").u(ms.applied).str(" ready=").u(ms.ready).end();
  w.str("MV relinearised at=");
  for (std::size_t i = 0; i < ms.n_relinearised; ++i)
    (i > 0 ? w.str(",") : w).u(ms.relinearised[i]);
  w.end();
  w.str("MV counts samples=").u(g_acq.samples).str(" read_errors=").u(g_acq.read_errors);
  w.str(" not_fresh=").u(g_acq.not_fresh).str(" device_errors=").u(g_acq.device_errors);
  w.str(" att=").u(g_acq.att_samples).str(" records=").u(sink.emitted());
  w.str(" record_failures=").u(sink.failed()).end();
  // Produced vs consumed samples and lost events are exact; the depths, latencies and the
  // solve's duration depend on the board's clock (host: none, polled, so zero).
  w.str("MV acq clock=").u(clocked ? 1 : 0).str(" tick_us=").u(clocked ? opt.tick_us : 0);
  w.str(" produced=").u(g_acq.samples).str(" consumed=");
  w.u(g_acq.consumed.load(std::memory_order_relaxed)).str(" lost=").u(g_acq.lost_events);
  w.str(" max_depth=").u(g_acq.max_depth).str(" max_depth_solving=").u(g_acq.max_depth_solve);
  w.str(" max_latency_us=").u(max_latency_us).str(" max_latency_solving_us=");
  w.u(max_latency_solve_us).end();
  w.str("MV solve ticket=").u(job.schedule.ticket()).str(" solve_us=").u(job.solve_us);
  w.str(" ticks_during=").u(job.ticks_during).str(" forced=").u(job.forced).end();
  if (g_acq.lost_events != 0 || g_acq.consumed.load(std::memory_order_relaxed) != g_acq.samples)
    rc = rc != 0 ? rc : 7;
  const pipeline::DeviceCounters& pc = g_pipeline.counters();
  w.str("MV pipeline records=").u(pc.records).str(" att_rejected=").u(pc.att_rejected);
  w.str(" att_gaps=").u(pc.att_gaps).str(" mag_missing=").u(pc.mag_missing);
  w.str(" horizon_expired=").u(pc.horizon_expired).str(" extrapolated=").u(pc.extrapolated);
  w.str(" max_queued=").u(pc.max_queued).str(" sink_errors=").u(pc.sink_errors).end();
  if (opt.core) {
    const core::SensorModel<Scalar> model = g_loop.active_model();
    report_model(w, "model", model);
    const core::SensorModel<Scalar> fm = ekf.model();
    report_vec(w, "b", fm.o.data(), 3);
#if MAGVEC_APP_VECTOR
    // The filter's 1-sigmas: W (row-major, structural zeros 0), offset (nT), Rm (rad).
    const core::VfSigmas<Scalar> sg = ekf.sigmas();
    Scalar sigma[15];
    for (int i = 0; i < 9; ++i)
      sigma[i] = sg.w(i / 3, i % 3);
    for (int i = 0; i < 3; ++i) {
      sigma[9 + i] = sg.o_nT(i);
      sigma[12 + i] = sg.rm_rad(i);
    }
    report_vec(w, "sigma", sigma, 15);
#else
    const core::Vec<Scalar, 12> sigma = ekf.sigma();
    report_vec(w, "sigma", sigma.data(), 12);
    report_g(w, ekf);
#endif
    const Scalar vrms = g_loop.last_validation_rms_nT();
    report_vec(w, "validation_rms", &vrms, 1);
    const double rmse_cal = st.cal_samples > 0 ? std::sqrt(st.sum_sq_f_cal / st.cal_samples) : 0.0;
    const double rmse_uncal =
        st.uncal_samples > 0 ? std::sqrt(st.sum_sq_f_uncal / st.uncal_samples) : 0.0;
    const double rmse_hn = st.hn_samples > 0 ? std::sqrt(st.sum_sq_hn_cal / st.hn_samples) : 0.0;
    w.str("MV stats ").hex(rmse_cal).sp().hex(st.max_abs_f_cal).sp().hex(rmse_hn);
    w.sp().hex(rmse_uncal).end();
    w.str("MV summary rmse_F_nT=").fixed(rmse_cal, 4).str(" max_abs_F_nT=");
    w.fixed(st.max_abs_f_cal, 4).str(" rmse_hn_nT=").fixed(rmse_hn, 4);
    w.str(" rmse_F_uncalibrated_nT=").fixed(rmse_uncal, 1).str(" b_nT=");
    w.fixed(static_cast<double>(model.o(0)), 3).str(",").fixed(static_cast<double>(model.o(1)), 3);
    w.str(",").fixed(static_cast<double>(model.o(2)), 3).end();
    if (!ekf.initialised() || g_loop.state() != core::CalState::kApplied || !stored)
      rc = rc != 0 ? rc : 5;
  }
  w.str("MV end rc=").u(static_cast<std::uint64_t>(rc)).end();
  return rc;
}

}  // namespace magvec::app
