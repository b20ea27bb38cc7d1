"""Every kept result follows θ: a layout changed in place (a new θ, an optimiser's step, a loaded
state dict, a dtype round trip, a frozen ρ) gives, on every path that keeps something between
calls, the values of a layout freshly made at its new θ with nothing kept.

The paths: ``simulate`` of a float32 image (a fixed layout's cached area weights), of a float64
image (the exact walk over a kept mesh), with a seeded camera (the sensor's per-pixel inputs),
back-warping (nearest and bilinear: the operators' layout templates and θ values), the
fabrication polygons (``pixel_polygons_um``) and a Kornia ``SensorAugmentation``.
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

import layoutwarp as lw
from layoutwarp.caches import clear_caches
from layoutwarp.kernels.mesh import mesh_spec
from layoutwarp.layoutfile import layout_from_spec, layout_key, layout_spec
from layoutwarp.layouts import FAMILIES, phi_curv
from layoutwarp.operators import base as ops

F64 = torch.float64
SIZE, SRC = (5, 6), (30, 36)
CAMERA = lw.SensorPhysics((60.0, 72.0), photons_per_um2=40.0, read_noise_e=1.5, adc_bits=10, seed=4)


class SwirlLayout(lw.Layout):
    """A user's family, not registered: φ_curv of θ with the axes' roles swapped."""

    family = "swirl"

    def phi(self, p: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
        return phi_curv(p, theta.flip(-1))


def _make(family: str, gen: torch.Generator, learn: bool) -> lw.Layout:
    """A layout of ``family`` at a random θ (|θ| ≲ 0.5; a grid's control points moved a little)."""
    if family == "swirl":
        theta = (0.5 * torch.rand(2, generator=gen, dtype=F64) - 0.25).tolist()
        return SwirlLayout(theta, learn=learn)
    layout = lw.make_layout(family, learn=True)
    scale = 0.04 if family == "grid" else 0.3
    with torch.no_grad():
        layout.rho.add_(scale * torch.randn(layout.rho.shape, generator=gen, dtype=layout.rho.dtype))
    return layout if learn else layout_from_spec(layout_spec(layout))


def _fresh(layout: lw.Layout) -> lw.Layout:
    """A fixed layout made anew at ``layout``'s θ (as float64 numbers) and settings."""
    if isinstance(layout, SwirlLayout):
        return SwirlLayout(layout.theta_as(F64).detach(), bound=layout.bound)
    return layout_from_spec(layout_spec(layout))


def _outputs(layout: lw.Layout, gen_seed: int = 0) -> dict[str, torch.Tensor | str]:
    """What every kept path gives for ``layout`` (no gradient: the paths that keep results), and
    the keys kept per layout object: its identity as text (what meshes are kept by) and its
    compiled form (a fixed centre's values, read once per tensor and version)."""
    g = torch.Generator().manual_seed(gen_seed)
    img = torch.rand(1, 3, *SRC, generator=g)
    pred = torch.rand(1, 2, *SIZE, generator=g)
    with torch.no_grad():
        out = {
            "simulate float32": lw.simulate(img, layout, SIZE),
            "simulate float64": lw.simulate(img.double(), layout, SIZE),
            "simulate with physics": lw.simulate(img, layout, SIZE, physics=CAMERA, seed=3),
            "backwarp nearest": lw.backwarp(pred, layout, SRC),
            "backwarp bilinear": lw.backwarp(pred, layout, SRC, mode="bilinear"),
        }
        polygons, _ = lw.export.pixel_polygons_um(layout, SIZE, (60.0, 72.0), tol_um=0.05)
        out["export polygons"] = torch.cat([torch.as_tensor(p).flatten() for p in polygons])
        if not isinstance(layout, SwirlLayout):
            augmentation = lw.SensorAugmentation(SIZE, copy.deepcopy(layout))
            out["augmentation"] = augmentation(img)
            out["layout key"] = layout_key(layout)
            if not getattr(layout, "learn_center", False):  # a learned centre is θ, not the spec's
                out["mesh spec"] = repr(mesh_spec(layout))
    return out


def _other_theta(layout: lw.Layout, gen: torch.Generator) -> torch.Tensor:
    """Another valid θ of ``layout``'s family, well away from its own."""
    family = "swirl" if isinstance(layout, SwirlLayout) else layout.family
    return _make(family, gen, learn=False).theta_as(F64)


def _set_theta(layout: lw.Layout, gen: torch.Generator) -> None:
    layout.set_theta(_other_theta(layout, gen))


def _optimiser_step(layout: lw.Layout, gen: torch.Generator) -> None:
    opt = torch.optim.SGD([layout.rho], lr=0.1 if layout.family == "grid" else 2.0)  # a grid folds
    opt.zero_grad()
    target = torch.rand(1, 1, *SIZE, generator=gen)
    (lw.simulate(torch.rand(1, 1, *SRC, generator=gen), layout, SIZE) - target).square().sum().backward()
    opt.step()


def _rho_add(layout: lw.Layout, gen: torch.Generator) -> None:
    scale = 0.03 if layout.family == "grid" else 0.3
    with torch.no_grad():
        layout.rho.add_(scale * torch.randn(layout.rho.shape, generator=gen, dtype=layout.rho.dtype))


def _load_state_dict(layout: lw.Layout, gen: torch.Generator) -> None:
    other = copy.deepcopy(layout)
    other.set_theta(_other_theta(layout, gen))
    layout.load_state_dict(other.state_dict())


def _load_centre(layout: lw.Layout, gen: torch.Generator) -> None:
    """A curv layout's state dict with a fixed centre elsewhere (a setting, not θ)."""
    other = lw.CurvLayout(layout.theta_as(F64).detach(), center=(0.25, -0.15), learn=layout.learnable_param)
    layout.load_state_dict(other.state_dict())


def _dtype_round_trip(layout: lw.Layout, gen: torch.Generator) -> None:
    layout.to(F64)
    _outputs(layout)  # kept in float64 meanwhile
    layout.to(torch.float32)


def _freeze(layout: lw.Layout, gen: torch.Generator) -> None:
    layout.rho.requires_grad_(False)


#: Each way a layout's state changes: (its function, whether θ moves, whether it needs ρ learned).
CHANGES = {
    "set_theta": (_set_theta, True, False),
    "optimiser step": (_optimiser_step, True, True),
    "rho.add_ under no_grad": (_rho_add, True, True),
    "load_state_dict": (_load_state_dict, True, False),
    ".to(float64) and back": (_dtype_round_trip, False, False),
    "requires_grad_(False)": (_freeze, False, True),
}
NAMES = [f for f in FAMILIES if f != "uniform"] + ["swirl"]  # uniform: no θ to change


CASES = [
    pytest.param(family, learn, change, id=f"{family}-{'learnable' if learn else 'fixed'}-{change}")
    for family in NAMES
    for learn in (False, True)
    for change, (_, _, needs_learn) in CHANGES.items()
    if learn or not needs_learn  # a fixed layout's ρ is no parameter: no step, no freezing
] + [pytest.param("curv", learn, "load_state_dict (another centre)") for learn in (False, True)]
CHANGES["load_state_dict (another centre)"] = (_load_centre, True, False)


@pytest.mark.parametrize(("family", "learn", "change"), CASES)
def test_every_kept_result_follows_a_layouts_change(family, learn, change, gen):
    """Outputs after the change (every cache warm with the values before) equal those of a
    freshly made layout at the new θ with every cache cleared; where θ moved, the outputs moved
    too, so a cache that answered with the old θ's values would fail here."""
    apply, moves, _ = CHANGES[change]
    layout = _make(family, gen, learn)
    before = _outputs(layout)  # every cache filled at the old θ
    apply(layout, gen)
    after = _outputs(layout)
    clear_caches()
    fresh = _outputs(_fresh(layout))
    assert after.keys() == fresh.keys()
    for name, value in after.items():
        if isinstance(value, str):  # a key: the fresh layout's, whether or not θ moved it
            assert value == fresh[name], f"{change}: {name}"
            continue
        torch.testing.assert_close(value, fresh[name], rtol=1e-5, atol=1e-5, msg=f"{change}: {name}")
        if moves and name != "simulate with physics":  # the noise may hide a small move
            old = before[name]
            moved = value.shape != old.shape or bool((value - old).abs().max() > 1e-4)
            assert moved, f"{change} did not move {name}"


#: A learnable layout's device path in numba's CUDA simulator: a step (its mesh's room and the
#: device mesh kept), ρ moved in place, a step again; then a layout made anew at that ρ, with
#: every cache cleared. Both steps' means and gradients written for the test to compare.
DEVICE_CHANGE = """
import sys
import numpy as np, torch
import layoutwarp as lw
from layoutwarp.caches import clear_caches
case = dict(np.load(sys.argv[1]))
size, tol = tuple(int(v) for v in case["size"]), float(case["tol"])
image = torch.from_numpy(case["image"])
def step(layout):
    layout.zero_grad()
    out = lw.simulate(image[None], layout, size, tol=tol)
    (out * torch.from_numpy(case["g"])).sum().backward()
    return out.detach().numpy(), layout.rho.grad.numpy().copy()
def make():
    theta, centre = case["theta"].tolist(), case["centre"].tolist()
    return lw.FoveaLayout(theta, center=centre, learn=True, dtype=torch.float64)
layout = make()
before = step(layout)
with torch.no_grad():
    layout.rho.add_(torch.from_numpy(case["delta"]))
after = step(layout)
rho = layout.rho.detach().clone()
clear_caches()
fresh = make()
with torch.no_grad():
    fresh.rho.copy_(rho)
again = step(fresh)
np.savez(sys.argv[2], before=before[0], after=after[0], again=again[0], g_after=after[1], g_again=again[1])
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
def test_the_kept_device_meshes_follow_rho_in_numbas_simulator(tmp_path, gen):
    """The CUDA path's kept rooms and device meshes (numba's simulator, no GPU): after ρ moved in
    place, a step gives the means and θ-gradient of a layout made anew at that ρ with nothing
    kept, and not the means from before."""
    from conftest import run_in_simulator

    size, src = (3, 4), (12, 14)
    case = {
        "theta": np.array([0.3, -0.2]),
        "centre": np.array([0.1, -0.15]),
        "delta": 0.3 * torch.randn(4, generator=gen, dtype=F64).numpy(),
        "image": torch.rand(1, *src, generator=gen, dtype=F64).numpy(),
        "g": torch.randn(1, 1, *size, generator=gen, dtype=F64).numpy(),
        "size": np.array(size),
        "tol": 1e-2,
    }
    np.savez(tmp_path / "case.npz", **case)
    run_in_simulator(DEVICE_CHANGE, tmp_path / "case.npz", tmp_path / "out.npz", wait=True)
    got = np.load(tmp_path / "out.npz")
    assert np.abs(got["after"] - got["before"]).max() > 1e-3  # ρ's move moved the means
    np.testing.assert_allclose(got["after"], got["again"], rtol=0, atol=1e-12)
    np.testing.assert_allclose(got["g_after"], got["g_again"], rtol=1e-10, atol=1e-12)


def test_a_write_the_version_counter_cannot_see_is_mended_by_clear_caches(gen):
    """θ written through ``.data`` (no version moves: the caches cannot see it) gives the old θ's
    values until ``clear_caches``, then the new θ's, as the caches' page says."""
    layout = lw.CurvLayout((0.3, -0.2))
    img = torch.rand(1, 1, *SRC, generator=gen)
    before = lw.simulate(img, layout, SIZE)
    layout.fixed_theta.data.copy_(torch.tensor([-0.2, 0.4], dtype=F64))
    assert torch.equal(lw.simulate(img, layout, SIZE), before)  # not seen: documented
    clear_caches()
    assert torch.equal(lw.simulate(img, layout, SIZE), lw.simulate(img, lw.CurvLayout((-0.2, 0.4)), SIZE))


def _data_halved(layout: lw.Layout) -> None:
    held = layout.rho if layout.learnable_param else layout.fixed_theta  # what θ is made of
    held.data = held.data * 0.5  # a new tensor's data: no version counter moves


#: Changes no version counter sees, to what θ is made of: (its function, whether θ's values move).
UNCOUNTED = {
    "a new .data": (_data_halved, True),
    ".to(float64)": (lambda layout: layout.to(F64), None),  # a learnable θ now computed in float64
    ".to(bfloat16)": (lambda layout: layout.to(torch.bfloat16), None),  # a learnable ρ rounded
    "requires_grad_(False)": (lambda layout: layout.rho.requires_grad_(False), True),  # in float64
}
UNCOUNTED_CASES = [
    pytest.param(family, change, learn, id=f"{family}-{change}-{'learnable' if learn else 'fixed'}")
    for family in ("curv", "grid")  # θ made by tanh of ρ, and ρ itself (an unbounded family)
    for change in UNCOUNTED
    for learn in (False, True)
    if learn or change != "requires_grad_(False)"  # a fixed layout's ρ is no parameter
]


@pytest.mark.parametrize(("family", "change", "learn"), UNCOUNTED_CASES)
def test_a_layouts_remembered_theta_follows_what_no_version_counts(family, change, learn, gen):
    """The θ values a fixed call keys its weights by, remembered per layout
    (``operators.base.layout_theta_values``) and per tensor (``theta_values``), are θ's as the
    operators take it now, read afresh, after each change that no version counter sees, bit for
    bit (a stale float32 θ would differ in float64); and the call's output is the one it gives
    with every cache and memo cleared."""
    apply, moves = UNCOUNTED[change]
    layout = _make(family, gen, learn)
    image = torch.rand(1, 2, 30, 36, generator=gen)
    with torch.no_grad():
        lw.simulate(image, layout, (5, 6))  # every memo and cache filled before the change
    before = ops.layout_theta_values(layout)
    with torch.no_grad():
        apply(layout)
    now = tuple(ops.operator_theta(layout).detach().double().tolist())
    assert ops.layout_theta_values(layout) == now
    assert ops.theta_values(ops.operator_theta(layout)) == now
    exact = family == "grid" and change in (".to(float64)", "requires_grad_(False)")  # θ = ρ, widened
    if (moves or (moves is None and learn)) and not exact:  # a fixed θ is kept in float64 as set
        assert now != before, "the change did not move θ: the test would see nothing"
    with torch.no_grad():
        out = lw.simulate(image, layout, (5, 6))
        clear_caches()
        torch.testing.assert_close(out, lw.simulate(image, layout, (5, 6)), rtol=0, atol=0)


def test_a_kept_resampler_is_built_at_its_keys_theta_when_a_thread_sets_another_meanwhile(monkeypatch, gen):
    """Weights are kept under the θ values their key was made of: where another thread sets the
    layout's θ between the key and the build (forced here, right after the key), the kept
    weights are still the key θ's, so a later layout at that θ reads the right ones."""
    layout = lw.CurvLayout((0.3, -0.24), learn=True)
    image = torch.rand(1, 2, 30, 36, generator=gen)
    keyed = ops.layout_theta_values

    def key_then_set(lay: lw.Layout) -> tuple[float, ...]:
        values = keyed(lay)
        lay.set_theta((-0.1, 0.35))  # the other thread
        return values

    monkeypatch.setattr(ops, "layout_theta_values", key_then_set)
    with torch.no_grad():
        lw.simulate(image, layout, (5, 6))  # keys at (0.3, -0.24), builds after the set
    monkeypatch.undo()
    at_key = lw.CurvLayout((0.3, -0.24), learn=True)
    with torch.no_grad():
        kept = lw.simulate(image, at_key, (5, 6))  # the weights kept under the key
        clear_caches()
        torch.testing.assert_close(kept, lw.simulate(image, at_key, (5, 6)), rtol=1e-6, atol=1e-6)
