"""The compiled learnable path (layoutwarp.kernels.mesh + layoutwarp::exact) against the
torch reference: the same mesh, values and θ-gradients to rounding, on random and hard layouts."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import torch.autograd.forward_ad as fwad
from conftest import grad_tol, ptx_or_skip, run_in_simulator
from torch import Tensor

import layoutwarp as lw
from layoutwarp import kernels
from layoutwarp.integrators import integrate_exact
from layoutwarp.kernels import mesh as mk
from layoutwarp.layoutfile import layout_from_spec
from layoutwarp.mesh import pixel_mesh, smooth_pieces
from layoutwarp.testing import count_ops
from layoutwarp.topology import MeshTopology

pytestmark = pytest.mark.skipif(not lw.kernels.available(), reason="needs numba")


def _random_layout(family: str, rng: np.random.Generator, hard: bool = False) -> lw.Layout:
    th = rng.uniform(0.9, 0.99, 2) if hard else rng.uniform(0.1, 0.8, 2)
    th = th * rng.choice([-1.0, 1.0], 2)
    if family == "curv-off":
        c = rng.uniform(-0.9 if hard else -0.5, 0.9 if hard else 0.5, 2)
        return lw.CurvLayout(th.tolist(), center=c.tolist(), learn=True, dtype=torch.float64)
    if family == "fovea":
        c = rng.uniform(-0.9 if hard else -0.5, 0.9 if hard else 0.5, 2)
        return lw.FoveaLayout(th.tolist(), center=c.tolist(), learn=True, dtype=torch.float64)
    return lw.make_layout(family, th.tolist(), learn=True, dtype=torch.float64)


FAMILIES = ["curv", "curv-off", "fovea", "elliptic"]
SIZES = [(1, 1), (1, 6), (5, 7), (8, 6), (13, 17)]


def test_only_the_built_in_classes_are_compiled():
    class MyCurv(lw.CurvLayout):  # a user's subclass may change φ: it keeps the torch path
        pass

    assert mk.mesh_spec(MyCurv((0.2, 0.1))) is None
    assert mk.mesh_spec(lw.RectLayout((0.2, 0.1))) is None
    assert mk.mesh_spec(lw.CurvLayout((0.2, 0.1))).nparams == 2
    assert mk.mesh_spec(lw.FoveaLayout((0.2, 0.1), center=(0.1, 0.2))).nparams == 4


@pytest.mark.parametrize("hard", [False, True])
@pytest.mark.parametrize("family", FAMILIES)
def test_compiled_mesh_is_the_torch_mesh(family: str, hard: bool):
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    for size in SIZES:
        layout = _random_layout(family, rng, hard)
        tol = float(10 ** rng.uniform(-4, -2))
        cm = mk.build_mesh(mk.mesh_spec(layout), size, layout.theta.detach().numpy(), tol)
        ref = pixel_mesh(layout, size, tol=tol, dtype=torch.float64)  # θ requires grad: with_grad counts
        assert np.array_equal(cm.edge_offsets, ref.edge_offsets.numpy()), (size, tol)
        assert np.array_equal(cm.seg_start, ref.seg_start.numpy())
        assert np.array_equal(cm.seg_end, ref.seg_end.numpy())
        assert np.array_equal(cm.seg_edge, ref.seg_edge.numpy())
        np.testing.assert_allclose(cm.vertices, ref.vertices.detach().numpy(), rtol=0, atol=1e-13)


@pytest.mark.parametrize("family", FAMILIES)
def test_vertex_derivatives_match_forward_mode_autograd(family: str):
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    layout = _random_layout(family, rng)
    size = (7, 9)
    theta = layout.theta.detach()
    cm = mk.build_mesh(mk.mesh_spec(layout), size, theta.numpy(), 1e-3)
    counts = torch.from_numpy(cm.counts)
    cols = []
    for k in range(theta.numel()):
        with fwad.dual_level():
            dual = fwad.make_dual(theta, torch.eye(theta.numel(), dtype=theta.dtype)[k])
            mesh = pixel_mesh(layout, size, subdivisions=counts, dtype=torch.float64, theta=dual)
            cols.append(fwad.unpack_dual(mesh.vertices).tangent)
    ref = torch.stack(cols, -1).numpy()
    # a kink that touches the sensor's side (a learned centre's quarter-ellipse) is a double root:
    # both sides agree only to ~1e-8 there
    np.testing.assert_allclose(cm.dverts, ref, rtol=0, atol=1e-7 * max(1.0, np.abs(ref).max()))


@pytest.mark.parametrize("dtype,rel", [(torch.float64, 1e-12), (torch.float32, 1e-6)])
@pytest.mark.parametrize("hard", [False, True])
@pytest.mark.parametrize("family", FAMILIES)
def test_compiled_values_and_theta_gradients_match_the_torch_reference(family, hard, dtype, rel):
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    layout = _random_layout(family, rng, hard)
    size = tuple(int(v) for v in rng.integers(3, 14, 2))
    image = torch.rand(2, int(rng.integers(20, 60)), int(rng.integers(20, 60)), dtype=dtype)
    tol = 1e-3
    theta = layout.theta.detach().clone().requires_grad_(True)
    # the compiled path, with the pixels' areas (what sensor physics uses) in the loss too
    out, areas = integrate_exact(image, layout, size, tol=tol, theta=theta, return_areas=True)
    weights = torch.randn(out.shape, dtype=torch.float64)
    w_areas = torch.randn(areas.shape, dtype=torch.float64) / float(areas.detach().mean())
    (grad,) = torch.autograd.grad((out * weights).sum() + (areas * w_areas).sum(), theta)
    cm = mk.build_mesh(mk.mesh_spec(layout), size, theta.detach().numpy(), tol)
    theta_ref = theta.detach().clone().requires_grad_(True)
    mesh = pixel_mesh(
        layout, size, subdivisions=torch.from_numpy(cm.counts), dtype=torch.float64, theta=theta_ref
    )
    ref, ref_areas = integrate_exact(image, layout, size, mesh=mesh, backend="torch", return_areas=True)
    (grad_ref,) = torch.autograd.grad((ref * weights).sum() + (ref_areas * w_areas).sum(), theta_ref)
    assert torch.allclose(out, ref, rtol=0, atol=rel)
    assert torch.allclose(areas, ref_areas, rtol=0, atol=1e-13 * float(ref_areas.detach().max()))
    # float64: rounding times the conditioning near |θ| = 1 (see grad_tol)
    scale = max(float(grad_ref.abs().max()), 1.0)
    gtol = grad_tol(layout, grad_ref) if dtype == torch.float64 else rel * scale
    assert float((grad - grad_ref).abs().max()) <= gtol, (grad, grad_ref)


@pytest.mark.parametrize("hard", [False, True])
@pytest.mark.parametrize("family", FAMILIES)
def test_mesh_integrals_are_the_built_meshs_forward_and_reynolds_jacobian(family: str, hard: bool):
    """Placing vertices chunk by chunk and integrating them in cache gives the plain forward over
    build_mesh's mesh bit for bit, and a Jacobian whose contraction with any edge gradient is the
    backward's Reynolds weights times each end's normal velocity, summed over segments."""
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    layout = _random_layout(family, rng, hard)
    size = tuple(int(v) for v in rng.integers(1, 15, 2))
    src = tuple(int(v) for v in rng.integers(5, 70, 2))
    img = rng.uniform(-3, 7, (int(rng.integers(1, 4)), *src))
    tol, spec, theta = 1e-4, mk.mesh_spec(layout), layout.theta.detach().numpy()
    tables = lw.kernels.prefix_tables(img, lw.kernels.BLOCK)
    out, jac = mk.mesh_integrals(spec, size, theta, tol, tables, src)
    cm = mk.build_mesh(spec, size, theta, tol)
    verts = mk.pixel_vertices(cm, src)
    k = (cm.seg_start, cm.seg_end, cm.edge_offsets)
    assert np.array_equal(out, lw.kernels.exact_forward(verts, *k, *tables, lw.kernels.BLOCK, 1))
    grad = rng.standard_normal(out.shape)
    wa, wb = lw.kernels.exact_backward(
        verts, cm.seg_start, cm.seg_end, cm.seg_edge, tables[0], lw.kernels.BLOCK, grad, 1
    )
    d = verts[cm.seg_end] - verts[cm.seg_start]
    normal = np.stack([d[:, 1], -d[:, 0]], 1) * (np.array([src[1], src[0]]) / 2)  # ν, in [-1, 1] units
    va = np.einsum("sc,scp->sp", normal, cm.dverts[cm.seg_start])
    vb = np.einsum("sc,scp->sp", normal, cm.dverts[cm.seg_end])
    ref = (wa[:, None] * va + wb[:, None] * vb).sum(0)
    got = np.einsum("ne,nep->p", grad, jac)
    scale = np.abs(wa[:, None] * va).sum(0).max() + np.abs(wb[:, None] * vb).sum(0).max()
    assert np.abs(got - ref).max() <= 1e-12 * max(scale, 1.0), (got, ref)


def test_theta_gradient_is_the_contraction_on_any_thread_count(monkeypatch):
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    p, e = int(rng.choice([2, 4])), int(rng.integers(1, 30000))
    g, jac = rng.standard_normal((3, e)), rng.standard_normal((3, e, p)) * 10.0 ** rng.uniform(-3, 3, p)
    ref = np.einsum("ne,nep->p", g, jac)
    got = mk.theta_gradient(g, jac)
    scale = np.abs(g[..., None] * jac).sum((0, 1))
    assert got.shape == (p,) and np.all(np.abs(got - ref) <= 1e-13 * scale), (got, ref)
    monkeypatch.setattr(kernels.base, "SMALL_WORK", 0)  # shares however small the work
    before = torch.get_num_threads()
    try:
        for n in (1, 3):
            torch.set_num_threads(n)
            assert np.array_equal(mk.theta_gradient(g, jac), got)
    finally:
        torch.set_num_threads(before)


@pytest.mark.parametrize("size", SIZES)
def test_edge_gradient_is_the_quotient_rule_then_combine_adjoint(size: tuple[int, int]):
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    n = int(rng.integers(1, 4))
    grad, means = rng.standard_normal((n, *size)), rng.random((n, *size))
    areas = rng.uniform(0.1, 2.0, size)
    pix = np.concatenate([grad / areas, -(grad * means).sum(0, keepdims=True) / areas])
    ref = MeshTopology(size).combine_adjoint(pix)
    np.testing.assert_array_equal(mk.edge_gradient(grad, means, areas), ref)
    area_grad = rng.standard_normal(size)  # where the areas are an output of their own (physics)
    pix_own = pix.copy()
    pix_own[-1] += area_grad
    np.testing.assert_array_equal(
        mk.edge_gradient(grad, means, areas, area_grad), MeshTopology(size).combine_adjoint(pix_own)
    )
    # and it is the transpose of combine: <combine(x), pix> = <x, combine_adjoint(pix)>
    x = rng.standard_normal(ref.shape)
    lhs = float((MeshTopology(size).combine(x) * pix).sum())
    assert abs(lhs - float((x * ref).sum())) <= 1e-12 * max(1.0, abs(lhs))


@pytest.mark.parametrize("family", FAMILIES)
def test_compiled_theta_gradient_matches_central_differences(family: str):
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    size, h = (6, 8), 1e-6
    image = torch.rand(1, 37, 45, dtype=torch.float64)
    ends = MeshTopology(size).edge_ends()

    def pieces(layout: lw.Layout, th: torch.Tensor) -> int:
        return len(smooth_pieces(layout, *ends, theta=th)[0])

    for _ in range(10):  # a layout whose kinks stay inside their edges within θ ± h
        layout = _random_layout(family, rng)
        theta = layout.theta.detach().clone()
        steps = torch.eye(theta.numel(), dtype=theta.dtype) * h
        if all(pieces(layout, theta + s * e) == pieces(layout, theta) for e in steps for s in (-1, 1)):
            break
    theta.requires_grad_(True)
    out = integrate_exact(image, layout, size, tol=1e-3, theta=theta)
    weights = torch.randn(out.shape, dtype=torch.float64)
    (grad,) = torch.autograd.grad((out * weights).sum(), theta)
    counts = torch.from_numpy(mk.build_mesh(mk.mesh_spec(layout), size, theta.detach().numpy(), 1e-3).counts)

    def f(th: torch.Tensor) -> float:  # the same segment counts: smooth in θ
        with torch.no_grad():
            mesh = pixel_mesh(layout, size, subdivisions=counts, dtype=torch.float64, theta=th)
            return float((integrate_exact(image, layout, size, mesh=mesh) * weights).sum())

    for k, e in enumerate(steps):
        fd = (f(theta.detach() + e) - f(theta.detach() - e)) / (2 * h)
        assert abs(fd - float(grad[k])) <= 1e-5 * max(1.0, abs(fd)), (k, fd, float(grad[k]))


def test_a_training_step_runs_few_torch_operations():
    layout = lw.CurvLayout((0.35, -0.25), learn=True)
    image = torch.rand(1, 3, 96, 128)

    def step() -> None:
        lw.simulate(image, layout, (17, 23)).sum().backward()
        layout.rho.grad = None

    step()  # a process's first step looks at the compiled code's cache (its warm-up's operators)
    assert count_ops(step) <= 50
    camera = lw.SensorPhysics((96.0, 128.0), photons_per_um2=20.0, read_noise_e=2.0, adc_bits=10)

    def recorded_step() -> None:  # the areas come from the compiled path too: no torch mesh
        lw.simulate(image, layout, (17, 23), physics=camera).sum().backward()
        layout.rho.grad = None

    recorded_step()  # the measurement's group: the same first look
    assert count_ops(recorded_step) <= 90
    # and the step's gradient is the torch reference's (the same float32 tables)
    layout.rho.grad = None
    lw.simulate(image, layout, (17, 23)).sum().backward()
    compiled = layout.rho.grad.clone()
    layout.rho.grad = None
    tol = lw.data_tolerance(torch.float32)[0]
    integrate_exact(image[0], layout, (17, 23), tol=tol, backend="torch").sum().backward()
    ref = layout.rho.grad
    assert float((compiled - ref).abs().max()) <= 1e-6 * float(ref.abs().max())


@pytest.mark.slow  # a minute of PTX compiling
def test_the_device_mesh_kernels_compile_for_the_device_without_one():
    """Every kernel of :func:`~layoutwarp.kernels.mesh.build_mesh_device` compiles to PTX (no GPU
    needed: numba-cuda and the CUDA compilers), with every shared function it calls."""
    for name, (fn, signature) in mk.CUDA_KERNELS.items():
        ptx = ptx_or_skip(fn, signature=signature)
        assert ".target sm_80" in ptx and ".entry" in ptx, name
    with pytest.raises(ValueError, match="signature"):
        lw.kernels.cuda_ptx(mk.CUDA_KERNELS["counts"][0])


#: Runs in a process of its own: numba's CUDA simulator, the device functions as plain Python;
#: one case a file, each case's results to its own file.
DEVICE_MESH = """
import sys
import numpy as np, torch
import layoutwarp as lw
from layoutwarp.kernels import mesh as mk
for path in sys.argv[1:]:
    case = dict(np.load(path))
    kind, centred, nparams = int(case["kind"]), bool(case["centred"]), int(case["theta"].size)
    spec = mk.MeshSpec(kind, tuple(case["center"]), centred, nparams)
    dm = mk.build_mesh_device(spec, tuple(case["size"]), torch.from_numpy(case["theta"]), float(case["tol"]),
                              tuple(case["src"]))
    m, status = dm.mesh, dm.room.look()
    nseg, nv = int(m.edge_offsets[-1]), m.vertices.shape[0] - m.seg_start.shape[0] + int(m.edge_offsets[-1])
    assert status["segments"] == nseg and not status["overflowed"], status
    # the room left over: segments of no length at vertex 0
    assert not m.seg_start[nseg:].any() and not m.seg_end[nseg:].any() and not m.seg_edge[nseg:].any()
    used = {"verts": m.vertices[:nv], "pv": dm.pixel_vertices[:nv], "dverts": dm.dverts[:nv],
            "ss": m.seg_start[:nseg], "se": m.seg_end[:nseg], "sedge": m.seg_edge[:nseg],
            "eo": m.edge_offsets, "counts": dm.counts[:status["pieces"]]}
    np.savez(path.replace("case", "out"), **{k: v.numpy() for k, v in used.items()})
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
@pytest.mark.heavy
def test_the_device_mesh_is_the_compiled_mesh_in_numbas_simulator(tmp_path):
    """Without a GPU: :func:`~layoutwarp.kernels.mesh.build_mesh_device`'s kernels and launches
    (one thread per corner, edge or vertex, in buffers with room to spare) in numba's CUDA
    simulator against :func:`~layoutwarp.kernels.mesh.build_mesh` on the CPU, for each family
    (θ near ±1 and the centre near the border for the hard ones): the same segment counts and
    indices, the same vertices and pixel vertices, θ-derivatives to rounding; the totals the
    status reports; the room left over holding segments of no length."""

    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    cases = [("curv", False), ("curv-off", True), ("fovea", False), ("fovea", True), ("elliptic", True)]
    inputs = {}
    for i, (family, hard) in enumerate(cases):
        layout = _random_layout(family, rng, hard)
        size = (int(rng.integers(1, 7)), int(rng.integers(1, 7)))
        src = (int(rng.integers(5, 60)), int(rng.integers(5, 60)))
        tol = float(10 ** rng.uniform(-4, -2))
        spec, theta = mk.mesh_spec(layout), layout.theta.detach().numpy()
        np.savez(
            tmp_path / f"case{i}.npz", kind=spec.kind, center=np.array(spec.center), centred=spec.centred,
            theta=theta, size=np.array(size), src=np.array(src), tol=tol,
        )  # fmt: skip
        inputs[i] = (f"{family}, hard={hard}", spec, size, src, theta, tol)
    run_in_simulator(DEVICE_MESH, *(tmp_path / f"case{i}.npz" for i in inputs))
    for i, (name, spec, size, src, theta, tol) in inputs.items():
        got = np.load(tmp_path / f"out{i}.npz")
        cm = mk.build_mesh(spec, size, theta, tol)
        refs = {"counts": cm.counts, "eo": cm.edge_offsets, "ss": cm.seg_start, "se": cm.seg_end}
        refs |= {"sedge": cm.seg_edge, "verts": cm.vertices, "pv": mk.pixel_vertices(cm, src)}
        for key, ref in refs.items():
            assert np.array_equal(got[key], ref), (name, key)
        scale = max(1.0, float(np.abs(cm.dverts).max()))
        assert got["dverts"].shape == cm.dverts.shape, name
        assert float(np.abs(got["dverts"] - cm.dverts).max()) <= 1e-14 * scale, name


#: A device mesh whose pieces reach the cap of their segments, in numba's CUDA simulator.
DEVICE_CAP = """
import json, sys, warnings
import torch
import layoutwarp as lw
from layoutwarp.kernels import mesh as mk
layout = lw.EllipticLayout((0.97, 0.97))
spec, theta = mk.mesh_spec(layout), layout.theta.detach().double()
out = {}
for cap in (64, 1 << 14):
    dm = mk.build_mesh_device(spec, (1, 6), theta, 1e-3, (12, 12), max_subdiv=cap)
    out[f"counts_{cap}"] = int(dm.counts[: int(dm.room.status[mk.PIECES])].max())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        out[f"look_{cap}"] = dm.room.look()["capped"]  # what the mesh wrote, read now
    out[f"warned_{cap}"] = sum("reached max_subdiv" in str(w.message) for w in caught)
mk.build_mesh_device(spec, (1, 6), theta, 1e-3, (12, 12), max_subdiv=64)
out["status"] = mk.device_status()["capped"]  # told at once, then cleared
out["again"] = mk.device_status()["capped"]
json.dump(out, open(sys.argv[1], "w"))
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
def test_a_device_mesh_whose_pieces_reach_the_cap_says_so_in_numbas_simulator(tmp_path):
    """Without a GPU: a device mesh with a piece at ``max_subdiv`` segments writes the cap to its
    room's status; the next look warns (as the CPU meshes warn at once), `device_status` tells
    it and clears it; at the default cap the same strip reaches nothing."""
    run_in_simulator(DEVICE_CAP, tmp_path / "out.json")
    got = json.loads((tmp_path / "out.json").read_text())
    assert got["counts_64"] == 64 and got["look_64"] and got["warned_64"] == 1
    assert got["counts_16384"] < 1 << 14 and not got["look_16384"] and got["warned_16384"] == 0
    assert got["status"] and not got["again"]


#: A learnable step through the device path in numba's CUDA simulator: means, areas, θ's gradient
#: and the step's launches (numba kernels and torch operators), written for the test to compare.
DEVICE_STEP = """
import json, sys
import numpy as np, torch
import layoutwarp as lw
from layoutwarp.testing import count_host_reads, count_launches
from layoutwarp.integrators import integrate_exact
from layoutwarp.layoutfile import layout_from_spec
case = dict(np.load(sys.argv[1]))
spec = json.loads(str(case["spec"]))
layout = layout_from_spec(spec, learn=True)
image = torch.from_numpy(case["image"])
size = tuple(int(v) for v in case["size"])
out, areas = integrate_exact(image, layout, size, tol=float(case["tol"]), return_areas=True)
(out * torch.from_numpy(case["g"])).sum().add((areas * torch.from_numpy(case["ga"])).sum()).backward()
grad = layout.rho.grad.clone()
# the same with grad mode on in the backward (create_graph): tensors that require grad reach the kernels
out, areas = integrate_exact(image, layout, size, tol=float(case["tol"]), return_areas=True)
loss = (out * torch.from_numpy(case["g"])).sum().add((areas * torch.from_numpy(case["ga"])).sum())
assert torch.equal(torch.autograd.grad(loss, layout.rho, create_graph=True)[0], grad)
def step():
    layout.zero_grad()
    lw.simulate(image[None], layout, size, tol=float(case["tol"])).sum().backward()
def training_step():  # as an optimizer moves θ in place between steps
    with torch.no_grad():
        layout.rho.mul_(0.999)
    step()
step()  # the first call imports and caches what every later step takes as it is
launches = count_launches(step)
kernels = sum(v for k, v in launches.items() if k.startswith("numba:"))
reads = count_host_reads(training_step)
np.savez(sys.argv[2], out=out.detach().numpy(), areas=areas.detach().numpy(), grad=grad.numpy(),
         launches=sum(launches.values()), kernels=kernels, reads=sum(reads.values()),
         names=json.dumps(launches))
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
@pytest.mark.parametrize("family", ["curv", "fovea"])
def test_a_learnable_step_on_the_device_path_matches_the_cpu_in_numbas_simulator(family: str, tmp_path):
    """Without a GPU: a learnable layout's whole device path (the mesh built there, the exact
    forward, the pixels' means and areas in one kernel, the backward from the means' and the
    areas' gradients to θ in two) in numba's CUDA simulator against the compiled CPU path: the
    same means and areas to rounding, θ's gradient to float32's (θ's dtype); a training step's
    GPU launches, counted (numba kernels and torch operators, `count_launches`: at most 12, 8 of
    them numba kernels, the loss's two included; ρ → θ, the means' rounding and their gradient's
    way back are inside the kernels), and its reads of a device value back to the host
    (`count_host_reads`): none."""
    import json

    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    th = (rng.uniform(0.1, 0.8, 2) * rng.choice([-1.0, 1.0], 2)).tolist()
    spec = {"family": "curv", "theta": th}
    if family == "fovea":
        centre = rng.uniform(-0.5, 0.5, 2).tolist()
        spec = {"family": "fovea", "theta": th, "center": centre, "learn_center": True}
    size = (int(rng.integers(2, 5)), int(rng.integers(2, 5)))  # small: the kernels run as Python
    src = (int(rng.integers(8, 20)), int(rng.integers(8, 20)))
    image = rng.uniform(-1, 3, (2, *src)).astype(np.float64)
    g, ga = rng.standard_normal((2, *size)), rng.standard_normal(size)
    tol = 1e-2  # a few hundred segments: the kernels run as Python, a thread each
    case = {"spec": json.dumps(spec), "image": image, "size": np.array(size), "tol": tol, "g": g, "ga": ga}
    np.savez(tmp_path / "case.npz", **case)
    run_in_simulator(DEVICE_STEP, tmp_path / "case.npz", tmp_path / "out.npz", wait=True)
    got = np.load(tmp_path / "out.npz")
    layout = layout_from_spec(spec, learn=True)
    out, areas = integrate_exact(torch.from_numpy(image), layout, size, tol=tol, return_areas=True)
    (out * torch.from_numpy(g)).sum().add((areas * torch.from_numpy(ga)).sum()).backward()
    assert np.abs(got["out"] - out.detach().numpy()).max() <= 1e-12 * np.abs(image).max()
    assert np.abs(got["areas"] - areas.detach().numpy()).max() <= 1e-14
    ref = layout.rho.grad.numpy()
    assert np.abs(got["grad"] - ref).max() <= 1e-6 * max(1.0, np.abs(ref).max())  # θ in float32
    assert int(got["launches"]) <= 12 and int(got["kernels"]) <= 8, str(got["names"])
    assert int(got["reads"]) == 0


#: A learnable layout's device meshes in numba's CUDA simulator when they outgrow their room, and
#: when an image holds NaN: written for the test to compare.
DEVICE_ROOM = """
import json, sys, warnings
import numpy as np, torch
import layoutwarp as lw
from layoutwarp.kernels import mesh as mk
from layoutwarp.integrators import integrate_exact
from layoutwarp.testing import count_host_reads
case = dict(np.load(sys.argv[1]))
image, size, tol = torch.from_numpy(case["image"]), tuple(int(v) for v in case["size"]), float(case["tol"])
layout = lw.FoveaLayout((0.02, -0.02), center=tuple(case["center"]), learn=True, learn_center=True)
def step():
    return integrate_exact(image, layout, size, tol=tol)
def means():
    return step().detach().numpy()
means()  # a nearly straight mesh: a small room
room = list(mk.MESH_ROOMS.values())[-1]
layout.set_theta(case["theta"])
out = {}
with warnings.catch_warnings(record=True) as caught:
    warnings.simplefilter("always")
    reads = count_host_reads(lambda: out.update(chords=step().detach()))  # outgrows its room: a chord a piece
    out["chords"] = out["chords"].numpy()
    out["next"] = means()  # warned: the room grew before this one
    out["warned"] = sum("outgrew its room" in str(w.message) for w in caught)
out["reads"] = sum(reads.values())
out["status_chords"] = mk.device_status()["overflowed"]  # reported since the last call
out["exact"] = means()
out["status_clean"] = mk.device_status()["overflowed"]
room.pieces = room.segments = 2 * size[0] * size[1] + size[0] + size[1]  # as many as edges
room.status[mk.PIECES] = room.status[mk.SEGMENTS] = 0  # nothing for the room to grow by
with warnings.catch_warnings():
    warnings.simplefilter("ignore", RuntimeWarning)
    out["quads"] = means()  # outgrows its pieces' room: one chord an edge
status = mk.device_status()
out["status_over"], out["status_nan"] = status["overflowed"], status["nonfinite"]
out["after_quads"] = means()  # the pieces' room grew, and the segments' was measured again
bad = image.clone()
bad[0, 2, 3] = float("nan")
lw.simulate(bad[None], layout, size, tol=tol, allow_nonfinite=False)  # checked on the device: no wait
out["nan_seen"] = mk.device_status()["nonfinite"]
lw.simulate(bad[None], layout, size, tol=tol, allow_nonfinite=False)
means()  # unchecked (integrate_exact's default): raises nothing
try:
    lw.simulate(image[None], layout, size, tol=tol)  # checked (simulate's default)
    out["raised"] = ""
except ValueError as err:
    out["raised"] = str(err)
fixed = lw.CurvLayout((0.3, -0.2))  # a fixed layout's forward: one kernel, checked there too
lw.simulate(image[None], fixed, size)
out["fixed_reads"] = sum(count_host_reads(lambda: lw.simulate(bad[None], fixed, size)).values())
out["fixed_nan_seen"] = mk.device_status()["nonfinite"]
lw.simulate(bad[None], fixed, size)
try:
    lw.simulate(image[None], fixed, size)
    out["fixed_raised"] = ""
except ValueError as err:
    out["fixed_raised"] = str(err)
np.savez(sys.argv[2], **out)
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
def test_a_device_mesh_that_outgrows_its_room_integrates_chords_and_says_so_in_numbas_simulator(tmp_path):
    """Without a GPU: a learnable fovea layout whose θ jumps from nearly straight to strongly
    curved outgrows the room its device meshes were sized for. That step waits for nothing (no
    host read), integrates one straight chord per smooth piece (the means of
    ``pixel_mesh(..., subdivisions=1)`` to rounding), and the next step warns, has grown the
    room, and gives the compiled CPU path's means. Pieces that outgrow theirs give one chord per
    edge (the quads of the deformed corners), and the step after it is exact again.
    `device_status` reports the overflow, and a NaN a
    checked step met on the device; a later step raises for it. A fixed layout's forward checks
    on the device too, reading nothing back."""

    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    theta = [float(rng.uniform(0.6, 0.85)), -float(rng.uniform(0.6, 0.85))]
    center = rng.uniform(-0.4, 0.4, 2)
    size, src = (3, 4), (int(rng.integers(10, 16)), int(rng.integers(10, 16)))
    image = rng.uniform(-1, 3, (2, *src))
    case = {"image": image, "size": np.array(size), "tol": 1e-2, "center": center, "theta": [*theta, *center]}
    np.savez(tmp_path / "case.npz", **case)
    run_in_simulator(DEVICE_ROOM, tmp_path / "case.npz", tmp_path / "out.npz", wait=True)
    got = np.load(tmp_path / "out.npz")
    layout = lw.FoveaLayout(theta, center=tuple(center), learn=True, learn_center=True)
    img, scale = torch.from_numpy(image), np.abs(image).max()
    exact = integrate_exact(img, layout, size, tol=1e-2).detach().numpy()
    chords = lw.pixel_mesh(layout, size, subdivisions=1, dtype=torch.float64)
    by_chords = integrate_exact(img, layout, size, mesh=chords).detach().numpy()
    ne = MeshTopology(size).num_edges
    ea, eb = MeshTopology(size).edge_corners()
    quads = lw.PixelMesh(
        size, chords.vertices[: (size[0] + 1) * (size[1] + 1)], ea, eb, torch.arange(ne), torch.arange(ne + 1)
    )
    by_quads = integrate_exact(img, layout, size, mesh=quads).detach().numpy()
    assert int(got["reads"]) == 0
    assert np.abs(got["chords"] - by_chords).max() <= 1e-12 * scale
    assert np.abs(by_chords - exact).max() > 1e-4 * scale  # the chords are coarser: a real difference
    assert int(got["warned"]) == 1
    assert np.abs(got["next"] - exact).max() <= 1e-12 * scale
    assert np.abs(got["exact"] - exact).max() <= 1e-12 * scale
    assert bool(got["status_chords"]) and not bool(got["status_clean"])
    assert np.abs(got["quads"] - by_quads).max() <= 1e-12 * scale
    assert bool(got["status_over"]) and not bool(got["status_nan"])
    assert np.abs(got["after_quads"] - exact).max() <= 1e-12 * scale
    assert bool(got["nan_seen"])
    assert "held NaN or Inf" in str(got["raised"])
    assert int(got["fixed_reads"]) == 0 and bool(got["fixed_nan_seen"])
    assert "held NaN or Inf" in str(got["fixed_raised"])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("family", FAMILIES)
def test_compiled_path_on_cuda_matches_cpu(family: str):
    if not lw.kernels.cuda_available("float32"):
        pytest.skip("numba's CUDA target does not run here")
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    layout = _random_layout(family, rng)
    image = torch.rand(3, 50, 70)
    outs, grads = [], []
    for device in ("cpu", "cuda"):
        lay = layout.to(device)
        theta = lay.theta.detach().clone().requires_grad_(True)
        out, areas = integrate_exact(image.to(device), lay, (9, 11), tol=1e-3, theta=theta, return_areas=True)
        (out.sum() + 100 * areas.sum() + 10 * areas[2, 3]).backward()
        outs.append(out.cpu())
        grads.append(theta.grad.cpu())
    assert torch.allclose(outs[0], outs[1], rtol=0, atol=1e-6)
    assert torch.allclose(grads[0], grads[1], rtol=1e-6, atol=1e-8)


def _cuda_learnable_layer(family: str, rng: np.random.Generator) -> lw.SensorLayer:
    """A learnable curv ± or fovea layer (learned centre) on the GPU, θ of mixed sign."""
    th = [float(rng.uniform(0.2, 0.6)), -float(rng.uniform(0.2, 0.6))]
    if family == "fovea":
        layout = lw.FoveaLayout(th, center=(0.2, -0.1), learn=True, learn_center=True)
    else:
        layout = lw.CurvLayout(th, learn=True)
    return lw.SensorLayer((33, 47), layout).cuda()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("family", ["curv", "fovea"])
def test_a_learnable_step_captured_in_a_cuda_graph_matches_the_uncaptured_step(family: str):
    """On a GPU: a learnable layer's forward and backward captured in one CUDA graph
    (``torch.cuda.graph``: capture fails on any wait for the device) and replayed with a new
    image and a θ moved in place, as an optimizer moves it, give the uncaptured step's values and
    θ-gradient; `device_status` then reports no overflow."""
    if not lw.kernels.cuda_available("float32"):
        pytest.skip("numba's CUDA target does not run here")
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    layer = _cuda_learnable_layer(family, rng)
    rho = layer.layout.rho
    images = [torch.rand(2, 3, 150, 200, device="cuda") for _ in range(2)]
    static = images[0].clone()

    def step() -> tuple[Tensor, Tensor]:
        out = layer(static)
        (out * out).mean().backward()
        return out

    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):  # warm-up: the caches, the room, the kernels compiled
        for _ in range(3):
            rho.grad = None
            step()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    rho.grad = None
    with torch.cuda.graph(graph):
        static_out = step()
    static_grad = rho.grad  # the graph's own: each replay writes it
    for image, scale in zip(images, (1.0, 0.97), strict=True):
        static.copy_(image)
        with torch.no_grad():
            rho.mul_(scale)  # θ moves between steps
        graph.replay()
        captured, captured_grad = static_out.clone(), static_grad.clone()
        eager = layer(static)
        (eager_grad,) = torch.autograd.grad((eager * eager).mean(), rho)
        assert torch.allclose(captured, eager.detach(), rtol=0, atol=1e-6)
        assert torch.allclose(captured_grad, eager_grad, rtol=1e-5, atol=1e-8)
    assert not lw.device_status()["overflowed"]


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_model_holding_a_learnable_layer_compiles_with_reduce_overhead_on_cuda():
    """On a GPU: ``torch.compile(mode="reduce-overhead")`` (CUDA graphs) over a model holding a
    learnable `SensorLayer` gives eager's outputs and θ-gradients, step after step."""
    if not lw.kernels.cuda_available("float32"):
        pytest.skip("numba's CUDA target does not run here")
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    model = torch.nn.Sequential(_cuda_learnable_layer("curv", rng), torch.nn.Conv2d(3, 4, 3)).cuda()
    torch._dynamo.utils.counters.clear()
    compiled = torch.compile(model, mode="reduce-overhead", fullgraph=True)
    rho = model[0].layout.rho
    for _ in range(4):
        image = torch.rand(2, 3, 150, 200, device="cuda")
        rho.grad = None
        out = compiled(image)
        out.square().mean().backward()
        got, got_grad = out.detach().clone(), rho.grad.clone()
        rho.grad = None
        ref = model(image)
        ref.square().mean().backward()
        assert torch.allclose(got, ref.detach(), rtol=0, atol=1e-5)
        assert torch.allclose(got_grad, rho.grad, rtol=1e-5, atol=1e-8)
        with torch.no_grad():
            rho.mul_(0.98)
    assert not torch._dynamo.utils.counters["inductor"]["cudagraph_skips"]  # CUDA graphs were used


def test_the_compiled_form_reads_a_fixed_centre_again_after_it_changes():
    """The compiled form's fixed centre is read once per centre tensor and version: a centre
    written in place, or a new layout (whose tensor may reuse a freed one's memory), gives its own
    values."""
    for x in (0.1, -0.3, 0.25):  # new layouts, the old ones freed
        layout = lw.FoveaLayout((0.2, 0.3), center=(x, 0.05))
        assert mk.mesh_spec(layout).center == pytest.approx((x, 0.05))
    with torch.no_grad():
        layout.fixed_center.copy_(torch.tensor([0.4, -0.2]))
    assert mk.mesh_spec(layout).center == pytest.approx((0.4, -0.2))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("family", ["curv", "fovea"])
def test_direct_cuda_launches_give_the_dispatchers_values_bit_for_bit(family: str, monkeypatch):
    """On a GPU: a learnable step whose kernels launch directly (`cuda_launch`'s arguments
    marshalled by layoutwarp, numba's dispatcher skipped) gives the values and θ-gradient of the
    same step launched through numba's dispatcher, bit for bit, and the direct launch stayed on."""
    from layoutwarp.kernels import device as kd

    if not lw.kernels.cuda_available("float32"):
        pytest.skip("numba's CUDA target does not run here")
    rng = np.random.default_rng(int(torch.randint(0, 2**31, ())))
    layer = _cuda_learnable_layer(family, rng)
    image = torch.rand(2, 3, 150, 200, device="cuda")

    def step() -> tuple[Tensor, Tensor]:
        layer.zero_grad()
        out = layer(image)
        (out * out).mean().backward()
        return out.detach().clone(), layer.layout.rho.grad.clone()

    monkeypatch.setattr(kd, "FAST_LAUNCH", False)
    through_numba = step()
    monkeypatch.setattr(kd, "FAST_LAUNCH", True)
    before = sum(kd.LAUNCHES.values())
    step()  # the dispatcher launches once per kind of argument list, and its choice is kept
    direct = step()
    assert not kd.DIRECT_OFF, kd.DIRECT_OFF
    assert kd._DIRECT and sum(kd.LAUNCHES.values()) > before
    assert torch.equal(direct[0], through_numba[0]) and torch.equal(direct[1], through_numba[1])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_a_direct_cuda_launch_marshals_arguments_as_numbas_dispatcher_does():
    """On a GPU: `_direct_params` of tensors (contiguous, transposed, 1-D integer, offset into
    storage), numbers, a bool and a host-mapped array equals numba's own marshalling of the same
    arguments (``_Kernel._prepare_args``), value for value."""
    from layoutwarp.kernels import device as kd

    if not lw.kernels.cuda_available("float32"):
        pytest.skip("numba's CUDA target does not run here")
    base = torch.rand(7, 5, device="cuda", dtype=torch.float64)
    mapped = kd.host_mapped(3, torch.device("cuda"))
    args = (torch.rand(4, 6, device="cuda"), base.t(), torch.arange(9, device="cuda"), base[2:], 3, 0.25,
            True, mapped)  # fmt: skip
    kd.cuda_launch(_eight_arguments, 1, 0, *args)
    dispatcher = kd._CUDA_KERNELS[_eight_arguments]
    arrays = [kd._device_array(a) for a in args]
    kernel = dispatcher.overloads[tuple(dispatcher.typeof_pyval(a) for a in arrays)]
    theirs: list = []
    for t, v in zip(kernel.argument_types, arrays, strict=True):
        kernel._prepare_args(t, v, 0, [], theirs)
    ours = kd._direct_params(args)
    value = lambda v: getattr(v, "value", v)  # noqa: E731
    assert [value(v) for v in ours] == [value(v) for v in theirs]
    torch.cuda.synchronize()
    assert float(args[0][0, 0]) == 3.25 and int(mapped[0]) == 1


cuda = None  # numba.cuda, bound by the first launch (layoutwarp.kernels.cuda_launch)


def _eight_arguments(a, b, c, d, n, x, flag, status):
    """A kernel of the argument kinds layoutwarp's kernels take (see the test above)."""
    if cuda.grid(1) == 0:
        a[0, 0] = n + x + b[0, 0] * 0 + c[0] * 0 + d[0, 0] * 0
        if flag:
            status[0] = 1
