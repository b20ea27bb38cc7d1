"""The peak memory of a learnable layout's training step, each layout in a fresh process.

Three steps (forward and backward of ``out.sum()`` through ``simulate``, exact, default
tolerance) on a random 2048x1024 RGB image to a 257x129 sensor, for the layouts of
``examples/training_step.py``; prints the growth of the process's peak resident memory over
what it held with the image loaded (Linux ``ru_maxrss``).
Run: ``python examples/step_memory.py``.
"""

from __future__ import annotations

import json
import subprocess
import sys

STEP = """
import json, resource, sys, torch
import layoutwarp as lw
from layoutwarp import kernels
from layoutwarp.layoutfile import layout_from_spec

lw.jit.set_mode("wait")  # time the compiled kernels, never the torch path while they compile
kernels.retain_freed_memory()
img = torch.rand(1, 3, 1024, 2048, generator=torch.Generator().manual_seed(0))
layout = layout_from_spec(json.loads(sys.argv[1]), learn=True)
lw.simulate(img[:, :, :64, :64], layout, (4, 4)).sum().backward()  # compiled kernels loaded
base = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
for _ in range(3):
    lw.simulate(img, layout, (129, 257)).sum().backward()
print((resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - base) / 1024)
"""


def main() -> None:
    sys.path.insert(0, __file__.rsplit("/", 1)[0])
    from training_step import SPECS

    for name, spec in SPECS.items():
        run = subprocess.run(
            [sys.executable, "-c", STEP, json.dumps(spec)], capture_output=True, text=True, check=True
        )
        print(f"{name:7s} step peak memory {float(run.stdout.split()[-1]):6.1f} MB over the image")


if __name__ == "__main__":
    main()
