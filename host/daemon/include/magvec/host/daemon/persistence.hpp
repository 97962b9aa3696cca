// magvecd's one persistence path: the accepted calibration is <state_dir>/cal.json (the CLI's
// calibration file format, written atomically: temp file, fsync, rename, fsync of the directory),
// loaded at start. A file that cannot be read is never overwritten: load() refuses to start
// (kExitCorruptParams) and the operator repairs or removes it.
#pragma once

#include <cstddef>
#include <cstdint>
#include <string>

#include "magvec/core/sensor_model.hpp"
#include "magvec/host/daemon/pipeline.hpp"

namespace magvec::host::daemon {

struct PersistedCalibration {
  bool present{false};
  core::SensorModel<double> model{};
  std::uint32_t cal_id{0};
  double time_offset_s{0};  // cal.json time_offset_s
  OutputQuality output{};   // cal.json output (absent: aligned, sigmas not known)
};

// The outcome of writing a calibration (CalibrationStore::write).
struct PersistOutcome {
  bool ok{false};
  std::string error;               // when !ok
  PersistedCalibration written{};  // when ok: what the file now holds
  std::string why;                 // what asked for it ("auto-accept", ...)
};

class CalibrationStore {
 public:
  explicit CalibrationStore(std::string state_dir);

  const std::string& path() const noexcept { return path_; }
  // Reads the file (not present: an empty calibration). Throws DaemonError(kExitCorruptParams)
  // when it exists but cannot be read; the file is left untouched. First removes the temporary
  // files a killed write left next to it (leftovers_removed()).
  PersistedCalibration load();
  std::size_t leftovers_removed() const noexcept { return leftovers_removed_; }
  // Writes `status`'s active calibration (cal_id, validation RMS, calibrator in the provenance)
  // with `time_offset_s` to `path`; on failure the outcome's error, the previous file intact.
  // Touches no store: safe on another thread (PersistWorker), then mark_persisted(written).
  static PersistOutcome write(const std::string& path, const CalibrationStatus& status,
                              double time_offset_s, const std::string& why);
  void mark_persisted(const PersistedCalibration& p) { persisted_ = p; }
  // write() to path() and mark_persisted(), on the calling thread.
  bool save(const CalibrationStatus& status, double time_offset_s, const std::string& why,
            std::string* error);
  // The calibration in the file (what load() read or save()/mark_persisted() recorded last).
  const PersistedCalibration& persisted() const noexcept { return persisted_; }

 private:
  std::size_t remove_leftovers();
  std::string path_;
  PersistedCalibration persisted_{};
  std::size_t leftovers_removed_{0};
};

}  // namespace magvec::host::daemon
