"""Speed against error, measured in one process: integrators and their anchors.

Every time is the median of repeats after a warm-up; every ratio is against an anchor
measured in the same run (``cv2.resize(INTER_AREA)``, a bare ``grid_sample`` stratified
Monte Carlo with 16 samples per pixel). Errors are against a float64 exact reference.
Peak memory is measured in a spawned child (growth of its resident set over one call).
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from .layouts import CurvLayout, Layout, RectLayout, UniformLayout
from .mesh import sample_points
from .sensor import simulate

__all__ = ["Row", "blurred_noise", "format_table", "run"]


@dataclass
class Row:
    """One measured configuration."""

    layout: str
    method: str
    setting: str
    forward_ms: float
    backward_ms: float | None = None
    rmse: float | None = None
    max_err: float | None = None
    peak_mb: float | None = None
    extra: dict = field(default_factory=dict)


def blurred_noise(h: int, w: int, c: int = 3, sigma: float = 2.0, seed: int = 0) -> torch.Tensor:
    """A ``(1, c, h, w)`` float32 image of Gaussian-blurred uniform noise in [0, 1]."""
    rng = np.random.default_rng(seed)
    img = rng.random((h, w, c), dtype=np.float32)
    img = cv2.GaussianBlur(img, (0, 0), sigma)
    img = (img - img.min()) / (img.max() - img.min())
    return torch.from_numpy(np.ascontiguousarray(img.reshape(h, w, c).transpose(2, 0, 1)))[None]


def _time(fn: Callable[[], object], repeats: int) -> float:
    fn()
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3)


def _status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(key)


def _memory_child(spec: dict, conn) -> None:  # pragma: no cover - runs in a spawned process
    torch.set_num_threads(spec["threads"])
    img = blurred_noise(*spec["src"])
    npimg = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    layout = {"uniform": UniformLayout, "rect": RectLayout, "curv": CurvLayout}[spec["layout"]]
    layout = layout() if spec["layout"] == "uniform" else layout(spec["theta"])
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset the peak resident set (VmHWM) to the current one
    before = _status_mb("VmRSS")
    with torch.no_grad():
        if spec["method"] == "inter_area":
            cv2.resize(npimg, spec["size"][::-1], interpolation=cv2.INTER_AREA)
        else:
            simulate(img, layout, spec["size"], spec["method"], **spec["opts"])
    conn.send(_status_mb("VmHWM") - before)
    conn.close()


def peak_memory_mb(spec: dict) -> float | None:
    """Growth of the resident set over one forward call, in MiB, in a fresh spawned process.

    ``spec`` names the run: ``layout``, ``theta``, ``method``, ``opts``, ``src``, ``size``,
    ``threads``. (A forked child would deadlock in torch's thread pool.)
    """
    if not os.path.exists("/proc/self/clear_refs"):
        return None
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=_memory_child, args=(spec, child))
    proc.start()
    value = parent.recv() if parent.poll(900) else None
    proc.join()
    return value


def _grid_sample_mc(img: torch.Tensor, layout: Layout, size, s: int, gen) -> torch.Tensor:
    """Anchor: stratified Monte Carlo as saliency samplers do it (φ, grid_sample, mean)."""
    h, w = size
    u = sample_points(size, s, jitter=True, generator=gen, dtype=torch.float32)
    p = layout.phi(u, layout.theta.detach().float())
    n, c = img.shape[:2]
    out = F.grid_sample(img.reshape(1, n * c, *img.shape[-2:]), p[None], mode="bilinear", align_corners=False)
    return out.reshape(n, c, h, s, w, s).mean((3, 5))


def run(
    src: tuple[int, int] = (1024, 2048),
    size: tuple[int, int] = (129, 257),
    theta: tuple[float, float] = (0.3, 0.2),
    tols: tuple[float, ...] = (1e-2, 1e-3, 1e-4),
    mc_samples: tuple[int, ...] = (1, 2, 4, 8),
    repeats: int = 5,
    memory: bool = True,
    threads: int | None = None,
) -> dict:
    """Measure integrators against anchors on a blurred-noise image; returns a JSON-able dict."""
    if threads:
        torch.set_num_threads(threads)
    img = blurred_noise(*src)
    npimg = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    h, w = size
    rows: list[Row] = []
    input_mb = img.numel() * 4 / 2**20

    def mem(layout_name, method, opts):
        if not memory:
            return None
        spec = {
            "layout": layout_name,
            "theta": theta,
            "method": method,
            "opts": opts,
            "src": src,
            "size": size,
            "threads": torch.get_num_threads(),
        }
        return peak_memory_mb(spec)

    # anchors
    t_area = _time(lambda: cv2.resize(npimg, (w, h), interpolation=cv2.INTER_AREA), repeats)
    rows.append(
        Row("uniform", "anchor: cv2.resize INTER_AREA", "-", t_area, peak_mb=mem("uniform", "inter_area", {}))
    )
    curv, rect = CurvLayout(theta), RectLayout(theta)
    gen = torch.Generator().manual_seed(0)
    t_gs = _time(lambda: _grid_sample_mc(img, curv, size, 4, gen), repeats)
    rows.append(Row("curv", "anchor: grid_sample MC", "16 spp", t_gs))

    for name, layout in (("uniform", UniformLayout()), ("rect", rect), ("curv", curv)):
        with torch.no_grad():
            ref = simulate(img.double(), layout, size, tol=1e-6)
        if name == "curv":
            exact_settings = [("exact", {"tol": t}, f"tol={t:g}") for t in tols]
        else:
            exact_settings = [("exact", {}, "exact")]
        for method, opts, setting in (
            exact_settings
            + [("montecarlo", {"samples": s, "seed": 0}, f"{s * s} spp") for s in mc_samples]
            + [("point", {}, "1 spp")]
        ):

            def fwd(method=method, opts=opts, layout=layout):
                with torch.no_grad():
                    return simulate(img, layout, size, method, **opts)

            t_f = _time(fwd, repeats)
            out = fwd()
            err = (out.double() - ref).abs()
            t_b = None
            if layout.theta.numel():
                layout.rho.requires_grad_(True)

                def fwd_bwd(method=method, opts=opts, layout=layout):
                    y = simulate(img, layout, size, method, **opts)
                    y.sum().backward()
                    layout.rho.grad = None

                def fwd_grad(method=method, opts=opts, layout=layout):
                    return simulate(img, layout, size, method, **opts)

                t_fg = _time(fwd_grad, repeats)
                t_b = _time(fwd_bwd, repeats) - t_fg
            label = "separable" if (method == "exact" and layout.separable) else method
            rows.append(
                Row(
                    name,
                    label,
                    setting,
                    t_f,
                    t_b,
                    float(err.pow(2).mean().sqrt()),
                    float(err.max()),
                    mem(name, method, opts),
                    {"forward_with_grad_ms": t_fg if t_b is not None else None},
                )
            )
    return {
        "src_hw": list(src),
        "sensor_hw": list(size),
        "theta": list(theta),
        "threads": torch.get_num_threads(),
        "input_mb": input_mb,
        "anchors_ms": {"inter_area": t_area, "grid_sample_mc16": t_gs},
        "rows": [asdict(r) for r in rows],
    }


def format_table(result: dict) -> str:
    """A plain-text table with ratios against the anchors of the same run."""
    a = result["anchors_ms"]
    lines = [
        f"source {result['src_hw'][1]}x{result['src_hw'][0]}x3 float32 -> sensor "
        f"{result['sensor_hw'][1]}x{result['sensor_hw'][0]}, θ={tuple(result['theta'])}, "
        f"{result['threads']} threads; anchors: INTER_AREA {a['inter_area']:.2f} ms, "
        f"grid_sample MC-16 {a['grid_sample_mc16']:.2f} ms",
        f"{'layout':8s} {'method':30s} {'setting':9s} {'fwd ms':>8s} {'/AREA':>6s} {'/GS16':>6s} "
        f"{'bwd/fwd':>7s} {'RMSE':>9s} {'max err':>9s} {'peak/in':>7s}",
    ]
    for r in result["rows"]:
        bwd = (
            "" if r["backward_ms"] is None else f"{r['backward_ms'] / r['extra']['forward_with_grad_ms']:.2f}"
        )
        rmse = "" if r["rmse"] is None else f"{r['rmse']:.2e}"
        mx = "" if r["max_err"] is None else f"{r['max_err']:.2e}"
        peak = "" if r["peak_mb"] is None else f"{r['peak_mb'] / result['input_mb']:.2f}"
        lines.append(
            f"{r['layout']:8s} {r['method']:30s} {r['setting']:9s} {r['forward_ms']:8.2f} "
            f"{r['forward_ms'] / a['inter_area']:6.2f} {r['forward_ms'] / a['grid_sample_mc16']:6.2f} "
            f"{bwd:>7s} {rmse:>9s} {mx:>9s} {peak:>7s}"
        )
    return "\n".join(lines)


def main_bench(quick: bool, json_path: str | None) -> dict:
    """Run (``quick``: a 512x256 source, 65x33 sensor, fewer repeats) and print the table."""
    if quick:
        result = run(src=(256, 512), size=(33, 65), repeats=3, memory=False)
    else:
        result = run()
    print(format_table(result))
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        Path(json_path).write_text(json.dumps(result, indent=2))
    return result
