"""A fixed layout's forward against the memory limit and the resizers, in interleaved rounds.

For each source size, sensor size and batch: one read of the image (``x.sum()``: the memory
limit), ``F.interpolate(mode="area")`` (a uniform grid), ``cv2.resize(INTER_AREA)`` (per image, the
HWC copies made beforehand) and ``simulate`` of a fixed curv layout (θ of mixed sign) and of the
uniform layout, every call after its warm-up (the area weights built), float32, no gradient. Then
the curv layout's weights: their bytes against one float32 plane of the image, and how long they
take to build against ten forwards.

    python examples/fixed_forward.py [--rounds 30] [--threads 2] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import time

import cv2
import numpy as np
import torch
import torch.nn.functional as F

import layoutwarp as lw
from layoutwarp.experiments.timing import interleaved_times
from layoutwarp.resampler import AreaResampler

CASES = [((1024, 2048), (129, 257), (1, 8)), ((256, 512), (65, 129), (1, 8)), ((28, 28), (4, 4), (1, 64))]


def one_case(src: tuple[int, int], size: tuple[int, int], batch: int, rounds: int) -> dict[str, float]:
    """Median µs of every call, in the same rounds."""
    x = torch.rand(batch, 3, *src, generator=torch.Generator().manual_seed(0))
    hwc = [np.ascontiguousarray(x[b].permute(1, 2, 0).numpy()) for b in range(batch)]
    curv, uniform = lw.CurvLayout((0.3, -0.24)), lw.UniformLayout()
    calls = {
        "read": lambda: x.sum(),
        "interpolate": lambda: F.interpolate(x, size=size, mode="area"),
        "inter_area": lambda: [cv2.resize(a, size[::-1], interpolation=cv2.INTER_AREA) for a in hwc],
        "curv": lambda: lw.simulate(x, curv, size),
        "uniform": lambda: lw.simulate(x, uniform, size),
    }
    with torch.no_grad():
        times = interleaved_times(list(calls.values()), rounds)
    return {k: float(np.median(t)) * 1e3 for k, t in zip(calls, times, strict=True)}


def weights(src: tuple[int, int], size: tuple[int, int], forward_us: float) -> dict[str, float]:
    """The curv layout's weights: bytes over a float32 plane, build time over ten forwards."""
    t = time.perf_counter()
    res = AreaResampler(lw.CurvLayout((0.3, -0.24)), size, src)
    build = time.perf_counter() - t
    plane = 4 * src[0] * src[1]
    return {
        "bytes_over_plane": res.runs.nbytes / plane,
        "build_s": build,
        "build_over_10": build / (10 * forward_us * 1e-6),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--rounds", type=int, default=30)
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--json", help="also write the figures to this file")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    lw.jit.set_mode("wait")  # the compiled product, never the torch path while it compiles
    out = []
    print(f"{args.threads} threads, float32 RGB, µs (median of {args.rounds} interleaved rounds)")
    for src, size, batches in CASES:
        for batch in batches:
            t = one_case(src, size, batch, args.rounds)
            row = {"src": src, "size": size, "batch": batch, "us": t}
            row["curv_over_read"], row["curv_over_inter_area"] = (
                t["curv"] / t["read"],
                t["curv"] / t["inter_area"],
            )
            row["curv_over_interpolate"] = t["curv"] / t["interpolate"]
            row["uniform_over_interpolate"] = t["uniform"] / t["interpolate"]
            if batch == 1:
                row["weights"] = weights(src, size, t["curv"])
            out.append(row)
            print(
                f"{src[1]}x{src[0]} -> {size[1]}x{size[0]}, batch {batch}: read {t['read']:.0f}, "
                f"interpolate {t['interpolate']:.0f}, INTER_AREA {t['inter_area']:.0f}, curv {t['curv']:.0f} "
                f"({row['curv_over_read']:.1f}x read, {row['curv_over_inter_area']:.2f}x INTER_AREA, "
                f"{row['curv_over_interpolate']:.2f}x interpolate), uniform {t['uniform']:.0f} "
                f"({row['uniform_over_interpolate']:.2f}x interpolate)"
                + (
                    f"; weights {row['weights']['bytes_over_plane']:.2f}x a float32 plane, built in "
                    f"{row['weights']['build_s'] * 1e3:.0f} ms = "
                    f"{row['weights']['build_over_10']:.1f}x ten forwards"
                    if "weights" in row
                    else ""
                ),
                flush=True,
            )
    if args.json:
        with open(args.json, "w") as f:
            json.dump(out, f, indent=1)


if __name__ == "__main__":
    main()
