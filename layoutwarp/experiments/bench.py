"""Speed against error, measured in one process: integrators, their anchors, and scaling.

Every time is the median of repeats after a warm-up; every ratio is against an anchor
measured in the same run: ``cv2.resize(INTER_AREA)`` (the uniform box integral),
``cv2.remap(INTER_LINEAR)`` on precomputed maps (point sampling) and a bare ``grid_sample``
stratified Monte Carlo with 16 samples per pixel. Forward errors are against a float64 exact
reference; on the synthetic scene also against the scene's analytic pixel means
([`SineScene`][]). Gradient errors are against central finite differences of the float64
exact forward. Peak memory is measured in a spawned child (growth of its resident set) on the
CPU, and as the growth of allocated GPU memory on a CUDA device.
The caller chooses torch's thread count (``layoutwarp bench --threads``); nothing here sets it.
"""

from __future__ import annotations

import json
import multiprocessing as mp
import os
import time
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .. import jit, kernels, resampler
from ..checks import check_size
from ..coords import uniform_corners
from ..doctor import run_info
from ..files import atomic_write
from ..integrators import data_tolerance, integrate_exact
from ..kernels.mesh import build_mesh, mesh_spec
from ..layoutfile import layout_from_spec
from ..layouts import Layout, make_layout
from ..maps import forward_maps, sample_points
from ..mesh import pixel_mesh
from ..sensor import simulate
from ..testing import count_ops
from .scene import SineScene, blurred_noise, load_photo
from .timing import (
    cuda_peak_mb,
    interleaved_times,
    time_backward,
    time_call,
    time_overhead,
    time_paired,
)

__all__ = [
    "ENTRY_POINTS",
    "README_EXAMPLE",
    "BenchConfig",
    "Row",
    "bench_layouts",
    "fd_theta_gradient",
    "first_calls",
    "format_scaling",
    "format_table",
    "interleaved_times",
    "main_bench",
    "preprocess_baseline",
    "report_text",
    "run",
    "scaling",
]


@dataclass
class Row:
    """One measured configuration (times in ms, errors in image units, memory in MiB)."""

    image: str
    layout: str
    method: str
    setting: str
    forward_ms: float
    backward_ms: float | None = None
    rmse: float | None = None
    max_err: float | None = None
    scene_rmse: float | None = None
    grad_rel_err: float | None = None
    peak_mb: float | None = None
    extra: dict = field(default_factory=dict)


def status_mb(key: str) -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith(key + ":"):
                return int(line.split()[1]) / 1024
    raise KeyError(key)


def memory_child(spec: dict, conn) -> None:  # pragma: no cover - runs in a spawned process
    torch.set_num_threads(spec["threads"])
    if "cache_size" in spec:  # how many fixed layouts' area weights simulate keeps
        resampler.RESAMPLERS.maxsize = spec["cache_size"]
    img = blurred_noise(*spec["src"])
    npimg = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    layout = layout_from_spec(spec["layout"])
    maps = forward_maps(layout, spec["size"], spec["src"]).numpy() if spec["method"] == "remap" else None
    if spec["method"] not in ("inter_area", "remap"):  # load the code (compiled kernels) once, on a
        with torch.no_grad():  # small image and sensor: the measured call builds its own mesh
            simulate(blurred_noise(48, 64), layout, (5, 7), spec["method"], **spec["opts"])
    with open("/proc/self/clear_refs", "w") as f:
        f.write("5")  # reset the peak resident set (VmHWM) to the current one
    before = status_mb("VmRSS")
    with torch.no_grad():
        if spec["method"] == "inter_area":
            cv2.resize(npimg, spec["size"][::-1], interpolation=cv2.INTER_AREA)
        elif maps is not None:
            _remap(npimg, maps)
        else:
            simulate(img, layout, spec["size"], spec["method"], **spec["opts"])
    conn.send(status_mb("VmHWM") - before)
    conn.close()


def peak_memory_mb(spec: dict) -> float | None:
    """Growth of the resident set over one forward call, in MiB, in a fresh spawned process.

    The child first runs the method once on a small image and sensor, so that loading code
    (the compiled kernels) is not counted; the measured call builds its mesh and tables anew.

    ``spec`` names the run: ``layout`` (a [`layout_from_spec`][] dict), ``method`` (a
    [`simulate`][] method, ``"inter_area"`` or ``"remap"``), ``opts``, ``src``, ``size``,
    ``threads``, and optionally ``cache_size`` (the ``maxsize`` of
    [`RESAMPLERS`][layoutwarp.resampler.RESAMPLERS]). (A forked child would deadlock in torch's
    thread pool.)
    """
    if not os.path.exists("/proc/self/clear_refs"):
        return None
    ctx = mp.get_context("spawn")
    parent, child = ctx.Pipe()
    proc = ctx.Process(target=memory_child, args=(spec, child))
    proc.start()
    value = parent.recv() if parent.poll(900) else None
    proc.join()
    return value


def _remap(npimg: np.ndarray, maps: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """Anchor: point sampling with ``cv2.remap`` (bilinear, replicated border) on precomputed maps."""
    return cv2.remap(npimg, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def _grid_sample_mc(img: Tensor, layout: Layout, size, s: int, gen) -> Tensor:
    """Anchor: stratified Monte Carlo as saliency samplers do it (φ, grid_sample, mean)."""
    h, w = size
    u = sample_points(size, s, jitter=True, generator=gen, dtype=torch.float32, device=img.device)
    p = layout.phi(u, layout.theta.detach().float())
    n, c = img.shape[:2]
    out = F.grid_sample(img.reshape(1, n * c, *img.shape[-2:]), p[None], mode="bilinear", align_corners=False)
    return out.reshape(n, c, h, s, w, s).mean((3, 5))


def _exact64(img64: Tensor, layout: Layout, size, subdivisions: int, theta: Tensor) -> Tensor:
    """Float64 exact forward with θ; curved edges on a fixed-subdivision mesh (smooth in θ, for
    finite differences), straight-edged layouts on their exact mesh."""
    if layout.straight_edges:
        mesh = pixel_mesh(layout, size, theta=theta)
    else:
        mesh = pixel_mesh(layout, size, subdivisions=subdivisions, theta=theta)
    return integrate_exact(img64.flatten(0, 1), layout, size, mesh=mesh)


def fd_theta_gradient(
    img64: Tensor,
    layout: Layout,
    theta: Sequence[float] | Tensor,
    size,
    weights: Tensor,
    h: float = 1e-6,
    subdiv: int = 64,
) -> Tensor:
    """Central finite differences of ``Σ weights · exact(θ)`` in float64, shape ``(P,)``.

    Curved edges use ``subdiv`` equal parameter steps (no adaptive choice), so the forward
    is smooth in θ and the differences are not polluted by changing subdivisions. The box
    image makes the loss only piecewise smooth in θ (its derivative jumps whenever an edge
    crosses a source row or column), so the step is small: edges move by about
    ``1e-6 · source size`` pixels and few of them cross a boundary inside the window.
    """
    th = torch.as_tensor(theta, dtype=torch.float64)

    def loss(t: Tensor) -> float:
        with torch.no_grad():
            return float((_exact64(img64, layout, size, subdiv, t) * weights).sum())

    grads = []
    for k in range(th.numel()):
        step = torch.zeros_like(th)
        step[k] = h
        grads.append((loss(th + step) - loss(th - step)) / (2 * h))
    return torch.tensor(grads, dtype=torch.float64)


def _theta_grad(layout: Layout) -> Tensor:
    """``∂loss/∂θ`` from the gradient in ``layout.rho`` (θ's transform is elementwise)."""
    (dtheta,) = torch.autograd.grad(layout.theta.sum(), layout.rho)
    return layout.rho.grad.double() / dtheta.double()


def _settings(layout: Layout, name: str, tols, mc_samples) -> list[tuple[str, dict, str]]:
    if layout.straight_edges:
        exact = [("exact", {}, "exact")]
    else:  # the default call (tolerance from the data), then given tolerances
        exact = [("exact", {}, "default")] + [
            ("exact", {"tol": t}, f"tol={t:g}") for t in (tols if name in PAPER_ROWS else (1e-3,))
        ]
    samples = mc_samples if name in PAPER_ROWS else (4,)
    return (
        exact
        + [("montecarlo", {"samples": s, "seed": 0}, f"{s * s} spp") for s in samples]
        + [("point", {}, "1 spp")]
    )


#: Rows with every tolerance and sample count; the other families get the default, 1e-3, 16 spp.
PAPER_ROWS = ("uniform", "rect", "curv", "curv ±")


def bench_layouts(theta: tuple[float, float]) -> dict[str, dict]:
    """The benchmark's layouts by row name, as [`layout_from_spec`][] dicts: the paper's
    families at θ (``"curv ±"`` with mixed-sign θ: S-shaped pixel edges), a smooth spline and an
    8x8 control grid (fixed pseudo-random parameters) and the curvilinear fovea off the centre."""
    gen = torch.Generator().manual_seed(20261122)
    logits = (torch.randn(16, generator=gen, dtype=torch.float64) * 0.5).tolist()
    ctrl = uniform_corners((8, 8)).clone()
    ctrl[1:-1, 1:-1] += (torch.rand(7, 7, 2, generator=gen, dtype=torch.float64) - 0.5) * 0.1
    return {
        "uniform": {"family": "uniform"},
        "rect": {"family": "rect", "theta": list(theta)},
        "curv": {"family": "curv", "theta": list(theta)},
        "curv ±": {"family": "curv", "theta": [theta[0], -theta[1]]},
        "spline": {"family": "spline", "theta": logits, "knots": [8, 8], "kind": "smooth"},
        "grid 8x8": {"family": "grid", "control": ctrl.tolist()},
        "fovea": {"family": "fovea", "theta": list(theta), "center": [0.3, -0.2], "learn_center": True},
    }


@dataclass(frozen=True)
class BenchConfig:
    """What [`run`][] measures.

    Attributes:
        src: source image size ``(H, W)``.
        size: sensor size ``(h, w)``.
        theta: θ of the rect and curv layouts.
        tols: tolerances of the exact curvilinear integrator (besides the data default).
        mc_samples: Monte Carlo samples per axis (``s²`` per pixel).
        repeats: timed repeats after one warm-up (median reported).
        memory: measure peak memory in spawned children (photo image only).
        photo: photo file (default: the bundled ``kodim20``; skipped if none is found).
        device: where the integrators and the ``grid_sample`` anchor run (images and layouts
            are moved there; times wait for the GPU); the OpenCV anchors and every reference
            stay on the CPU. Peak memory is host RSS in children on ``"cpu"``, the growth of
            allocated GPU memory on ``"cuda"`` (then also ``extra["train_peak_mb"]``, forward +
            backward of the learnable layout).
        only: measure only these rows of [`bench_layouts`][] (the anchors always).
    """

    src: tuple[int, int] = (1024, 2048)
    size: tuple[int, int] = (129, 257)
    theta: tuple[float, float] = (0.35, 0.25)
    tols: tuple[float, ...] = (1e-2, 1e-3, 1e-4)
    mc_samples: tuple[int, ...] = (1, 2, 4, 8, 16)
    repeats: int = 5
    memory: bool = True
    photo: str | Path | None = None
    device: str = "cpu"
    only: tuple[str, ...] | None = None

    @classmethod
    def quick(cls, **changes: Any) -> BenchConfig:
        """Small sizes and few repeats (``layoutwarp bench --quick``)."""
        return cls(**({"src": (256, 512), "size": (33, 65), "repeats": 3, "memory": False} | changes))


@jit.use_mode("wait")  # the compiled kernels are timed, never the torch path while they compile
def run(config: BenchConfig | None = None, progress: Callable[[str], None] | None = None) -> dict:
    """Measure every integrator against the anchors on a photo and a synthetic scene.

    Args:
        config: what to measure (default: [`BenchConfig`][]'s full run).
        progress: called with a short message before each configuration.

    Returns:
        a JSON-able dict: sizes, anchors (ms), and one [`Row`][] per configuration.
    """
    cfg = config or BenchConfig()
    say = progress or (lambda msg: None)
    scene = SineScene.random(3)
    images = {"synthetic": scene.image(*cfg.src).float()}
    pic = load_photo(*cfg.src, cfg.photo)
    if pic is not None:
        images = {"photo": pic, **images}
    first = next(iter(images.values()))
    setups = bench_layouts(cfg.theta)
    say("anchors")
    anchors = _anchors(cfg, first, layout_from_spec(setups["curv"]).to(cfg.device))
    rows: list[Row] = []
    for image_name, img in images.items():
        for name, spec in setups.items():
            if not cfg.only or name in cfg.only:
                rows += _layout_rows(cfg, image_name, img, name, spec, scene, anchors, say)
    if not cfg.only or "curv" in cfg.only:
        say(f"{next(iter(images))}: sensor physics")
        rows += physics_rows(cfg, next(iter(images)), first, anchors)
        say(f"{next(iter(images))}: a fixed layout's cached area weights")
        rows.append(reuse_row(cfg, next(iter(images)), first))
        say(f"{next(iter(images))}: training steps of learnable layouts")
        rows += training_rows(cfg, next(iter(images)), first)
    return {
        "src_hw": list(cfg.src),
        "sensor_hw": list(cfg.size),
        "theta": list(cfg.theta),
        "default_tol": data_tolerance(torch.float32)[0],
        "threads": torch.get_num_threads(),
        "device": str(cfg.device),
        "input_mb": first.numel() * 4 / 2**20,
        "images": list(images),
        "scene": asdict(scene),
        "anchors_ms": anchors,
        "rows": [asdict(r) for r in rows],
        "run": run_info(cfg.device),
    }


def _anchors(cfg: BenchConfig, img: Tensor, curv: Layout) -> dict[str, float]:
    """``cv2.resize(INTER_AREA)`` and a bare ``grid_sample`` MC-16 of the curv layout, in ms."""
    t_area = time_call(_forward_fn(img, curv, cfg.size, "inter_area", {}), cfg.repeats)
    gen = torch.Generator(cfg.device).manual_seed(0)  # samples drawn on the device, as a GPU user would
    dev_img = img.to(cfg.device)
    t_gs = time_call(lambda: _grid_sample_mc(dev_img, curv, cfg.size, 4, gen), cfg.repeats)
    return {"inter_area": t_area, "grid_sample_mc16": t_gs}


def _layout_rows(
    cfg: BenchConfig,
    image_name: str,
    img: Tensor,
    name: str,
    spec: dict,
    scene: SineScene,
    anchors: dict[str, float],
    say: Callable[[str], None],
) -> list[Row]:
    """Every row of one layout on one image: its anchors, then each method and setting."""
    size, repeats = cfg.size, cfg.repeats
    on_cuda = torch.device(cfg.device).type == "cuda"
    photo = image_name == "photo"
    layout = layout_from_spec(spec)
    say(f"{image_name} {name}: float64 references")
    img64 = img.double()
    with torch.no_grad():
        ref = simulate(img64, layout, size, tol=1e-7)
    truth = scene.pixel_means(layout, size)[None] if image_name == "synthetic" else None
    gw = 1 + torch.rand(ref.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    g_ref = None
    if layout.theta.numel():
        g_ref = fd_theta_gradient(
            img64, layout_from_spec(spec, dtype=torch.float64), layout.theta.detach(), size, gw
        )

    def errors(out: Tensor) -> dict:
        err = (out.double() - ref).abs()
        d = {"rmse": float(err.pow(2).mean().sqrt()), "max_err": float(err.max())}
        if truth is not None:
            d["scene_rmse"] = float((out.double() - truth).pow(2).mean().sqrt())
        return d

    def mem(method: str, opts: dict) -> float | None:
        if not (photo and cfg.memory and not on_cuda):
            return None
        spec_ = {"layout": spec, "method": method, "opts": opts, "src": cfg.src, "size": size}
        return peak_memory_mb(spec_ | {"threads": torch.get_num_threads()})

    rows = []
    npi = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    maps = forward_maps(layout, size, cfg.src).numpy()  # point-sampling anchor: maps made once
    t_remap = time_call(lambda: _remap(npi, maps), repeats)
    anchors[f"remap_linear_{name}"] = t_remap
    out = torch.from_numpy(_remap(npi, maps)).permute(2, 0, 1)[None]
    rows.append(
        Row(
            image_name,
            name,
            "anchor: cv2.remap LINEAR",
            "1 spp",
            t_remap,
            peak_mb=mem("remap", {}),
            **errors(out),
        )
    )
    if name == "uniform":
        out = torch.from_numpy(cv2.resize(npi, size[::-1], interpolation=cv2.INTER_AREA)).permute(2, 0, 1)[
            None
        ]
        t = anchors["inter_area"]
        rows.append(
            Row(
                image_name,
                name,
                "anchor: cv2.resize AREA",
                "-",
                t,
                peak_mb=mem("inter_area", {}),
                **errors(out),
            )
        )
    if name == "curv":
        out = _grid_sample_mc(img, layout, size, 4, torch.Generator().manual_seed(0))
        rows.append(
            Row(
                image_name,
                name,
                "anchor: grid_sample MC",
                "16 spp",
                anchors["grid_sample_mc16"],
                **errors(out),
            )
        )
        if on_cuda and photo:
            dev_img, dev_curv = img.to(cfg.device), layout_from_spec(spec).to(cfg.device)
            gen = torch.Generator(cfg.device).manual_seed(0)
            rows[-1].peak_mb = cuda_peak_mb(lambda: _grid_sample_mc(dev_img, dev_curv, size, 4, gen))
    dev_layout, dev_img = layout_from_spec(spec).to(cfg.device), img.to(cfg.device)  # the timed copies
    dev_learn = layout_from_spec(spec, learn=True).to(cfg.device)  # the same layout, learnable
    for method, opts, setting in _settings(dev_layout, name, cfg.tols, cfg.mc_samples):
        say(f"{image_name} {name}: {method} {setting}")

        def fwd(method=method, opts=opts):
            with torch.no_grad():
                return simulate(dev_img, dev_layout, size, method, **opts)

        row = Row(image_name, name, method, setting, time_call(fwd, repeats), **errors(fwd().cpu()))
        if method == "exact" and dev_layout.separable:
            row.method = "separable"
        if g_ref is not None:

            def fwd_grad(method=method, opts=opts):
                return simulate(dev_img, dev_learn, size, method, **opts)

            row.extra["forward_with_grad_ms"] = time_call(
                fwd_grad, repeats
            )  # learnable: mesh rebuilt every call
            row.backward_ms = time_backward(fwd_grad, dev_learn, repeats)
            (fwd_grad().double().cpu() * gw).sum().backward()
            g = _theta_grad(dev_learn).cpu()
            dev_learn.rho.grad = None
            row.grad_rel_err = float((g - g_ref).norm() / g_ref.norm())
            row.extra["grad"], row.extra["grad_ref"] = g.tolist(), g_ref.tolist()
        if photo:
            row.peak_mb = cuda_peak_mb(fwd) if on_cuda else mem(method, opts)
            if on_cuda and g_ref is not None:
                row.extra["train_peak_mb"] = cuda_peak_mb(lambda f=fwd_grad: f().sum().backward())
                dev_learn.rho.grad = None
        rows.append(row)
    return rows


def reuse_row(cfg: BenchConfig, image_name: str, img: Tensor) -> Row:
    """A fixed curv layout's repeated exact forward (``simulate`` keeps its area weights,
    [`resampler_for`][layoutwarp.resampler.resampler_for]), and its first call, which builds them
    (``extra["first_call_ms"]``), at the data tolerance; ``extra["over_inter_area"]``: the
    repeated call over ``cv2.resize(INTER_AREA)`` timed with it in interleaved pairs (the CPU
    image, as the anchor). The error is against the compiled kernel's float64 result;
    ``extra["walk_ms"]``: the same call with no weights kept (``resampler.RESAMPLERS.maxsize = 0``), the
    compiled walk over the mesh."""
    from ..integrators import integrate_exact

    layout = layout_from_spec(bench_layouts(cfg.theta)["curv"]).to(cfg.device)
    dev_img = img.to(cfg.device)

    def fwd():
        with torch.no_grad():
            return simulate(dev_img, layout, cfg.size)

    resampler.RESAMPLERS.clear()
    first = time_call(fwd, 0)
    inter_area = _forward_fn(img, layout, cfg.size, "inter_area", {})

    def read() -> None:  # the memory limit: one read of the image
        dev_img.sum()

    def interpolate() -> None:  # a uniform grid's box integral in torch
        torch.nn.functional.interpolate(dev_img, size=cfg.size, mode="area")

    area, repeat, t_read, t_interp = time_paired([inter_area, fwd, read, interpolate], cfg.repeats * 2 + 1)
    tol = data_tolerance(torch.float32)[0]
    kept_runs = resampler.resampler_for(layout, cfg.size, tuple(img.shape[-2:]), tol, cfg.device)
    cpu_layout = layout_from_spec(bench_layouts(cfg.theta)["curv"])  # Module.cpu() moves in place
    with torch.no_grad():  # the reference on the CPU, the timed layout left on its device
        ref = integrate_exact(img.flatten(0, 1), cpu_layout, cfg.size, tol=data_tolerance(torch.float32)[0])
    err = (fwd().cpu().double().flatten(0, 1) - ref).abs()
    kept, resampler.RESAMPLERS.maxsize = resampler.RESAMPLERS.maxsize, 0
    try:
        walk = time_call(fwd, cfg.repeats)
    finally:
        resampler.RESAMPLERS.maxsize = kept
    extra = {"first_call_ms": first, "over_inter_area": repeat / area, "walk_ms": walk}
    extra |= {"read_ms": t_read, "over_read": repeat / t_read, "over_interpolate": repeat / t_interp}
    if kept_runs is not None:  # the weights' bytes over one float32 plane of the image
        extra["weights_over_plane"] = kept_runs.runs.nbytes / (4 * img.shape[-1] * img.shape[-2])
    if cfg.memory and cfg.device == "cpu":  # the first call's memory without the weights
        spec = {"layout": bench_layouts(cfg.theta)["curv"], "method": "exact", "opts": {}, "src": cfg.src}
        spec |= {"size": cfg.size, "threads": torch.get_num_threads(), "cache_size": 0}
        extra["walk_peak_mb"] = peak_memory_mb(spec)
    return Row(
        image_name,
        "curv",
        "exact, cached weights",
        "default",
        repeat,
        rmse=float(err.pow(2).mean().sqrt()),
        max_err=float(err.max()),
        extra=extra,
    )


def _learnable_mesh(layout: Layout, size: tuple[int, int]) -> object:
    """The mesh a training step of ``layout`` builds: compiled where the family has a compiled
    form ([`layoutwarp.kernels.mesh`][]), else [`pixel_mesh`][] with θ's autograd graph."""
    tol = data_tolerance(torch.float32)[0]
    spec = mesh_spec(layout)
    if spec is None:
        return pixel_mesh(layout, size, tol=tol)
    return build_mesh(spec, size, layout.theta_as(torch.float64).detach().cpu().numpy(), tol)


def training_rows(cfg: BenchConfig, image_name: str, img: Tensor) -> list[Row]:
    """What learning a layout costs a step: forward and backward of ``out.sum()`` for learnable
    curv and fovea layouts with mixed-sign θ at the default tolerance, batch 1 and 4 (the image
    repeated), against our 16-sample Monte Carlo step (the paper's method; the reference code's
    proxy) of the same layout, timed in alternation; ``extra``: the torch operator calls of one
    step (profiler), and for the exact step the learnable layout's mesh build alone, the ratio to
    the Monte Carlo step (``over_mc16``) and to the compiled exact forward of the same layout
    fixed (``over_fixed_forward``, its mesh built once), and the step's median when called in a
    row as a training loop calls it (``in_a_row_ms``: what one step leaves running, such as
    another library's spinning worker threads, meets the next)."""
    tx, ty = cfg.theta
    specs = {
        "curv ±": {"family": "curv", "theta": [tx, -ty]},
        "fovea": {"family": "fovea", "theta": [tx, -ty], "center": [0.3, -0.2], "learn_center": True},
    }
    tol = data_tolerance(torch.float32)[0]
    rows = []
    for name, spec in specs.items():
        layout = layout_from_spec(spec, learn=True).to(cfg.device)
        fixed = layout_from_spec(spec).to(cfg.device)
        mesh_ms = time_call(lambda layout=layout: _learnable_mesh(layout, cfg.size), cfg.repeats)
        for batch in (1, 4):
            x = img.to(cfg.device).expand(batch, -1, -1, -1).contiguous()
            planes = x.reshape(-1, *x.shape[-2:])
            mesh = pixel_mesh(fixed, cfg.size, tol=tol, dtype=torch.float64)

            def forward(fixed=fixed, planes=planes, mesh=mesh) -> None:
                with torch.no_grad():
                    integrate_exact(planes, fixed, cfg.size, mesh=mesh)

            def step(layout=layout, x=x, method="exact", opts=None) -> None:
                simulate(x, layout, cfg.size, method, **(opts or {})).sum().backward()
                layout.rho.grad = None

            def mc16(step=step) -> None:
                step(method="montecarlo", opts={"samples": 4, "seed": 0})

            t_ex, t_mc, t_fwd = time_paired([step, mc16, forward], cfg.repeats)
            extra = {
                "batch": batch,
                "ops": count_ops(step),
                "mesh_ms": mesh_ms,
                "in_a_row_ms": time_call(step, cfg.repeats),
                "over_mc16": t_ex / t_mc,
                "over_fixed_forward": t_ex / t_fwd,
            }
            rows.append(Row(image_name, name, "train step, exact", f"default b{batch}", t_ex, extra=extra))
            extra = {"batch": batch, "ops": count_ops(mc16)}
            rows.append(
                Row(image_name, name, "train step, montecarlo", f"16 spp b{batch}", t_mc, extra=extra)
            )
    return rows


#: The camera of the physics rows: 12-bit, shot and read noise, a full well; the source image spans
#: the sensor with square 2.73 µm source pixels at 2048x1024.
BENCH_PHYSICS = {
    "photons_per_um2": 200.0,
    "quantum_efficiency": 0.6,
    "read_noise_e": 3.0,
    "dark_e_per_um2": 0.1,
    "full_well_per_um2": 2000.0,
    "adc_bits": 12,
    "seed": 0,
}


def physics_rows(cfg: BenchConfig, image_name: str, img: Tensor, anchors: dict[str, float]) -> list[Row]:
    """What sensor physics costs (fixed curv layout, the data tolerance, no gradient): the forward
    with noise, full well and ADC against the same forward without (``extra["over_plain"]``: the
    median of the rounds' ratios over ``200 × repeats`` rounds that call both), and the PSFs on the
    source image against INTER_AREA; the Airy row's error is the RMSE of its truncated kernel
    against one holding 99.9 % of the energy, relative to the image's range
    (``extra["truncated_energy"]``: what the kernel leaves out)."""
    from ..physics import SensorPhysics, apply_psf, kernel_arguments

    h, w = cfg.src
    extent = (2.734375 * h, 2.734375 * w)  # µm: 2.73 µm source pixels at 2048x1024
    layout = layout_from_spec(bench_layouts(cfg.theta)["curv"]).to(cfg.device)
    dev_img = img.to(cfg.device)
    ph = SensorPhysics(sensor_um=extent, **BENCH_PHYSICS)

    def plain():
        with torch.no_grad():
            return simulate(dev_img, layout, cfg.size)

    def measured():
        with torch.no_grad():
            return simulate(dev_img, layout, cfg.size, physics=ph)

    # a difference of a few percent between two times, on a machine whose speed drifts by 1.5x
    # within seconds: many pairs (1000 at the default repeats, about 5 s; the median moves by about
    # a point between runs of 200), and the overhead as the median of each round's ratio, both
    # calls of a round meeting the same machine state
    tp, tq, over = time_overhead(plain, measured, cfg.repeats * 200)
    noise = float((measured().cpu().double() - plain().cpu().double()).pow(2).mean().sqrt())
    extra = {"over_plain": over, "plain_ms": tp, "physics": ph.to_dict()}
    if cfg.device == "cpu" and kernels.available():
        # the measurement kernel alone on the forward's means, called in a row: the overhead's floor
        areas = pixel_mesh(
            layout, cfg.size, tol=data_tolerance(torch.float32)[0], dtype=torch.float64
        ).areas()
        args = kernel_arguments(ph, areas)
        mean = plain().reshape(-1, areas.numel()).numpy()
        out, nt = np.empty_like(mean), kernels.threads()
        extra["kernel_ms"] = time_call(lambda: kernels.sensor_measure(mean, *args, out, nt), cfg.repeats * 40)
        quiet = (*args[:-2], 0, args[-1])  # the same camera without noise: what the sampler costs
        extra["kernel_noise_free_ms"] = time_call(
            lambda: kernels.sensor_measure(mean, *quiet, out, nt), cfg.repeats * 40
        )
    rows = [Row(image_name, "curv", "exact + physics", "noise,FW,ADC", tq, rmse=noise, extra=extra)]
    # learning a layout under this camera: the training step of a learnable curv (mixed-sign θ)
    # with and without physics (the reparameterised noise; the areas from the compiled path)
    learnable = layout_from_spec({"family": "curv", "theta": [cfg.theta[0], -cfg.theta[1]]}, learn=True)
    learnable = learnable.to(cfg.device)

    def step(physics: SensorPhysics | None = None) -> None:
        simulate(dev_img, learnable, cfg.size, physics=physics).sum().backward()
        learnable.rho.grad = None

    t_plain, t_phys, over = time_overhead(step, lambda: step(ph), cfg.repeats * 4)
    extra = {"over_plain": over, "plain_ms": t_plain, "ops": count_ops(lambda: step(ph))}
    rows.append(Row(image_name, "curv ±", "physics train step", "noise,FW,ADC", t_phys, extra=extra))
    flat = dev_img.reshape(-1, h, w)
    for kind in ("gaussian", "airy"):
        psf = SensorPhysics(sensor_um=extent, photons_per_um2=1.0, psf=kind)
        t = time_call(lambda psf=psf: apply_psf(flat, psf), cfg.repeats)
        row = Row(
            image_name, "-", f"psf {kind}", "f/5.6", t, extra={"over_inter_area": t / anchors["inter_area"]}
        )
        if kind == "airy":
            ref = apply_psf(
                flat, SensorPhysics(sensor_um=extent, photons_per_um2=1.0, psf=kind, psf_energy=0.999)
            )
            err = (apply_psf(flat, psf).double() - ref.double()).cpu()
            row.rmse, row.max_err = float(err.pow(2).mean().sqrt()), float(err.abs().max())
            row.extra["truncated_energy"] = 1 - psf.psf_energy
        rows.append(row)
    return rows


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
    timing; ``layoutwarp bench --quick`` has compiled what the README example uses already);
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


def _forward_fn(img: Tensor, layout: Layout, size, method: str, opts: dict) -> Callable[[], object]:
    """A no-grad forward call: a [`simulate`][] method, ``"inter_area"`` or ``"remap"`` (OpenCV)."""
    npimg = np.ascontiguousarray(img[0].permute(1, 2, 0).numpy())
    if method == "inter_area":
        return lambda: cv2.resize(npimg, size[::-1], interpolation=cv2.INTER_AREA)
    if method == "remap":
        m = forward_maps(layout, size, img.shape[-2:]).numpy()
        return lambda: _remap(npimg, m)

    def fn():
        with torch.no_grad():
            return simulate(img, layout, size, method, **opts)

    return fn


SCALING_METHODS: dict[str, tuple[str, str, dict]] = {
    "cv2.resize AREA": ("uniform", "inter_area", {}),
    "cv2.remap LINEAR (curv)": ("curv", "remap", {}),
    "separable (rect)": ("rect", "exact", {}),
    "exact tol=1e-3 (curv)": ("curv", "exact", {"tol": 1e-3}),
    "montecarlo 16 spp (curv)": ("curv", "montecarlo", {"samples": 4, "seed": 0}),
}


@jit.use_mode("wait")
def scaling(
    srcs: Sequence[tuple[int, int]] = ((256, 512), (512, 1024), (1024, 2048)),
    sizes: Sequence[tuple[int, int]] = ((33, 65), (65, 129), (129, 257)),
    theta: tuple[float, float] = (0.35, 0.25),
    repeats: int = 5,
) -> dict:
    """Forward time of representative methods over a grid of source and sensor sizes.

    Returns the times (ms) and, per method, the median log-log slope of time against
    source pixels (sensor size fixed) and against sensor pixels (source fixed): 1 is linear.
    """
    times: dict[str, list[list[float]]] = {}
    for label, (family, method, opts) in SCALING_METHODS.items():
        layout = make_layout(family, None if family == "uniform" else theta)
        times[label] = [
            [
                time_call(_forward_fn(blurred_noise(*src), layout, size, method, opts), repeats)
                for size in sizes
            ]
            for src in srcs
        ]
    src_px = np.log([a * b for a, b in srcs])
    sen_px = np.log([a * b for a, b in sizes])
    slopes = {}
    for label, grid in times.items():
        t = np.log(np.asarray(grid))
        slopes[label] = {
            "vs_source_pixels": float(
                np.median([np.polyfit(src_px, t[:, j], 1)[0] for j in range(len(sizes))])
            ),
            "vs_sensor_pixels": float(np.median([np.polyfit(sen_px, t[i], 1)[0] for i in range(len(srcs))])),
        }
    return {
        "srcs_hw": [list(s) for s in srcs],
        "sizes_hw": [list(s) for s in sizes],
        "times_ms": times,
        "slopes": slopes,
    }


def _fmt(v: float | None, spec: str) -> str:
    return "" if v is None else format(v, spec)


def format_table(result: dict) -> str:
    """A plain-text table with ratios against the anchors of the same run."""
    a = result["anchors_ms"]
    lines = [
        f"source {result['src_hw'][1]}x{result['src_hw'][0]}x3 float32 -> sensor "
        f"{result['sensor_hw'][1]}x{result['sensor_hw'][0]}, θ={tuple(result['theta'])}, "
        f"{result['threads']} threads, {result.get('device', 'cpu')}; "
        f"anchors: INTER_AREA {a['inter_area']:.2f} ms, "
        f"grid_sample MC-16 {a['grid_sample_mc16']:.2f} ms",
        "errors: RMSE/max against float64 exact; 'scene' RMSE against the analytic pixel means "
        "(synthetic only); grad: relative error of dL/dθ against float64 finite differences",
        "fwd ms: a fixed layout (its mesh is built once and reused); train ms: forward + backward "
        "of a learnable layout (mesh rebuilt every call, as in training); bwd/fwd within training",
    ]
    # the text columns as wide as their longest entry, so every number stays under its header
    w = {
        k: max([len(k), *(len(r[k]) for r in result["rows"])])
        for k in ("image", "layout", "method", "setting")
    }
    lines.append(
        f"{'image':{w['image']}s} {'layout':{w['layout']}s} {'method':{w['method']}s} "
        f"{'setting':{w['setting']}s} {'fwd ms':>8s} {'/AREA':>6s} "
        f"{'/GS16':>6s} {'train ms':>8s} {'bwd/fwd':>7s} {'RMSE':>8s} {'max err':>8s} {'scene':>8s} "
        f"{'grad':>8s} {'peak/in':>7s}"
    )
    for r in result["rows"]:
        fg = r["extra"].get("forward_with_grad_ms")
        bwd = None if r["backward_ms"] is None else r["backward_ms"] / fg
        train = None if r["backward_ms"] is None else r["backward_ms"] + fg
        peak = None if r["peak_mb"] is None else r["peak_mb"] / result["input_mb"]
        lines.append(
            f"{r['image']:{w['image']}s} {r['layout']:{w['layout']}s} {r['method']:{w['method']}s} "
            f"{r['setting']:{w['setting']}s} {r['forward_ms']:8.2f} "
            f"{r['forward_ms'] / a['inter_area']:6.2f} {r['forward_ms'] / a['grid_sample_mc16']:6.2f} "
            f"{_fmt(train, '8.1f'):>8s} {_fmt(bwd, '.2f'):>7s} {_fmt(r['rmse'], '.2e'):>8s} "
            f"{_fmt(r['max_err'], '.2e'):>8s} "
            f"{_fmt(r['scene_rmse'], '.2e'):>8s} {_fmt(r['grad_rel_err'], '.1e'):>8s} "
            f"{_fmt(peak, '.2f'):>7s}"
        )
    return "\n".join(lines)


def format_scaling(result: dict) -> str:
    """The scaling grid (ms) and fitted slopes as text."""
    sizes = [f"{w}x{h}" for h, w in result["sizes_hw"]]
    lines = [f"scaling: forward ms; rows = source, columns = sensor {', '.join(sizes)}"]
    for label, grid in result["times_ms"].items():
        s = result["slopes"][label]
        lines.append(
            f"  {label:26s} slope vs source px {s['vs_source_pixels']:.2f}, "
            f"vs sensor px {s['vs_sensor_pixels']:.2f}"
        )
        for (h, w), row in zip(result["srcs_hw"], grid, strict=True):
            lines.append(f"    {w}x{h}: " + "  ".join(f"{t:9.2f}" for t in row))
    return "\n".join(lines)


def main_bench(
    quick: bool,
    json_path: str | None,
    plot_path: str | None = None,
    *,
    memory: bool = True,
    with_scaling: bool = True,
    photo: str | None = None,
    device: str = "cpu",
    only: Sequence[str] | None = None,
    text_path: str | None = None,
) -> dict:
    """Run the benchmark (``quick``: small sizes, few repeats), print tables (and write them to
    ``text_path`` as a fenced Markdown block, which the docs include), write JSON and plot."""
    say = lambda msg: print(f"  .. {msg}", flush=True)  # noqa: E731
    rows = tuple(only) if only else None
    with jit.use_mode("wait"):  # what it times, compiled first, two units at a time
        jit.compile_missing(2, say)
    if quick:
        config = BenchConfig.quick(mc_samples=(1, 4, 16), photo=photo, device=device, only=rows)
        result = run(config, progress=say)
        if with_scaling:
            result["scaling"] = scaling(((128, 256), (256, 512)), ((17, 33), (33, 65)), repeats=2)
    else:
        result = run(BenchConfig(memory=memory, photo=photo, device=device, only=rows), progress=say)
        if with_scaling:
            result["scaling"] = scaling()
    entries = ("README example",) if quick else ("README example", *ENTRY_POINTS)
    result["first_calls"] = first_calls(entries, progress=say, fill=not quick)
    text = report_text(result)
    print(text)
    if text_path:
        atomic_write(text_path, "```text\n" + text + "\n```\n")  # a fenced block the docs include
    if json_path:
        Path(json_path).parent.mkdir(parents=True, exist_ok=True)
        atomic_write(json_path, json.dumps(result, indent=2))
    if plot_path:
        from .plots import pareto_figure

        print(f"wrote {pareto_figure(result, plot_path)}")
    return result


def format_first_calls(calls: dict) -> list[str]:
    """A line per entry point of [`first_calls`][]' result."""
    return [
        f"first call from an empty kernel cache, {name}: {c['first_s']:.1f} s "
        f"(warm {c['warm_s']:.1f} s, {c['first_s'] - c['warm_s']:+.1f} s)"
        + ("; " + ", ".join(f"{k} {v:.1f} s" for k, v in c["steps"].items()) if "steps" in c else "")
        for name, c in calls.items()
    ]


def report_text(result: dict) -> str:
    """Everything the benchmark prints: the table, the training steps, the cached weights, the
    physics, the compile time and the scaling grid; first, the backends it ran on."""
    backends = result.get("run", {}).get("backends")
    lines = ([f"backends: {backends}"] if backends else []) + [format_table(result)]
    for r in result["rows"]:
        if r["method"].startswith("train step"):
            lines.append(
                f"{r['layout']:8s} {r['method']:24s} {r['setting']:12s} {r['forward_ms']:8.1f} ms  "
                f"{r['extra']['ops']:5d} torch ops"
                + (
                    f"  (mesh build {r['extra']['mesh_ms']:.1f} ms; {r['extra']['over_mc16']:.2f}x the "
                    f"MC-16 step, {r['extra']['over_fixed_forward']:.1f}x the fixed forward; "
                    f"{r['extra'].get('in_a_row_ms', float('nan')):.1f} ms in a row)"
                    if "mesh_ms" in r["extra"]
                    else ""
                )
            )
    for r in result["rows"]:
        if r["method"] == "exact, cached weights":
            lines.append(
                f"a fixed layout's repeated exact forward: {r['forward_ms']:.2f} ms "
                f"({r['extra']['over_inter_area']:.2f}x INTER_AREA, "
                f"{r['extra'].get('over_interpolate', float('nan')):.2f}x F.interpolate(area), "
                f"{r['extra'].get('over_read', float('nan')):.1f}x one read of the image, x.sum() "
                f"{r['extra'].get('read_ms', float('nan')):.2f} ms; in rounds); its weights "
                f"{r['extra'].get('weights_over_plane', float('nan')):.2f}x a float32 plane; its first call, "
                f"which builds the area weights: {r['extra']['first_call_ms']:.1f} ms; with no weights "
                f"kept (resampler.RESAMPLERS.maxsize = 0), the compiled walk: {r['extra']['walk_ms']:.2f} ms"
                + (
                    f", its first call {r['extra']['walk_peak_mb'] / result['input_mb']:.2f} input copies "
                    "of memory"
                    if r["extra"].get("walk_peak_mb") is not None
                    else ""
                )
            )
        if r["method"] == "exact + physics":
            lines.append(
                f"sensor physics (noise, full well, 12-bit ADC): {r['forward_ms']:.2f} ms against "
                f"{r['extra']['plain_ms']:.2f} ms without, {100 * r['extra']['over_plain']:+.1f} % "
                "(the median of the rounds' ratios)"
                + (
                    f"; the measurement kernel alone {r['extra']['kernel_ms']:.3f} ms, "
                    f"{r['extra'].get('kernel_noise_free_ms', float('nan')):.3f} ms without noise"
                    if "kernel_ms" in r["extra"]
                    else ""
                )
            )
        if r["method"] == "physics train step":
            lines.append(
                f"learning a layout under that camera (curv ±, train step): {r['forward_ms']:.1f} ms "
                f"against {r['extra']['plain_ms']:.1f} ms without physics, "
                f"{100 * r['extra']['over_plain']:+.0f} %; {r['extra']['ops']} torch ops"
            )
    lines += format_first_calls(result.get("first_calls", {}))
    c = result.get("compile")  # results written before the first-call lines: their compile probe
    if c:
        lines.append(
            f"first exact forward+backward in a new process: {c['first_process']['first_call_s']:.2f} s "
            f"with an empty kernel cache (compiling), {c['second_process']['first_call_s']:.2f} s with the "
            "cache filled"
        )
    if "scaling" in result:
        lines.append(format_scaling(result["scaling"]))
    return "\n".join(lines)


def preprocess_baseline(files: list[Path], size: tuple[int, int], out: str | Path) -> float:
    """Seconds for the plain OpenCV loop over ``files``: imread, resize INTER_AREA, imwrite."""
    h, w = check_size(size)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    for k, path in enumerate(files):
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            continue
        cv2.imwrite(str(out / f"{k}{path.suffix}"), cv2.resize(img, (w, h), interpolation=cv2.INTER_AREA))
    return time.perf_counter() - t0
