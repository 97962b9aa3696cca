// magvec: command-line front end (simulate, calibrate, apply, run, replay, report).
#include <CLI/CLI.hpp>
#include <iostream>

#include "magvec/version.hpp"

int main(int argc, char** argv) {
  CLI::App app{"magvec: strapdown magnetic vector calibration and compensation"};
  app.set_version_flag("--version", std::string("magvec ") + magvec::kVersion);
  app.require_subcommand(0, 1);
  CLI11_PARSE(app, argc, argv);
  if (app.get_subcommands().empty()) {
    std::cout << app.help();
  }
  return 0;
}
