"""The first call a user meets, timed: the README's example and the other entry points, each in a
fresh process from an empty numba cache and from a warm one (what `layoutwarp bench` reports as
first calls)."""

from __future__ import annotations

import json
import os
from collections.abc import Callable, Sequence

from .. import jit

__all__ = ["ENTRY_POINTS", "README_EXAMPLE", "first_calls"]


#: The README's example (import, a learnable curv step at 2048x1024 RGB -> 257x129, a fixed
#: forward, a call with physics): the first call a user meets. Prints its seconds as JSON.
README_EXAMPLE = """
import json, time
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
steps = dict(zip(names, [t[0] - t0] + [b - a for a, b in zip(t, t[1:])]))
lw.jit.stop_worker()
print(json.dumps({"total": t[-1] - t0, "steps": steps}))
"""


#: Other entry points a user meets first, each timed from ``import`` to its answer in a process
#: of its own (``{SAMPLES}``: the bundled samples, ``{TMP}``: a scratch folder).
ENTRY_POINTS = {
    "float64 learnable step": "img = torch.rand(1, 3, 256, 512, dtype=torch.float64)\n"
    "lw.simulate(img, lw.CurvLayout((0.3, -0.24), learn=True).double(), (33, 65)).sum().backward()",
    "Monte Carlo forward": "img = torch.rand(1, 3, 512, 1024)\n"
    "lw.simulate(img, lw.CurvLayout((0.3, -0.24)), (65, 129), 'montecarlo', samples=4, seed=0)",
    **{
        f"{family} learnable step": f"img = torch.rand(1, 3, 512, 1024)\n"
        f"lw.simulate(img, lw.make_layout({family!r}, learn=True), (65, 129)).sum().backward()"
        for family in ("rect", "fovea", "elliptic", "spline", "grid")
    },
    "preprocess": "lw.preprocess_folder('{SAMPLES}/photos', '{TMP}/pre', lw.CurvLayout((0.3, -0.2)),"
    " (24, 32), progress=False)",
    "export": "lw.export_layout(lw.CurvLayout((0.3, -0.2)), (48, 64), '{TMP}/mask.svg', (3000.0, 4000.0))",
}


_ENTRY = """
import json, time
t0 = time.perf_counter()
import torch, layoutwarp as lw
{CODE}
t1 = time.perf_counter()
lw.jit.stop_worker()
print(json.dumps({{"total": t1 - t0}}))
"""


def first_calls(
    entries: Sequence[str] = ("README example",),
    progress: Callable[[str], None] | None = None,
    fill: bool = True,
) -> dict:
    """Seconds from a fresh process's start to the answer of each entry point (``"README
    example"``, [`README_EXAMPLE`][], or a key of [`ENTRY_POINTS`][]): ``first_s`` with an
    empty numba cache in the default (background) mode, as a new installation meets it, and
    ``warm_s`` with this installation's cache (``fill``: filled first in wait mode, outside the
    timing; ``False`` where the caller has compiled what the entry points use already);
    their difference is what the first call costs. Each process stops its background worker at
    the end, so the throw-away cache is not filled after it."""
    import subprocess
    import sys
    import tempfile

    from .data import samples_dir

    say = progress or (lambda msg: None)

    def once(code: str, env: dict[str, str]) -> dict:
        res = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True)
        if res.returncode:
            raise RuntimeError(f"first-call probe failed: {res.stderr[-2000:]}")
        return json.loads(res.stdout.strip().splitlines()[-1])

    out = {}
    for name in entries:
        say(f"first call: {name}")
        with tempfile.TemporaryDirectory() as tmp:
            if name == "README example":
                code = README_EXAMPLE
            else:
                body = ENTRY_POINTS[name].replace("{SAMPLES}", str(samples_dir())).replace("{TMP}", tmp)
                code = _ENTRY.format(CODE=body)
            cold = once(
                code, {**os.environ, "NUMBA_CACHE_DIR": os.path.join(tmp, "cache"), jit.ENV: "background"}
            )
            home = {**os.environ, jit.ENV: "wait"}
            if fill:
                once(code, home)  # this installation's cache holds what the entry uses
            warm = once(code, home)
        out[name] = {
            "first_s": cold["total"],
            "warm_s": warm["total"],
            **({"steps": cold["steps"]} if "steps" in cold else {}),
        }
    return out
