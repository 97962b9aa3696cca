// The CSV recording reader (magvec calibrate/apply input). The input is the file's content,
// written to an in-memory file (memfd) that the reader opens by path.
// Invariants: the only exception is CsvError naming the file; every record has a finite time, a
// field that is either finite on all axes or a dropout (all NaN), finite F and theta when present,
// and a finite orthonormal attitude when present; line numbers increase.
#include <sys/mman.h>
#include <unistd.h>

#include <cmath>
#include <string>

#include "fuzz_check.hpp"
#include "magvec/host/io/csv.hpp"

using namespace magvec;

namespace {

int memfd() {
  static const int fd = ::memfd_create("magvec_csv_fuzz", 0);
  return fd;
}

}  // namespace

extern "C" int LLVMFuzzerTestOneInput(const std::uint8_t* data, std::size_t size) {
  const int fd = memfd();
  FUZZ_CHECK(fd >= 0);
  FUZZ_CHECK(::ftruncate(fd, 0) == 0);
  FUZZ_CHECK(::pwrite(fd, data, size, 0) == static_cast<ssize_t>(size));
  const std::string path = "/proc/self/fd/" + std::to_string(fd);
  try {
    host::io::CsvReader reader(path);
    host::io::CsvRecord r;
    std::uint64_t last_line = 0;
    while (reader.next(&r)) {
      FUZZ_CHECK(r.line > last_line);
      last_line = r.line;
      FUZZ_CHECK(std::isfinite(r.t_s));
      if (r.dropout) {
        FUZZ_CHECK(r.m_nT.array().isNaN().all());
      } else {
        FUZZ_CHECK(r.m_nT.allFinite());
      }
      if (r.f_nT) FUZZ_CHECK(std::isfinite(*r.f_nT));
      if (r.theta_deg) FUZZ_CHECK(std::isfinite(*r.theta_deg));
      if (r.r_bn) {
        FUZZ_CHECK(r.r_bn->allFinite());
        const double err = (*r.r_bn * r.r_bn->transpose() - core::Mat3<double>::Identity()).norm();
        FUZZ_CHECK(err < 1e-6);
      }
      for (std::size_t c = 0; c < reader.columns().size(); ++c)
        (void)reader.text(c);
    }
  } catch (const host::io::CsvError& e) {
    FUZZ_CHECK(e.file() == path);
    FUZZ_CHECK(std::string(e.what()).rfind(path, 0) == 0);
  }
  return 0;
}
