// SBG INS CAN frames through the attitude decoder. Input: 1 configuration byte (quaternion or
// Euler source), then frames of [id selector, dlc | extended bit, dlc data bytes].
// Invariants: every frame lands in exactly one counter/result (samples, malformed, missing_time,
// ignored, duplicates, or consumed); a frame identical to the previous configured frame is a
// duplicate, and so is an attitude frame whose fresh EKF_INFO time is the last sample's; a sample
// is stamped with the receive time of its attitude frame and the INS time of the last EKF_INFO, its
// quaternion is unit and finite, its accuracies finite and non-negative, its solution mode the low
// bits of the last SOLUTION_STATUS; a sample needs a fresh EKF_INFO (at most one sample per
// EKF_INFO).
// Position (EKF_POS, EKF_ALTITUDE): every such frame lands in the position counters only (fixes,
// malformed, out_of_range, duplicates) or is consumed; a fix needs both halves received intact
// since the last fix (a rejected half ends the pair), lies within the documented ranges, is
// finite, stamped with its completing frame's receive time and the last EKF_INFO time, and is
// valid only when the last SOLUTION_STATUS said POSITION_VALID.
#include <cmath>

#include "fuzz_check.hpp"
#include "magvec/drivers/sbg_can.hpp"

using namespace magvec;
using namespace magvec::drivers;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  fuzz::Bytes in(data, size);
  sbg::DecoderConfig cfg;
  cfg.source =
      (in.u8() & 1u) != 0 ? sbg::AttitudeMessage::kEuler : sbg::AttitudeMessage::kQuaternion;
  const sbg::CanIds& ids = cfg.ids;
  const std::uint32_t known[] = {ids.status_01, ids.status_03,   ids.ekf_info,
                                 ids.ekf_quat,  ids.ekf_euler,   ids.ekf_orientation_acc,
                                 ids.ekf_pos,   ids.ekf_altitude};
  sbg::CanDecoder dec(cfg);

  std::uint64_t frames = 0, samples = 0, malformed = 0, missing = 0, ignored = 0, duplicates = 0;
  std::uint64_t fixes = 0, pos_malformed = 0, pos_out_of_range = 0, pos_duplicates = 0;
  bool lat_lon_fresh = false, altitude_fresh = false;
  bool info_since_sample = false;
  std::uint32_t last_info_time = 0;
  bool have_prev = false, have_sample = false;
  std::uint64_t last_sample_ins = 0;
  hal::CanFrame prev;
  while (in.size() > 0) {
    hal::CanFrame f;
    const std::uint8_t sel = in.u8();
    f.id = sel < 192 ? known[sel % 8] : 0x100u + (sel & 0x3Fu);
    const std::uint8_t d = in.u8();
    f.dlc = static_cast<std::uint8_t>(d & 0x0Fu) % 9u;
    f.extended = (d & 0x80u) != 0;
    for (std::size_t i = 0; i < f.dlc; ++i)
      f.data[i] = in.u8();  // bytes beyond dlc stay zero (the hal::CanFrame contract)
    f.t_us = 1000 * ++frames;
    bool configured = false;
    for (const std::uint32_t id : known)
      configured = configured || (!f.extended && f.id == id);
    bool repeat = configured && have_prev && f.id == prev.id && f.dlc == prev.dlc;
    for (std::size_t i = 0; repeat && i < f.dlc; ++i)
      repeat = f.data[i] == prev.data[i];
    if (configured) {
      prev = f;
      have_prev = true;
    }
    const sbg::FeedResult r = dec.feed(f);
    FUZZ_CHECK(!repeat || r == sbg::FeedResult::kDuplicate);
    const bool pos_frame = !f.extended && (f.id == ids.ekf_pos || f.id == ids.ekf_altitude);
    if (pos_frame) {
      bool& half = f.id == ids.ekf_pos ? lat_lon_fresh : altitude_fresh;
      switch (r) {
        case sbg::FeedResult::kConsumed:
          half = true;
          break;
        case sbg::FeedResult::kDuplicate:
          FUZZ_CHECK(repeat);
          ++pos_duplicates;
          break;
        case sbg::FeedResult::kMalformed:
          half = false;
          ++pos_malformed;
          break;
        case sbg::FeedResult::kOutOfRange:
          half = false;
          ++pos_out_of_range;
          break;
        case sbg::FeedResult::kPosition: {
          // The other half arrived intact since the last fix.
          FUZZ_CHECK(f.id == ids.ekf_pos ? altitude_fresh : lat_lon_fresh);
          lat_lon_fresh = altitude_fresh = false;
          ++fixes;
          const hal::PositionSample& p = dec.position();
          FUZZ_CHECK(std::isfinite(p.lat_deg) && std::abs(p.lat_deg) <= 90.0);
          FUZZ_CHECK(std::isfinite(p.lon_deg) && std::abs(p.lon_deg) <= 180.0);
          FUZZ_CHECK(p.altitude_m >= sbg::kMinAltitude_m && p.altitude_m <= sbg::kMaxAltitude_m);
          FUZZ_CHECK(std::abs(p.undulation_m) <= sbg::kMaxUndulation_m);
          FUZZ_CHECK(p.t_us == f.t_us);
          FUZZ_CHECK(p.t_ins_us == dec.raw().ekf_time_us);
          FUZZ_CHECK((p.flags & ~(hal::kPosValid | hal::kPosStatusKnown)) == 0);
          FUZZ_CHECK((p.flags & hal::kPosValid) == 0 ||
                     ((p.flags & hal::kPosStatusKnown) != 0 &&
                      (dec.raw().solution_status & sbg::kSolPositionValid) != 0));
          break;
        }
        default:
          FUZZ_CHECK(false);  // kIgnored, kSample, kMissingTime: never for a position frame
      }
      continue;
    }
    switch (r) {
      case sbg::FeedResult::kIgnored:
        ++ignored;
        break;
      case sbg::FeedResult::kDuplicate:
        ++duplicates;
        if (!repeat) {
          // An epoch already sampled: its attitude frame, a fresh EKF_INFO of the same time.
          FUZZ_CHECK(have_sample && info_since_sample);
          FUZZ_CHECK(dec.sample().t_ins_us == last_info_time);
          FUZZ_CHECK(f.id == (cfg.source == sbg::AttitudeMessage::kQuaternion ? ids.ekf_quat
                                                                              : ids.ekf_euler));
          info_since_sample = false;
        }
        break;
      case sbg::FeedResult::kMalformed:
        ++malformed;
        // A corrupt time or attitude frame ends the epoch.
        if (f.id == ids.ekf_info ||
            f.id ==
                (cfg.source == sbg::AttitudeMessage::kQuaternion ? ids.ekf_quat : ids.ekf_euler)) {
          info_since_sample = false;
        }
        break;
      case sbg::FeedResult::kMissingTime:
        ++missing;
        break;
      case sbg::FeedResult::kConsumed:
        if (f.id == ids.ekf_info && !f.extended) {
          info_since_sample = true;
          last_info_time = dec.raw().ekf_time_us;
        }
        break;
      case sbg::FeedResult::kPosition:
      case sbg::FeedResult::kOutOfRange:
        FUZZ_CHECK(false);  // only position frames (above)
        break;
      case sbg::FeedResult::kSample: {
        ++samples;
        FUZZ_CHECK(info_since_sample);
        info_since_sample = false;
        const hal::AttitudeSample& s = dec.sample();
        FUZZ_CHECK(!have_sample || s.t_ins_us != last_sample_ins);  // never one epoch twice
        have_sample = true;
        last_sample_ins = s.t_ins_us;
        FUZZ_CHECK(s.t_us == f.t_us);
        FUZZ_CHECK(s.t_ins_us == last_info_time);
        double n2 = 0;
        for (const double q : s.q_nb) {
          FUZZ_CHECK(std::isfinite(q));
          n2 += q * q;
        }
        FUZZ_CHECK(std::abs(n2 - 1.0) < 1e-9);
        for (const double sg : s.sigma_rad)
          FUZZ_CHECK(std::isfinite(sg) && sg >= 0);
        FUZZ_CHECK(s.solution_mode == (dec.raw().solution_status & sbg::kSolutionModeMask));
        FUZZ_CHECK(f.id == (cfg.source == sbg::AttitudeMessage::kQuaternion ? ids.ekf_quat
                                                                            : ids.ekf_euler));
        break;
      }
    }
  }
  const hal::AttitudeCounters& c = dec.counters();
  FUZZ_CHECK(c.samples == samples);
  FUZZ_CHECK(c.malformed == malformed);
  FUZZ_CHECK(c.missing_time == missing);
  FUZZ_CHECK(c.ignored == ignored);
  FUZZ_CHECK(c.duplicates == duplicates);
  FUZZ_CHECK(samples + malformed + missing + ignored + duplicates <= frames);
  const hal::PositionCounters& pc = dec.position_counters();
  FUZZ_CHECK(pc.samples == fixes);
  FUZZ_CHECK(pc.malformed == pos_malformed);
  FUZZ_CHECK(pc.out_of_range == pos_out_of_range);
  FUZZ_CHECK(pc.duplicates == pos_duplicates);
  FUZZ_CHECK(samples + malformed + missing + ignored + duplicates + fixes + pos_malformed +
                 pos_out_of_range + pos_duplicates <=
             frames);
  return 0;
}
