"""Fabrication masks: a layout's pixels as polygons in micrometres (GDSII, DXF, SVG) or rasters.

Coordinates: the sensor spans ``[0, W_um] × [0, H_um]``; in Python its extent is given as
``sensor_um = (H_um, W_um)``, in the order of ``size = (h, w)`` (the command line writes
``WIDTHxHEIGHT`` for both). SVG and the rasters keep image
orientation (origin top-left, y down, row 0 at the top); GDSII and DXF use the CAD
convention (origin bottom-left, y up), so ``y_cad = H_um − y_image`` and the picture is the
same. Pixel ``(i, j)`` (row ``i``, column ``j``) is polygon number ``i · w + j`` in every
format.

Curved pixel edges become polylines whose deviation from the true edge (measured at the
middle of every segment) is at most ``tol_um``; straight-edged layouts need one segment per
straight piece. ``manhattan=True`` replaces every segment by an axis-aligned step, for processes that
only allow Manhattan geometry. ``grid_um`` snaps every vertex to the manufacturing grid.
Neighbouring pixels share their edge vertices exactly (each edge is built once), so the
polygons tile the sensor without gaps or overlaps, also after snapping.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import cv2
import numpy as np
import torch
from torch import Tensor
from tqdm import tqdm

from .checks import (
    ArgumentError,
    check_available,
    check_choice,
    check_extent,
    check_int,
    check_number,
    check_size,
)
from .coords import sensor_to_pixels, uniform_corners
from .files import atomic_write
from .layouts import Layout, check_layout
from .mesh import pixel_mesh, polygon_area, smooth_pieces
from .physics import SensorPhysics, as_physics, pixel_snr
from .topology import MeshTopology

__all__ = [
    "FORMATS",
    "RASTER_BYTES",
    "RASTER_MAX_SIDE",
    "ExportReport",
    "check_raster",
    "distance_subdivisions",
    "export_format",
    "export_layout",
    "index_mask_paths",
    "pixel_polygons_um",
    "report_json",
]

FORMATS = ("gds", "dxf", "svg", "png")
GDS_DBU_UM = 1e-3  # the GDSII database unit (precision 1e-9 m) in µm
GDS_MAX_LAYER = 32767  # layers and datatypes are 2-byte signed integers in a GDSII file
GDS_MAX_POINTS = 8190  # the most vertices one GDSII boundary record holds; longer ones are fractured


@dataclass
class ExportReport:
    """Numbers about an exported mask (lengths in µm, areas in µm²)."""

    path: str
    format: str
    pixels: int
    sensor_um: tuple[float, float]  # (H_um, W_um)
    min_pitch_um: float
    max_pitch_um: float
    min_area_um2: float
    max_area_um2: float
    vertices: int  # after snapping (a GDSII file always snaps, to its 1 nm grid): can be fewer than unsnapped
    tol_um: float
    max_deviation_um: float
    grid_um: float | None
    manhattan: bool
    files: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    physics: dict | None = None  # with export_layout(physics=): the camera and per-pixel numbers

    def summary(self) -> str:
        lines = [
            f"{self.format} mask {self.path}: {self.pixels} pixels on {self.sensor_um[1]:g} x "
            f"{self.sensor_um[0]:g} µm (width x height), {self.vertices} vertices"
            + (
                " (after snapping to the grid: vertices it makes repeated or collinear are dropped)"
                if self.grid_um
                else ""
            ),
            f"  pitch {self.min_pitch_um:.4g} .. {self.max_pitch_um:.4g} µm, "
            f"area {self.min_area_um2:.4g} .. {self.max_area_um2:.4g} µm²",
            f"  edges within {self.max_deviation_um:.3g} µm of the layout (tolerance {self.tol_um:g} µm"
            + (f", grid {self.grid_um:g} µm" if self.grid_um else "")
            + (", Manhattan" if self.manhattan else "")
            + ")",
        ]
        if self.physics is not None:
            p = self.physics
            full = (
                f"full well {p['min_full_well_e']:.4g} .. {p['max_full_well_e']:.4g} e⁻"
                if np.isfinite(p["max_full_well_e"])
                else "no full well"
            )
            snr = f"SNR {p['min_snr']:.3g} .. {p['max_snr']:.3g}"
            lines.append(f"  at {p['photons_per_um2']:g} photons/µm²: {full}, {snr}")
        return "\n".join(lines + [f"  warning: {w}" for w in self.warnings])


def distance_subdivisions(
    layout: Layout,
    size: tuple[int, int],
    tol: float,
    *,
    scale: tuple[float, float] = (2.0, 2.0),
    manhattan: bool = False,
    min_counts: Tensor | np.ndarray | None = None,
    max_subdiv: int = 4096,
) -> tuple[Tensor, float]:
    """Segments per smooth piece so that every polyline stays within a distance of its curve.

    The geometric counterpart of the value tolerance of [`pixel_mesh`][] (used for fabrication
    masks, where the edge's position is what matters): each smooth piece of every edge
    ([`smooth_pieces`][], a vertex on every kink) is split into ``2^k`` equal parameter steps
    until the curve's distance from every chord, measured at the step's middle, is at most
    ``tol``. Distances are in the units of ``scale``, the sensor's extent ``(H, W)``
    (micrometres for a mask; the default ``(2, 2)`` measures in sensor coordinates). With
    ``manhattan``, a segment's axis-aligned Z step adds ``min(|ΔX|, |ΔY|) / 2`` to its deviation.
    Straight-edged layouts need no steps beyond one per piece unless ``manhattan``.

    Args:
        layout: the pixel layout (its θ, without gradient).
        size: sensor size ``(H, W)``.
        tol: the largest deviation, in the units of ``scale``.
        scale: the sensor's extent ``(H, W)`` in the unit of ``tol``.
        manhattan: count the deviation of axis-aligned steps.
        min_counts: ``(E,)`` fewest segments per piece of each edge (default 1).
        max_subdiv: cap on segments per piece.

    Returns:
        ``(counts, deviation)``: ``(pieces,)`` int64 counts for ``pixel_mesh(...,
        subdivisions=counts)`` and the largest deviation measured.
    """
    theta = layout.theta_as(torch.float64).detach().cpu()
    a, b = MeshTopology(check_size(size)).edge_ends()
    owner, t0, t1 = smooth_pieces(layout, a, b, theta=theta)
    pa = a[owner] + t0[:, None] * (b - a)[owner]  # smooth pieces in uniform coordinates
    pd = (t1 - t0)[:, None] * (b - a)[owner]
    first = (
        np.ones(len(owner), dtype=np.int64) if min_counts is None else np.asarray(min_counts)[owner.numpy()]
    )
    n = first.astype(np.int64).copy()
    dev = np.zeros(len(owner))
    while (not layout.straight_edges) or manhattan:  # double the steps of every piece not yet within
        bad = np.zeros(len(owner), dtype=bool)
        for k in np.unique(n):
            idx = np.flatnonzero(n == k)
            t = torch.linspace(0, 1, 2 * k + 1, dtype=torch.float64)
            with torch.no_grad():
                q = layout.phi(pa[idx, None] + t[None, :, None] * pd[idx, None], theta)
            p = sensor_to_pixels(q, scale).numpy()  # vertices and midpoints
            dev[idx] = np.linalg.norm(p[:, 1::2] - (p[:, 0:-1:2] + p[:, 2::2]) / 2, axis=-1).max(1)
            if manhattan:  # a Z step deviates from its chord by at most min(|dx|, |dy|) / 2
                dev[idx] += np.abs(np.diff(p[:, ::2], axis=1)).min(-1).max(1) / 2
            bad[idx] = (dev[idx] > tol) & (k < max_subdiv)
        if not bad.any():
            break
        n[bad] *= 2
    return torch.from_numpy(n), float(dev.max(initial=0.0))


def _edge_polylines(
    layout: Layout,
    size: tuple[int, int],
    sensor_um: tuple[float, float],
    tol_um: float,
    manhattan: bool,
    min_steps: np.ndarray | None = None,
) -> tuple[list[np.ndarray], float]:
    """Every edge as a polyline in µm (image orientation) within ``tol_um``; and the max deviation
    ([`distance_subdivisions`][], then the mesh with those counts)."""
    counts, dev = distance_subdivisions(
        layout, size, tol_um, scale=sensor_um, manhattan=manhattan, min_counts=min_steps
    )
    theta = layout.theta_as(torch.float64).detach().cpu()
    mesh = pixel_mesh(layout, size, subdivisions=counts, dtype=torch.float64, theta=theta)
    out = mesh.edge_polylines(sensor_to_pixels(mesh.vertices, sensor_um))
    if manhattan:
        nh = mesh.topology.num_horizontal
        out = [_staircase(p, e < nh) for e, p in enumerate(out)]
    return out, dev


def _staircase(p: np.ndarray, horizontal: bool) -> np.ndarray:
    """Axis-aligned Z steps through the points ``p`` of one edge.

    A horizontal edge steps ``p_k → (m_x, p_k.y) → (m_x, p_k+1.y) → p_k+1`` with ``m`` the
    middle of the step, so it leaves and enters every vertex horizontally (a vertical edge
    likewise vertically). At each mesh corner the four edges then run off along four
    different axis directions and their staircases cannot cross there.
    """
    m = (p[:-1] + p[1:]) / 2
    if horizontal:
        c1, c2 = np.stack([m[:, 0], p[:-1, 1]], -1), np.stack([m[:, 0], p[1:, 1]], -1)
    else:
        c1, c2 = np.stack([p[:-1, 0], m[:, 1]], -1), np.stack([p[1:, 0], m[:, 1]], -1)
    out = np.empty((3 * len(p) - 2, 2))
    out[0::3], out[1::3], out[2::3] = p, c1, c2
    return out


def _clean(ring: np.ndarray) -> np.ndarray:
    """Drop repeated vertices and vertices on a straight line through their neighbours.

    Iterated until stable, so spikes that snapping folds onto a line (out and back along the
    same segment) disappear too. Exact for integer (snapped) coordinates.
    """
    while len(ring) > 3:
        ring = ring[np.any(ring != np.roll(ring, 1, axis=0), axis=1)]  # repeated vertices
        if len(ring) < 3:
            break
        prev, nxt = np.roll(ring, 1, axis=0), np.roll(ring, -1, axis=0)
        u, v = ring - prev, nxt - ring
        straight = u[:, 0] * v[:, 1] - u[:, 1] * v[:, 0] == 0  # on the line through both neighbours
        if not straight.any():
            break
        ring = ring[~straight]
    return ring


def _self_crossing(ring: np.ndarray) -> bool:
    """Whether two non-adjacent sides of an axis-aligned ring touch or cross."""
    a, b = ring, np.roll(ring, -1, axis=0)
    n = len(ring)
    if n < 4:
        return False
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    idx = np.arange(n)
    gap = np.abs(idx[:, None] - idx[None, :])
    apart = (gap > 1) & (gap < n - 1)  # not the same side, not neighbours
    overlap_x = (lo[:, None, 0] <= hi[None, :, 0]) & (lo[None, :, 0] <= hi[:, None, 0])
    overlap_y = (lo[:, None, 1] <= hi[None, :, 1]) & (lo[None, :, 1] <= hi[:, None, 1])
    return bool((apart & overlap_x & overlap_y).any())


#: Sensors of this many pixels or more show progress on a terminal by default.
PROGRESS_PIXELS = 100_000


def _bar(items, desc: str, progress: bool | None) -> tqdm:
    """``items`` with a progress bar: always (``True``), never (``False``), or on a terminal for
    `PROGRESS_PIXELS` items or more (``None``)."""
    if progress is None:  # tqdm's None: drawn on a terminal only
        disable = None if len(items) >= PROGRESS_PIXELS else True
    else:
        disable = not progress
    return tqdm(items, desc=desc, unit="px", leave=False, disable=disable)


def pixel_polygons_um(
    layout: Layout,
    size: tuple[int, int],
    sensor_um: tuple[float, float],
    *,
    tol_um: float = 0.01,
    grid_um: float | None = None,
    manhattan: bool = False,
    progress: bool | None = None,
) -> tuple[list[np.ndarray], dict]:
    """Every pixel's closed polygon in µm (image orientation), row-major.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)`` in pixels.
        sensor_um: sensor extent ``(H_um, W_um)``, in the order of ``size``.
        tol_um: largest deviation of a curved edge's polyline from the edge.
        grid_um: snap vertices to this grid (None: no snapping); it must be finer than the
            smallest pixel (``ValueError`` otherwise).
        manhattan: axis-aligned steps instead of slanted segments.
        progress: a progress bar on stderr (``None``: on a terminal, for sensors of
            `PROGRESS_PIXELS` pixels or more).

    Returns:
        ``(polygons, info)``: ``(n_k, 2)`` float64 arrays (first vertex not repeated) and
        ``{"max_deviation_um", "width_um", "height_um", "self_touching"}`` (per-pixel mean
        edge lengths as ``(h, w)`` arrays, before snapping; the number of Manhattan outlines
        that still touch themselves after refinement, which a coarse grid can force at acute
        corners).
    """
    h, w = check_size(size)
    sensor_um = check_extent(sensor_um)
    tol_um = check_number(tol_um, "tol_um", 0, lo_open=True)
    if grid_um is not None:
        grid_um = check_number(grid_um, "grid_um", 0, lo_open=True)
        pitch = _smallest_chord_um(layout, (h, w), sensor_um)
        if grid_um >= pitch:
            raise ArgumentError(
                "grid_um",
                f"grid_um = {grid_um:g} µm is not finer than the smallest pixel (pitch {pitch:.4g} µm); "
                f"use a grid below {pitch:.4g} µm",
            )
    topo = MeshTopology((h, w))
    nh = topo.num_horizontal
    steps = np.ones(topo.num_edges, dtype=np.int64)
    for _ in range(12):  # Manhattan: refine the edges of any ring whose steps cross, and retry
        with torch.no_grad():
            lines, dev = _edge_polylines(layout, (h, w), sensor_um, tol_um, manhattan, steps)
        snapped = [np.rint(p / grid_um).astype(np.int64) for p in lines] if grid_um else lines
        polys, crossed = [], []
        bar = _bar(topo.pixel_edges().reshape(-1, 4), "pixel outlines", progress)
        for edges in bar:
            top, right, bottom, left = (snapped[e] for e in edges)
            ring = _clean(np.concatenate([top[:-1], right[:-1], bottom[::-1][:-1], left[::-1][:-1]]))
            if manhattan and _self_crossing(ring):
                crossed += edges.tolist()
            polys.append(ring * grid_um if grid_um else ring)
        if not crossed:
            break
        steps[np.unique(crossed)] *= 2
    length = np.array([np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in lines])
    lh, lv = length[:nh].reshape(h + 1, w), length[nh:].reshape(h, w + 1)
    info = {
        "max_deviation_um": dev,
        "width_um": (lh[:-1] + lh[1:]) / 2,
        "height_um": (lv[:, :-1] + lv[:, 1:]) / 2,
        "self_touching": len(crossed) // 4,
    }
    return polys, info


def _smallest_chord_um(layout: Layout, size: tuple[int, int], sensor_um: tuple[float, float]) -> float:
    """The shortest distance between neighbouring pixel corners, in µm (a bound on the pitch)."""
    with torch.no_grad():
        c = sensor_to_pixels(
            layout.phi(uniform_corners(size), layout.theta_as(torch.float64).detach().cpu()), sensor_um
        )
    dx = (c[:, 1:] - c[:, :-1]).norm(dim=-1)
    dy = (c[1:] - c[:-1]).norm(dim=-1)
    return float(min(dx.min(), dy.min()))


def _write_gds(path: Path, polys, hu: float, layer: int, datatype: int, cell: str) -> None:
    import gdstk

    lib = gdstk.Library("LAYOUTWARP", unit=1e-6, precision=1e-9)
    c = lib.new_cell(cell)
    for p in polys:
        c.add(gdstk.Polygon(np.stack([p[:, 0], hu - p[:, 1]], -1), layer=layer, datatype=datatype))
    atomic_write(path, lambda tmp: lib.write_gds(tmp, max_points=GDS_MAX_POINTS))


def _write_dxf(path: Path, polys, hu: float, layer: int) -> None:
    import ezdxf
    from ezdxf import units

    doc = ezdxf.new("R2010", units=units.InsertUnits.Microns)
    doc.header["$MEASUREMENT"] = 1  # metric
    name = f"PIXELS_{layer}"
    doc.layers.add(name)
    msp = doc.modelspace()
    for p in polys:
        msp.add_lwpolyline(
            np.stack([p[:, 0], hu - p[:, 1]], -1).tolist(),
            format="xy",
            close=True,
            dxfattribs={"layer": name},
        )
    atomic_write(path, doc.saveas)


def _write_svg(path: Path, polys, wu: float, hu: float, size, progress: bool | None = None) -> None:
    stroke = min(wu / size[1], hu / size[0]) / 50
    parts = [
        '<?xml version="1.0" encoding="UTF-8"?>',
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{wu / 1000:g}mm" height="{hu / 1000:g}mm" '
        f'viewBox="0 0 {wu!r} {hu!r}">',
        f'<g fill="none" stroke="black" stroke-width="{stroke:.6g}">',
    ]
    w = size[1]
    for k, p in enumerate(_bar(polys, "writing SVG", progress)):
        pts = " ".join(f"{x!r},{y!r}" for x, y in p.tolist())
        parts.append(f'<polygon id="p{k // w}_{k % w}" points="{pts}"/>')
    parts += ["</g>", "</svg>", ""]
    atomic_write(path, lambda tmp: Path(tmp).write_text("\n".join(parts)))


def _imwrite(path: str, arr: np.ndarray) -> None:
    if not cv2.imwrite(path, arr):
        raise OSError(f"OpenCV could not write {path}")


#: A raster mask's memory: the boundary lines (uint8), the pixel index (int32) and its uint16 copy.
RASTER_BYTES = 7
#: The raster's largest side: OpenCV draws in int32 fixed point with 4 fractional bits.
RASTER_MAX_SIDE = 2**27 - 1


def _raster_shape(px_per_um: float, extent_um: tuple[float, float]) -> tuple[int, int]:
    return max(1, round(extent_um[0] * px_per_um)), max(1, round(extent_um[1] * px_per_um))


def check_raster(px_per_um: float | None, extent_um: tuple[float, float]) -> float:
    """The PNG mask's resolution (raster pixels per µm; ``None``: 4096 raster pixels on the longer
    side), refused before any work when its raster cannot be drawn or held in memory.

    Raises:
        ArgumentError: naming ``px_per_um``, the raster size and what it needs, in one line.
    """
    if px_per_um is None:
        return 4096 / max(extent_um)
    ppu = check_number(px_per_um, "px_per_um", 0, lo_open=True)
    h, w = _raster_shape(ppu, extent_um)
    what = f"px_per_um {ppu:g} makes a {w}x{h} raster mask"
    if max(h, w) > RASTER_MAX_SIDE:
        raise ArgumentError(
            "px_per_um", f"{what}, over the {RASTER_MAX_SIDE} raster pixels a side OpenCV draws"
        )
    check_available(h * w * RASTER_BYTES, "px_per_um", what, f"{RASTER_BYTES} bytes a raster pixel")
    return ppu


def _write_png(path: Path, polys, wu: float, hu: float, px_per_um: float, line_width: int) -> list[str]:
    shape = _raster_shape(px_per_um, (hu, wu))
    shift = 4
    pts = [np.round(p * px_per_um * (1 << shift) - (1 << (shift - 1))).astype(np.int32) for p in polys]
    lines = np.zeros(shape, np.uint8)
    cv2.polylines(lines, pts, True, 255, thickness=max(1, line_width), lineType=cv2.LINE_8, shift=shift)
    atomic_write(path, lambda tmp: _imwrite(tmp, lines))
    big = len(polys) + 1 > np.iinfo(np.uint16).max
    index = np.zeros(shape, np.int32)
    for k, p in enumerate(pts):
        cv2.fillPoly(index, [p], k + 1, lineType=cv2.LINE_8, shift=shift)
    ipath, other = index_mask_paths(path)[:: -1 if big else 1]
    if big:
        atomic_write(ipath, lambda tmp: np.save(tmp, index))
    else:
        atomic_write(ipath, lambda tmp: _imwrite(tmp, index.astype(np.uint16)))
    other.unlink(missing_ok=True)  # an earlier export's to this path: no stale mask beside it
    return [str(ipath)]


def export_format(path: str | Path, format: str | None = None) -> str:
    """The format an export to ``path`` writes: ``format`` (any case), which must match the file's
    suffix, or the suffix itself; one of ``FORMATS``.

    Raises:
        ArgumentError: in one line, naming ``path`` where its suffix is none of them and no
            ``format`` is given, else ``format`` where it is none of them or differs.
    """
    path = Path(path)
    suffix = path.suffix.lstrip(".").lower()
    if format is None and suffix not in FORMATS:  # the file name chose: it is the one to name
        names = ", ".join(f"*.{f}" for f in FORMATS)
        raise ArgumentError("path", f"{path.name!r} names no export format: name it {names}")
    fmt = check_choice((format or suffix).lower(), FORMATS, "format")
    if format is not None and suffix != fmt:
        raise ArgumentError(
            "format", f"format {fmt!r} does not match the file name {path.name!r}; name it *.{fmt}"
        )
    return fmt


def index_mask_paths(path: str | Path) -> tuple[Path, Path]:
    """Where a PNG export to ``path`` writes its pixel index mask beside the outlines:
    ``<stem>_index.png`` (uint16), or ``<stem>_index.npy`` for more than 65 534 pixels (an export
    removes the other of the two, an earlier export's to the same path)."""
    path = Path(path)
    return path.with_name(path.stem + "_index.png"), path.with_name(path.stem + "_index.npy")


def export_layout(
    layout: Layout,
    size: tuple[int, int],
    path: str | Path,
    sensor_um: tuple[float, float],
    *,
    format: str | None = None,
    tol_um: float = 0.01,
    grid_um: float | None = None,
    manhattan: bool = False,
    layer: int = 1,
    datatype: int = 0,
    cell: str = "SENSOR",
    px_per_um: float | None = None,
    line_width: int = 1,
    min_feature_um: float | None = None,
    physics: SensorPhysics | None = None,
    progress: bool | None = None,
) -> ExportReport:
    """Write the pixel boundaries of ``layout`` as a fabrication mask.

    Args:
        layout: the pixel layout.
        size: sensor size ``(h, w)``.
        path: output file; ``format`` defaults to its suffix (``.gds``, ``.dxf``, ``.svg``,
            ``.png``).
        sensor_um: sensor extent ``(H_um, W_um)``, in the order of ``size``.
        format: ``"gds"`` (gdstk; unit 1 µm, precision 1 nm; one polygon per pixel on
            ``layer``/``datatype`` in cell ``cell``), ``"dxf"`` (ezdxf; R2010, units µm, one
            closed LWPOLYLINE per pixel on layer ``PIXELS_<layer>``), ``"svg"`` (user units of
            the viewBox are µm; the root's width and height give the physical size in mm, a CSS
            unit, so a viewer shows the sensor at 1:1; one ``<polygon id="p<i>_<j>">`` per pixel)
            or ``"png"`` (boundary lines of ``line_width`` raster pixels at ``px_per_um``, plus
            ``<stem>_index.png``: uint16 pixel index + 1 per raster pixel, 0 on no pixel;
            ``.npy`` int32 above 65534 pixels).
        tol_um: curved-edge tolerance; grid_um: manufacturing grid (GDSII: default the 1 nm
            database unit, which the file stores anyway); manhattan: axis-aligned steps (see
            [`pixel_polygons_um`][]).
        px_per_um: raster resolution (default: 4096 raster pixels on the longer side).
        min_feature_um: warn when the smallest pitch is below this.
        physics: add each pixel's full well and its SNR for a flat field at the physics' exposure
            (``photons_per_um2``, [`pixel_snr`][]; the pixel areas are the
            exported polygons') to the report (``physics``: the camera, ``full_well_e`` and
            ``snr`` per pixel, row-major). Its ``sensor_um`` is replaced by this sensor's.
        progress: progress bars on stderr while outlines are built and written (``None``: on
            a terminal, for sensors of `PROGRESS_PIXELS` (100 000) pixels or more).

    Returns:
        an [`ExportReport`][] (also printed by ``layoutwarp export``).
    """
    path = Path(path)
    fmt = export_format(path, format)
    check_layout(layout)
    size = check_size(size)
    hu, wu = check_extent(sensor_um)
    # GDSII writes layers and datatypes as 2-byte signed integers (0..32767 in practice)
    layer, datatype = (
        check_int(layer, "layer", 0, GDS_MAX_LAYER),
        check_int(datatype, "datatype", 0, GDS_MAX_LAYER),
    )
    line_width = check_int(line_width, "line_width", 1)
    if not (isinstance(cell, str) and cell.strip()):
        raise ArgumentError("cell", f"cell must be a non-empty name, got {cell!r}")
    physics = as_physics(physics)
    if fmt == "png":
        px_per_um = check_raster(px_per_um, (hu, wu))
    elif px_per_um is not None:
        raise ArgumentError("px_per_um", f"px_per_um sets a PNG mask's resolution; a {fmt} mask has none")
    if fmt == "gds" and grid_um is None:
        grid_um = GDS_DBU_UM  # GDSII stores integers: snap here so the report matches the file
        pitch = _smallest_chord_um(layout, size, (hu, wu))
        if grid_um >= pitch:  # no grid was asked for: the sensor is what is too small
            raise ArgumentError(
                "sensor_um",
                f"sensor_um = {wu:g}x{hu:g} µm gives pixels of pitch {pitch:.4g} µm, not above GDSII's "
                f"{GDS_DBU_UM:g} µm grid; a GDSII mask needs a larger sensor (or use dxf, svg or png)",
            )
    polys, info = pixel_polygons_um(
        layout, size, (hu, wu), tol_um=tol_um, grid_um=grid_um, manhattan=manhattan, progress=progress
    )
    areas = np.array([abs(float(polygon_area(p))) for p in polys])
    pitch = np.minimum(info["width_um"], info["height_um"])
    report = ExportReport(
        path=str(path),
        format=fmt,
        pixels=len(polys),
        sensor_um=(hu, wu),
        min_pitch_um=float(pitch.min()),
        max_pitch_um=float(np.maximum(info["width_um"], info["height_um"]).max()),
        min_area_um2=float(areas.min()),
        max_area_um2=float(areas.max()),
        vertices=int(sum(len(p) for p in polys)),
        tol_um=tol_um,
        max_deviation_um=info["max_deviation_um"],
        grid_um=grid_um,
        manhattan=manhattan,
        files=[str(path)],
    )
    if physics is not None:
        physics = replace(physics, sensor_um=(hu, wu))
        numbers = pixel_snr(torch.from_numpy(areas), physics)
        report.physics = physics.to_dict() | {
            "full_well_e": numbers["full_well_e"].tolist(),
            "snr": numbers["snr"].tolist(),
            "min_full_well_e": float(numbers["full_well_e"].min()),
            "max_full_well_e": float(numbers["full_well_e"].max()),
            "min_snr": float(numbers["snr"].min()),
            "max_snr": float(numbers["snr"].max()),
        }
    if min_feature_um is not None and report.min_pitch_um < min_feature_um:
        k = int(pitch.argmin())
        report.warnings.append(
            f"smallest pitch {report.min_pitch_um:.4g} µm (pixel row {k // size[1]}, column {k % size[1]}) "
            f"is below the minimum feature size {min_feature_um:g} µm"
        )
    if info["self_touching"]:
        report.warnings.append(
            f"{info['self_touching']} Manhattan pixel outlines touch themselves near acute corners "
            f"at grid {grid_um:g} µm; use a finer grid"
        )
    if info["max_deviation_um"] > (tol_um + (grid_um or 0.0)) * (
        1 + 1e-9
    ):  # snapping moves edges by the grid
        report.warnings.append(
            f"edges are up to {info['max_deviation_um']:.4g} µm from the layout, more than tol_um "
            f"{tol_um:g} µm: the subdivision cap binds (θ near ±1 bends edges sharply); check the mask"
        )
    if (areas <= 0).any():
        report.warnings.append(f"{int((areas <= 0).sum())} pixels collapsed to zero area (grid too coarse)")
    longest = max(len(p) for p in polys)
    if fmt == "gds" and longest > GDS_MAX_POINTS:
        report.warnings.append(
            f"a pixel outline has {longest} vertices, more than a GDSII boundary holds ({GDS_MAX_POINTS}): "
            "it is written as several polygons; use a larger tol_um"
        )
    if fmt == "gds":
        _write_gds(path, polys, hu, layer, datatype, cell)
    elif fmt == "dxf":
        _write_dxf(path, polys, hu, layer)
    elif fmt == "svg":
        _write_svg(path, polys, wu, hu, size, progress)
    else:
        report.files += _write_png(path, polys, wu, hu, px_per_um, line_width)
    return report


def report_json(report: ExportReport) -> str:
    """The report as JSON text. The extent is written twice, each key naming its order:
    ``sensor_um_hw`` (height, width, as the API takes it) and ``sensor_um_wxh`` (the command
    line's ``WIDTHxHEIGHT``)."""
    data = asdict(report)
    hu, wu = data.pop("sensor_um")
    data = {"sensor_um_hw": [hu, wu], "sensor_um_wxh": f"{wu:g}x{hu:g}", **data}
    return json.dumps(data, indent=2)
