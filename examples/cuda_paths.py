"""The exact integrator's two CUDA paths against a bare ``grid_sample`` Monte Carlo, on a GPU.

Times (median of 20 after a warm-up) and peak growth of allocated GPU memory of:
the anchor (φ at 16 jittered samples per pixel drawn on the device, ``grid_sample``, mean),
``integrate_exact`` with the numba CUDA kernels (``backend="numba"``) and with the torch
reference (``backend="torch"``), for a fixed layout (mesh built once) and for a training step
of a learnable one (mesh rebuilt, forward + backward). The photo is 2048x1024 RGB float32, the
sensor 257x129, θ = (0.35, ±0.25). Run: ``python examples/cuda_paths.py`` (needs a CUDA GPU).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

import layoutwarp as lw
from layoutwarp.experiments.scene import load_photo
from layoutwarp.integrators import data_tolerance

lw.jit.set_mode("wait")  # time the compiled kernels, never the torch path while they compile

SIZE = (129, 257)


def timed(fn: Callable[[], object], repeats: int = 20) -> float:
    fn()
    times = []
    for _ in range(repeats):
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        fn()
        torch.cuda.synchronize()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def peak_mib(fn: Callable[[], object]) -> float:
    torch.cuda.synchronize()
    torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated()
    fn()
    torch.cuda.synchronize()
    return (torch.cuda.max_memory_allocated() - base) / 2**20


def main() -> None:
    if not torch.cuda.is_available():
        raise SystemExit("examples/cuda_paths.py needs a CUDA GPU")
    img = load_photo(1024, 2048, None).cuda()  # (1, 3, H, W)
    planes = img[0].contiguous()
    input_mib = img.numel() * 4 / 2**20
    gen = torch.Generator("cuda").manual_seed(0)
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}; photo 2048x1024x3 float32 -> 257x129")
    print(f"{'θ':14s} {'tol':8s} {'path':22s} {'fwd ms':>7s} {'/GS16':>6s} {'train ms':>8s} {'peak/in':>7s}")
    for theta in ((0.35, 0.25), (0.35, -0.25)):
        layout = lw.CurvLayout(theta).cuda()

        def anchor(layout=layout):
            u = lw.maps.sample_points(SIZE, 4, jitter=True, generator=gen, dtype=torch.float32, device="cuda")
            p = layout.phi(u, layout.theta.detach().float())
            out = F.grid_sample(img, p[None], mode="bilinear", align_corners=False)
            return out.reshape(1, 3, SIZE[0], 4, SIZE[1], 4).mean((3, 5))

        t_gs = timed(anchor)
        print(
            f"{theta!s:14s} {'-':8s} {'grid_sample MC-16':22s} {t_gs:7.2f} {1:6.2f} {'':>8s} "
            f"{peak_mib(anchor) / input_mib:7.2f}"
        )
        for tol in (data_tolerance(torch.float32)[0], 1e-3, 1e-4):
            mesh = lw.pixel_mesh(layout, SIZE, tol=tol, dtype=torch.float64)
            learnable = lw.CurvLayout(theta, learn=True).cuda()
            for backend in ("numba", "torch"):

                def fwd(layout=layout, mesh=mesh, backend=backend):
                    with torch.no_grad():
                        return lw.integrators.integrate_exact(
                            planes, layout, SIZE, mesh=mesh, backend=backend
                        )

                def train(learnable=learnable, tol=tol, backend=backend):
                    lw.integrators.integrate_exact(
                        planes, learnable, SIZE, tol=tol, backend=backend
                    ).sum().backward()

                t_f, t_t = timed(fwd), timed(train, 10)
                print(
                    f"{theta!s:14s} {tol:<8.2g} {'exact, ' + backend:22s} {t_f:7.2f} {t_f / t_gs:6.2f} "
                    f"{t_t:8.2f} {peak_mib(fwd) / input_mib:7.2f}"
                )


if __name__ == "__main__":
    main()
