#!/usr/bin/env python3
"""Runs the firmware image under qemu-system-arm and compares its report with the host twin.

Modes:
  double  M7 image (Scalar = double) vs magvec_app_host_double: bit-identical (every reported
          value, counter and record line);
  float   M4F image (Scalar = float) vs magvec_app_host_double: intensity RMSE within 1.1x, every
          G and b element within FRACTION (3) of its 1-sigma (the EKF's float32 tolerance).
  cli     no image: magvec_app_host_double vs `magvec run --profile mcu` (--cli): every record
          line of the twin bit-identical to the CLI's record of the same number (the CSV holds
          shortest round-trip decimals, so exact doubles).
double and float: the on-target checks (power-cut sweep, reload from flash) passed,
sample/attitude counts identical. double with --cli: the CLI's records are compared too.
Exit 77 (ctest SKIP_RETURN_CODE) when the image or qemu is missing: build the m4f/m7 presets.
"""
import argparse
import csv
import math
import os
import shutil
import struct
import subprocess
import sys
import tempfile

SKIP = 77


def skip(msg):
    print(f"SKIP: {msg}")
    sys.exit(SKIP)


def value(tok):
    return struct.unpack(">d", bytes.fromhex(tok))[0]


def parse(text):
    out = {"rec": [], "lines": {}, "raw": {}, "rec_raw": []}  # raw: the exact hex tokens
    for line in text.splitlines():
        if not line.startswith("MV "):
            continue
        parts = line.split()
        key = parts[1]
        if key == "rec":  # t_us flags cal_id raw(3) h_s(3) F sigma_F h_n(3)
            out["rec_raw"].append(line)
            out["rec"].append((int(parts[2]), int(parts[3], 16), int(parts[4]),
                               [value(t) for t in parts[5:]]))
        elif key in ("model", "b", "sigma", "g", "g_sigma", "validation_rms", "stats"):
            out[key] = [value(t) for t in parts[2:]]
            out["raw"][key] = parts[2:]
        else:
            out["lines"][key] = " ".join(parts[2:])
    return out


def run(cmd, timeout):
    p = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, timeout=timeout,
                       text=True)
    return p.returncode, p.stdout, p.stderr


class Checker:
    def __init__(self):
        self.failures = 0

    def check(self, ok, what):
        print(("ok    " if ok else "FAIL  ") + what)
        if not ok:
            self.failures += 1


def same(x, y):
    return (math.isnan(x) and math.isnan(y)) or (x == y and math.copysign(1, x) ==
                                                  math.copysign(1, y))


def compare_cli(c, twin, cli, timeout):
    """The twin's record lines (every kRecordEvery-th record) against `magvec run --profile mcu`,
    whose CSV has every record: record k of the CLI is row k."""
    with tempfile.TemporaryDirectory() as d:
        out = os.path.join(d, "records.csv")
        rc, stdout, err = run([cli, "run", "--profile", "mcu", "--out", out], timeout)
        c.check(rc == 0, f"magvec run --profile mcu exit code {rc} {err.strip()}")
        if rc != 0:
            return
        print("cli:    " + stdout.strip().splitlines()[0])
        with open(out, newline="") as f:
            rows = list(csv.DictReader(line for line in f if not line.startswith("#")))
    # The twin's record lines are a thinned subset; each is found by its time stamp.
    by_t = {round(float(r["t_s"]) * 1e6): (k + 1, r) for k, r in enumerate(rows)}
    differ = []
    for t_us, flags, cal_id, v in twin["rec"]:
        if t_us not in by_t:
            differ.append(f"t_us {t_us}: no CLI record")
            continue
        k, r = by_t[t_us]
        cli_v = [float(r[n]) for n in ("hx_nT", "hy_nT", "hz_nT", "hsx_nT", "hsy_nT", "hsz_nT",
                                       "F_nT", "sigma_F_nT", "hE_nT", "hN_nT", "hU_nT")]
        ok = (int(float(r["flags"])) == flags and int(float(r["cal_id"])) == cal_id and
              all(same(x, y) for x, y in zip(v, cli_v)))
        if not ok:
            differ.append(f"record {k}: twin {t_us} {flags:#x} {cal_id} {v}; cli {dict(r)}")
    for line in differ[:3]:
        print("  " + line)
    # Every record, not only the compared ones: as many as the twin's pipeline emitted.
    pipe = dict(kv.split("=", 1) for kv in twin["lines"].get("pipeline", "").split() if "=" in kv)
    c.check(len(twin["rec"]) > 0 and not differ and str(len(rows)) == pipe.get("records"),
            f"magvec run --profile mcu: {len(twin['rec'])} of its {len(rows)} records (the twin's "
            f"pipeline: {pipe.get('records')}) compared with the twin's record lines, "
            f"{len(differ)} differ")
    cal_ids = {int(float(r["cal_id"])) for r in rows}
    c.check(1 in cal_ids, f"the CLI's run applied its calibration (cal_id {sorted(cal_ids)})")


def rel_close(a, b, rel, floor):
    return abs(a - b) <= rel * max(abs(a), abs(b), floor)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--machine", help="double and float modes: the qemu machine")
    ap.add_argument("--elf", help="double and float modes: the image")
    ap.add_argument("--host", required=True, help="host twin with the same Scalar as the image")
    ap.add_argument("--host-double", help="float mode: the double host twin")
    ap.add_argument("--mode", choices=["double", "float", "cli"], required=True)
    ap.add_argument("--cli", help="double and cli modes: the magvec CLI")
    ap.add_argument("--fraction", type=float, default=3.0,
                    help="float mode: allowed |float - double| in units of the 1-sigma")
    ap.add_argument("--timeout", type=float, default=120)
    a = ap.parse_args()

    if a.mode == "cli":
        c = Checker()
        rc, host_out, err = run([a.host], a.timeout)
        c.check(rc == 0, f"host twin {os.path.basename(a.host)} exit code {rc}")
        h = parse(host_out)
        print("host:   " + h["lines"].get("summary", "(no summary)"))
        compare_cli(c, h, a.cli, a.timeout)
        print(f"{c.failures} failure(s)")
        return 1 if c.failures else 0
    if not a.machine or not a.elf:
        ap.error("--machine and --elf are needed in the double and float modes")

    if not os.path.exists(a.elf):
        skip(f"{a.elf} not built (cmake --preset m4f/m7 && cmake --build --preset m4f/m7, "
             "or toolchain/test)")
    qemu = shutil.which("qemu-system-arm")
    if qemu is None:
        skip("qemu-system-arm not installed (toolchain/setup)")

    c = Checker()
    # -icount: the image's sample clock (SysTick) on instruction time (one instruction per
    # virtual nanosecond, idle time skipped), so ticks and main loop interleave deterministically.
    cmd = [qemu, "-M", a.machine, "-nographic", "-monitor", "none", "-serial", "none",
           "-icount", "shift=0,sleep=off", "-semihosting-config", "enable=on,target=native",
           "-kernel", a.elf]
    rc, target_out, err = run(cmd, a.timeout)
    c.check(rc == 0, f"qemu {a.machine} exit code {rc} (0 = on-target checks passed) {err.strip()}")
    t = parse(target_out)
    c.check(t["lines"].get("end") == "rc=0", f"target report complete: end {t['lines'].get('end')}")
    print("target: " + t["lines"].get("summary", "(no summary)"))
    print("target: pcut " + t["lines"].get("pcut", "?") + " | reload " +
          t["lines"].get("reload", "?"))

    rc, host_out, err = run([a.host], a.timeout)
    c.check(rc == 0, f"host twin {os.path.basename(a.host)} exit code {rc}")
    h = parse(host_out)
    print("host:   " + h["lines"].get("summary", "(no summary)"))

    for key in ("boot", "pcut", "reload", "counts", "pipeline"):
        c.check(t["lines"].get(key) == h["lines"].get(key),
                f"{key} identical: '{t['lines'].get(key)}'")
    # Acquisition on the sample clock's interrupt, the solve in the main loop's idle time: every
    # sample produced was consumed, none lost to a full queue.
    acq = dict(kv.split("=", 1) for kv in t["lines"].get("acq", "").split() if "=" in kv)
    samples = dict(kv.split("=", 1) for kv in t["lines"].get("counts", "").split() if "=" in kv)
    c.check(acq.get("clock") == "1", f"target acquired on its sample clock: {t['lines'].get('acq')}")
    c.check(acq.get("lost") == "0" and acq.get("produced") == acq.get("consumed") ==
            samples.get("samples"), f"target: {acq.get('produced')} samples produced, "
            f"{acq.get('consumed')} consumed, {acq.get('lost')} events lost")
    print(f"target: solve {t['lines'].get('solve')}; queue max depth {acq.get('max_depth')} "
          f"({acq.get('max_depth_solving')} while solving), worst acquisition-to-pipeline "
          f"latency {acq.get('max_latency_us')} us ({acq.get('max_latency_solving_us')} us while "
          f"solving), tick {acq.get('tick_us')} us")
    c.check("initialised=1" in t["lines"].get("ekf", ""), "EKF initialised on target")
    c.check(t["lines"].get("loop", "").startswith("state=applied cal_id=1"),
            f"SensorLoop applied the calibration on target: {t['lines'].get('loop')}")

    if a.mode == "double":
        # Bit for bit: the same IEEE-754 double operations in the same order on both (no FMA
        # contraction, scalar Eigen, the portable elementary functions of firmware/app instead of
        # newlib's and glibc's), so every reported value and every record must be identical.
        for key in ("ekf", "loop", "milestones", "summary"):
            c.check(t["lines"].get(key) == h["lines"].get(key), f"{key} identical: "
                    f"target '{t['lines'].get(key)}' host '{h['lines'].get(key)}'")
        for key in ("model", "b", "sigma", "g", "g_sigma", "validation_rms", "stats"):
            c.check(key in t["raw"] and t["raw"][key] == h["raw"].get(key),
                    f"{key}: {len(t.get(key, []))} values bit-identical to the host twin")
        diff = sum(1 for tr, hr in zip(t["rec_raw"], h["rec_raw"]) if tr != hr)
        c.check(len(t["rec"]) > 0 and len(t["rec"]) == len(h["rec"]) and diff == 0,
                f"records bit-identical: {len(t['rec'])} target, {len(h['rec'])} host, "
                f"{diff} differ")
        if a.cli:
            compare_cli(c, t, a.cli, a.timeout)
        print(f"{c.failures} failure(s)")
        return 1 if c.failures else 0
    rc, d_out, err = run([a.host_double], a.timeout)
    c.check(rc == 0, f"host double twin exit code {rc}")
    ref = parse(d_out)
    print("double: " + ref["lines"].get("summary", "(no summary)"))
    # Float: the image computes in float32, the reference in double; the estimates are compared
    # in units of their 1-sigma (FRACTION, default 3), the intensity RMSE within 1.1x. Reported:
    # the largest relative difference and the largest difference in sigma.
    worst_rel = 0.0
    for key in ("model", "b", "g"):
        for x, y in zip(t[key], ref[key]):
            worst_rel = max(worst_rel, abs(x - y) / max(abs(x), abs(y), 1e-300))
    print(f"largest relative difference of W, b, G vs the host: {worst_rel:.3g}")
    rmse_t, rmse_r = t["stats"][0], ref["stats"][0]
    c.check(rmse_t <= 1.1 * rmse_r and rmse_r <= 1.1 * rmse_t,
            f"intensity RMSE image {rmse_t:.4f} nT vs host double {rmse_r:.4f} nT (within 1.1x)")
    worst = 0.0
    for key, skey, off in (("g", "g_sigma", 0), ("b", "sigma", 9)):
        for i in range(len(ref[key])):
            z = abs(t[key][i] - ref[key][i]) / ref[skey][off + i]
            worst = max(worst, z)
            c.check(z <= a.fraction, f"{key}[{i}] image {t[key][i]:.9g} host double "
                    f"{ref[key][i]:.9g}: {z:.3f} sigma (<= {a.fraction})")
    print(f"largest |image - host double| / sigma: {worst:.3f}")
    c.check(len(t["rec"]) == len(h["rec"]) and len(t["rec"]) > 0 and
            all(tr[0] == hr[0] for tr, hr in zip(t["rec"], h["rec"])),
            f"{len(t['rec'])} record lines at the same sample times")
    worst_rec = 0.0
    for tr, hr in zip(t["rec"], ref["rec"]):
        for x, y in zip(tr[3][3:7], hr[3][3:7]):  # h_s and F
            worst_rec = max(worst_rec, abs(x - y) / max(abs(x), abs(y), 1e-300))
    print(f"largest relative difference of the records' h_s, F vs the host: {worst_rec:.3g}")

    print(f"{c.failures} failure(s)")
    return 1 if c.failures else 0


if __name__ == "__main__":
    sys.exit(main())
