// magvec: command-line front end (simulate, calibrate, apply, run, replay, ctl, report, soak).
// Subcommands register themselves (commands.hpp); errors end with a message and a non-zero exit.
#include <CLI/CLI.hpp>
#include <exception>
#include <iostream>

#include "commands.hpp"
#include "magvec/version.hpp"

int main(int argc, char** argv) {
  CLI::App app{"magvec: strapdown magnetic vector calibration and compensation"};
  app.set_version_flag("--version", std::string("magvec ") + magvec::kVersion);
  app.require_subcommand(0, 1);
  magvec::host::cli::register_simulate(app);
  magvec::host::cli::register_demo(app);
  magvec::host::cli::register_apply(app);
  magvec::host::cli::register_run(app);
  magvec::host::cli::register_report(app);
  magvec::host::cli::register_calibrate(app);
  magvec::host::cli::register_replay(app);
  magvec::host::cli::register_ctl(app);
  magvec::host::cli::register_soak(app);
  try {
    app.parse(argc, argv);
  } catch (const CLI::ParseError& e) {
    return app.exit(e);
  } catch (const magvec::host::cli::CommandExit& e) {
    if (e.what()[0] != '\0') std::cerr << "magvec: error: " << e.what() << "\n";
    return e.status();
  } catch (const std::exception& e) {
    std::cerr << "magvec: error: " << e.what() << "\n";
    return 1;
  }
  if (app.get_subcommands().empty()) std::cout << app.help();
  return 0;
}
