"""A learnable layout's training step against our 16-sample Monte Carlo step and the fixed forward.

Times, in interleaved rounds (each round calls all three once, so they meet the same machine
state): forward and backward of ``out.sum()`` through ``simulate`` for a learnable layout
(exact, default tolerance), the same step by Monte Carlo with 4x4 samples a pixel (the
reference method's cost), and the compiled exact forward of the same layout fixed with its mesh
built once; on a random 2048x1024 RGB image to a 257x129 sensor, for curv and fovea with
mixed-sign θ, and prints the medians and the two ratios of the issue's goals; then the step
again, ``--rounds`` times in a row, as a training loop calls it. The allocator
keeps freed memory as in the ``layoutwarp`` command (``--no-retain``: as a plain process).
Run: ``python examples/training_step.py [--rounds 12] [--threads 2] [--no-retain]``.
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

import layoutwarp as lw
from layoutwarp import kernels
from layoutwarp.integrators import integrate_exact
from layoutwarp.layoutfile import layout_from_spec

lw.jit.set_mode("wait")  # time the compiled kernels, never the torch path while they compile

SPECS = {
    "curv ±": {"family": "curv", "theta": [0.35, -0.25]},
    "fovea": {"family": "fovea", "theta": [0.35, -0.25], "center": [0.3, -0.2], "learn_center": True},
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=12, help="interleaved rounds (default 12)")
    parser.add_argument("--threads", type=int, default=2, help="torch threads (default 2)")
    parser.add_argument("--no-retain", action="store_true", help="leave the allocator as it is")
    args = parser.parse_args()
    if not args.no_retain:
        kernels.retain_freed_memory()
    torch.set_num_threads(args.threads)
    img = torch.rand(1, 3, 1024, 2048, generator=torch.Generator().manual_seed(0))
    size = (129, 257)
    for name, spec in SPECS.items():
        layout, fixed = layout_from_spec(spec, learn=True), layout_from_spec(spec)
        mesh = lw.pixel_mesh(fixed, size, tol=2**-12, dtype=torch.float64)

        def step(method: str = "exact", opts: dict | None = None, layout=layout) -> None:
            lw.simulate(img, layout, size, method, **(opts or {})).sum().backward()
            layout.rho.grad = None

        def forward(fixed=fixed, mesh=mesh) -> None:
            with torch.no_grad():
                integrate_exact(img[0], fixed, size, mesh=mesh)

        calls = {
            "step": step,
            "MC-16 step": lambda step=step: step("montecarlo", {"samples": 4, "seed": 0}),
            "fixed forward": forward,
        }
        times: dict[str, list[float]] = {k: [] for k in calls}
        for call in calls.values():  # warm-up: compiles and fills the caches
            call()
        for _ in range(args.rounds):
            for key, call in calls.items():
                t0 = time.perf_counter()
                call()
                times[key].append(1e3 * (time.perf_counter() - t0))
        ms = {k: statistics.median(v) for k, v in times.items()}
        in_a_row = []  # as a training loop calls it: what one step leaves running meets the next
        for _ in range(args.rounds):
            t0 = time.perf_counter()
            step()
            in_a_row.append(1e3 * (time.perf_counter() - t0))
        print(
            f"{name:7s} step {ms['step']:6.1f} ms, MC-16 step {ms['MC-16 step']:6.1f} ms, "
            f"fixed forward {ms['fixed forward']:5.1f} ms: {ms['step'] / ms['MC-16 step']:.2f}x the "
            f"MC-16 step, {ms['step'] / ms['fixed forward']:.2f}x the fixed forward; "
            f"steps in a row {statistics.median(in_a_row):6.1f} ms"
        )


if __name__ == "__main__":
    main()
