"""How many GPU launches each call makes, and how long a learnable step's CUDA kernels take to
compile, measured without a GPU.

    python examples/gpu_launches.py            # launches per call (numba's CUDA simulator)
    python examples/gpu_launches.py --compile  # compile time of a learnable step's CUDA kernels

Launches: the device paths run on the CPU in numba's CUDA simulator (``NUMBA_ENABLE_CUDASIM=1``;
the script sets it and runs itself again), and `count_launches` counts every numba kernel launch
and every torch operator that would run a kernel or a copy on a GPU, for a learnable curv ± and
fovea training step (``simulate(...).sum().backward()``), a fixed layout's forward and the same
with sensor physics, and the values each reads back to the host (``count_host_reads``: on a GPU,
a wait). Both check their output for NaN on the device, inside a kernel they launch anyway. The
torch profiler also counts cuBLAS's inner kernels.

Compile time: every CUDA kernel of a learnable float32 step compiled to PTX for compute
capability 8.0, in a fresh process (what a first CUDA call compiles before it runs; the driver's
PTX-to-machine-code step, which needs a GPU, comes on top).
"""

from __future__ import annotations

import os
import subprocess
import sys
import time


def launches() -> None:
    import warnings

    import torch

    import layoutwarp as lw
    from layoutwarp.testing import count_host_reads, count_launches

    lw.jit.set_mode("wait")
    warnings.filterwarnings("ignore", "overflow encountered")  # the samplers' uint64 wrap, as Python
    img = torch.rand(1, 3, 24, 32, generator=torch.Generator().manual_seed(0))
    size = (4, 5)
    camera = lw.SensorPhysics((280.0, 560.0), photons_per_um2=50, read_noise_e=2.0, adc_bits=12, seed=0)
    calls = {}
    fovea = lw.FoveaLayout((0.35, -0.25), center=(0.3, -0.2), learn=True, learn_center=True)
    for name, layout in (
        ("learnable curv ± step", lw.CurvLayout((0.35, -0.25), learn=True)),
        ("learnable fovea step", fovea),
    ):

        def step(layout=layout) -> None:
            layout.zero_grad()
            lw.simulate(img, layout, size).sum().backward()

        calls[name] = step
    fixed = lw.CurvLayout((0.35, -0.25))
    calls["fixed forward"] = lambda: lw.simulate(img, fixed, size)
    calls["fixed forward + physics"] = lambda: lw.simulate(img, fixed, size, physics=camera)
    for name, call in calls.items():
        with torch.no_grad() if name.startswith("fixed") else torch.enable_grad():
            call()  # compiles (here: nothing) and fills the caches
            counts = count_launches(call)
        kernels = sum(v for k, v in counts.items() if k.startswith("numba:"))
        reads = sum(count_host_reads(call).values())
        print(f"{name:26s} {sum(counts.values()):3d} launches ({kernels} numba kernels), {reads} host reads")
        print("    " + ", ".join(f"{k} {v}" for k, v in sorted(counts.items(), key=lambda kv: -kv[1])))


def compile_time() -> None:
    from layoutwarp import kernels
    from layoutwarp.kernels import mesh

    start = time.perf_counter()
    kernels.cuda_ptx("forward", "float32")  # imports numba-cuda, then the first kernel
    for fn, signature in mesh.CUDA_KERNELS.values():  # the mesh's, then the integrals' and gradients'
        kernels.cuda_ptx(fn, signature=signature)
    n = 1 + len(mesh.CUDA_KERNELS)
    print(f"a learnable step's {n} CUDA kernels compiled to PTX in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    if "--compile" in sys.argv:
        compile_time()
    elif os.environ.get("NUMBA_ENABLE_CUDASIM") != "1":
        env = {**os.environ, "NUMBA_ENABLE_CUDASIM": "1", "NUMBA_DISABLE_JIT": "1", "LAYOUTWARP_JIT": "wait"}
        sys.exit(subprocess.run([sys.executable, __file__, *sys.argv[1:]], env=env).returncode)
    else:
        launches()
