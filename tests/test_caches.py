"""One rule for what layoutwarp keeps: bounded caches of results by value, per-object memos of
keys that follow an object's changes and die with it; every one of them in `CACHES`."""

from __future__ import annotations

import gc
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest
import torch

import layoutwarp as lw
from layoutwarp.caches import CACHES, LRU, ObjectMemo, clear_caches, tensor_token


def test_every_cache_is_registered_and_cleared_in_one_place():
    img, layout = torch.rand(1, 1, 30, 40), lw.CurvLayout((0.3, 0.1))
    lw.simulate(img, layout, (5, 6))  # area weights (on torch's mesh or the compiled one)
    lw.simulate(img, layout, (5, 6), physics=lw.SensorPhysics((6.0, 8.0), photons_per_um2=9))
    lw.pixel_mesh(layout, (5, 6))  # a mesh, kept by its layout's key
    names = {"meshes", "resamplers", "sensors", "sensors on devices", "layout keys", "fixed centres"}
    assert names <= set(CACHES)
    sizes = {n: len(CACHES[n]) for n in ("meshes", "resamplers", "sensors", "layout keys")}
    assert all(sizes.values()), (sizes, lw.jit.mode(), lw.jit.status())
    clear_caches()
    assert all(len(cache) == 0 for cache in CACHES.values())


def test_an_lru_keeps_the_last_used_and_a_size_of_zero_keeps_none():
    cache, built = LRU("test lru", 2), []
    for key in ("a", "b", "a", "c"):
        cache.get(key, lambda key=key: built.append(key) or key.upper())
    assert cache.keys() == ["a", "c"] and built == ["a", "b", "c"]  # b least recently used: out
    with cache.kept():
        cache.get("d", lambda: "D")
    assert cache.keys() == ["a", "c"]
    cache.get("e", lambda: "E", keep=False)
    assert "e" not in cache.keys()
    cache.maxsize = 0
    cache.clear()
    assert cache.get("f", lambda: "F") == "F" and len(cache) == 0
    del CACHES["test lru"]


def test_an_object_memo_follows_changes_and_dies_with_its_object():
    memo, calls = ObjectMemo("test memo"), []
    t = torch.zeros(3)

    def value(x):
        return lambda: calls.append(1) or float(x.sum())

    assert memo.get(t, (t._version,), value(t)) == 0.0 and memo.get(t, (t._version,), value(t)) == 0.0
    assert len(calls) == 1
    t += 1  # in place: a new version
    assert memo.get(t, (t._version,), value(t)) == 3.0 and len(calls) == 2
    del t
    gc.collect()
    assert len(memo) == 0
    del CACHES["test memo"]


def test_a_tensor_token_is_its_identity_and_version():
    a, b = torch.zeros(2), torch.zeros(2)
    first = tensor_token(a)
    assert tensor_token(a) is first and tensor_token(b) is not first
    a.add_(1)
    assert tensor_token(a) is not first


def test_simulate_from_four_threads_at_once_gives_the_single_threaded_values(gen):
    """Four threads share one fixed layout (and a learnable one) and call ``simulate`` at once on
    images of different sizes and sensor sizes, caches small enough that they push each other's
    entries out: every result equals the same call made alone, bit for bit."""
    fixed, learn = lw.CurvLayout((0.3, -0.2)), lw.FoveaLayout((0.2, 0.1), center=(0.1, -0.2), learn=True)
    cases = [
        (torch.rand(2, 1, 24 + 8 * k, 30 + 6 * k, generator=gen), (4 + k, 5 + k), layout)
        for k in range(4)
        for layout in (fixed, learn)
    ]

    def run(case):
        img, size, layout = case
        out = lw.simulate(img, layout, size)
        grad = torch.autograd.grad(out.sum(), layout.rho)[0] if layout.rho.requires_grad else None
        return out.detach(), grad

    alone = [run(c) for c in cases]
    saved = {
        name: CACHES[name].maxsize for name in ("resamplers", "meshes") if hasattr(CACHES[name], "maxsize")
    }
    for name in saved:
        CACHES[name].maxsize = 2  # entries pushed out while other threads use theirs
    try:
        got = _in_four_threads(run, cases, rounds=3)
    finally:
        for name, size in saved.items():
            CACHES[name].maxsize = size
    for i, (out, grad) in enumerate(alone):
        assert torch.equal(got[i][0], out), i
        if grad is not None:
            assert torch.equal(got[i][1], grad), i


def test_monte_carlo_of_a_map_with_forward_mode_jacobians_from_four_threads_at_once(gen):
    """The elliptic layout's Jacobian comes from ``torch.func.jvp``, whose forward-mode levels are
    one stack per process: four threads' Monte Carlo calls at once (seeded) give the values of
    the same calls made alone, with no error."""
    layout = lw.make_layout("elliptic", (0.4, -0.3))
    cases = [(torch.rand(1, 2, 20 + 4 * k, 24, generator=gen), k) for k in range(4)]

    def run(case: tuple) -> torch.Tensor:
        return lw.simulate(case[0], layout, (5, 6), "montecarlo", seed=case[1])

    alone = [run(c) for c in cases]
    got = _in_four_threads(run, cases, rounds=5)
    for k in range(4):
        assert torch.equal(got[k], alone[k])


def _in_four_threads(run: Callable[[Any], Any], cases: list, rounds: int) -> dict[int, Any]:
    """``run`` of every case, ``rounds`` times, from four threads at once (thread ``t`` takes the
    cases ``t, t + 4, ...``): the last result of each case; the first error raised again here."""
    import threading

    got: dict[int, Any] = {}
    errors: list[BaseException] = []

    def worker(t: int) -> None:
        try:
            for _ in range(rounds):
                for i in range(t, len(cases), 4):
                    got[i] = run(cases[i])
        except BaseException as exc:  # raised below, not lost in the thread
            errors.append(exc)

    threads = [threading.Thread(target=worker, args=(t,)) for t in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    if errors:
        raise errors[0]
    return got


@pytest.mark.parametrize("method", ["point", "montecarlo"])
def test_a_numpy_or_tensor_tolerance_reaches_the_sampling_integrators_areas(method, gen):
    """``tol`` given as a numpy or 0-d torch number (with physics, the sampling integrators take
    the pixels' areas from ``layoutwarp::pixel_areas``): the same record as the Python float's."""
    camera = lw.SensorPhysics(sensor_um=(80.0, 80.0), photons_per_um2=500.0, seed=1)
    img, layout = torch.rand(1, 3, 32, 32, generator=gen), lw.CurvLayout((0.3, -0.2), learn=True)
    for tol in (np.float64(1e-4), np.float32(1e-4), torch.tensor(1e-4, dtype=torch.float64)):
        got = lw.simulate(img, layout, (8, 8), method, tol=tol, seed=1, physics=camera)
        want = lw.simulate(img, layout, (8, 8), method, tol=float(tol), seed=1, physics=camera)
        assert torch.equal(got, want)
