// Subcommands of the magvec CLI. Each lives in its own file cmd_<name>.cpp and registers itself on
// the application with register_<name>(app); main.cpp calls every register function.
// A subcommand reports bad input by throwing (CLI::ValidationError for option values it checks
// itself, std::exception otherwise); main prints the message and exits non-zero.
#pragma once

namespace CLI {
class App;
}

namespace magvec::host::cli {

void register_simulate(CLI::App& app);
void register_demo(CLI::App& app);
void register_apply(CLI::App& app);
void register_run(CLI::App& app);
void register_report(CLI::App& app);

}  // namespace magvec::host::cli
