"""The README's example as a new installation meets it: a fresh process with an empty numba cache
(a new ``NUMBA_CACHE_DIR``), timing import, a learnable curv step at 2048x1024 RGB → 257x129, a
fixed-layout forward and a call with physics (see docs/speed.md, "The first call").

    python examples/first_call.py [--mode background|wait|off]
"""

from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile

EXAMPLE = """
import time
t0 = time.perf_counter()
import torch, layoutwarp as lw
t = [time.perf_counter()]
img = torch.rand(1, 3, 1024, 2048)
lw.simulate(img, lw.CurvLayout((0.3, -0.24), learn=True), (129, 257)).sum().backward()
t.append(time.perf_counter())
with torch.no_grad():
    lw.simulate(img, lw.CurvLayout((0.3, -0.1)), (129, 257))
t.append(time.perf_counter())
phys = lw.SensorPhysics((2800, 5600), photons_per_um2=50)
lw.simulate(img, lw.CurvLayout((0.3, -0.1)), (129, 257), physics=phys)
t.append(time.perf_counter())
names = ("import", "learnable curv step", "fixed forward", "call with physics")
steps = [t[0] - t0] + [b - a for a, b in zip(t, t[1:])]
print("; ".join(f"{n} {s:.1f} s" for n, s in zip(names, steps)) + f"; in all {t[-1] - t0:.1f} s")
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--mode", choices=("background", "wait", "off"), default="background")
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "LAYOUTWARP_JIT": args.mode}
        res = subprocess.run([sys.executable, "-c", EXAMPLE], env=env)
        # the background worker may still be filling the cache: it ends by itself; this run's cache
        # is thrown away with the folder (a real installation keeps it)
    return res.returncode


if __name__ == "__main__":
    sys.exit(main())
