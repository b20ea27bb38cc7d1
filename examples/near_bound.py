"""How the curved families' pixel areas hold the tolerance as θ nears ±1.

For curv and elliptic at |θ| from 0.999 to 1 − 10⁻⁷ (both signs, and mixed), on a 1x5 sensor (a
column of five pixels) and a 6x6 one, at the default tolerance of float images (2⁻¹²): each
pixel's area from its polyline
(`lw.pixel_mesh`) against its boundary sampled along φ at 2000 equal steps an edge plus 3000
graded geometrically to 1e-13 from each end (where φ bends as θ nears ±1). Prints the worst
pixel's relative error over the tolerance, the segments, and whether the mesh warned that a piece
reached ``max_subdiv``; a row over 1 without that warning is a silent one.

    python examples/near_bound.py [--tol 2.44e-4]
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np
import torch

import layoutwarp as lw
from layoutwarp.mesh import polygon_area

F64 = torch.float64


def boundary_areas(layout: lw.Layout, size: tuple[int, int]) -> np.ndarray:
    """Every pixel's area, ``(h, w)``, from its four sides mapped by φ at graded parameters."""
    h, w = size
    t = np.unique(
        np.r_[np.linspace(0, 1, 2001), np.geomspace(1e-13, 0.5, 3000), 1 - np.geomspace(1e-13, 0.5, 3000)]
    )
    t = torch.tensor(t[:-1], dtype=F64)  # each side from its start, up to its end (the next side's start)
    x = torch.linspace(-1, 1, w + 1, dtype=F64)
    y = torch.linspace(-1, 1, h + 1, dtype=F64)
    x0, y0 = torch.meshgrid(x[:-1], y[:-1], indexing="xy")
    x1, y1 = torch.meshgrid(x[1:], y[1:], indexing="xy")
    corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]  # counter-clockwise in sensor coordinates
    sides = []
    for (ax, ay), (bx, by) in zip(corners, corners[1:] + corners[:1], strict=True):
        sides.append(
            torch.stack(
                [ax[..., None] + (bx - ax)[..., None] * t, ay[..., None] + (by - ay)[..., None] * t], -1
            )
        )
    ring = torch.cat(sides, -2)  # (h, w, 4·len(t), 2)
    with torch.no_grad():
        return polygon_area(layout.phi(ring, layout.theta_as(F64))).abs().numpy()


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--tol", type=float, default=2.0**-12)
    args = ap.parse_args()
    print(f"{'family':9s} {'θ':>24s} {'size':>5s} {'error/tol':>10s} {'segments':>9s}  said")
    for family in ("curv", "elliptic"):
        for v in (0.999, 0.9999, 0.99999, 0.999999, 0.9999999):
            for sx, sy in ((1, 1), (-1, -1), (1, -1)):
                for size in ((5, 1), (6, 6)):
                    layout = lw.make_layout(family, (sx * v, sy * v), dtype=F64)
                    with warnings.catch_warnings(record=True) as said:
                        warnings.simplefilter("always")
                        mesh = lw.pixel_mesh(layout, size, tol=args.tol, dtype=F64)
                    capped = any("max_subdiv" in str(m.message) for m in said)
                    ref = boundary_areas(layout, size)
                    err = float((np.abs(mesh.areas().numpy() - ref) / ref).max()) / args.tol
                    word = "max_subdiv warned" if capped else ("SILENT" if err > 1 else "")
                    theta, wxh = f"({sx * v:.7g}, {sy * v:.7g})", f"{size[1]}x{size[0]}"
                    print(f"{family:9s} {theta:>24s} {wxh:>5s} {err:10.3g} {mesh.num_segments:9d}  {word}")


if __name__ == "__main__":
    main()
