// `magvec demo` (placeholder until the demo step is implemented below).
#include <CLI/CLI.hpp>

#include "commands.hpp"

namespace magvec::host::cli {
void register_demo(CLI::App&) {}
}  // namespace magvec::host::cli
