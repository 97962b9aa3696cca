// The operator's words for a core::Guidance (core/calibration_guidance.hpp): the core has no
// strings, so the text is made here, once, for magvecd's calibration state (its `hint` field) and
// everything that shows it.
#pragma once

#include <cmath>
#include <string>

#include "magvec/core/calibration_guidance.hpp"

namespace magvec::host::daemon {

inline const char* guidance_hint_name(core::GuidanceHint h) noexcept {
  switch (h) {
    case core::GuidanceHint::kNone:
      return "none";
    case core::GuidanceHint::kReady:
      return "ready";
    case core::GuidanceHint::kNoField:
      return "no_field";
    case core::GuidanceHint::kNoReference:
      return "no_reference";
    case core::GuidanceHint::kNoAttitude:
      return "no_attitude";
    case core::GuidanceHint::kTurn:
      return "turn";
    case core::GuidanceHint::kPitch:
      return "pitch";
    case core::GuidanceHint::kRoll:
      return "roll";
    case core::GuidanceHint::kKeepMoving:
      return "keep_moving";
  }
  return "unknown";
}

// 8-point compass name of a heading in degrees clockwise from north.
inline const char* compass_point(int heading_deg) noexcept {
  static constexpr const char* kPoints[8] = {"N", "NE", "E", "SE", "S", "SW", "W", "NW"};
  const int h = ((heading_deg % 360) + 360) % 360;
  return kPoints[((h + 22) / 45) % 8];
}

inline std::string guidance_text(const core::Guidance<double>& g) {
  auto turn = [](int heading_deg) {
    return "turn towards " + std::string(compass_point(heading_deg)) + " (heading " +
           std::to_string(heading_deg) + " deg)";
  };
  // Every empty cell a turn through all headings reaches after the manoeuvre's tilt.
  auto cells = [&g] {
    return g.target_cells > 0
               ? " (" + std::to_string(g.target_cells) +
                     (g.target_cells == 1 ? " empty cell" : " empty cells") + " in reach)"
               : std::string();
  };
  switch (g.hint) {
    case core::GuidanceHint::kNone:
      return "";
    case core::GuidanceHint::kReady:
      return "ready: the solve can be tried";
    case core::GuidanceHint::kNoField:
      return "no magnetometer reading yet";
    case core::GuidanceHint::kNoReference:
      return "needs the scalar reference: samples without F are refused (scalar magnetometer, "
             "calibration.reference_field_nT, or a valid INS position for the model)";
    case core::GuidanceHint::kNoAttitude:
      return "keep still: attitude missing (INS not aligned or not received)";
    case core::GuidanceHint::kTurn:
      return turn(g.heading_deg) + cells();
    case core::GuidanceHint::kPitch:
    case core::GuidanceHint::kRoll: {
      std::string s;
      if (g.hint == core::GuidanceHint::kPitch) {
        s = std::string("tilt nose-") + (g.pitch_deg > 0 ? "up" : "down") + " by " +
            std::to_string(std::abs(g.pitch_deg)) + " deg";
      } else {
        s = std::string("roll ") + (g.roll_deg > 0 ? "right" : "left") + " by " +
            std::to_string(std::abs(g.roll_deg)) + " deg";
      }
      if (g.heading_deg >= 0) s += ", then " + turn(g.heading_deg);
      return s + cells();
    }
    case core::GuidanceHint::kKeepMoving:
      if (g.cells_fraction < 1)
        return "keep turning and tilting: no empty cell within reach of a " +
               std::to_string(core::kGuidanceMaxTiltDeg) + "-deg tilt";
      if (g.samples_fraction < 1) return "keep turning: more samples needed";
      return "keep manoeuvring: the estimate is converging";
  }
  return "";
}

}  // namespace magvec::host::daemon
