// The cal.json reader (magvec apply, magvecd's persisted calibration). Invariants: the only
// exception is CalibrationFileError naming the source; an accepted file has a finite, invertible
// W, a finite offset and a unit misalignment quaternion, finite noise figures or NaN, a time offset
// within +-10 s; writing it and reading the text back succeeds and gives the same model, time
// offset and counts.
#include <cmath>
#include <string>

#include "calibration/calibration_file.hpp"
#include "fuzz_check.hpp"

using namespace magvec;
using namespace magvec::host;

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const std::string text(reinterpret_cast<const char*>(data), size);
  CalibrationFile cal;
  try {
    cal = from_json_text(text, "fuzz/cal.json");
  } catch (const CalibrationFileError& e) {
    FUZZ_CHECK(std::string(e.what()).rfind("fuzz/cal.json: ", 0) == 0);
    return 0;
  }
  FUZZ_CHECK(cal.model.w.allFinite() && cal.model.o.allFinite());
  const double det = cal.model.w.determinant();
  FUZZ_CHECK(std::isfinite(det) && std::abs(det) > 1e-12);
  FUZZ_CHECK(std::abs(cal.model.rm.norm() - 1.0) < 1e-12);
  FUZZ_CHECK(std::isfinite(cal.time_offset_s) && std::abs(cal.time_offset_s) <= 10.0);
  if (cal.time_offset_sigma_s) FUZZ_CHECK(*cal.time_offset_sigma_s >= 0);
  for (const double v :
       {cal.noise.mag_nT, cal.noise.mag_sigma_nT, cal.noise.ins_deg, cal.noise.ins_sigma_deg})
    FUZZ_CHECK(std::isnan(v) || (std::isfinite(v) && v >= 0));

  std::string written;
  CalibrationFile back;
  try {
    written = to_json_text(cal);
    back = from_json_text(written, "fuzz/written.json");
  } catch (const std::exception& e) {
    std::fprintf(stderr, "written file rejected: %s\n", e.what());
    FUZZ_CHECK(false && "a file the reader accepted must survive write + read");
  }
  FUZZ_CHECK(back.model.w == cal.model.w);
  FUZZ_CHECK(back.model.o == cal.model.o);
  FUZZ_CHECK(std::abs(std::abs(back.model.rm.dot(cal.model.rm)) - 1.0) < 1e-12);
  FUZZ_CHECK(back.time_offset_s == cal.time_offset_s);
  FUZZ_CHECK(back.counts.samples == cal.counts.samples && back.counts.used == cal.counts.used);
  FUZZ_CHECK(back.sigma == cal.sigma);
  // Not asserted: to_json_text(back) == written. Rm_quat is renormalised on every read, which is
  // not idempotent in floating point, so the derived li/ge blocks may differ in the last bits.
  FUZZ_CHECK(from_json_text(to_json_text(back), "fuzz/again.json").model.w == cal.model.w);
  return 0;
}
