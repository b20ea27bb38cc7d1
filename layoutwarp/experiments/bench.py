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

import contextlib
import json
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path

import cv2
import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor

from .. import jit, resampler
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
from .benchconfig import PAPER_ROWS, BenchConfig, bench_layouts
from .benchphysics import physics_rows
from .benchtext import report_text
from .firstcalls import ENTRY_POINTS, first_calls
from .memory import peak_memory_mb
from .scene import SineScene, blurred_noise, fd_theta_gradient, load_photo
from .timing import (
    Row,
    cuda_peak_mb,
    time_backward,
    time_call,
    time_paired,
)

__all__ = [
    "main_bench",
    "run",
    "scaling",
]


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
    images = {"synthetic": scene.image(*cfg.src).float()} if "synthetic" in cfg.images else {}
    pic = load_photo(*cfg.src, cfg.photo) if "photo" in cfg.images else None
    if pic is not None:
        images = {"photo": pic, **images}
    if not images:
        raise ValueError(f"images must name photo (found) or synthetic, got {cfg.images!r}")
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
        "fd_directions": cfg.fd_directions,
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
    with torch.no_grad(), jit.use_mode("off") if cfg.torch_references else contextlib.nullcontext():
        ref = simulate(img64, layout, size, tol=1e-7)
        gw = 1 + torch.rand(ref.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
        g_ref = directions = None
        n = layout.theta.numel()
        if n and cfg.fd_directions is not None and cfg.fd_directions < n:  # unit random directions
            directions = torch.randn(cfg.fd_directions, n, generator=torch.Generator().manual_seed(2))
            directions = directions.double() / directions.double().norm(dim=1, keepdim=True)
        if n:
            g_ref = fd_theta_gradient(
                img64, layout_from_spec(spec, dtype=torch.float64), layout.theta.detach(), size, gw,
                directions=directions,
            )  # fmt: skip
    truth = scene.pixel_means(layout, size)[None] if image_name == "synthetic" else None

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
            g = g if directions is None else directions @ g.double()  # along the directions checked
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
    # what it times, compiled first, two units at a time (quick: float32's, its references torch's)
    units = tuple(u for u in jit.UNITS if not (quick and u.endswith("float64")))
    with jit.use_mode("wait"):
        jit.compile_missing(2, say, units)
    if quick:
        images = {"images": ("photo",)} if photo else {}  # the photo given, else the synthetic scene
        config = BenchConfig.quick(mc_samples=(1, 4, 16), photo=photo, device=device, only=rows, **images)
        result = run(config, progress=say)
        if with_scaling:
            result["scaling"] = scaling(((128, 256), (256, 512)), ((17, 33), (33, 65)), repeats=2)
    else:
        result = run(BenchConfig(memory=memory, photo=photo, device=device, only=rows), progress=say)
        if with_scaling:
            result["scaling"] = scaling()
    if not quick:  # each a process of its own, twice: from an empty cache, then warm
        result["first_calls"] = first_calls(("README example", *ENTRY_POINTS), progress=say)
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
