"""Peak memory of the compiled exact forward alone (the banded kernel), per tolerance.

Run from the repository root:  python examples/kernel_memory.py [TOL ...]

One fresh process per tolerance: builds the mesh of the benchmark's mixed-sign curvilinear
layout (θ = (0.35, −0.25), 2048x1024x3 float32 → 257x129), compiles the kernel on a tiny
input, then resets the process's peak resident memory (``/proc/self/clear_refs``, Linux) and
reports how far one kernel call raises it, in copies of the 24 MiB input. The mesh itself and
its construction are not counted (``layoutwarp bench`` measures the whole call).
"""

from __future__ import annotations

import argparse
import ctypes
import subprocess
import sys

import numpy as np
import torch

import layoutwarp as lw
from layoutwarp import kernels

lw.jit.set_mode("wait")  # time the compiled kernels, never the torch path while they compile


def rss_mib(key: str) -> float:
    with open("/proc/self/status") as f:
        return next(int(line.split()[1]) / 1024 for line in f if line.startswith(key))


def arrays(mesh: lw.PixelMesh, src: tuple[int, int]) -> list[np.ndarray]:
    tensors = (mesh.pixel_vertices(src), mesh.seg_start, mesh.seg_end, mesh.edge_offsets, mesh.seg_edge)
    return [np.ascontiguousarray(t.detach().numpy()) for t in tensors]


def measure(tol: float) -> None:
    layout, size = lw.CurvLayout((0.35, -0.25)), (129, 257)
    image = np.random.default_rng(0).random((3, 1024, 2048), dtype=np.float32)
    small = lw.pixel_mesh(layout, (3, 3), tol=tol, dtype=torch.float64)
    kernels.exact_forward_banded(*arrays(small, (64, 64)), image[:, :64, :64].copy(), kernels.BLOCK, 8, 2)
    mesh = lw.pixel_mesh(layout, size, tol=tol, dtype=torch.float64)
    args = arrays(mesh, (1024, 2048))
    band = kernels.band_rows(image, 2)
    ctypes.CDLL("libc.so.6").malloc_trim(0)
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset the peak (VmHWM) to the current resident size
    base = rss_mib("VmRSS:")
    kernels.exact_forward_banded(*args, image, kernels.BLOCK, band, 2)
    grown = rss_mib("VmHWM:") - base
    segments, copies = mesh.num_segments, grown / 24
    print(f"tol {tol:g}: {segments} segments, kernel peak +{grown:.1f} MiB ({copies:.2f} input copies)")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("tols", nargs="*", type=float, default=[1e-2, 1e-3, 1e-4], metavar="TOL")
    parser.add_argument("--one", type=float, help=argparse.SUPPRESS)  # a child process: one tolerance
    args = parser.parse_args()
    if args.one is not None:
        measure(args.one)
    else:
        for tol in args.tols:
            subprocess.run([sys.executable, __file__, "--one", repr(tol)], check=True)
