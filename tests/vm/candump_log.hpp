// The compact log format of can-utils' candump -L / canplayer (lib.c sprint_canframe):
//   "(<seconds>.<microseconds>) <interface> <ID>#<DATA>"
// ID: 3 hex digits (standard) or 8 (extended), DATA: 2 hex digits per byte, "R" for RTR frames.
// Used by the guest tests to write logs that canplayer replays and to read candump's captures.
#pragma once

#include <cstdint>
#include <cstdio>
#include <optional>
#include <string>

#include "magvec/hal/can_bus.hpp"

namespace magvec::vmtest {

struct LoggedFrame {
  std::uint64_t t_us{0};
  std::string interface;
  hal::CanFrame frame{};
};

inline std::string format_candump_line(const hal::CanFrame& f, std::uint64_t t_us,
                                       const std::string& interface) {
  char head[64];
  std::snprintf(head, sizeof head, "(%llu.%06llu) ",
                static_cast<unsigned long long>(t_us / 1000000),
                static_cast<unsigned long long>(t_us % 1000000));
  char id[16];
  std::snprintf(id, sizeof id, f.extended ? "%08X#" : "%03X#", f.id);
  std::string line = head + interface + " " + id;
  for (std::size_t i = 0; i < f.dlc && i < 8; ++i) {
    char b[3];
    std::snprintf(b, sizeof b, "%02X", f.data[i]);
    line += b;
  }
  return line;
}

inline std::optional<LoggedFrame> parse_candump_line(const std::string& line) {
  unsigned long long sec = 0;
  unsigned long long usec = 0;
  char interface[32] = {};
  char frame[64] = {};
  if (std::sscanf(line.c_str(), "(%llu.%llu) %31s %63s", &sec, &usec, interface, frame) != 4)
    return std::nullopt;
  const std::string text(frame);
  const auto hash = text.find('#');
  if (hash != 3 && hash != 8) return std::nullopt;
  LoggedFrame out;
  out.t_us = sec * 1000000 + usec;
  out.interface = interface;
  out.frame.extended = hash == 8;
  out.frame.id = static_cast<std::uint32_t>(std::stoul(text.substr(0, hash), nullptr, 16));
  const std::string data = text.substr(hash + 1);
  if (data.size() % 2 != 0 || data.size() > 16) return std::nullopt;
  out.frame.dlc = static_cast<std::uint8_t>(data.size() / 2);
  for (std::size_t i = 0; i < out.frame.dlc; ++i) {
    out.frame.data[i] = static_cast<std::uint8_t>(std::stoul(data.substr(2 * i, 2), nullptr, 16));
  }
  return out;
}

}  // namespace magvec::vmtest
