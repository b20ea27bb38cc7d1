"""The benchmark's references: the synthetic scene's analytic integrals and the FD gradient."""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
import torch
from conftest import rand_theta

import layoutwarp as lw
from layoutwarp.experiments.bench import run, scaling
from layoutwarp.experiments.benchconfig import BenchConfig
from layoutwarp.experiments.benchtext import format_scaling, format_table, report_text
from layoutwarp.experiments.plots import pareto_figure
from layoutwarp.experiments.scene import SineScene, fd_theta_gradient

F64 = torch.float64


def _sin_mean(k: float, ph: float, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    return (np.cos(k * lo + ph) - np.cos(k * hi + ph)) / (k * (hi - lo))


def test_scene_pixel_means_rect_closed_form(seed):
    scene = SineScene.random(2, seed=seed)
    gen = torch.Generator().manual_seed(seed)
    layout = lw.make_layout("rect", rand_theta(gen, 0.9), dtype=F64)
    size = (7, 11)
    got = scene.pixel_means(layout, size).numpy()
    c = lw.pixel_mesh(layout, size).corners.detach().numpy()
    xs, ys = c[0, :, 0], c[:, 0, 1]  # rect pixels are axis-aligned rectangles
    for ch in range(2):
        mx = _sin_mean(scene.a[ch], scene.p[ch], xs[:-1], xs[1:])
        my = _sin_mean(scene.b[ch], scene.q[ch], ys[:-1], ys[1:])
        expected = 0.5 + 0.4 * my[:, None] * mx[None]
        assert np.abs(got[ch] - expected).max() < 1e-13


def test_scene_pixel_means_curv_against_fine_polygons(seed):
    # independent route: Green's theorem along a very fine polyline mesh of the pixels
    # (within 1e-10 of the curves), Gauss-Legendre on every straight segment
    scene = SineScene((9.0,), (5.0,), (0.3,), (1.1,))
    gen = torch.Generator().manual_seed(seed)
    layout = lw.make_layout("curv", rand_theta(gen, 0.9), dtype=F64)
    size = (4, 5)
    got = scene.pixel_means(layout, size)[0].numpy().ravel()
    x, wq = np.polynomial.legendre.leggauss(8)
    t, wq = (x + 1) / 2, wq / 2
    # up to θ = 0.9 an edge needs more than the default 4096 segments to stay within 1e-10
    fine = lw.pixel_mesh(layout, size, tol=1e-10, max_subdiv=1 << 16)
    for k, poly in enumerate(fine.polygons()):
        a, b = poly, np.roll(poly, -1, axis=0)
        q = a[:, None] + t[None, :, None] * (b - a)[:, None]  # (segments, nodes, 2)
        p = 0.5 * q[..., 0] - 0.4 / 9.0 * np.cos(9.0 * q[..., 0] + 0.3) * np.sin(5.0 * q[..., 1] + 1.1)
        integral = float(((p * wq).sum(1) * (b - a)[:, 1]).sum())
        area = float(((a[:, 0] + b[:, 0]) / 2 * (b - a)[:, 1]).sum())
        assert abs(integral / area - got[k]) < 1e-8


def test_scene_image_is_cell_average_and_box_integral_converges():
    scene = SineScene.random(1, seed=3)
    img = scene.image(8, 12)[0, 0].numpy()
    # cell (2, 5): average by a fine midpoint rule
    ys = np.linspace(-1 + 2 * 2 / 8, -1 + 2 * 3 / 8, 2001)[:-1] + 0.5 * (2 / 8) / 2000
    xs = np.linspace(-1 + 2 * 5 / 12, -1 + 2 * 6 / 12, 2001)[:-1] + 0.5 * (2 / 12) / 2000
    f = 0.5 + 0.4 * np.sin(scene.b[0] * ys[:, None] + scene.q[0]) * np.sin(scene.a[0] * xs[None] + scene.p[0])
    assert abs(img[2, 5] - f.mean()) < 1e-7
    # the exact box integral of finer and finer images approaches the analytic means (O(h²))
    layout = lw.make_layout("curv", (0.4, -0.3), dtype=F64)
    truth = scene.pixel_means(layout, (6, 8))
    errs = [
        float((lw.simulate(scene.image(s, s), layout, (6, 8), tol=1e-9)[0] - truth).abs().max())
        for s in (48, 96, 192)
    ]
    assert errs[0] > errs[1] > errs[2] and errs[1] / errs[2] > 3


def test_fd_gradient_matches_exact_autograd(seed):
    gen = torch.Generator().manual_seed(seed)
    img = torch.rand(1, 2, 60, 80, generator=gen, dtype=F64)
    size = (9, 13)
    w = 1 + torch.rand(1, 2, *size, generator=gen, dtype=F64)
    for family in ("rect", "curv"):
        theta = rand_theta(gen, 0.8).requires_grad_(True)
        layout = lw.make_layout(family, dtype=F64)
        fd = fd_theta_gradient(img, layout, theta.detach(), size, w, subdiv=128)
        # the same 128-segment polylines that the finite differences see
        mesh = lw.pixel_mesh(layout, size, subdivisions=1 if family == "rect" else 128, theta=theta)
        (g,) = torch.autograd.grad(
            (lw.integrators.integrate_exact(img[0], layout, size, mesh=mesh) * w[0]).sum(), theta
        )
        assert float((g - fd).norm() / fd.norm()) < 1e-5, (family, g, fd)
        # the true curved edges (tol 1e-9) differ from 128-segment polylines by O(1/128²)
        (g,) = torch.autograd.grad(
            (lw.integrators.integrate_exact(img[0], layout, size, tol=1e-9, theta=theta) * w[0]).sum(), theta
        )
        assert float((g - fd).norm() / fd.norm()) < 1e-3, (family, g, fd)


def test_fd_gradient_along_directions_is_the_projected_gradient(seed):
    """The derivatives along random directions (``--quick``'s check of a large θ) equal the
    directions times the gradient from each entry's differences (the loss is smooth in θ)."""
    gen = torch.Generator().manual_seed(seed)
    img = torch.rand(1, 2, 40, 48, generator=gen, dtype=F64)
    size = (5, 6)
    w = 1 + torch.rand(1, 2, *size, generator=gen, dtype=F64)
    layout = lw.make_layout("grid", grid=(3, 3), dtype=F64)
    theta = 0.05 * torch.randn(layout.theta.numel(), generator=gen, dtype=F64)
    full = fd_theta_gradient(img, layout, theta, size, w)
    directions = torch.randn(3, theta.numel(), generator=gen, dtype=F64)
    along = fd_theta_gradient(img, layout, theta, size, w, directions=directions)
    assert along.shape == (3,)
    torch.testing.assert_close(along, directions @ full, rtol=1e-5, atol=1e-9 * float(full.norm()))


def test_run_small_reports_every_method_and_plots(tmp_path):
    small = {"src": (48, 96), "size": (7, 13), "tols": (1e-3,), "mc_samples": (1, 4), "repeats": 1}
    res = run(BenchConfig(**small, memory=False, fd_directions=4))  # the grid's 98 θ along 4
    rows = res["rows"]
    assert {r["image"] for r in rows} == set(res["images"]) and "synthetic" in res["images"]
    methods = {(r["layout"], r["method"]) for r in rows}
    for lay in ("uniform", "rect", "curv"):
        assert {(lay, "montecarlo"), (lay, "point"), (lay, "anchor: cv2.remap LINEAR")} <= methods
    assert ("rect", "separable") in methods and ("curv", "exact") in methods
    by = {(r["image"], r["layout"], r["method"], r["setting"]): r for r in rows}
    sep = by[("synthetic", "rect", "separable", "exact")]
    assert sep["rmse"] < 1e-6 and sep["grad_rel_err"] < 1e-3
    assert len(sep["extra"]["grad"]) == 2  # rect's θ: every entry (2 < 4 directions)
    grid = by[("synthetic", "grid 8x8", "exact", "exact")]  # checked along 4 random directions
    assert len(grid["extra"]["grad"]) == 4 and grid["grad_rel_err"] < 1e-3
    area = by[("synthetic", "uniform", "anchor: cv2.resize AREA", "-")]
    assert area["rmse"] < 1e-6 and math.isfinite(area["scene_rmse"])
    mc = [by[("synthetic", "curv", "montecarlo", f"{s} spp")]["rmse"] for s in (1, 16)]
    assert mc[1] < mc[0]
    text = format_table(res)
    assert "separable" in text and "/AREA" in text
    steps = [r for r in rows if r["method"].startswith("train step")]
    assert {(r["layout"], r["extra"]["batch"]) for r in steps} == {
        (n, b) for n in ("curv ±", "fovea") for b in (1, 4)
    }
    assert all(r["extra"]["ops"] >= 5 and r["forward_ms"] > 0 for r in steps)
    exact_steps = [r for r in steps if r["method"] == "train step, exact"]
    assert all(r["extra"]["in_a_row_ms"] > 0 for r in exact_steps) and "ms in a row" in report_text(res)
    reuse = next(r for r in rows if r["method"] == "exact, cached weights")
    assert reuse["extra"]["first_call_ms"] > 0 and reuse["max_err"] < 1e-5 and reuse["extra"]["walk_ms"] > 0
    phys = {r["method"]: r for r in rows if r["method"] in ("exact + physics", "psf gaussian", "psf airy")}
    assert set(phys) == {"exact + physics", "psf gaussian", "psf airy"}
    assert phys["exact + physics"]["extra"]["plain_ms"] > 0 and phys["exact + physics"]["rmse"] > 0  # noisy
    ex = phys["exact + physics"]["extra"]  # the kernel alone, with and without its sampler
    assert ex["kernel_ms"] > 0 and ex["kernel_noise_free_ms"] > 0 and "without noise" in report_text(res)
    learning = next(r for r in rows if r["method"] == "physics train step")  # the compiled path
    assert learning["extra"]["plain_ms"] > 0 and 10 < learning["extra"]["ops"] < 100
    assert "learning a layout under that camera" in report_text(res)
    assert 0 < phys["psf airy"]["rmse"] < 0.05 and phys["psf airy"]["extra"][
        "truncated_energy"
    ] == pytest.approx(0.05)
    png = pareto_figure(res, tmp_path / "p.png")
    assert png.stat().st_size > 20_000


def test_paired_timing_takes_every_order_so_each_call_follows_each_other_as_often():
    from collections import Counter

    from layoutwarp.experiments.timing import interleaved_times

    calls: list[str] = []
    fns = [lambda name=name: calls.append(name) for name in "abc"]
    times = interleaved_times(fns, 12)  # each call's ms, round by round
    assert len(times) == 3 and all(len(t) == 12 and min(t) >= 0 for t in times)
    rounds = ["".join(calls[3 + 3 * k : 6 + 3 * k]) for k in range(12)]  # after the warm-up calls
    assert calls[:3] == ["a", "b", "c"] and sorted(rounds[:6]) == sorted(rounds[6:])
    assert sorted(rounds[:6]) == ["abc", "acb", "bac", "bca", "cab", "cba"]
    # within a round each call follows each other equally often (a rotation of one order would
    # give each call the same predecessor in every round: ab, bc, ca only)
    follows = Counter((r[i], r[i + 1]) for r in rounds for i in range(2))
    assert follows == Counter({tuple(pair): 4 for pair in ("ab", "ac", "ba", "bc", "ca", "cb")})


def test_scaling_fits_slopes():
    res = scaling(((32, 64), (64, 128)), ((5, 9), (9, 17)), repeats=1)
    assert set(res["slopes"]) == set(res["times_ms"])
    for grid in res["times_ms"].values():
        assert np.all(np.isfinite(grid)) and np.asarray(grid).shape == (2, 2)
    assert "slope vs source px" in format_scaling(res)


def test_the_quick_run_measures_the_synthetic_scene_with_torchs_references_and_compiles_float32():
    """``bench --quick``: the synthetic scene (the photo only where one is given), its float64
    references on the torch path, and the float32 units alone compiled first; no image, or a
    unit not in ``jit.UNITS``, is refused in one line."""
    quick = BenchConfig.quick()
    assert quick.images == ("synthetic",) and quick.torch_references and not BenchConfig().torch_references
    assert quick.fd_directions == 4 and BenchConfig().fd_directions is None  # the full run: every entry
    with pytest.raises(ValueError, match="images must name photo"):
        run(BenchConfig.quick(src=(32, 64), size=(5, 9), images=()))
    with pytest.raises(ValueError, match=r"units must be of mesh, .*, got 'learn/float16'"):
        lw.jit.compile_missing(units=("mesh", "learn/float16"))


def test_run_measures_only_the_rows_asked_for():
    config = BenchConfig.quick(
        src=(32, 64),
        size=(5, 9),
        tols=(1e-3,),
        mc_samples=(1,),
        repeats=1,
        only=("fovea",),
        images=("photo", "synthetic"),
    )
    res = run(config)
    assert {r["layout"] for r in res["rows"]} == {"fovea"}
    assert set(res["anchors_ms"]) >= {"inter_area", "grid_sample_mc16"}
    # on the photo (the synthetic scene's θ-gradient is ~100x smaller, so float32 input rounding
    # dominates its relative error at this tiny size)
    fovea = [r for r in res["rows"] if r["method"] == "exact" and r["image"] == "photo"]
    assert len(fovea) == 2 and all(r["grad_rel_err"] < 1e-3 for r in fovea)


@pytest.mark.skipif(not os.path.exists("/proc/self/clear_refs"), reason="needs Linux's /proc")
def test_the_memory_child_measures_a_fixed_layouts_first_call_with_and_without_cached_weights(monkeypatch):
    # run in this process (the bench spawns it): the growth it reports, and whether the call it
    # measured built area weights (cache_size 0: the compiled walk, no weights)
    from layoutwarp import resampler
    from layoutwarp.experiments.benchconfig import bench_layouts
    from layoutwarp.experiments.memory import memory_child

    sent: list[float] = []

    class Conn:
        def send(self, value: float) -> None:
            sent.append(value)

        def close(self) -> None:
            pass

    monkeypatch.setattr(resampler.RESAMPLERS, "maxsize", resampler.RESAMPLERS.maxsize)  # restored afterwards
    spec = {"layout": bench_layouts((0.3, 0.2))["curv"], "method": "exact", "opts": {}}
    spec |= {"src": (64, 96), "size": (9, 13), "threads": torch.get_num_threads()}
    for size, built in ((0, False), (4, True)):
        resampler.RESAMPLERS.clear()
        memory_child(spec | {"cache_size": size}, Conn())
        assert resampler.RESAMPLERS.maxsize == size and bool(len(resampler.RESAMPLERS)) == built
    assert len(sent) == 2 and all(v >= 0 for v in sent)


@pytest.mark.skipif(not lw.kernels.available(), reason="needs numba")
def test_first_calls_time_an_entry_point_from_an_empty_cache_and_warm(tmp_path, monkeypatch):
    """firstcalls.first_calls runs an entry point in a fresh process with a throw-away empty cache
    (background mode) and with this installation's, reports both, and its report line gives the
    difference; the throw-away cache is left by a stopped worker (nothing compiles on after)."""
    from layoutwarp.experiments.benchtext import format_first_calls
    from layoutwarp.experiments.firstcalls import ENTRY_POINTS, first_calls

    monkeypatch.setenv("NUMBA_CACHE_DIR", str(tmp_path / "home"))  # this test's "installation"
    out = first_calls(["export"], fill=True)
    assert set(out) == {"export"} and set(ENTRY_POINTS) >= {"export", "preprocess", "float64 learnable step"}
    first, warm = out["export"]["first_s"], out["export"]["warm_s"]
    assert 0.2 < first < 120 and 0.2 < warm < 120
    (line,) = format_first_calls(out)
    expected = f"export: {first:.1f} s (warm {warm:.1f} s, {first - warm:+.1f} s)"
    assert line == f"first call from an empty kernel cache, {expected}"


def test_the_bench_table_keeps_every_number_under_its_header_whatever_the_settings_length():
    """A setting longer than the column (tol=0.0001) once pushed its row's numbers one column on."""
    from layoutwarp.experiments.benchtext import format_table

    row = {"extra": {}, "backward_ms": None, "rmse": 1e-6, "max_err": 2e-6, "scene_rmse": None}
    row |= {"grad_rel_err": None, "peak_mb": None, "forward_ms": 2.5}
    rows = [
        row | {"image": "photo", "layout": "curv ±", "method": "exact", "setting": s}
        for s in ("default", "tol=0.0001", "1 spp")
    ]
    result = {
        "anchors_ms": {"inter_area": 4.0, "grid_sample_mc16": 17.0},
        "src_hw": [8, 8],
        "sensor_hw": [2, 2],
    }
    result |= {"theta": [0.3, 0.2], "threads": 2, "input_mb": 1.0, "rows": rows}
    lines = format_table(result).splitlines()
    head = next(line for line in lines if line.startswith("image"))
    end = head.index("fwd ms") + len("fwd ms")
    for line in lines[-3:]:
        assert line[end - 4 : end] == "2.50", line  # right-aligned under "fwd ms"
