// Runs the drawing script of `magvec report` (see report.hpp): python3 + matplotlib only draw.
#include <spawn.h>
#include <sys/wait.h>
#include <unistd.h>

#include <cerrno>
#include <cstdlib>
#include <cstring>
#include <filesystem>
#include <string>
#include <vector>

#include "report/report.hpp"

extern char** environ;

namespace magvec::host::report {
namespace {

namespace fs = std::filesystem;

// Exit codes of magvec_report.py for missing modules (kept in sync with the script).
constexpr int kExitNoMatplotlib = 3;
constexpr int kExitNoNumpy = 4;

std::string env_or(const char* name, const std::string& fallback) {
  const char* v = std::getenv(name);
  return (v != nullptr && *v != '\0') ? std::string(v) : fallback;
}

}  // namespace

std::string locate_script() {
  if (const char* v = std::getenv("MAGVEC_REPORT_SCRIPT"); v != nullptr && *v != '\0') {
    if (!fs::is_regular_file(v)) {
      throw ReportError(std::string("MAGVEC_REPORT_SCRIPT=") + v + ": no such file");
    }
    return v;
  }
  std::vector<fs::path> candidates;
  std::error_code ec;
  const fs::path exe = fs::read_symlink("/proc/self/exe", ec);
  if (!ec) {
    candidates.push_back(exe.parent_path() / "magvec_report.py");
    candidates.push_back(exe.parent_path().parent_path() / "share" / "magvec" / "magvec_report.py");
  }
#ifdef MAGVEC_REPORT_SCRIPT_SOURCE
  candidates.emplace_back(MAGVEC_REPORT_SCRIPT_SOURCE);
#endif
  for (const fs::path& p : candidates) {
    if (fs::is_regular_file(p, ec)) return p.string();
  }
  std::string tried;
  for (const fs::path& p : candidates)
    tried += "\n  " + p.string();
  throw ReportError("cannot find the report script magvec_report.py; tried:" + tried +
                    "\n(set MAGVEC_REPORT_SCRIPT to its path)");
}

void render(const std::string& out_dir, const std::vector<std::string>& figures) {
  const std::string python = env_or("MAGVEC_PYTHON", "/usr/bin/python3");
  if (::access(python.c_str(), X_OK) != 0) {
    throw ReportError(python +
                      " not found: the report needs Python 3 with matplotlib; install the Debian "
                      "packages python3 python3-matplotlib python3-numpy "
                      "(apt-get install python3 python3-matplotlib python3-numpy)");
  }
  const std::string script = locate_script();
  std::vector<std::string> args = {python, script, out_dir};
  std::vector<char*> argv;
  for (std::string& a : args)
    argv.push_back(a.data());
  argv.push_back(nullptr);
  pid_t pid = 0;
  const int rc = ::posix_spawn(&pid, python.c_str(), nullptr, nullptr, argv.data(), environ);
  if (rc != 0) throw ReportError("cannot run " + python + ": " + std::strerror(rc));
  int status = 0;
  while (::waitpid(pid, &status, 0) < 0) {
    if (errno != EINTR) throw ReportError(std::string("waitpid: ") + std::strerror(errno));
  }
  if (!WIFEXITED(status)) throw ReportError("the report script " + script + " was killed");
  const int code = WEXITSTATUS(status);
  if (code == kExitNoMatplotlib) {
    throw ReportError(
        "python3 cannot import matplotlib: install the Debian package "
        "python3-matplotlib (apt-get install python3-matplotlib)");
  }
  if (code == kExitNoNumpy) {
    throw ReportError(
        "python3 cannot import numpy: install the Debian package python3-numpy "
        "(apt-get install python3-numpy)");
  }
  if (code != 0) {
    throw ReportError("the report script " + script + " failed (exit " + std::to_string(code) +
                      ")");
  }
  const fs::path dir(out_dir);
  if (!fs::is_regular_file(dir / "index.html")) {
    throw ReportError("the report script did not write " + (dir / "index.html").string());
  }
  for (const std::string& f : figures) {
    if (!fs::is_regular_file(dir / f)) {
      throw ReportError("the report script did not write " + (dir / f).string());
    }
  }
}

}  // namespace magvec::host::report
