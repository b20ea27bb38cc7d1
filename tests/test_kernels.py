"""The compiled kernels against the torch reference: values and θ-gradients to 1e-12 (float64)
and 1e-6 (float32) on random layouts, sizes and the hard cases; gradcheck on the kernel."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from conftest import grad_tol, ptx_or_skip, rand_theta, run_in_simulator

import layoutwarp as lw
from layoutwarp import kernels

F64 = torch.float64
pytestmark = pytest.mark.skipif(not kernels.available(), reason="numba is not installed")


def rint(gen, lo, hi):
    return int(torch.randint(lo, hi + 1, (1,), generator=gen))


def both(img, layout, size, theta=None, weights=None, **kw):
    """Values, and θ-gradients of Σ weights · values, from both backends."""
    out = []
    for backend in ("numba", "torch"):
        th = (layout.theta.detach() if theta is None else theta).clone().requires_grad_(True)
        val = lw.integrators.integrate_exact(img, layout, size, theta=th, backend=backend, **kw)
        w = torch.ones_like(val) if weights is None else weights
        (g,) = torch.autograd.grad((val * w).sum(), th)
        out.append((val.detach(), g))
    return out


def random_case(family: str, gen: torch.Generator) -> tuple:
    """A random float64 image (1-4 channels, 5-90 px a side, values in [-3, 7)), a layout of
    ``family`` with θ in ±0.95, a sensor size (1-24 a side) and loss weights."""
    src = (rint(gen, 5, 90), rint(gen, 5, 90))
    size = (rint(gen, 1, 24), rint(gen, 1, 24))
    layout = lw.make_layout(family, rand_theta(gen, 0.95), dtype=F64)
    img = torch.rand(rint(gen, 1, 4), *src, generator=gen, dtype=F64) * 10 - 3
    return img, layout, size, torch.randn(img.shape[0], *size, generator=gen, dtype=F64)


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_values_and_gradients_match_the_reference_in_float64(family, gen):
    for _ in range(4):
        img, layout, size, w = random_case(family, gen)
        (va, ga), (vb, gb) = both(img, layout, size, weights=w, tol=1e-6)
        assert float((va - vb).abs().max()) <= 1e-12 * float(vb.abs().max())
        assert float((ga - gb).abs().max()) <= grad_tol(layout, gb)


def test_float32_matches_the_reference(gen):
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    img = torch.rand(3, 300, 257, generator=gen) + 1000  # a large offset: prefix sums must stay local
    a = lw.integrators.integrate_exact(img, layout, (31, 29), tol=1e-4, backend="numba")
    b = lw.integrators.integrate_exact(img, layout, (31, 29), tol=1e-4, backend="torch")
    assert float((a - b).abs().max()) <= 1e-6 * float(b.abs().max())


@pytest.mark.parametrize(
    ("theta", "size", "src"),
    [
        ((0.0, 0.0), (4, 4), (28, 28)),  # every edge on a source cell boundary
        ((0.3, -0.5), (1, 1), (9, 13)),
        ((0.3, -0.5), (1, 17), (9, 13)),
        ((0.7, 0.2), (60, 70), (20, 30)),  # pixels smaller than source cells
        ((-0.4, 0.6), (3, 5), (1, 1)),  # one source pixel
    ],
)
def test_hard_cases_match_the_reference(theta, size, src, gen):
    layout = lw.CurvLayout(theta, dtype=F64)
    img = torch.rand(2, *src, generator=gen, dtype=F64)
    (va, ga), (vb, gb) = both(img, layout, size, tol=1e-5)
    assert torch.isfinite(va).all() and torch.isfinite(ga).all()
    assert float((va - vb).abs().max()) <= 1e-12
    assert float((ga - gb).abs().max()) <= 1e-12 * max(float(gb.abs().max()), 1.0)


def test_extreme_theta_matches_the_reference_to_its_rounding(gen):
    # At θ = ±(1 − e), e = 1e-6, pixels are ~e wide and ∂φ/∂θ carries 1/D² with D down to e:
    # values divide Green's sum (terms up to W_src · max|L| along the perimeter) by tiny areas;
    # bound them by that scale. The θ-gradient is conditioned like 1/e²: a one-ulp move of θ
    # moves either backend's gradient by up to 12 % of max|g| (seed 1094171718), and over 200
    # seeds the backends differed by up to 114 eps/e² of max|g| (a fixed 64 eps/e² failed for
    # that seed), yet never by more than 0.93 of the sum of both backends' largest one-ulp moves
    # (median 0.13). So the bound is four such moves: the backends agree as far as the
    # gradient is defined at all; a wrong term in either would not hide under it.
    e = 1e-6
    layout = lw.CurvLayout((1 - e, -(1 - e)), dtype=F64)
    size, src = (7, 9), (40, 50)
    img = torch.rand(2, *src, generator=gen, dtype=F64)
    (va, ga), (vb, gb) = both(img, layout, size, tol=1e-5)
    assert torch.isfinite(va).all() and torch.isfinite(ga).all()
    mesh = lw.pixel_mesh(layout, size, tol=1e-5)
    v = mesh.pixel_vertices(src)
    edge_len = mesh.sum_over_edges((v[mesh.seg_end] - v[mesh.seg_start]).norm(dim=-1))
    perimeter = edge_len[torch.from_numpy(mesh.topology.pixel_edges())].sum(-1)
    value_scale = float((src[1] * perimeter / mesh.areas(v).abs()).max())  # Σ|terms| / area
    assert float((va - vb).abs().max()) <= 1e-15 * value_scale
    eps = torch.finfo(F64).eps
    moves = [both(img, layout, size, theta=layout.theta.detach() * (1 + k * eps), tol=1e-5) for k in (-1, 1)]
    moved = sum(max(float((m[b][1] - g).abs().max()) for m in moves) for b, g in ((0, ga), (1, gb)))
    assert float((ga - gb).abs().max()) <= 4 * moved


def test_a_segment_across_a_column_line_by_a_few_ulps_integrates_as_one_on_it(gen):
    # ΔX of a few ulps across a column line makes X → t ill-conditioned: column ranges taken from
    # the rounded X ends of a row piece lost 2 % of a segment's ΔY (seed 3834281190); its ∫ P dY
    # must equal, to rounding, the vertical segment's on the line: Σ_rows ΔY_r · Σ_{c < line} L
    hs, ws, n = 24, 20, 60
    img = torch.rand(2, hs, ws, generator=gen, dtype=F64)
    line = torch.randint(1, ws, (n,), generator=gen).to(F64)
    ulp = torch.finfo(F64).eps * 16
    ya, yb = (torch.rand(2, n, generator=gen, dtype=F64) * hs).unbind()
    xa = line + torch.randint(-3, 4, (n,), generator=gen) * ulp
    xb = line - torch.randint(-16, 17, (n,), generator=gen) * ulp
    verts = torch.stack([torch.stack([xa, ya], 1), torch.stack([xb, yb], 1)], 1).reshape(-1, 2)
    ss, se, eo = np.arange(0, 2 * n, 2), np.arange(1, 2 * n, 2), np.arange(n + 1)
    tables = kernels.prefix_tables(img.numpy(), kernels.BLOCK)
    got = kernels.exact_forward(verts.numpy(), ss, se, eo, *tables, kernels.BLOCK, 1)
    rows = torch.arange(hs, dtype=F64)
    ylo, yhi = torch.minimum(ya, yb), torch.maximum(ya, yb)
    dy = (torch.minimum(yhi[:, None], rows + 1) - torch.maximum(ylo[:, None], rows)).clamp_min(0)
    dy = dy * torch.sign(yb - ya)[:, None]  # (n, hs)
    left = torch.cumsum(img, -1)  # Σ_{c ≤ j} L[r, c]
    p = left[:, :, line.long() - 1].permute(0, 2, 1)  # (2, n, hs): Σ_{c < line}
    ref = (dy[None] * p).sum(-1).numpy()
    np.testing.assert_allclose(got[:2], ref, rtol=0, atol=1e-11)


def test_gradcheck_on_the_kernel(gen):
    layout = lw.CurvLayout(dtype=F64)
    img = torch.rand(2, 13, 17, generator=gen, dtype=F64)
    size = (4, 5)

    def f(t):  # fixed subdivision: the adaptive count changes with θ, finite differences must not
        mesh = lw.pixel_mesh(layout, size, subdivisions=4, theta=t)
        return lw.integrators.integrate_exact(img, layout, size, mesh=mesh, backend="numba")

    theta = rand_theta(gen, 0.8).requires_grad_(True)
    assert torch.autograd.gradcheck(f, (theta,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_auto_uses_the_reference_for_image_gradients(gen):
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    img = torch.rand(1, 20, 30, generator=gen, dtype=F64, requires_grad=True)
    out = lw.integrators.integrate_exact(img, layout, (4, 5))
    (g,) = torch.autograd.grad(out.sum(), img)
    assert torch.allclose(g.sum(), torch.tensor(20.0, dtype=F64))  # each pixel's weights sum to 1
    with pytest.raises(ValueError, match="backend='numba' needs"):
        lw.integrators.integrate_exact(img, layout, (4, 5), backend="numba")


def test_concurrent_calls_from_threads(gen):
    import threading

    layout = lw.CurvLayout(rand_theta(gen), learn=True)
    img = torch.rand(3, 120, 150, generator=gen)
    expected = lw.integrators.integrate_exact(img, layout, (12, 15), tol=1e-4).detach()
    results, errors = [], []

    def work():
        try:
            for _ in range(5):
                out = lw.integrators.integrate_exact(img, layout, (12, 15), tol=1e-4)
                out.sum().backward()
                results.append(out.detach())
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=work) for _ in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len(results) == 20 and all(torch.equal(r, expected) for r in results)


def test_bands_of_any_height_give_the_same_sums(gen):
    """A large image is integrated in bands of rows (one band's prefix table at a time);
    segments crossing bands are split between them: every band height must give the sums of
    the whole-table kernel."""
    import numpy as np

    src = (rint(gen, 20, 70), rint(gen, 20, 70))
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    img = (torch.rand(2, *src, generator=gen, dtype=F64) * 10 - 3).numpy()
    mesh = lw.pixel_mesh(layout, (rint(gen, 2, 12), rint(gen, 2, 12)), tol=1e-5, dtype=F64)
    tensors = (mesh.pixel_vertices(src).double(), mesh.seg_start, mesh.seg_end, mesh.edge_offsets)
    arrays = [np.ascontiguousarray(t.numpy()) for t in tensors]
    one = kernels.exact_forward(*arrays, *kernels.prefix_tables(img, kernels.BLOCK), kernels.BLOCK, 2)
    for band in (1, 2, rint(gen, 3, src[0] - 1), src[0]):
        seg_edge = mesh.seg_edge.numpy()
        out = kernels.exact_forward_banded(*arrays, seg_edge, img, kernels.BLOCK, band, kernels.threads())
        assert np.abs(out - one).max() <= 1e-13 * np.abs(one).max()
    assert kernels.band_rows(np.zeros((3, 1024, 2048), np.float32), 2) == 42  # a 1 MiB table
    assert kernels.band_rows(np.zeros((1, 5, 10**7), np.float64), 2) == 1
    assert kernels.band_rows(np.zeros((64, 28, 28), np.float32), 2) == 4  # 7 bands for 2 threads


def test_the_banded_path_matches_the_reference(gen, monkeypatch):
    """Images above ``WHOLE_TABLE_BYTES`` take the banded forward (and the backward builds its
    own table): values and θ-gradients as the reference's, forced here on small images."""
    monkeypatch.setattr(kernels, "WHOLE_TABLE_BYTES", 0)
    for _ in range(3):
        src = (rint(gen, 20, 90), rint(gen, 5, 90))
        size = (rint(gen, 1, 16), rint(gen, 1, 16))
        layout = lw.CurvLayout(rand_theta(gen, 0.95), dtype=F64)
        img = torch.rand(rint(gen, 1, 3), *src, generator=gen, dtype=F64) * 10 - 3
        w = torch.randn(img.shape[0], *size, generator=gen, dtype=F64)
        (va, ga), (vb, gb) = both(img, layout, size, weights=w, tol=1e-6)
        assert float((va - vb).abs().max()) <= 1e-12 * float(vb.abs().max())
        assert float((ga - gb).abs().max()) <= grad_tol(layout, gb)


# ----------------------------------------------------------------------------------------
# CUDA: the same kernels on the GPU against the torch reference on the CPU
# ----------------------------------------------------------------------------------------
#: Runs in a process of its own: numba's CUDA simulator, with the device functions as plain Python;
#: one case a file, each case's results to its own file.
SIMULATED = """
import sys
import numpy as np
from layoutwarp import kernels
for path in sys.argv[1:]:
    case = dict(np.load(path))
    img, verts, ss, se = case["img"], case["verts"], case["ss"], case["se"]
    sedge, eo, grad = case["sedge"], case["eo"], case["grad"]
    n, h, w = img.shape
    assert kernels.cuda_available(str(img.dtype))  # the smoke test, through the simulator
    incl = np.full((h, w, n), np.nan, dtype=img.dtype)
    offsets = np.full((h, (w + kernels.BLOCK - 1) // kernels.BLOCK, n), np.nan)
    kernels.cuda_launch("prefix_blocks", h * offsets.shape[1] * n, 0, img, kernels.BLOCK, incl)
    kernels.cuda_launch("prefix_offsets", h * n, 0, kernels.BLOCK, incl, offsets)
    per_seg, out = np.zeros((ss.size, n + 1)), np.zeros((n + 1, eo.size - 1))  # added to, as on the GPU
    kernels.cuda_launch("forward", ss.size, 0, verts, ss, se, incl, offsets, kernels.BLOCK, per_seg)
    kernels.cuda_launch("edge_sums", eo.size - 1, 0, per_seg, eo, out)
    wa, wb = np.zeros(ss.size), np.zeros(ss.size)
    kernels.cuda_launch("backward", ss.size, 0, verts, ss, se, sedge, incl, kernels.BLOCK, grad, wa, wb)
    np.savez(path.replace("case", "sim"), incl=incl, offsets=offsets, out=out, wa=wa, wb=wb)
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
def test_the_cuda_kernels_run_as_the_cpu_kernels_in_numbas_simulator(gen, tmp_path):
    """Without a GPU: the CUDA kernels' sources and launches (one thread per item, the grid
    guards, the prefix tables' and the edge sums' indexing) in numba's CUDA simulator against
    the compiled CPU kernels, on the same mesh and image: segments on cell lines (θ = 0, flat
    and vertical), random curved layouts in both dtypes, and pixels narrower than source cells."""

    cases = [
        ("rect", (0.0, 0.0), (4, 4), (28, 28), np.float64),  # segments on cell lines, flat and vertical
        ("curv", None, None, None, np.float64),
        ("curv", None, None, None, np.float32),
        ("curv", (0.7, 0.2), (12, 5), (5, 40), np.float64),  # pixels narrower than source cells
    ]
    refs = {}
    for i, (family, theta, size, src, dtype) in enumerate(cases):
        theta = rand_theta(gen, 0.95) if theta is None else theta
        size = size or (rint(gen, 1, 8), rint(gen, 1, 8))
        src = src or (rint(gen, 5, 60), rint(gen, 5, 60))
        img = (torch.rand(rint(gen, 1, 3), *src, generator=gen, dtype=F64) * 10 - 3).numpy().astype(dtype)
        # 1e-3: a thousand segments or so, each a Python thread in the simulator
        mesh = lw.pixel_mesh(lw.make_layout(family, theta, dtype=F64), size, tol=1e-3, dtype=F64)
        arrays = (mesh.pixel_vertices(src), mesh.seg_start, mesh.seg_end, mesh.seg_edge, mesh.edge_offsets)
        verts, ss, se, sedge, eo = (np.ascontiguousarray(t.detach().numpy()) for t in arrays)
        grad = torch.randn(img.shape[0] + 1, eo.size - 1, generator=gen, dtype=F64).numpy()
        np.savez(tmp_path / f"case{i}.npz", img=img, verts=verts, ss=ss, se=se, sedge=sedge, eo=eo, grad=grad)
        incl, offsets = kernels.prefix_tables(img, kernels.BLOCK)
        out = kernels.exact_forward(verts, ss, se, eo, incl, offsets, kernels.BLOCK, 1)
        wa, wb = kernels.exact_backward(verts, ss, se, sedge, incl, kernels.BLOCK, grad, 1)
        expected = {"incl": incl, "offsets": offsets, "out": out, "wa": wa, "wb": wb}
        refs[i] = (f"{family} θ={theta} {size} from {src} {np.dtype(dtype)}", dtype, expected)
    run_in_simulator(SIMULATED, *(tmp_path / f"case{i}.npz" for i in refs))
    for i, (name, dtype, expected) in refs.items():
        sim = np.load(tmp_path / f"sim{i}.npz")
        # float32 tables: plain Python and numba round a float32 sum's intermediate steps differently
        rel = 1e-13 if dtype == np.float64 else 1e-6
        for key, ref in expected.items():
            got = sim[key]
            assert got.shape == ref.shape and np.isfinite(got).all(), (name, key)
            assert np.abs(got - ref).max() <= rel * max(np.abs(ref).max(), 1.0), (name, key)


@pytest.mark.slow  # a minute of PTX compiling: the samplers are large
def test_the_measurement_and_product_kernels_compile_for_the_device_without_one():
    """The CUDA kernels of the measurement and of the fixed-layout product (with the measurement
    fused) compile to PTX, the samplers' rounding (``np.floor``, ``np.rint``, which numba-cuda
    types but has no loop for until layoutwarp adds it) as the device's instructions."""
    from layoutwarp.kernels import noise, runs

    for table in (noise.CUDA_KERNELS, runs.CUDA_KERNELS):
        for name, (fn, signature) in table.items():
            ptx = ptx_or_skip(fn, signature=signature)
            assert ".entry" in ptx and "cvt.rmi" in ptx and "cvt.rni" in ptx, name


CUDA_KERNEL_NAMES = ("prefix_blocks", "prefix_offsets", "forward", "edge_sums", "backward")


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_every_cuda_kernel_compiles_for_the_device_without_one(dtype):
    """The CUDA kernels, with every shared per-segment function they call, compile to PTX for
    compute capability 8.0, for images of either dtype: what a GPU's first call would do, caught
    on any machine with numba-cuda and the CUDA compilers, GPU or not."""
    for name in CUDA_KERNEL_NAMES:
        ptx = ptx_or_skip(name, dtype)
        assert ".target sm_80" in ptx and ".entry" in ptx, name
        if name == "prefix_blocks":  # the image's dtype reaches the device code
            assert (".f32" in ptx) == (dtype == "float32"), name
    with pytest.raises(ValueError, match="kernel must be one of"):
        kernels.cuda_ptx("nonsense", dtype)


def cuda_kernels_or_skip(dtype: str = "float64") -> None:
    if not torch.cuda.is_available():
        pytest.skip("no CUDA GPU here")
    if not kernels.cuda_available(dtype):
        pytest.skip("numba's CUDA target does not run here (the torch path serves CUDA; see the warning)")


def on_cuda(img, layout, size, theta, weights, **kw):
    """Values and θ-gradients of Σ weights · values from the CUDA kernels, back on the CPU."""
    th = theta.cuda().requires_grad_(True)
    val = lw.integrators.integrate_exact(img.cuda(), layout.to("cuda"), size, theta=th, backend="numba", **kw)
    (g,) = torch.autograd.grad((val * weights.cuda()).sum(), th)
    return val.detach().cpu(), g.cpu()


def on_cpu_reference(img, layout, size, theta, weights, **kw):
    th = theta.clone().requires_grad_(True)
    val = lw.integrators.integrate_exact(img, layout.to("cpu"), size, theta=th, backend="torch", **kw)
    (g,) = torch.autograd.grad((val * weights).sum(), th)
    return val.detach(), g


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_cuda_kernels_match_the_reference_in_float64(family, gen):
    cuda_kernels_or_skip()
    for _ in range(4):
        img, layout, size, w = random_case(family, gen)
        theta = layout.theta.detach()
        va, ga = on_cuda(img, layout, size, theta, w, tol=1e-6)
        vb, gb = on_cpu_reference(img, layout, size, theta, w, tol=1e-6)
        assert float((va - vb).abs().max()) <= 1e-12 * float(vb.abs().max())
        assert float((ga - gb).abs().max()) <= grad_tol(layout, gb)


@pytest.mark.parametrize(
    ("theta", "size", "src"),
    [((0.0, 0.0), (4, 4), (28, 28)), ((0.3, -0.5), (1, 17), (9, 13)), ((0.7, 0.2), (60, 70), (20, 30))],
)
def test_cuda_kernels_match_the_reference_on_hard_cases(theta, size, src, gen):
    cuda_kernels_or_skip()
    layout = lw.CurvLayout(theta, dtype=F64)
    img = torch.rand(2, *src, generator=gen, dtype=F64)
    w = torch.randn(2, *size, generator=gen, dtype=F64)
    th = layout.theta.detach()
    va, ga = on_cuda(img, layout, size, th, w, tol=1e-5)
    vb, gb = on_cpu_reference(img, layout, size, th, w, tol=1e-5)
    assert float((va - vb).abs().max()) <= 1e-12
    assert float((ga - gb).abs().max()) <= 1e-12 * max(float(gb.abs().max()), 1.0)


def test_cuda_kernels_match_the_reference_in_float32(gen):
    cuda_kernels_or_skip("float32")
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    img = torch.rand(3, 300, 257, generator=gen) + 1000  # prefix sums must stay local
    a = lw.integrators.integrate_exact(
        img.cuda(), layout.to("cuda"), (31, 29), tol=1e-4, backend="numba"
    ).cpu()
    b = lw.integrators.integrate_exact(img, layout.to("cpu"), (31, 29), tol=1e-4, backend="torch")
    assert float((a - b).abs().max()) <= 1e-6 * float(b.abs().max())


def test_gradcheck_on_the_cuda_kernels(gen):
    cuda_kernels_or_skip()
    layout = lw.CurvLayout(dtype=F64).to("cuda")
    img = torch.rand(2, 13, 17, generator=gen, dtype=F64).cuda()

    def f(t):
        mesh = lw.pixel_mesh(layout, (4, 5), subdivisions=4, theta=t)
        return lw.integrators.integrate_exact(img, layout, (4, 5), mesh=mesh, backend="numba")

    theta = rand_theta(gen, 0.8).cuda().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (theta,), eps=1e-6, atol=1e-5, rtol=1e-4)


def test_a_failing_cuda_target_warns_once_and_leaves_the_torch_path(monkeypatch):
    numba_cuda = pytest.importorskip("numba.cuda")

    def broken(*args):
        raise RuntimeError("no kernel image is available")

    monkeypatch.setattr(kernels.device, "_CUDA_OK", {})
    monkeypatch.setattr(kernels.device, "cuda_launch", broken)
    monkeypatch.setattr(numba_cuda, "is_available", lambda: True)
    with pytest.warns(RuntimeWarning, match="CUDA kernels do not run here.*torch path on CUDA"):
        assert not kernels.cuda_available("float32")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # answered from the first check: no second warning
        assert not kernels.cuda_available("float32")


@pytest.mark.skipif(not kernels.available(), reason="needs numba")
def test_kernel_threads_follow_torchs_count_and_numbas_threading_layer_never_starts():
    from numba.np.ufunc import parallel as numba_parallel

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(1)  # e.g. OMP_NUM_THREADS=1 for jobs that share the cores
        assert kernels.threads() == 1
        torch.set_num_threads(3)
        assert kernels.threads() == 3 and kernels.threads(kernels.base.SMALL_WORK - 1) == 1
        seen: list[str] = []
        kernels.run_shares(lambda t, nt, out: out.append(f"{t}/{nt}"), 3, seen)
        assert sorted(seen) == ["0/3", "1/3", "2/3"]
        layout = lw.CurvLayout((0.3, -0.2), learn=True)  # a learnable step and a fixed forward
        lw.simulate(torch.rand(1, 3, 64, 64), layout, (7, 9)).sum().backward()
        lw.simulate(torch.rand(1, 3, 64, 64), lw.CurvLayout((0.3, -0.2)), (7, 9))
        assert not numba_parallel._is_initialized  # numba's own OpenMP pool never starts
    finally:
        torch.set_num_threads(before)


def _teams() -> list[str]:
    """The teams [`run_shares`][] can run on here: torch's OpenMP threads where its runtime is GNU
    OpenMP's, and a pool of Python threads."""
    try:
        kernels.base.set_team("openmp")
    except ValueError:
        return ["python"]
    finally:
        kernels.base.set_team(None)
    return ["openmp", "python"]


@pytest.mark.parametrize("team", _teams())
def test_shares_run_at_once_on_either_team_share_0_on_the_caller_and_errors_reach_it(team):
    """Every share runs once, all at once (each waits for the others at a barrier), share 0 on the
    calling thread; an error in a share is raised on the calling thread; a learnable step's values
    and θ-gradient (its kernels on two threads) are the same bit for bit on either team."""
    import threading

    def step() -> tuple[torch.Tensor, torch.Tensor]:
        layout = lw.CurvLayout((0.3, -0.2), learn=True)
        img = torch.rand(1, 3, 512, 1024, generator=torch.Generator().manual_seed(0))
        out = lw.simulate(img, layout, (33, 65))
        (g,) = torch.autograd.grad((out * torch.linspace(-1, 1, out.numel()).view_as(out)).sum(), layout.rho)
        return out.detach(), g

    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        reference = step()  # the default team
        kernels.base.set_team(team)
        seen: list[tuple[int, int, int]] = []
        barrier = threading.Barrier(3, timeout=30)

        def share(t: int, nt: int) -> int:
            barrier.wait()  # all three at once, or a BrokenBarrierError
            seen.append((t, nt, threading.get_ident()))
            return 10 * t

        assert kernels.run_shares(share, 3) == [0, 10, 20]
        assert sorted(s[:2] for s in seen) == [(0, 3), (1, 3), (2, 3)]
        assert len({s[2] for s in seen}) == 3 and (0, 3, threading.get_ident()) in seen

        def fails(t: int, nt: int) -> None:
            if t == 2:
                raise KeyError(f"share {t} of {nt}")

        with pytest.raises(KeyError, match="share 2 of 3"):
            kernels.run_shares(fails, 3)
        got = step()
        assert torch.equal(got[0], reference[0]) and torch.equal(got[1], reference[1])
    finally:
        kernels.base.set_team(None)
        torch.set_num_threads(before)


def test_the_team_comes_from_layoutwarp_team_and_a_bad_name_is_refused_in_one_line(monkeypatch):
    """``LAYOUTWARP_TEAM=python`` runs the shares on the pool of Python threads (``layoutwarp
    doctor`` says so); a name that is neither ``openmp`` nor ``python`` is refused, naming the
    variable, at the first kernel."""
    import threading

    base = kernels.base
    try:
        monkeypatch.setenv(base.TEAM_ENV, "python")
        base.set_team(None)
        names = base.run_shares(lambda t, nt: threading.current_thread().name, 2)
        assert names[0] == threading.current_thread().name and names[1].startswith("layoutwarp")
        assert base.team_name() == "python" and " threads, Python ones;" in lw.doctor.cpu_backend()
        monkeypatch.setenv(base.TEAM_ENV, "bogus")
        base.set_team(None)
        with pytest.raises(ValueError, match=r"^LAYOUTWARP_TEAM must be 'openmp' or 'python', got 'bogus'$"):
            base.run_shares(lambda t, nt: t, 2)
        with pytest.raises(ValueError, match=r"^set_team: name must be 'openmp' or 'python', got 'gpu'$"):
            base.set_team("gpu")
    finally:
        base.set_team(None)


def test_a_busy_machine_runs_the_default_team_on_python_threads_and_a_chosen_one_as_chosen(monkeypatch):
    """While the machine is busy, the default team's shares run on the Python threads (which
    sleep rather than spin while they wait); a team chosen by name runs as chosen."""
    import threading

    base = kernels.base
    monkeypatch.delenv(base.TEAM_ENV, raising=False)
    monkeypatch.setattr(base, "machine_busy", lambda: True)
    name = lambda t, nt: threading.current_thread().name  # noqa: E731
    try:
        base.set_team(None)
        assert base.run_shares(name, 2)[1].startswith("layoutwarp")
        if "openmp" in _teams():
            base.set_team("openmp")
            assert not base.run_shares(name, 2)[1].startswith("layoutwarp")
    finally:
        base.set_team(None)


@pytest.mark.skipif(not hasattr(__import__("signal"), "SIGINT"), reason="needs SIGINT")
def test_ctrl_c_during_the_shares_raises_and_never_returns_a_share_left_unrun():
    """SIGINT at random moments while shares run on torch's OpenMP threads (the main thread runs
    share 0 in a ctypes callback, whose entry may take the signal and drop it): every call either
    returns every share's result or raises ``KeyboardInterrupt``; none returns with a share that
    never ran, and ctypes reports none of them (2 s of calls in a process of its own)."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import os, random, signal, threading, time, numba, torch
        from layoutwarp.kernels import base
        torch.set_num_threads(2)

        @numba.njit(nogil=True)
        def body(t, nt, n):
            s = 0.0
            for i in range(n):
                s += i * 1e-12
            return t + 1 + 0 * s

        body(0, 1, 1)
        # Ctrl-C as a terminal's shell gives it, whatever the test's own process passed on (a
        # child inherits an ignored or blocked SIGINT: twice a test run saw no interrupt at all)
        signal.signal(signal.SIGINT, signal.default_int_handler)
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
        import faulthandler, sys
        faulthandler.dump_traceback_later(90, exit=True)  # a hang: every thread's stack, then out
        go, done = threading.Event(), threading.Event()

        def interrupt():
            go.wait()  # not before the calls: a SIGINT in Thread.start ended the child (load)
            while not done.is_set():
                time.sleep(random.uniform(0.0005, 0.005))
                os.kill(os.getpid(), signal.SIGINT)

        interrupter = threading.Thread(target=interrupt, daemon=True)
        interrupter.start()
        wrong = raised = calls = 0
        start = time.time()
        go.set()
        while True:
            try:
                try:
                    now = time.time() - start  # a second on each team: the Python threads' pool
                    if now >= 2:  # holds the signals while its locks are held (one left held hung
                        break  # the process at its exit)
                    base.set_team("python" if now >= 1 else None)
                    calls += 1
                    wrong += base.run_shares(body, 2, 20000) != [1, 2]
                except KeyboardInterrupt:
                    raised += 1
            except KeyboardInterrupt:  # in the loop's own lines, between calls (a loaded machine)
                pass
        while interrupter.is_alive():  # no more signals once it is gone
            try:
                done.set()
                interrupter.join()
            except KeyboardInterrupt:
                pass
        for _ in range(3):
            try:
                time.sleep(0.05)
            except KeyboardInterrupt:
                pass
        print(calls, raised, wrong)
        sys.stdout.flush()
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr[-3000:]
    calls, raised, wrong = map(int, res.stdout.split())
    assert wrong == 0 and raised > 10 and calls > raised, res.stderr
    assert "Exception ignored" not in res.stderr  # a plain KeyboardInterrupt, no report of ctypes'


@pytest.mark.skipif(not hasattr(__import__("os"), "fork"), reason="needs fork")
def test_a_child_forked_after_the_openmp_team_ran_runs_its_shares_on_threads_of_its_own():
    """GNU OpenMP's threads are not a forked child's: after the parent's kernels ran on torch's
    team, a child forked from it runs its shares on Python threads and gives the parent's values
    (a team there would wait for ever; the child is given 60 s). The child runs torch on one
    thread, as a DataLoader worker does (torch's own ops on two would wait for ever there)."""
    import subprocess
    import sys
    import textwrap

    code = textwrap.dedent("""
        import os, sys, torch, layoutwarp as lw
        torch.set_num_threads(2)
        img = torch.rand(1, 3, 512, 1024, generator=torch.Generator().manual_seed(0))
        want = lw.simulate(img, lw.CurvLayout((0.3, -0.2)), (33, 65))
        assert lw.kernels.run_shares(lambda t, nt: t, 2) == [0, 1]
        pid = os.fork()
        if pid == 0:
            torch.set_num_threads(1)
            ok = lw.kernels.run_shares(lambda t, nt: t, 2) == [0, 1]
            tol = lw.data_tolerance(torch.float32)[0]
            kept = lw.resampler.resampler_for(lw.CurvLayout((0.3, -0.2)), (33, 65), (512, 1024), tol, "cpu")
            runs = kept.runs
            x = img.reshape(3, -1).numpy()
            out = torch.empty(3, 33 * 65).numpy()
            lw.kernels.runs_apply(runs.arrays(), x, out, 2)  # the product's chunks on two threads
            again = lw.simulate(img, lw.CurvLayout((0.3, -0.2)), (33, 65))
            same = torch.equal(torch.from_numpy(out).view(1, 3, 33, 65), want) and torch.equal(again, want)
            os._exit(0 if ok and same else 1)
        _, status = os.waitpid(pid, 0)
        print(os.waitstatus_to_exitcode(status))
    """)
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.split() == ["0"]


def _random_curved(rng: np.random.Generator, limit: float) -> lw.Layout:
    """A curv, fovea or elliptic layout of mixed-sign θ, ``|θ|`` in ``[0.1, limit]``."""
    th = (float(rng.uniform(0.1, limit)), -float(rng.uniform(0.1, limit)))
    return [lw.CurvLayout(th), lw.FoveaLayout(th, center=(0.2, -0.1)), lw.EllipticLayout(th)][rng.integers(3)]


def _random_runs(gen: torch.Generator) -> tuple:
    """The float64 area weights, and their `Runs`, of a random curved layout of mixed-sign θ, at a
    random sensor size over a random source (a pixel spans 1.5 to 8 source cells a side)."""
    from layoutwarp.kernels.runs import Runs
    from layoutwarp.mesh import pixel_mesh
    from layoutwarp.weights import area_weights

    rng = np.random.default_rng(int(torch.randint(0, 2**31, (), generator=gen)))
    layout = _random_curved(rng, 0.6)
    size = (int(rng.integers(3, 12)), int(rng.integers(3, 12)))
    src = tuple(int(n * rng.uniform(1.5, 8)) for n in size)
    mesh = pixel_mesh(layout, size, tol=1e-4, dtype=torch.float64)
    area = mesh.areas(mesh.pixel_vertices(src)).flatten().numpy()
    w = area_weights(layout, size, src, tol=1e-4, mesh=mesh)
    return w, Runs.of(w, area, src[1])


def _walk_and_reference(layout: lw.Layout, size: tuple, src: tuple) -> tuple:
    """A layout's runs built by the compiled walk (`kernels.build_runs`, a function of the thread
    count) and by numpy's matrix (`area_weights`, then `Runs.of`), from one float64 mesh."""
    from layoutwarp.kernels.runs import Runs
    from layoutwarp.mesh import pixel_mesh
    from layoutwarp.weights import area_weights

    mesh = pixel_mesh(layout, size, tol=1e-4, dtype=torch.float64)
    verts = mesh.pixel_vertices(src)
    area = mesh.areas(verts).flatten().numpy()
    cells = mesh.areas().flatten().numpy() * (src[0] * src[1] / 4)
    parts = [t.numpy() for t in (verts, mesh.seg_start, mesh.seg_end, mesh.edge_offsets)]

    def walk(threads: int) -> Runs:
        return kernels.build_runs(*parts, size, src, area, cells, threads)

    return walk, Runs.of(area_weights(layout, size, src, tol=1e-4, mesh=mesh), cells, src[1])


@pytest.mark.parametrize(
    ("family", "theta", "size", "src"),
    [
        ("random", None, None, None),
        ("random", None, None, None),
        ("rect", (0.0, 0.0), (4, 4), (28, 28)),  # every edge on a cell line: no cut cell at all
        ("rect", (0.3, -0.5), (5, 7), (33, 41)),
        ("curv", (0.7, 0.2), (24, 30), (8, 12)),  # pixels smaller than source cells
        ("curv", (0.97, -0.96), (9, 8), (70, 64)),  # near the bound: thin, strongly curved pixels
        ("curv", (0.4, -0.3), (1, 1), (37, 45)),  # one pixel: the whole image
        ("elliptic", (0.5, -0.6), (11, 13), (90, 100)),
    ],
)
def test_the_compiled_build_gives_the_runs_of_the_area_weights(family, theta, size, src, gen):
    """The runs the compiled walk builds pixel by pixel equal those numpy's matrix gives: the same
    runs, heads, tails and whole cells, and every cut weight within a float32 rounding (the two
    sum a row's steps in another order); on 1 and 3 threads, bit for bit."""
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (), generator=gen)))
    if family == "random":
        layout = _random_curved(rng, 0.8)
        size = (int(rng.integers(2, 14)), int(rng.integers(2, 14)))
        src = tuple(int(n * rng.uniform(0.6, 9)) + 1 for n in size)
    else:
        layout = lw.make_layout(family, theta)
    walk, ref = _walk_and_reference(layout, size, src)
    built = walk(2)
    for name in ("pix_runs", "run_start", "run_len", "run_head", "run_tail", "inv_area", "pix_cuts"):
        a, b = getattr(built, name), getattr(ref, name)
        assert a.dtype == b.dtype and np.array_equal(a, b), name
    assert built.shape == ref.shape and built.cut_weight.dtype == np.float32
    assert np.abs(built.cut_weight - ref.cut_weight).max(initial=0) <= 2**-23 * np.abs(ref.cut_weight).max(
        initial=0
    )
    one, three = walk(1), walk(3)
    assert all(np.array_equal(a, b) for a, b in zip(one.arrays(), three.arrays(), strict=True))


@pytest.mark.parametrize("family", ["curv", "fovea", "elliptic"])
def test_a_resampler_builds_its_runs_compiled_or_with_numpy_alike(family, gen, monkeypatch):
    """`AreaResampler` builds its runs by the compiled walk where the fixed kernels run, and from
    numpy's matrix where they do not (``LAYOUTWARP_JIT=off``): the same runs, and products equal
    to float32 rounding; on the compiled mesh (a sensor of `COMPILED_MESH_PIXELS` or more), the
    same products too."""
    import layoutwarp.weights as weights
    from layoutwarp.resampler import AreaResampler

    th = rand_theta(gen, 0.8)
    layout = lw.FoveaLayout(th, center=(0.2, -0.1)) if family == "fovea" else lw.make_layout(family, th)
    size, src = (13, 17), (96, 120)
    with lw.jit.use_mode("wait"), monkeypatch.context() as torch_mesh:
        torch_mesh.setattr(weights, "mesh_spec", lambda layout: None)  # torch's mesh, as "off" takes
        built = AreaResampler(layout, size, src)
    with lw.jit.use_mode("wait"):
        meshes, build_mesh = [], weights.build_mesh
        monkeypatch.setattr(weights, "COMPILED_MESH_PIXELS", 0)
        monkeypatch.setattr(weights, "build_mesh", lambda *a, **k: meshes.append(a) or build_mesh(*a, **k))
        on_compiled_mesh = AreaResampler(layout, size, src)
        assert len(meshes) == 1 and meshes[0][1] == size
    with lw.jit.use_mode("off"):
        ref = AreaResampler(layout, size, src)
    for a, b in zip(built.runs.arrays()[:-1], ref.runs.arrays()[:-1], strict=True):
        assert np.array_equal(a, b)
    x = torch.rand(3, *src, generator=gen)
    with lw.jit.use_mode("wait"):
        out, out_compiled = built.apply(x), on_compiled_mesh.apply(x)
    assert (out - ref.apply(x)).abs().max() <= 2e-7
    assert (out_compiled - out).abs().max() <= 2e-7
    assert torch.allclose(on_compiled_mesh.areas, built.areas, rtol=1e-13, atol=0)


def test_runs_hold_the_area_weights(gen):
    """A random curved layout's area weights held as runs give back the same matrix: every entry
    within a float32 rounding of the float64 weight, none lost or added."""
    w, runs = _random_runs(gen)
    back = runs.csr()
    assert back.shape == w.shape and back.nnz == w.nnz
    assert np.array_equal(back.indices, w.indices) and np.array_equal(back.indptr, w.indptr)
    assert np.abs(back.data - w.data).max() <= 2**-23 * np.abs(w.data).max()
    assert runs.run_head.min() >= 0 and runs.run_tail.min() >= 0
    assert (runs.run_head + runs.run_tail <= runs.run_len).all()


@pytest.mark.parametrize("planes", [1, 2, 3, 4, 5, 7, 8])
def test_the_runs_product_matches_scipy_for_any_plane_count(planes, gen):
    """The runs' product (planes in groups of three, and the one or two left) equals scipy's
    float64 product of the float64 weights to float32 rounding; NaN and ±inf are counted as the
    reference has them."""
    w, runs = _random_runs(gen)
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (), generator=gen)))
    x = rng.random((planes, w.shape[1]), dtype=np.float32)
    out = np.full((planes, w.shape[0]), np.nan, dtype=np.float32)
    assert kernels.runs_apply(runs.arrays(), x, out, 2) == 0  # every value written is finite
    ref = (w @ x.astype(np.float64).T).T
    assert np.abs(out - ref).max() <= 2e-7 * max(1.0, np.abs(ref).max())
    bad = rng.choice(x.size, size=int(rng.integers(1, 6)), replace=False)
    x.flat[bad] = rng.choice([np.nan, np.inf, -np.inf], size=bad.size)
    with np.errstate(invalid="ignore"):
        ref = (w @ x.astype(np.float64).T).T
    count = kernels.runs_apply(runs.arrays(), x, out, 1)
    assert count == int((~np.isfinite(ref)).sum())
    assert np.array_equal(np.isfinite(out), np.isfinite(ref))


@pytest.mark.parametrize("threads", [2, 3, 5])
def test_the_runs_product_is_the_same_on_any_number_of_threads_and_when_one_does_all(threads, gen):
    """The product's chunks shared among 2, 3 or 5 threads give the one-thread values bit for bit
    and its exact count of non-finite values; and a single thread of a pair that the other never
    joins (a thread the machine holds back) takes the other's chunks too: every value written."""
    from layoutwarp.kernels.runs import CHUNKS, _runs_share

    w, runs = _random_runs(gen)
    rng = np.random.default_rng(int(torch.randint(0, 2**31, (), generator=gen)))
    x = rng.random((4, w.shape[1]), dtype=np.float32)
    x.flat[rng.choice(x.size, size=3, replace=False)] = np.nan
    one, many = (np.full((4, w.shape[0]), -1.0, np.float32) for _ in range(2))
    count = kernels.runs_apply(runs.arrays(), x, one, 1)
    assert count == int((~np.isfinite(one)).sum()) > 0
    assert kernels.runs_apply(runs.arrays(), x, many, threads) == count
    assert np.array_equal(many, one, equal_nan=True)
    alone, claims = np.full_like(one, -1.0), np.zeros(CHUNKS * 2, np.uint8)
    bad = np.zeros(CHUNKS * 2, np.int64)
    _runs_share(0, 2, claims, bad, *runs.arrays(), x, alone)  # thread 1 never runs
    assert claims.all() and bad.sum() == count
    assert np.array_equal(alone, one, equal_nan=True)


def test_runs_split_where_a_row_of_a_pixel_leaves_it_and_comes_back():
    """A pixel's row of cells cut, whole, cut, whole, cut (a boundary crossing it and back), a gap,
    and a row wholly cut: runs whose heads and tails are the cut cells, the whole cells between
    them scaled once, and the product equal to the matrix's."""
    import scipy.sparse

    from layoutwarp.kernels.runs import Runs

    area = np.array([4.0, 2.0])
    whole = 1 / area
    #  pixel 0, source row 0 (width 10): cut, whole, cut, whole, cut | gap | whole whole; row 1: cut cut
    cells = [[0, 1, 2, 3, 4, 6, 7, 10, 11], [12, 13]]
    values = [[0.05, whole[0], 0.1, whole[0], 0.02, whole[0], whole[0], 0.03, 0.04], [0.2, 0.3]]
    w = scipy.sparse.csr_matrix((np.concatenate(values), np.concatenate(cells), [0, 9, 11]), shape=(2, 20))
    runs = Runs.of(w, area, 10)
    assert runs.run_start.tolist() == [0, 3, 6, 10, 12]
    assert runs.run_len.tolist() == [3, 2, 2, 2, 2]
    assert runs.run_head.tolist() == [1, 0, 0, 2, 2] and runs.run_tail.tolist() == [1, 1, 0, 0, 0]
    x = np.random.default_rng(0).random((2, 20), dtype=np.float32)
    out = np.empty((2, 2), np.float32)
    kernels.runs_apply(runs.arrays(), x, out, 1)
    assert np.allclose(out, (w @ x.astype(np.float64).T).T, rtol=1e-6)
    assert (abs(runs.csr() - w.astype(np.float32)) > 1e-7).nnz == 0


@pytest.mark.parametrize(
    ("family", "theta", "size", "src"),
    [
        ("rect", (0.0, 0.0), (4, 4), (28, 28)),  # every edge on a cell line, flat and vertical
        ("rect", None, None, None),
        ("curv", None, None, None),
        ("curv", (0.7, 0.2), (24, 30), (8, 12)),  # pixels smaller than source cells
    ],
)
def test_the_forwards_moments_give_the_backwards_weights(family, theta, size, src, gen):
    """A training step's forward also gathers each segment's Reynolds moments
    (:func:`kernels.segment_moments`), and its backward contracts them with the gradient: the
    weights of the backward's own walk over the table, on segments inside cells, along row lines
    (flat) and along column lines (vertical); the forward's integrals are the plain forward's."""
    theta = rand_theta(gen, 0.95) if theta is None else theta
    size = size or (rint(gen, 2, 20), rint(gen, 2, 20))
    src = src or (rint(gen, 5, 90), rint(gen, 5, 90))
    img = (torch.rand(rint(gen, 1, 4), *src, generator=gen, dtype=F64) * 10 - 3).numpy()
    mesh = lw.pixel_mesh(lw.make_layout(family, theta, dtype=F64), size, tol=1e-6, dtype=F64)
    tensors = (mesh.pixel_vertices(src).double(), mesh.seg_start, mesh.seg_end, mesh.edge_offsets)
    verts, seg_start, seg_end, edge_offsets = [np.ascontiguousarray(t.numpy()) for t in tensors]
    seg_edge = np.ascontiguousarray(mesh.seg_edge.numpy())
    tables = kernels.prefix_tables(img, kernels.BLOCK)
    n = img.shape[0]
    grad = torch.randn(n + 1, edge_offsets.size - 1, generator=gen, dtype=F64).numpy()
    plain = kernels.exact_forward(verts, seg_start, seg_end, edge_offsets, *tables, kernels.BLOCK, 1)
    wa, wb = kernels.exact_backward(verts, seg_start, seg_end, seg_edge, tables[0], kernels.BLOCK, grad, 1)
    acc, ma, mb = np.empty((1, n + 1)), np.empty((1, n)), np.empty((1, n))
    out, ma_w, mb_w = np.zeros_like(plain), np.empty_like(wa), np.empty_like(wb)
    for s in range(seg_start.size):  # in each edge's segment order, as the forward sums them
        (x0, y0), (x1, y1) = verts[seg_start[s]], verts[seg_end[s]]
        kernels.segment_moments(x0, y0, x1, y1, *tables, kernels.BLOCK, acc, ma, mb)
        e = seg_edge[s]
        out[:, e] += acc[0]
        ma_w[s] = grad[n, e] / 2 + grad[:n, e] @ ma[0]
        mb_w[s] = grad[n, e] / 2 + grad[:n, e] @ mb[0]
    assert np.array_equal(out, plain)
    scale = max(np.abs(wa).max(), np.abs(wb).max())
    assert np.abs(ma_w - wa).max() <= 1e-13 * scale and np.abs(mb_w - wb).max() <= 1e-13 * scale
    if family == "rect" and size == (4, 4):  # the case is what it says: flat and on-line segments
        d = verts[seg_end] - verts[seg_start]
        assert (d[:, 1] == 0).any() and ((d[:, 0] == 0) & (verts[seg_start, 0] % 1 == 0)).any()


@pytest.mark.skipif(__import__("platform").libc_ver()[0] != "glibc", reason="glibc's mallopt")
def test_retained_memory_spares_the_page_faults_of_repeated_allocations():
    """In a process of its own: a training step's pattern (allocate and free arrays of some MB,
    again and again) faults in fresh pages every time by default, and hardly at all once the
    allocator keeps freed memory."""
    import subprocess
    import sys

    code = """
import resource, sys
import numpy as np
from layoutwarp import kernels
if sys.argv[1] == "1":
    assert kernels.retain_freed_memory()
def faults():
    return resource.getrusage(resource.RUSAGE_SELF).ru_minflt
def step():  # four arrays of 16 MiB written, then all freed
    arrays = [np.ones(2 << 20) for _ in range(4)]
    del arrays
for _ in range(3):
    step()
before = faults()
for _ in range(10):
    step()
print(faults() - before)
"""
    counts = [
        int(
            subprocess.run(
                [sys.executable, "-c", code, flag], capture_output=True, text=True, check=True
            ).stdout
        )
        for flag in ("0", "1")
    ]
    assert counts[0] > 10_000 and counts[1] < 200, counts  # by default the freed top is trimmed


@pytest.mark.parametrize("shape", [(1,), (3, 4), (2, 700), (0,)])
def test_each_threads_work_space_lies_a_page_from_every_other_and_from_the_heap(shape):
    """Work space written by several threads at once: thread t's rows, as its kernels take them
    (``own``), lie at least ``APART`` bytes from every other thread's and from the array's ends
    (its neighbours in the heap), and hold its shape."""
    from layoutwarp.kernels.base import APART, own, per_thread, serial

    @serial
    def fill(t: int, nt: int, rows: np.ndarray) -> None:
        mine = own(rows, t, nt)
        mine[...] = t + 1

    nt = 3
    rows = per_thread(nt, shape)
    rows[...] = np.nan
    kernels.run_shares(fill, nt, rows)  # the compiled own: each thread's rows, and only those
    mine = [own.py_func(rows, t, nt) for t in range(nt)]
    assert all((m == t + 1).all() for t, m in enumerate(mine))
    assert np.isnan(rows).sum() == rows.size - nt * math.prod(shape)
    starts = [m.ctypes.data - rows.ctypes.data for m in mine]
    assert all(m.shape == shape for m in mine)
    size = mine[0].nbytes
    if size == 0:
        return
    edges = [0, *[x for s in starts for x in (s, s + size)], rows.nbytes]
    gaps = [b - a for a, b in zip(edges[::2], edges[1::2], strict=True)]
    assert min(gaps) >= APART, gaps


def test_the_runs_build_resumes_where_a_threads_rows_ran_out_of_room(gen, monkeypatch):
    """`build_runs` writes each thread's runs into rows of its own, which it makes longer where a
    pixel might overflow them and goes on from that pixel: rows of one run to begin with (made
    longer many times, on two threads, in one block of pixels or in many) give the same runs, bit
    for bit, as the usual room."""
    from layoutwarp.kernels import weights as kw
    from layoutwarp.weights import fixed_runs

    layout = lw.CurvLayout(tuple(rand_theta(gen, 0.8)))
    usual = fixed_runs(layout, (9, 11), (70, 90), 1e-4)[0].arrays()
    grown: list[int] = []

    class OneRun(kw._Rows):
        def __init__(self, nt: int, runs: int) -> None:
            super().__init__(nt, 1)

        def grow(self, runs: int, cuts: int) -> None:
            grown.append(runs)
            super().grow(runs, cuts)

    monkeypatch.setattr(kw, "_Rows", OneRun)
    monkeypatch.setattr(kernels.base, "SMALL_WORK", 0)  # two shares however small
    before = torch.get_num_threads()
    torch.set_num_threads(2)
    try:
        tight = fixed_runs(layout, (9, 11), (70, 90), 1e-4)[0].arrays()
        monkeypatch.setattr(kw, "BLOCK_PIXELS", 22)  # and in blocks of two sensor rows
        blocks = fixed_runs(layout, (9, 11), (70, 90), 1e-4)[0].arrays()
    finally:
        torch.set_num_threads(before)
    assert len(grown) >= 5
    for got in (tight, blocks):
        assert all(a.dtype == b.dtype and np.array_equal(a, b) for a, b in zip(usual, got, strict=True))


def test_an_interrupt_ctypes_drops_is_raised_again_of_its_own_class():
    # the command line's SIGTERM is a KeyboardInterrupt subclass: dropped by ctypes at a share's
    # edge, it was reported as unraisable and raised again as a plain KeyboardInterrupt (status
    # 130, "interrupted"), or lost where it came at the share's exit
    from types import SimpleNamespace

    import numba

    from layoutwarp.cli import Terminated
    from layoutwarp.kernels import base

    told = []
    hook = base._unraisable(told.append)
    for kind in (Terminated, KeyboardInterrupt):
        hook(SimpleNamespace(exc_type=kind, object=base._run_job))
        assert base._DROPPED[0] is kind and told == []
    hook(SimpleNamespace(exc_type=ValueError, object=base._run_job))  # anything else: as before
    assert len(told) == 1
    base._DROPPED[0] = None
    team = base._openmp_team()
    if team is None:
        pytest.skip("no OpenMP team here")

    @numba.njit(nogil=True)
    def body(t, nt):
        return t + 1

    assert team(body, 2, ()) == [1, 2]
    base._DROPPED[0] = Terminated  # as the hook leaves it for the team on the main thread
    with pytest.raises(Terminated):
        team(body, 2, ())
    assert base._DROPPED[0] is None
