#!/usr/bin/env python3
"""The image's UART record path under qemu (a UART RecordSink for hardware).

Runs the image twice: once with the records on the semihosting console (default), once with the
option `uart`, the records going out through the polled CMSDK UART0 driver (mmio_uart.hpp) to
qemu's first serial backend (`-serial file:<tmp>`). Checks: both runs exit 0 (every on-target
check passed); the uart run announces records=uart and puts no record line on the console; the
serial file holds exactly the console run's record lines, in order, byte for byte (the run is
deterministic), as many as the image counted emitted, none failed.
Exit 77 (ctest SKIP_RETURN_CODE) when the image or qemu is missing.
"""
import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile

SKIP = 77


def skip(msg):
    print(f"SKIP: {msg}")
    sys.exit(SKIP)


def run(qemu, machine, elf, serial, args, timeout):
    sh = ",".join(["enable=on", "target=native", "arg=magvec_app"] + [f"arg={a}" for a in args])
    # -icount: the image's sample clock (SysTick) on instruction time, a deterministic run.
    p = subprocess.run([qemu, "-M", machine, "-nographic", "-monitor", "none", "-serial", serial,
                        "-icount", "shift=0,sleep=off", "-semihosting-config", sh, "-kernel", elf],
                       capture_output=True, text=True, timeout=timeout)
    return p.returncode, p.stdout, p.stderr


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--machine", required=True)
    ap.add_argument("--elf", required=True)
    ap.add_argument("--timeout", type=float, default=180)
    a = ap.parse_args()
    if not os.path.exists(a.elf):
        skip(f"{a.elf} not built (cmake --preset m4f && cmake --build --preset m4f)")
    qemu = shutil.which("qemu-system-arm")
    if qemu is None:
        skip("qemu-system-arm not installed (toolchain/setup)")

    failures = 0

    def check(ok, what):
        nonlocal failures
        print(("ok    " if ok else "FAIL  ") + what)
        failures += 0 if ok else 1

    rc, console_out, err = run(qemu, a.machine, a.elf, "none", [], a.timeout)
    check(rc == 0, f"console run exit code {rc} {err.strip()}")
    console_recs = [l for l in console_out.splitlines() if l.startswith("MV rec ")]
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "uart0.txt")
        rc, uart_out, err = run(qemu, a.machine, a.elf, f"file:{path}", ["uart"], a.timeout)
        check(rc == 0, f"uart run exit code {rc} {err.strip()}")
        with open(path, "rb") as f:
            raw = f.read()
    check("records=uart" in uart_out, "uart run announces records=uart")
    check(not any(l.startswith("MV rec ") for l in uart_out.splitlines()),
          "uart run writes no record line to the console")
    text = raw.decode("ascii", errors="replace")
    uart_lines = text.splitlines()
    uart_recs = [l for l in uart_lines if l.startswith("MV rec ")]
    check(len(uart_recs) == len(uart_lines), f"serial output is record lines only "
          f"({len(uart_lines) - len(uart_recs)} other line(s))")
    check(raw.endswith(b"\n"), "serial output ends with a complete line")
    check(len(console_recs) > 0, f"{len(console_recs)} record lines on the console run")
    check(uart_recs == console_recs,
          f"serial record lines identical to the console run's ({len(uart_recs)} vs "
          f"{len(console_recs)})")
    m = re.search(r"MV counts .* records=(\d+) record_failures=(\d+)", uart_out)
    check(m is not None and int(m.group(1)) == len(uart_recs) and m.group(2) == "0",
          f"image counted {m.group(1) if m else '?'} records emitted, "
          f"{m.group(2) if m else '?'} failed; the serial file holds {len(uart_recs)}")
    print(f"{failures} failure(s)")
    return 1 if failures else 0


if __name__ == "__main__":
    sys.exit(main())
