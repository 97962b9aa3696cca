// magvecd's exit codes and the error that carries one out of the daemon's pieces to main().
#pragma once

#include <stdexcept>
#include <string>

namespace magvec::host::daemon {

enum ExitCode : int {
  kExitOk = 0,
  kExitInternal = 1,
  kExitConfig = 2,  // bad configuration or usage
  kExitDevice = 3,
  kExitCorruptParams = 4,  // corrupt calibration file (never overwritten)
  kExitLcm = 5,
};

class DaemonError : public std::runtime_error {
 public:
  DaemonError(int code, const std::string& what) : std::runtime_error(what), code_(code) {}
  int code() const noexcept { return code_; }

 private:
  int code_;
};

}  // namespace magvec::host::daemon
