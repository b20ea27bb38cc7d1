"""What a learnable curvilinear layout costs a whole training run, against a rectangular one.

Runs ``layoutwarp train mnist --family curv`` and ``--family rect`` (a 4x4 sensor, θ learned
jointly with the network) in interleaved pairs, curv then rect, each a fresh process, and prints
every pair's wall times and their ratio, then the median ratio. By default each run is the quick
one on the bundled samples (3 epochs); ``--epochs N`` with ``LAYOUTWARP_DATA`` set trains on the
full MNIST instead. Run: ``python examples/train_pairs.py [--pairs 5] [--epochs N]``.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import tempfile
import time


def run(family: str, epochs: int | None, out: str) -> float:
    cmd = [sys.executable, "-m", "layoutwarp", "train", "mnist", "--family", family, "--size", "4x4"]
    cmd += ["--no-progress", "--seeds", "1", "--out", out]
    cmd += ["--epochs", str(epochs)] if epochs else ["--quick"]
    t0 = time.perf_counter()
    subprocess.run(cmd, check=True, capture_output=True)
    return time.perf_counter() - t0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", type=int, default=5, help="interleaved pairs (default: 5)")
    parser.add_argument("--epochs", type=int, default=None, help="full MNIST for N epochs (default: --quick)")
    args = parser.parse_args()
    ratios = []
    with tempfile.TemporaryDirectory() as tmp:
        run("curv", args.epochs, f"{tmp}/warm")  # compiles the kernels once (numba's disk cache)
        for k in range(args.pairs):
            t_curv = run("curv", args.epochs, f"{tmp}/curv{k}")
            t_rect = run("rect", args.epochs, f"{tmp}/rect{k}")
            ratios.append(t_curv / t_rect)
            print(f"pair {k + 1}: curv {t_curv:6.1f} s, rect {t_rect:6.1f} s, ratio {ratios[-1]:.2f}")
    print(f"median curv/rect: {statistics.median(ratios):.2f} (min {min(ratios):.2f}, max {max(ratios):.2f})")


if __name__ == "__main__":
    main()
