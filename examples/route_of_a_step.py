"""The route of one call through the package: which layoutwarp functions, in which files, a warm
learnable training step (forward and backward) calls, or with ``--fixed`` a fixed layout's plain
forward, in the order the files are entered.

    python examples/route_of_a_step.py [--fixed]
"""

from __future__ import annotations

import argparse
import sys
from types import FrameType
from typing import Any

import torch

import layoutwarp as lw


def route(step: Any) -> tuple[set[tuple[str, str]], list[str]]:
    """The (file, function) pairs of layoutwarp that ``step()`` calls, and the files in the order
    they are entered (a file entered again after another counts again)."""
    calls: set[tuple[str, str]] = set()
    order: list[str] = []

    def seen(frame: FrameType, event: str, arg: Any) -> None:
        name = frame.f_code.co_filename
        if event == "call" and "/layoutwarp/" in name and "site-packages" not in name:
            where = name.split("/layoutwarp/")[-1]
            calls.add((where, frame.f_code.co_name))
            if not order or order[-1] != where:
                order.append(where)

    sys.setprofile(seen)
    try:
        step()
    finally:
        sys.setprofile(None)
    return calls, order


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--fixed", action="store_true", help="a fixed layout's plain forward instead")
    args = ap.parse_args()
    lw.jit.set_mode("wait")  # the compiled route, not the torch path meanwhile
    x = torch.rand(1, 3, 60, 80, generator=torch.Generator().manual_seed(0))
    if args.fixed:
        layout = lw.CurvLayout((0.3, -0.2))

        def step() -> None:
            with torch.no_grad():
                lw.simulate(x, layout, (9, 11))
    else:
        layer = lw.SensorLayer((9, 11), "curv", theta=(0.3, -0.2))

        def step() -> None:
            layer.layout.rho.grad = None
            layer(x).sum().backward()

    step()  # warm: kernels loaded, caches filled
    calls, order = route(step)
    files = sorted({f for f, _ in calls})
    what = "a fixed layout's plain forward" if args.fixed else "a learnable training step"
    print(f"{what}: {len(calls)} functions in {len(files)} files, {len(order) - 1} moves between files")
    for f in files:
        print(f"  {f}: {', '.join(sorted(n for g, n in calls if g == f))}")


if __name__ == "__main__":
    main()
