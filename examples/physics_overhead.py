"""What sensor physics adds to a fixed layout's forward, and that forward against INTER_AREA.

Times four calls in the bench's interleaved rounds (``interleaved_times``: each round calls
every one once, so all meet the same machine state, and the rounds take the calls' 24 orders
in turn, so each follows each other as often, a call after OpenCV's spinning threads being
slower): ``cv2.resize(INTER_AREA)``, ``simulate`` of a
fixed curv layout (its cached area weights), the same with ``allow_nonfinite=True`` (no check
for NaN/Inf) and the same with the bench's camera (shot and read noise, full well, 12-bit ADC),
on a random 2048x1024 RGB image to a 257x129 sensor, and prints the medians, their ratio for
``simulate`` against INTER_AREA and, for the finiteness check and the physics, the median of
each round's ratio against ``simulate`` (both calls of a round meet the same machine state,
which drifts by 1.5x within seconds on small virtual machines), as ``layoutwarp bench`` does.
``--kernels`` then times the compiled calls beneath (the product alone, and the product with the
measurement written to a buffer of its own or over the means, as ``AreaResampler.apply`` does)
and prints each measurement's overhead on the product alone, the same way. (To compare a kernel
change with the code before it, run ``examples/paired_speed.py --against OTHER_CHECKOUT``.)
Run: ``python examples/physics_overhead.py [--rounds 500] [--threads 2] [--kernels]``
(500 rounds take about 8 s, and 5 s more with ``--kernels``; the median of the rounds' ratios
moves by about a point between runs of 120 rounds, by a few tenths at 1000).
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import cv2
import numpy as np
import torch

import layoutwarp as lw
from layoutwarp.cli import positive_int
from layoutwarp.experiments.benchphysics import BENCH_PHYSICS
from layoutwarp.experiments.timing import interleaved_times

lw.jit.set_mode("wait")  # time the compiled kernels, never the torch path while they compile

ROOT = Path(__file__).resolve().parents[1]


def over(slow: list[float], fast: list[float]) -> float:
    """The % that ``slow`` takes over ``fast``: the median of their rounds' ratios."""
    return 100 * (statistics.median([q / p for p, q in zip(fast, slow, strict=True)]) - 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=positive_int, default=500, help="interleaved rounds (default 500)")
    parser.add_argument(
        "--threads", type=positive_int, default=2, help="torch and OpenCV threads (default 2)"
    )
    parser.add_argument("--kernels", action="store_true", help="also time the compiled calls beneath")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    cv2.setNumThreads(args.threads)
    img = torch.rand(1, 3, 1024, 2048, generator=torch.Generator().manual_seed(0))
    hwc = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    camera = lw.SensorPhysics(sensor_um=(2800.0, 5600.0), **BENCH_PHYSICS)
    layout = lw.make_layout("curv", (0.35, 0.25))
    calls = {
        "INTER_AREA": lambda: cv2.resize(hwc, (257, 129), interpolation=cv2.INTER_AREA),
        "simulate": lambda: lw.simulate(img, layout, (129, 257)),
        "no finiteness check": lambda: lw.simulate(img, layout, (129, 257), allow_nonfinite=True),
        "simulate + physics": lambda: lw.simulate(img, layout, (129, 257), physics=camera),
    }
    with torch.no_grad():  # the warm-up call compiles, builds and caches the area weights
        times = dict(zip(calls, interleaved_times(list(calls.values()), args.rounds), strict=True))
    ms = {name: statistics.median(t) for name, t in times.items()}
    for name, value in ms.items():
        print(f"{name:20s} {value:7.2f} ms")
    print(f"simulate / INTER_AREA: {ms['simulate'] / ms['INTER_AREA']:.2f}x")
    print(
        f"finiteness check: {over(times['simulate'], times['no finiteness check']):+.1f} % (the same median)"
    )
    physics = over(times["simulate + physics"], times["simulate"])
    print(f"physics overhead: {physics:+.1f} % (median of the rounds' ratios)")
    if args.kernels:
        kernel_overheads(img, layout, camera, args.rounds)


def kernel_overheads(
    img: torch.Tensor,
    layout: lw.Layout,
    camera: lw.SensorPhysics,
    rounds: int,
) -> None:
    """The compiled calls under ``simulate``: the cached weights' product alone, and with the
    measurement (shot and read noise, full well, ADC) into a buffer of its own or over the means."""
    tol = lw.data_tolerance(img.dtype)[0]  # simulate's default for these images: its cached resampler
    res = lw.resampler.resampler_for(layout, (129, 257), tuple(img.shape[-2:]), tol, "cpu")
    runs, x = res.runs, np.ascontiguousarray(img.reshape(img.shape[1], -1).numpy())
    measured, nt = lw.measurement.kernel_arguments(camera, res.areas), lw.kernels.threads()

    def product(measure: str = "") -> None:
        mean = np.empty((x.shape[0], runs.shape[0]), np.float32)
        if not measure:
            lw.kernels.runs_apply(runs.arrays(), x, mean, nt)
            return
        out = mean if measure == "in place" else np.empty_like(mean)
        lw.kernels.measured_runs_apply(runs.arrays(), x, mean, *measured, out, nt)

    calls = {
        "product": product,
        "own buffer": lambda: product("own"),
        "in place": lambda: product("in place"),
    }
    times = dict(zip(calls, interleaved_times(list(calls.values()), rounds), strict=True))
    for name in list(calls)[1:]:
        pct = over(times[name], times["product"])
        print(f"product + measurement, {name:10s}: {pct:+.1f} % over the product alone")


if __name__ == "__main__":
    main()
