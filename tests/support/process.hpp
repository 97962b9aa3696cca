// Runs a shell command for end-to-end tests of the built binaries and captures its output.
#pragma once

#include <sys/wait.h>

#include <cstdio>
#include <string>

namespace magvec::test {

struct CommandResult {
  int status;          // exit status, -1 when the command did not exit normally
  std::string output;  // stdout + stderr
};

inline CommandResult run_shell(const std::string& command) {
  FILE* p = ::popen((command + " 2>&1").c_str(), "r");
  if (p == nullptr) return {-1, ""};
  std::string out;
  char buf[4096];
  std::size_t n = 0;
  while ((n = std::fread(buf, 1, sizeof(buf), p)) > 0)
    out.append(buf, n);
  const int st = ::pclose(p);
  return {WIFEXITED(st) ? WEXITSTATUS(st) : -1, out};
}

}  // namespace magvec::test
