#!/usr/bin/env python3
"""Flash/RAM split of a firmware image by symbol (arm-none-eabi-nm -S): core + loop (magvec::core,
Eigen, the app's SensorLoop glue), drivers (codecs, ParamStore), simulated devices and scenario
(magvec::drivers::sim, only in the emulated test images), app/board, C/C++ runtime (libc, libm,
libgcc soft-float: shared, listed apart). Usage: size_split.py <elf>"""
import collections
import subprocess
import sys


# The app's statically allocated core objects (calibrator, loop, attitude buffer).
CORE_OBJECTS = ("::g_cal", "::g_loop", "::g_attitude")


def group(name):
    if name.endswith(CORE_OBJECTS):
        return "core+loop"
    if name.startswith("magvec::core::") or name.startswith("Eigen::") or "magvec::core::" in name:
        return "core+loop"
    if name.startswith("magvec::drivers::sim::"):
        return "sim"
    if name.startswith("magvec::drivers::"):
        return "drivers"
    if name.startswith("magvec::app::") or name.startswith("(anonymous") or name in (
            "main", "Reset_Handler", "Default_Handler", "g_vectors"):
        return "app+board"
    return "runtime"


def main():
    out = subprocess.run(["arm-none-eabi-nm", "-S", "-C", "--size-sort", sys.argv[1]],
                         capture_output=True, text=True, check=True).stdout
    flash = collections.Counter()
    ram = collections.Counter()
    for line in out.splitlines():
        p = line.split(None, 3)
        if len(p) != 4:
            continue
        size, kind, name = int(p[1], 16), p[2].lower(), p[3]
        g = group(name)
        if kind in ("t", "r", "w", "v"):
            flash[g] += size
        elif kind in ("b", "d"):
            ram[g] += size
            if kind == "d":
                flash[g] += size
    for g in ("core+loop", "drivers", "sim", "app+board", "runtime"):
        print(f"{g:10s} flash {flash[g]:7d} B  ram {ram[g]:7d} B")


if __name__ == "__main__":
    main()
