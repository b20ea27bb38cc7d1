"""What a training step of a learnable layout costs on a GPU, against a bare ``grid_sample`` step.

For learnable curv (mixed-sign θ) and fovea layouts, 2048x1024 RGB float32 → 257x129, forward +
backward of ``out.sum()`` (median of 20 after a warm-up):

* the anchor: stratified Monte Carlo at 16 samples per pixel with ``grid_sample`` (φ of the
  jittered samples, bilinear look-up, mean per pixel), θ's gradient by autograd through it;
* ``simulate`` at the data tolerance, which runs the compiled learnable path
  (:mod:`layoutwarp.kernels.mesh`: mesh and vertex derivatives built on the device by
  ``build_mesh_device``, integrals and Reynolds weights in the CUDA kernels);
* the previous path, the mesh built by torch with θ's autograd graph (``pixel_mesh``) and the
  same CUDA kernels, and its θ-gradient, which the compiled one must equal.

It prints the times, their ratio to the anchor, the torch operations of each step (profiler) and
the relative difference of the two exact paths' θ-gradients. Run: ``python
examples/gpu_training_step.py`` (needs a CUDA GPU; output in ``examples/gpu/``).
"""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch
import torch.nn.functional as F

import layoutwarp as lw
from layoutwarp.experiments.scene import load_photo
from layoutwarp.integrators import data_tolerance, integrate_exact
from layoutwarp.testing import count_ops

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


def main() -> None:
    if not torch.cuda.is_available():
        raise SystemExit("examples/gpu_training_step.py needs a CUDA GPU")
    img = load_photo(1024, 2048, None).cuda()  # (1, 3, H, W)
    gen = torch.Generator("cuda").manual_seed(0)
    tol = data_tolerance(torch.float32)[0]
    print(f"{torch.cuda.get_device_name()}, torch {torch.__version__}; photo 2048x1024x3 float32 -> 257x129")
    print(f"{'layout':8s} {'step':34s} {'ms':>7s} {'/GS16':>6s} {'ops':>5s}")
    layouts = {
        "curv ±": lw.CurvLayout((0.35, -0.25), learn=True),
        "fovea": lw.FoveaLayout((0.35, -0.25), center=(0.3, -0.2), learn=True),
    }
    for name, layout in layouts.items():
        layout = layout.cuda()

        def anchor(layout=layout) -> None:
            u = lw.maps.sample_points(SIZE, 4, jitter=True, generator=gen, dtype=torch.float32, device="cuda")
            p = layout.phi(u, layout.theta.float())
            out = F.grid_sample(img, p[None], mode="bilinear", align_corners=False)
            out.reshape(1, 3, SIZE[0], 4, SIZE[1], 4).mean((3, 5)).sum().backward()
            layout.rho.grad = None

        def compiled(layout=layout) -> None:
            lw.simulate(img, layout, SIZE).sum().backward()
            layout.rho.grad = None

        def previous(layout=layout) -> None:
            mesh = lw.pixel_mesh(layout, SIZE, tol=tol, dtype=torch.float64)
            integrate_exact(img[0], layout, SIZE, mesh=mesh).sum().backward()
            layout.rho.grad = None

        t_gs = timed(anchor)
        for label, fn in (
            ("grid_sample MC-16, fwd + bwd", anchor),
            ("exact, compiled learnable path", compiled),
            ("exact, torch-built mesh", previous),
        ):
            t = t_gs if fn is anchor else timed(fn)
            print(f"{name:8s} {label:34s} {t:7.2f} {t / t_gs:6.2f} {count_ops(fn):5d}")
        grads = []
        for fn in (compiled, previous):
            layout.rho.grad = None
            if fn is compiled:
                lw.simulate(img, layout, SIZE).sum().backward()
            else:
                mesh = lw.pixel_mesh(layout, SIZE, tol=tol, dtype=torch.float64)
                integrate_exact(img[0], layout, SIZE, mesh=mesh).sum().backward()
            grads.append(layout.rho.grad.double().clone())
        layout.rho.grad = None
        rel = float((grads[0] - grads[1]).abs().max() / grads[1].abs().max())
        print(f"{name:8s} θ-gradient, compiled vs torch-built mesh: max relative difference {rel:.2e}")


if __name__ == "__main__":
    main()
