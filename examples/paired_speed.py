"""This checkout's kernels against another checkout's, in paired interleaved runs.

Times a learnable curv ± step, a learnable fovea step (forward and backward of ``out.sum()``
through ``simulate``, exact, default tolerance, mixed-sign θ) and a fixed curv layout's forward
(``simulate`` without gradient, its area weights kept) on a random 2048x1024 RGB image to a
257x129 sensor. Each run is a fresh process of one checkout, which times every call ``--calls``
times after a warm-up; runs alternate between the two checkouts (``--pairs`` of them), so both
meet the same machine state. Prints each call's median per checkout and the ratio, with the
spread of the per-pair ratios. Each checkout keeps its own compiled kernels (``NUMBA_CACHE_DIR``
under ``--cache``); the first pair compiles them if need be (not timed: a warm-up).

Run: ``python examples/paired_speed.py --against ../other-checkout [--pairs 6] [--calls 5]``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile

CHILD = r"""
import json, statistics, sys, time
import torch
import layoutwarp as lw
from layoutwarp import kernels
from layoutwarp.layoutfile import layout_from_spec

calls = int(sys.argv[1])
kernels.retain_freed_memory()
torch.set_num_threads(2)
img = torch.rand(1, 3, 1024, 2048, generator=torch.Generator().manual_seed(0))
size = (129, 257)
specs = {
    "curv ± step": {"family": "curv", "theta": [0.35, -0.25]},
    "fovea step": {"family": "fovea", "theta": [0.35, -0.25], "center": [0.3, -0.2], "learn_center": True},
}
work = {}
for name, spec in specs.items():
    layout = layout_from_spec(spec, learn=True)
    def step(layout=layout):
        lw.simulate(img, layout, size).sum().backward()
        layout.rho.grad = None
    work[name] = step
fixed = lw.CurvLayout((0.35, -0.25))
def forward():
    with torch.no_grad():
        lw.simulate(img, fixed, size)
work["fixed forward"] = forward
out = {}
for name, call in work.items():
    call(); call()  # warm-up: compiles, fills the caches
for _ in range(calls):
    for name, call in work.items():
        t0 = time.perf_counter()
        call()
        out.setdefault(name, []).append(1e3 * (time.perf_counter() - t0))
print(json.dumps(out))
"""


def run(tree: str, cache: str, calls: int) -> dict[str, list[float]]:
    env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": tree, "LAYOUTWARP_JIT": "wait"}
    cmd = [sys.executable, "-c", CHILD, str(calls)]
    res = subprocess.run(cmd, cwd=tree, env=env, capture_output=True, text=True, check=False)
    if res.returncode != 0:
        sys.exit(f"paired_speed: the run in {tree} failed:\n{res.stderr[-2000:]}")
    return json.loads(res.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--against", required=True, help="the other checkout (its root folder)")
    parser.add_argument("--pairs", type=int, default=6, help="runs of each checkout (default 6)")
    parser.add_argument("--calls", type=int, default=5, help="timed calls of each kind a run (default 5)")
    parser.add_argument("--cache", default=None, help="where the two kernel caches go (default: temporary)")
    args = parser.parse_args()
    here = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    other = os.path.abspath(args.against)
    if not os.path.isdir(os.path.join(other, "layoutwarp")):
        sys.exit(f"paired_speed: --against must be a checkout of layoutwarp, got {args.against!r}")
    cache = args.cache or tempfile.mkdtemp(prefix="paired-")
    trees = {"this": here, "other": other}
    caches = {k: os.path.join(cache, k) for k in trees}
    for k in trees:  # compiled first, untimed
        run(trees[k], caches[k], 1)
    times: dict[str, dict[str, list[float]]] = {k: {} for k in trees}
    ratios: dict[str, list[float]] = {}
    for i in range(args.pairs):
        got = {}
        for k in ("this", "other") if i % 2 == 0 else ("other", "this"):
            got[k] = run(trees[k], caches[k], args.calls)
            for name, ts in got[k].items():
                times[k].setdefault(name, []).extend(ts)
        for name in got["this"]:
            ratios.setdefault(name, []).append(
                statistics.median(got["this"][name]) / statistics.median(got["other"][name])
            )
        print(f"pair {i + 1}/{args.pairs} done", file=sys.stderr, flush=True)
    print(f"{'call':16s} {'this (ms)':>10s} {'other (ms)':>11s} {'ratio':>7s}  per-pair ratios")
    for name in times["this"]:
        a, b = statistics.median(times["this"][name]), statistics.median(times["other"][name])
        rs = ", ".join(f"{r:.3f}" for r in ratios[name])
        print(f"{name:16s} {a:10.1f} {b:11.1f} {a / b:7.3f}  {rs}")


if __name__ == "__main__":
    main()
