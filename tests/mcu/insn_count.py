#!/usr/bin/env python3
"""Instructions per sample of the firmware image, counted by qemu's TCG `insn` plugin.

The plugin is not shipped by Debian: it is built from tests/plugin/insn.c of Debian's qemu source
package (apt-get source with a private APT_CONFIG holding a deb-src entry; cached in --cache),
needs libglib2.0-dev. Counts are deterministic (inline counting).
Method: the image runs `quiet n=<k>` (full pipeline: attitude buffer + core::SensorLoop with the
EkfCalibrator) and `baseline n=<k>` (simulated devices and codecs only); D(k) = full - baseline is
the firmware's own work (the baseline also runs the sample clock and the acquisition queue). A
first quiet run reports the loop's milestones (the samples that completed the EKF's initial fit,
raised the solve ticket, had the solve's result installed, applied the calibration); the windows
are placed from them, and per-sample figures are differences of D between two k in one phase:
  calibrating: EKF update + compensation + loop (the filter running, before the solve), without
               the samples whose update relinearised the EKF's start-up set (reported apart)
  relinearisation: D(k) - D(k - 1) - the calibrating per-sample work, for each such sample k (the
               image reports them): the start-up set's term relinearised (docs/equations.md
               E-Acc-3), a few times per calibration, inside the sample as the initial fit is
  calibrated:  compensation + loop (after the calibration is applied)
  solve:       D(ready) - D(ready - 1) - the calibrating per-sample work: the calibrator's batch
               solve (misalignment fit of the EKF's model + Li canonicalisation), which the image
               runs in the main loop's idle time after sample `ready`, not inside a sample
  solving:     the largest D(k) - D(k - 1) for ready < k <= installed: a sample's own work while
               the solve is pending (the installing sample starts the validation)
  initial fit: D(init) - D(init - 1) - the collecting per-sample work: the EKF's start-up fit
--profile N: where the calibrating samples' instructions go, per function (the top N): qemu's
`hotblocks` contrib plugin (built like `insn`, its report limit lifted) counts each translation
block's executions in the same four runs; blocks are attributed to the ELF's symbols
(arm-none-eabi-nm) and the baseline's share is subtracted as above.
Exit 77 when the plugin cannot be built (no network, no glib headers) or the image is missing.
"""
import argparse
import bisect
import os
import re
import shutil
import subprocess
import sys
import tempfile

SKIP = 77
# The image's sample clock (SysTick) runs on instruction time: one instruction per virtual
# nanosecond, idle time skipped (deterministic interleaving of ticks and main loop).
ICOUNT = ["-icount", "shift=0,sleep=off"]
QEMU_SRC_VERSION = None  # the installed qemu's source version (dpkg), e.g. 1:7.2+dfsg-7+deb12u18


def skip(msg):
    print(f"SKIP: {msg}")
    sys.exit(SKIP)


# The plugins: library name -> (source in the qemu tree, edits to it).
PLUGINS = {
    "insn": ("tests/plugin/insn.c", []),
    # Every block in the report, not the top 20.
    "hotblocks": ("contrib/plugins/hotblocks.c",
                  [("static guint64 limit = 20;", "static guint64 limit = G_MAXUINT64;")]),
}


def build_plugin(cache, name="insn"):
    cache = os.path.abspath(cache)  # the private APT config needs absolute paths
    so = os.path.join(cache, f"lib{name}.so")
    if os.path.exists(so):
        return so
    os.makedirs(cache, exist_ok=True)
    ver = subprocess.run(["dpkg-query", "-W", "-f=${source:Version}", "qemu-system-arm"],
                         capture_output=True, text=True).stdout.strip()
    apt = os.path.join(cache, "apt")
    for d in ("etc/sources.list.d", "state/lists/partial", "cache/archives/partial"):
        os.makedirs(os.path.join(apt, d), exist_ok=True)
    with open(os.path.join(apt, "etc/sources.list"), "w") as f:
        f.write("deb-src http://deb.debian.org/debian bookworm main\n"
                "deb-src http://deb.debian.org/debian bookworm-updates main\n"
                "deb-src http://deb.debian.org/debian-security bookworm-security main\n")
    conf = os.path.join(apt, "apt.conf")
    with open(conf, "w") as f:
        f.write(f'Dir::Etc::SourceList "{apt}/etc/sources.list";\n'
                f'Dir::Etc::SourceParts "{apt}/etc/sources.list.d";\n'
                f'Dir::State "{apt}/state";\nDir::State::status "/var/lib/dpkg/status";\n'
                f'Dir::Cache "{apt}/cache";\nDebug::NoLocking "true";\n')
    env = dict(os.environ, APT_CONFIG=conf)
    src = os.path.join(cache, "src")
    os.makedirs(src, exist_ok=True)
    try:
        subprocess.run(["apt-get", "update", "-qq"], env=env, check=True, timeout=600)
        subprocess.run(["apt-get", "source", "--download-only", f"qemu={ver}" if ver else "qemu"],
                       env=env, cwd=src, check=True, timeout=900, capture_output=True)
        orig = [f for f in os.listdir(src) if f.endswith(".orig.tar.xz")][0]
        top = subprocess.run(["tar", "tf", os.path.join(src, orig)], capture_output=True,
                             text=True).stdout.split("/", 1)[0]
        path, edits = PLUGINS[name]
        subprocess.run(["tar", "xf", orig, f"{top}/{path}", f"{top}/include/qemu/qemu-plugin.h"],
                       cwd=src, check=True)
        c_file = os.path.join(src, top, path)
        text = open(c_file).read()
        for old, new in edits:
            if old not in text:
                raise OSError(f"{path}: '{old}' not found")
            text = text.replace(old, new)
        open(c_file, "w").write(text)
        glib = subprocess.run(["pkg-config", "--cflags", "glib-2.0"], capture_output=True,
                              text=True, check=True).stdout.split()
        subprocess.run(["gcc", "-O2", "-shared", "-fPIC", "-I", f"{src}/{top}/include/qemu", *glib,
                        c_file, "-o", so], check=True)
    except (subprocess.SubprocessError, IndexError, OSError) as e:
        skip(f"could not build the qemu insn plugin: {e}")
    return so


def image_cmd(qemu, machine, elf, args):
    """qemu running the image with app arguments `args` on the instruction-time clock."""
    sh = ",".join(["enable=on", "target=native", "arg=magvec_app"] + [f"arg={x}" for x in args])
    return [qemu, "-M", machine, "-nographic", "-monitor", "none", "-serial", "none", *ICOUNT,
            "-semihosting-config", sh, "-kernel", elf]


def count(qemu, machine, elf, plugin, args, timeout):
    with tempfile.NamedTemporaryFile(suffix=".log") as log:
        p = subprocess.run(image_cmd(qemu, machine, elf, args) +
                           ["-plugin", f"{plugin},inline=on", "-d", "plugin", "-D", log.name],
                           capture_output=True, text=True, timeout=timeout)
        text = open(log.name).read()
    m = re.search(r"insns: (\d+)", text)
    # Counting only (the mcu tests check the results): a run cut short by n=<k> may end before the
    # calibration is applied (exit code 5); anything else is a failure.
    if p.returncode not in (0, 5) or m is None:
        print(p.stdout, p.stderr, text)
        raise SystemExit(f"qemu run {args} failed (rc {p.returncode})")
    return int(m.group(1))


def block_profile(qemu, machine, elf, plugin, args, timeout):
    """Instructions executed per translation block start address (hotblocks: icount x ecount)."""
    with tempfile.NamedTemporaryFile(suffix=".log") as log:
        subprocess.run(image_cmd(qemu, machine, elf, args) +
                       ["-plugin", plugin, "-d", "plugin", "-D", log.name],
                       capture_output=True, timeout=timeout)
        lines = open(log.name).read().splitlines()
    out = {}
    for line in lines:
        parts = [x.strip() for x in line.split(",")]
        if len(parts) != 4 or not parts[0].startswith("0x"):
            continue
        pc = int(parts[0], 16)
        out[pc] = out.get(pc, 0) + int(parts[2]) * int(parts[3])
    return out


def function_profile(qemu, machine, elf, plugin, k0, k1, top, timeout):
    nm = shutil.which("arm-none-eabi-nm")
    if nm is None:
        skip("arm-none-eabi-nm not installed (toolchain/setup)")
    syms = []
    for line in subprocess.run([nm, "-S", "-C", elf], capture_output=True, text=True,
                               check=True).stdout.splitlines():
        p = line.split(None, 3)
        if len(p) == 4 and p[2].lower() in ("t", "w"):
            syms.append((int(p[0], 16) & ~1, int(p[1], 16), p[3]))
    syms.sort()
    starts = [x[0] for x in syms]

    def name(pc):
        i = bisect.bisect_right(starts, pc) - 1
        return syms[i][2] if i >= 0 and pc < syms[i][0] + max(syms[i][1], 1) else "?"

    per_fn = {}
    for k, sign in ((k1, 1), (k0, -1)):
        for mode, msign in (("quiet", 1), ("baseline", -1)):
            for pc, n in block_profile(qemu, machine, elf, plugin, [mode, f"n={k}"],
                                       timeout).items():
                fn = name(pc)
                per_fn[fn] = per_fn.get(fn, 0) + sign * msign * n
    total = sum(per_fn.values()) / (k1 - k0)
    print(f"per calibrating sample, by function (samples {k0}-{k1}; total {total:.0f}):")
    for fn, n in sorted(per_fn.items(), key=lambda x: -abs(x[1]))[:top]:
        print(f"{n / (k1 - k0):8.0f}  {fn[:150]}")


def milestones(qemu, machine, elf, timeout):
    p = subprocess.run(image_cmd(qemu, machine, elf, ["quiet"]), capture_output=True, text=True,
                       timeout=timeout)
    m = re.search(r"MV milestones init_fit=(\d+) solve=(\d+) applied=(\d+) ready=(\d+)",
                  p.stdout)
    n = re.search(r"MV counts samples=(\d+)", p.stdout)
    r = re.search(r"MV relinearised at=([\d,]*)", p.stdout)
    if p.returncode != 0 or m is None or n is None or r is None:
        print(p.stdout, p.stderr)
        raise SystemExit(f"quiet run failed (rc {p.returncode})")
    return {"init_fit": int(m.group(1)), "solve": int(m.group(2)), "applied": int(m.group(3)),
            "ready": int(m.group(4)), "samples": int(n.group(1)),
            "relinearised": [int(k) for k in r.group(1).split(",") if k]}


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--machine", default="mps2-an386")
    ap.add_argument("--elf", required=True)
    ap.add_argument("--cache", required=True)
    ap.add_argument("--budget", type=float, default=0, help="fail if calibrating/sample > this")
    ap.add_argument("--budget-only", action="store_true",
                    help="measure the calibrating per-sample figure only (the ctest)")
    ap.add_argument("--timeout", type=float, default=300)
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="only the calibrating samples' instructions by function, the top N")
    a = ap.parse_args()
    if not os.path.exists(a.elf):
        skip(f"{a.elf} not built")
    qemu = shutil.which("qemu-system-arm")
    if qemu is None:
        skip("qemu-system-arm not installed")
    plugin = build_plugin(a.cache)

    ms = milestones(qemu, a.machine, a.elf, a.timeout)
    init, ready, solve = ms["init_fit"], ms["ready"], ms["solve"]
    applied, total = ms["applied"], ms["samples"]
    if not (0 < init < ready < solve < applied < total):
        raise SystemExit(f"unexpected milestones {ms}")
    d = {}

    def core(k):
        if k not in d:
            full = count(qemu, a.machine, a.elf, plugin, ["quiet", f"n={k}"], a.timeout)
            base = count(qemu, a.machine, a.elf, plugin, ["baseline", f"n={k}"], a.timeout)
            d[k] = full - base
            print(f"n={k}: full {full} baseline {base} firmware {d[k]}")
        return d[k]

    c0, c1 = init + 100, ready - 100
    if a.profile > 0:
        function_profile(qemu, a.machine, a.elf, build_plugin(a.cache, "hotblocks"), c0, c1,
                         a.profile, a.timeout)
        return 0
    # The samples that relinearised the EKF's start-up set are events, measured apart.
    events = [k for k in ms["relinearised"] if c0 < k <= c1]
    event_insns = {k: core(k) - core(k - 1) for k in events}
    cal = (core(c1) - core(c0) - sum(event_insns.values())) / (c1 - c0 - len(events))
    print(f"per sample, calibrating (EKF update + compensation + loop): {cal:.0f} instructions")
    for k in events:
        print(f"relinearisation of the EKF's start-up set at sample {k}:    "
              f"{event_insns[k] - cal:.0f} instructions (with the window's average: "
              f"{(core(c1) - core(c0)) / (c1 - c0):.0f} per sample)")
    if a.budget_only:
        ok = a.budget <= 0 or cal <= a.budget
        print(f"{'ok' if ok else 'FAIL'}: {cal:.0f} instructions per calibrating sample, "
              f"budget {a.budget:.0f}")
        return 0 if ok else 1
    s0, s1 = applied + 100, min(total, applied + 2100)
    calibrated = (core(s1) - core(s0)) / (s1 - s0)
    collecting = (core(init - 1) - core(init - 101)) / 100
    solve_insns = core(ready) - core(ready - 1) - cal
    solving = {k: core(k) - core(k - 1) for k in range(ready + 1, solve + 1)}
    worst_k = max(solving, key=solving.get)
    init_insns = core(init) - core(init - 1) - collecting
    print(f"milestones: initial fit at sample {init}, solve ticket at {ready} (solved in idle "
          f"time), installed at {solve}, applied at {applied}")
    print(f"per sample, calibrated (compensation + loop):               {calibrated:.0f} instructions")
    print(f"per sample, collecting for the initial fit:                 {collecting:.0f} instructions")
    print(f"batch solve (misalignment fit + Li form), idle time:        {solve_insns:.0f} instructions")
    print(f"worst sample while the solve is pending (samples {ready + 1}-{solve}): "
          f"{solving[worst_k]} instructions (sample {worst_k})")
    print(f"EKF initial fit (quadric fit + Gauss-Newton + P0):          {init_insns:.0f} instructions")
    if a.budget > 0 and cal > a.budget:
        print(f"FAIL: {cal:.0f} > budget {a.budget:.0f} instructions per sample")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
