// Helpers of the guest tests (tests/vm): the guest's /init (toolchain/vm/init) exports
// where the kernel facilities are; these tests run only inside the VM, where a missing variable or
// device is a failure of the guest setup, never a reason to skip.
#pragma once

#include <gtest/gtest.h>

#include <cstdint>
#include <cstdlib>
#include <fstream>
#include <string>

namespace magvec::vmtest {

inline std::string env(const char* name, const char* fallback = "") {
  const char* v = std::getenv(name);
  return v != nullptr && *v != '\0' ? std::string(v) : std::string(fallback);
}

// Reads an unsigned integer from a sysfs attribute (module parameter); -1 when unreadable.
inline long long read_sysfs_number(const std::string& path) {
  std::ifstream f(path);
  long long v = -1;
  if (!(f >> v)) return -1;
  return v;
}

inline bool write_sysfs(const std::string& path, const std::string& value) {
  std::ofstream f(path);
  f << value;
  f.flush();
  return static_cast<bool>(f);
}

}  // namespace magvec::vmtest
