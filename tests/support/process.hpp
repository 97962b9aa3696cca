// Runs a shell command for end-to-end tests of the built binaries and captures its output.
// A sanitizer report in the output (the host-asan build runs sanitized binaries as children) fails
// the calling test even when the test expects the command to fail: its exit status alone would
// not tell a sanitizer's exit from the expected one. (GCC 12's UBSan, linked with ASan, ignores
// log_path and reports only on stderr, so the output is where a child's report can be seen.)
#pragma once

#include <gtest/gtest.h>
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
  for (const char* report :
       {": runtime error: ", "ERROR: AddressSanitizer", "ERROR: LeakSanitizer"}) {
    if (out.find(report) != std::string::npos)
      ADD_FAILURE() << "sanitizer report from `" << command << "`:\n" << out;
  }
  return {WIFEXITED(st) ? WEXITSTATUS(st) : -1, out};
}

}  // namespace magvec::test
