#!/usr/bin/env python3
"""Proves the firmware's no-heap link check fires: builds magvec_heap_probe (an application that
calls malloc and new, linked exactly like magvec_app.elf) in a bare-metal build tree and expects
the link to FAIL with an undefined __wrap_ allocator symbol, while the real image exists.
Exit 77 when the bare-metal tree has not been configured (cmake --preset m4f)."""
import os
import subprocess
import sys

build, image = sys.argv[1], sys.argv[2]
if not os.path.exists(os.path.join(build, "build.ninja")) or not os.path.exists(image):
    print(f"SKIP: {build} not configured/built (cmake --preset m4f && cmake --build --preset m4f)")
    sys.exit(77)
p = subprocess.run(["cmake", "--build", build, "--target", "magvec_heap_probe"],
                   capture_output=True, text=True, timeout=600)
out = p.stdout + p.stderr
fired = "undefined reference to `__wrap_malloc'" in out and "undefined reference to `__wrap__Znwj'" in out
print(f"magvec_heap_probe link exit code {p.returncode}; no-heap check fired: {fired}")
if p.returncode == 0 or not fired:
    print(out[-4000:])
    sys.exit(1)
print(f"ok: {image} linked under the same check")
sys.exit(0)
