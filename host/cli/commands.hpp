// Subcommands of the magvec CLI. Each lives in its own file cmd_<name>.cpp and registers itself on
// the application with register_<name>(app); main.cpp calls every register function.
// A subcommand reports bad input by throwing (CLI::ValidationError for option values it checks
// itself, std::exception otherwise); main prints the message and exits non-zero.
#pragma once

#include <stdexcept>
#include <string>

namespace CLI {
class App;
}

namespace magvec::host::cli {

void register_simulate(CLI::App& app);
void register_demo(CLI::App& app);
void register_apply(CLI::App& app);
void register_run(CLI::App& app);
void register_report(CLI::App& app);
void register_calibrate(CLI::App& app);
void register_replay(CLI::App& app);
void register_ctl(CLI::App& app);
void register_soak(CLI::App& app);

// Thrown by a subcommand that must end with a specific exit status (e.g. calibrate: 2 bad input,
// 3 refused calibration); main prints what() (when not empty) and returns status().
class CommandExit : public std::runtime_error {
 public:
  CommandExit(int status, const std::string& message)
      : std::runtime_error(message), status_(status) {}
  int status() const noexcept { return status_; }

 private:
  int status_;
};

}  // namespace magvec::host::cli
