// magvecd's persisted calibration; see persistence.hpp.
#include "magvec/host/daemon/persistence.hpp"

#include <spdlog/spdlog.h>

#include <filesystem>
#include <system_error>

#include "calibration/calibration_file.hpp"
#include "magvec/host/daemon/daemon_error.hpp"
#include "magvec/host/io/csv.hpp"
#include "magvec/version.hpp"

namespace magvec::host::daemon {

CalibrationStore::CalibrationStore(std::string state_dir)
    : path_((std::filesystem::path(std::move(state_dir)) / "cal.json").string()) {}

std::size_t CalibrationStore::remove_leftovers() {
  // cal.json only ever changes by io::AtomicFile's rename(), so a file with its temporary prefix
  // is a write that was killed (SIGKILL, power cut) before its rename: never the calibration in
  // force, and safe to remove.
  namespace fs = std::filesystem;
  const fs::path target(path_);
  const std::string prefix = io::AtomicFile::temporary_prefix(target.filename().string());
  std::size_t removed = 0;
  std::error_code ec;
  for (fs::directory_iterator it(target.parent_path(), ec), end; !ec && it != end;
       it.increment(ec)) {
    const std::string name = it->path().filename().string();
    if (name.rfind(prefix, 0) != 0 || !it->is_regular_file(ec)) continue;
    std::error_code rm;
    if (fs::remove(it->path(), rm)) {
      ++removed;
    } else if (rm) {
      spdlog::warn("cannot remove {} (left by an interrupted write): {}", it->path().string(),
                   rm.message());
    }
  }
  if (removed > 0)
    spdlog::info("removed {} temporary file(s) of an interrupted calibration write next to {}",
                 removed, path_);
  return removed;
}

PersistedCalibration CalibrationStore::load() {
  PersistedCalibration p;
  leftovers_removed_ = remove_leftovers();
  std::error_code ec;
  if (!std::filesystem::exists(path_, ec)) {
    spdlog::info("no persisted calibration ({}): starting uncalibrated", path_);
    persisted_ = p;
    return p;
  }
  try {
    const host::CalibrationFile f = host::read_calibration_file(path_);
    p.present = true;
    p.model = f.model;
    p.time_offset_s = f.time_offset_s;
    if (f.output) p.output = *f.output;
    // A file written by `magvec calibrate` has no cal_id: it becomes calibration 1.
    const auto it = f.quality.extra.find("cal_id");
    p.cal_id = it != f.quality.extra.end() && it->second >= 1 && it->second < 4e9
                   ? static_cast<std::uint32_t>(it->second)
                   : 1;
    spdlog::info("loaded persisted calibration {} (cal_id {}, method {}, {})", path_, p.cal_id,
                 f.provenance.method, f.provenance.created_utc);
  } catch (const std::exception& e) {
    throw DaemonError(kExitCorruptParams,
                      std::string("corrupt calibration file: ") + e.what() +
                          " - the file is left untouched; repair or remove it (magvecd does not "
                          "overwrite it)");
  }
  persisted_ = p;
  return p;
}

PersistOutcome CalibrationStore::write(const std::string& path, const CalibrationStatus& st,
                                       double time_offset_s, const std::string& why) {
  PersistOutcome o;
  o.why = why;
  host::CalibrationFile f;
  f.model = st.active;
  // The loop's calibrators do not estimate the time offset: the one in use is kept.
  f.time_offset_s = time_offset_s;
  f.quality.verdict = "ok";
  f.quality.reason = "accepted by magvecd (" + why + ")";
  f.quality.extra["cal_id"] = st.cal_id;
  f.quality.extra["validation_rms_nT"] = st.validation_rms_nT;
  f.output = st.output;
  f.provenance.input = "magvecd live calibration";
  f.provenance.method = st.calibrator;
  f.provenance.magvec_version = kVersion;
  f.provenance.created_utc = host::utc_now_iso8601();
  try {
    host::write_calibration_file(path, f);
  } catch (const std::exception& e) {
    o.error = e.what();
    return o;
  }
  o.ok = true;
  o.written.present = true;
  o.written.model = st.active;
  o.written.cal_id = st.cal_id;
  o.written.time_offset_s = time_offset_s;
  o.written.output = st.output;
  return o;
}

bool CalibrationStore::save(const CalibrationStatus& st, double time_offset_s,
                            const std::string& why, std::string* error) {
  const PersistOutcome o = write(path_, st, time_offset_s, why);
  if (!o.ok) {
    if (error != nullptr) *error = o.error;
    return false;
  }
  mark_persisted(o.written);
  return true;
}

}  // namespace magvec::host::daemon
