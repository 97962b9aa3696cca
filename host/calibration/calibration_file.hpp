// cal.json: the calibration result file (schema "magvec-calibration/1", documented in README.md).
// The canonical W / o_nT / Rm_quat are authoritative; the paper forms (li, ge, sine) are derived
// from them when written and checked for consistency when read.
#pragma once

#include <cstdint>
#include <limits>
#include <map>
#include <optional>
#include <stdexcept>
#include <string>
#include <vector>

#include "magvec/core/sensor_model.hpp"

namespace magvec::host {

class CalibrationFileError : public std::runtime_error {
 public:
  using std::runtime_error::runtime_error;
};

struct SineResult {
  core::SineParams<double> params;
  double inclination_rad{0};
};

struct CalibrationQuality {
  std::string verdict = "ok";  // ok, insufficient_coverage, ill_conditioned, ...
  std::string reason;          // human-readable explanation of the verdict
  double coverage{0};          // fraction of the sphere of directions covered [0, 1]
  double condition{0};         // condition number of the fit's normal matrix
  double residual_rms_before_nT{0};
  double residual_rms_after_nT{0};
  std::map<std::string, double> extra;  // further figures (e.g. component spread)
};

struct CalibrationCounts {
  std::uint64_t samples{0};            // rows read
  std::uint64_t used{0};               // rows that entered the fit
  std::uint64_t skipped_nonfinite{0};  // nan dropouts
  std::uint64_t rejected_outliers{0};
};

struct Provenance {
  std::string input;
  std::string method;
  std::string magvec_version;
  std::string created_utc;
};

// Noise figures a calibration used: estimated from the data's residuals, or given by the user.
// NaN where not applicable (no attitude: no INS figure).
struct NoiseFigures {
  double mag_nT = std::numeric_limits<double>::quiet_NaN();        // per axis, 1-sigma
  double mag_sigma_nT = std::numeric_limits<double>::quiet_NaN();  // 1-sigma of that estimate
  bool mag_estimated = false;  // false: the given value (--noise-nT) was used
  double ins_deg = std::numeric_limits<double>::quiet_NaN();  // per INS angle, 1-sigma
  double ins_sigma_deg = std::numeric_limits<double>::quiet_NaN();
  bool ins_estimated = false;
};

// What records carry while this calibration is active, from the sensor loop's held-out
// validation (JSON "output"; absent for calibrations not validated in a loop, e.g. `magvec
// calibrate`: the loop then falls back to its configured noise).
struct OutputQuality {
  bool aligned = true;  // Rm estimates the misalignment to the INS (h_n is E/N/U)
  double sigma_f_nT = std::numeric_limits<double>::quiet_NaN();    // 1-sigma of |h|
  double sigma_enu_nT = std::numeric_limits<double>::quiet_NaN();  // 1-sigma per E/N/U axis
  // The scale came from a geomagnetic model's F (magvecd without a scalar magnetometer): the
  // records carry kOutModelReference and sigma_f_nT includes the model's 1-sigma.
  bool model_reference = false;
};

// The geomagnetic model's field at the survey site (magvec calibrate --site/--date).
struct ModelReference {
  std::string name;                            // e.g. "WMM2025"
  double lat_deg{0}, lon_deg{0}, height_m{0};  // geodetic, height above the WGS84 ellipsoid
  std::string date;                            // YYYY-MM-DD
  double decimal_year{0};
  core::Vec3<double> enu_nT = core::Vec3<double>::Zero();
  core::Vec3<double> sigma_enu_nT = core::Vec3<double>::Zero();  // the model's stated 1-sigma
  double f_nT{0}, sigma_f_nT{0};
  double declination_deg{0}, sigma_declination_deg{0};
  double inclination_deg{0}, sigma_inclination_deg{0};
};

// Where the reference total field came from (JSON "reference"; absent in older files).
struct ReferenceInfo {
  // "measured" (the file's F_nT column), "model" (--site/--date), "given" (--field-nT) or
  // "data" (the median |m|: relative scale only).
  std::string source;
  double f_nT = std::numeric_limits<double>::quiet_NaN();        // F for rows without one
  double sigma_f_nT = std::numeric_limits<double>::quiet_NaN();  // its stated 1-sigma, if known
  std::optional<ModelReference> model;  // also present as a check when the F was measured
};

struct CalibrationFile {
  // False when the method refused before it had any solution (nothing to write, not even with
  // --force-write). Not stored in the file: a written file always holds a solution.
  bool has_solution = true;
  core::SensorModel<double> model;
  // Magnetometer time stamp minus the INS time of the attitude it belongs to [s]: positive when
  // the magnetometer lags the INS. A magnetometer sample stamped t pairs with the attitude at
  // t - time_offset_s (apply, run, replay and magvecd do so).
  double time_offset_s{0};
  // 1-sigma of time_offset_s when it was estimated; absent when it was fixed or not observable.
  std::optional<double> time_offset_sigma_s;
  NoiseFigures noise;
  std::optional<OutputQuality> output;
  std::optional<core::Vec3<double>> h_n_nT;
  std::optional<ReferenceInfo> reference;
  std::optional<SineResult> sine;
  // 1-sigma of the paper-form parameters, by name (e.g. "ks", "O_deg", "Kof_nT", "Rm_deg").
  std::map<std::string, std::vector<double>> sigma;
  CalibrationQuality quality;
  CalibrationCounts counts;
  Provenance provenance;
};

// Serialises to JSON text (pretty, stable key order).
std::string to_json_text(const CalibrationFile& cal);
// Parses and validates; throws CalibrationFileError naming `source` and the offending field.
CalibrationFile from_json_text(const std::string& text, const std::string& source);

// Atomic, power-cut-safe write (temp file in the same directory, fsync, rename, fsync directory).
void write_calibration_file(const std::string& path, const CalibrationFile& cal);
CalibrationFile read_calibration_file(const std::string& path);

// Current UTC time as ISO 8601 (for provenance).
std::string utc_now_iso8601();

}  // namespace magvec::host
