"""Pixel meshes: areas, tiling (shapely), subdivision where edges curve, tolerance, topology."""

from __future__ import annotations

import copy
import warnings

import numpy as np
import pytest
import shapely
import torch
from conftest import rand_theta

import layoutwarp as lw
from layoutwarp.mesh import polygon_area, segment_area, smooth_pieces
from layoutwarp.topology import MeshTopology

F64 = torch.float64
# sizes that break the reference code's arange(-1, 1, 2/n) (n + 1 cells), odd and even, 1xN
SIZES = [(1, 1), (1, 9), (9, 1), (49, 98), (98, 49), (7, 196), (196, 3), (4, 4), (5, 3)]


def layouts(gen):
    return [
        lw.UniformLayout(dtype=F64),
        lw.RectLayout(rand_theta(gen), dtype=F64),
        lw.CurvLayout(rand_theta(gen), dtype=F64),
    ]


@pytest.mark.parametrize("size", SIZES)
def test_mesh_areas_sum_to_sensor_area(size, gen):
    for layout in layouts(gen):
        mesh = lw.pixel_mesh(layout, size, tol=1e-4)
        areas = mesh.areas()
        assert areas.shape == size
        assert abs(float(areas.sum()) - 4) < 1e-12
        assert bool((areas > 0).all())
        assert mesh.corners.shape == (size[0] + 1, size[1] + 1, 2)


@pytest.mark.parametrize("size", [(6, 9), (1, 5), (49, 3)])
def test_mesh_polygons_tile_the_sensor(size, gen):
    for layout in layouts(gen):
        mesh = lw.pixel_mesh(layout, size, tol=1e-3)
        polys = [shapely.Polygon(p) for p in mesh.polygons()]
        assert len(polys) == size[0] * size[1]
        assert all(p.is_valid for p in polys)
        areas = np.array([p.area for p in polys]).reshape(size)
        assert np.abs(areas - mesh.areas().detach().numpy()).max() < 1e-14
        union = shapely.union_all(polys)
        assert abs(union.area - 4) < 1e-10  # no gaps ...
        assert abs(areas.sum() - union.area) < 1e-10  # ... and no overlaps
        # polygons are positively oriented in (x, y)
        assert all(shapely.is_ccw(p.exterior) for p in polys)


def test_straight_edges_are_never_subdivided(gen):
    for layout in (lw.UniformLayout(), lw.RectLayout(rand_theta(gen, 0.99))):
        mesh = lw.pixel_mesh(layout, (20, 30), tol=1e-9)
        assert int(mesh.subdivisions().max()) == 1


def test_curved_edges_subdivide_only_where_curved(gen):
    layout = lw.CurvLayout((0.7, -0.6), dtype=F64)
    mesh = lw.pixel_mesh(layout, (24, 24), tol=1e-5)
    n = mesh.subdivisions()
    assert int(n.max()) > 1
    # edges entirely outside the unit circle are straight: one segment
    h = w = 24
    c = lw.coords.uniform_corners((h, w))
    mids = torch.cat([((c[:, :-1] + c[:, 1:]) / 2).reshape(-1, 2), ((c[:-1] + c[1:]) / 2).reshape(-1, 2)])
    ends_a = torch.cat([c[:, :-1].reshape(-1, 2), c[:-1].reshape(-1, 2)])
    ends_b = torch.cat([c[:, 1:].reshape(-1, 2), c[1:].reshape(-1, 2)])
    outside = (ends_a.norm(dim=-1) >= 1) & (ends_b.norm(dim=-1) >= 1) & (mids.norm(dim=-1) >= 1)
    assert int(n[outside].max()) == 1
    # looser tolerance, fewer segments
    assert lw.pixel_mesh(layout, (24, 24), tol=1e-3).num_segments < mesh.num_segments


@pytest.mark.parametrize("tol", [1e-3, 1e-4, 1e-5])
def test_subdivision_meets_value_tolerance(tol, gen):
    # The polyline error of every pixel value must stay within tol · (value range).
    layout = lw.CurvLayout(rand_theta(gen, 0.9), dtype=F64)
    size = (9, 13)
    img = torch.rand(1, 64, 96, generator=gen, dtype=F64)
    fine = lw.integrators.integrate_exact(
        img, layout, size, mesh=lw.pixel_mesh(layout, size, subdivisions=4096)
    )
    got = lw.integrators.integrate_exact(img, layout, size, tol=tol)
    assert float((got - fine).abs().max()) <= tol * float(img.max() - img.min())


# θ near ±1 puts nearly all of an edge's bend into its last thousandth, where it meets the unit
# circle (curv) or the sensor's border (elliptic); five equal samples a piece missed it there
# (41-123x tol on these cases, 4x already at ±0.9)
HARD = [
    (lw.EllipticLayout, (0.97, 0.97)),
    (lw.EllipticLayout, (0.3, 0.97)),
    (lw.EllipticLayout, (0.8924, -0.97)),
    (lw.CurvLayout, (-0.97, -0.97)),
    (lw.CurvLayout, (0.97, 0.8924)),
]


@pytest.mark.parametrize("learn", [False, True])
@pytest.mark.parametrize(("family", "theta"), HARD)
def test_the_tolerance_holds_where_phi_bends_hardest(family, theta, learn):
    # every pixel's area within tol of polylines of 4096 segments a piece (values follow: a
    # pixel's mean moves by at most its area's error times the value range, over its area)
    layout = family(theta, learn=learn, dtype=F64)
    for size in [(2, 3), (3, 3), (4, 5)]:
        ref = lw.pixel_mesh(layout, size, subdivisions=4096).areas().detach()
        for tol in (1e-3, 1e-4):
            got = lw.pixel_mesh(layout, size, tol=tol, cache=False).areas().detach()
            assert float(((got - ref).abs() / ref).max()) <= tol, (size, tol)


def _fine_means(fixed: lw.Layout, img: torch.Tensor, size: tuple[int, int], pieces: int, theta: torch.Tensor):
    """The means of ``img`` over ``fixed``'s pixels at ``theta`` on polylines of ``pieces``
    segments a smooth piece (smooth in θ: the reference for central differences)."""
    mesh = lw.pixel_mesh(fixed, size, subdivisions=pieces, theta=theta)
    return lw.integrators.integrate_exact(img, fixed, size, mesh=mesh).flatten()


def _fine_jacobian(fixed: lw.Layout, img: torch.Tensor, size: tuple[int, int], pieces: int) -> torch.Tensor:
    """``d mean / dθ`` ``(pixels, 2)`` by central differences (step 1e-6) of `_fine_means`."""
    th0, h = fixed.theta.detach(), 1e-6

    def at(th: torch.Tensor) -> torch.Tensor:
        return _fine_means(fixed, img, size, pieces, th)

    return torch.stack([at(th0 + h * e) - at(th0 - h * e) for e in torch.eye(2, dtype=F64)], 1) / (2 * h)


def _jacobian(out: torch.Tensor, theta: torch.Tensor) -> torch.Tensor:
    """``d out / dθ`` ``(pixels, P)`` of flat means ``out`` by autograd."""
    return torch.stack([torch.autograd.grad(v, theta, retain_graph=True)[0] for v in out])


@pytest.mark.parametrize(
    ("family", "theta", "size"),
    [
        (lw.EllipticLayout, (0.9, -0.9), (5, 7)),
        (lw.CurvLayout, (0.9, -0.9), (5, 7)),
        (lw.CurvLayout, (0.95, -0.3), (7, 1)),
    ],
)
def test_theta_gradients_meet_the_tolerance_where_phi_bends_hardest(family, theta, size, gen):
    # every pixel's dmean/dθ within tol · (value range) of central differences on polylines of
    # 4096 segments a piece (the learnable count bounds the polylines' error in ∂φ/∂θ too)
    img = torch.rand(1, 24, 24, generator=gen, dtype=F64)
    fixed, layout = family(theta, dtype=F64), family(theta, learn=True, dtype=F64)
    ref = _fine_jacobian(fixed, img, size, 4096)
    tol = 1e-3
    theta_t = layout.theta  # one tensor: each read of layout.theta is a new one
    out = lw.integrators.integrate_exact(img, layout, size, tol=tol, theta=theta_t).flatten()
    assert float((_jacobian(out, theta_t) - ref).abs().max()) <= tol * float(img.max() - img.min())


@pytest.mark.parametrize(
    ("theta", "size", "column", "tol"),
    [((0.9634, -0.9729), (1, 6), 6, 1e-4), ((0.9114, 0.9307), (1, 13), 17, 2.0**-12)],
)
def test_theta_gradients_of_strips_whose_pieces_need_more_than_4096_segments(theta, size, column, tol):
    # a learnable elliptic strip near θ = ±1: the bound on ∂φ/∂θ asks up to about 13 000
    # segments of a piece (with 4096 the gradient erred by 8x and 2.5x tol: MAX_SUBDIV)
    img = torch.zeros(1, 24, 24, dtype=F64)
    img[..., column:] = 1.0  # a step: its edge crossed by the strip's boundaries
    fixed, layout = lw.EllipticLayout(theta, dtype=F64), lw.EllipticLayout(theta, learn=True, dtype=F64)
    ref = _fine_jacobian(fixed, img, size, 16384)
    theta_t = layout.theta
    mesh = lw.pixel_mesh(layout, size, tol=tol, theta=theta_t)
    capped = lw.pixel_mesh(layout, size, tol=tol, theta=theta_t, max_subdiv=4096)
    assert capped.num_segments < mesh.num_segments  # the old cap bound here
    out = lw.integrators.integrate_exact(img, layout, size, mesh=mesh).flatten()
    assert float((_jacobian(out, theta_t) - ref).abs().max()) <= tol


def test_a_piece_that_reaches_the_segment_cap_is_reported():
    # an elliptic strip near θ = ±1 at a fine tol asks for more segments of a piece than the cap
    layout = lw.EllipticLayout((0.97, 0.97), dtype=F64)
    with pytest.warns(RuntimeWarning, match="reached max_subdiv=256 segments"):
        lw.pixel_mesh(layout, (1, 6), tol=1e-4, max_subdiv=256, cache=False)
    if lw.kernels.available():  # the compiled count stage alike
        spec, th = lw.kernels.mesh.mesh_spec(layout), layout.theta.detach().numpy()
        with pytest.warns(RuntimeWarning, match="reached max_subdiv=256 segments"):
            lw.kernels.mesh.build_mesh(spec, (1, 6), th, 1e-4, max_subdiv=256)
    with warnings.catch_warnings():  # a usual layout at the default cap: nothing to say
        warnings.simplefilter("error")
        lw.pixel_mesh(lw.CurvLayout((0.3, -0.24), dtype=F64), (16, 32), tol=2.0**-12, cache=False)
        lw.pixel_mesh(layout, (1, 6), tol=1e-3, cache=False)


@pytest.mark.slow  # a fine reference's central differences: some seconds
@pytest.mark.xfail(
    strict=True,
    reason="known: the count stage bounds the area between polyline and curve (the values' error), "
    "not the shift of every cell line the boundary crosses, which the θ-gradient of a box image "
    "weighs: on this checkerboard of source pixels the gradient errs by 3.8x tol (1.5-2.6x at "
    "tol 1e-2 to 1e-6 on a coarser one)",
)
def test_theta_gradients_of_a_checkerboard_meet_the_tolerance():
    # every cell line a sensor pixel's edge crosses is a jump of the whole value range, so the
    # polyline's offset from the curve moves the gradient at each crossing (the values hold tol)
    theta, size, (hs, ws), tol = (0.7628, 0.7435), (8, 6), (128, 192), 1e-3
    yy, xx = torch.meshgrid(torch.arange(hs), torch.arange(ws), indexing="ij")
    img = ((yy + xx) % 2).to(F64)[None]
    fixed, layout = lw.CurvLayout(theta, dtype=F64), lw.CurvLayout(theta, learn=True, dtype=F64)
    ref = _fine_jacobian(fixed, img, size, 8192)
    theta_t = layout.theta
    out = lw.integrators.integrate_exact(img, layout, size, tol=tol, theta=theta_t).flatten()
    values = _fine_means(fixed, img, size, 8192, fixed.theta.detach())
    assert float((out.detach() - values).abs().max()) <= tol  # the values hold it
    assert float((_jacobian(out, theta_t) - ref).abs().max()) <= tol


STRIPS = [
    (lw.CurvLayout, (-0.2, 0.8), (1, 3)),
    (lw.EllipticLayout, (0.0, 0.8), (1, 3)),
    (lw.CurvLayout, (0.97, 0.25), (3, 1)),
    (lw.CurvLayout, (0.95, -0.3), (7, 1)),
    # a bend at the strip's centre, between the quarters of a piece (1.5x and 1.6x tol sampled
    # at quarters only)
    (lw.EllipticLayout, (-0.985, -0.9765), (1, 11)),
    (lw.CurvLayout, (-0.9826, -0.9547), (19, 1)),
    # long strips near θ = -0.96 (1.07x and 1.23x tol with the samples' area but quarters only)
    (lw.CurvLayout, (-0.96194, -0.93776), (1, 13)),
    (lw.CurvLayout, (-0.95965, -0.95853), (1, 17)),
]


@pytest.mark.parametrize(("family", "theta", "size"), STRIPS)
def test_the_tolerance_holds_on_a_strip_of_pixels(family, theta, size):
    # long edges across the whole sensor that turn as they go, their bend at one end: across
    # the chord of a piece that turns, its bend was underrated (9.5x tol at 3x1, 12.5x for the
    # elliptic one with five equal samples)
    layout = family(theta, dtype=F64)
    ref = lw.pixel_mesh(layout, size, subdivisions=16384).areas()
    for tol in (1e-2, 1e-3, 1e-4):
        got = lw.pixel_mesh(layout, size, tol=tol, cache=False).areas()
        assert float(((got - ref).abs() / ref).max()) <= tol, tol


@pytest.mark.parametrize(("theta", "size"), [((-0.97, 0.5), (7, 1)), ((-0.97, -0.97), (1, 3))])
def test_the_tolerance_holds_where_a_pixel_bends_far_inside_its_corners(theta, size):
    # elliptic strips at θ near -1 whose pixels keep 0.44x and 0.086x of their corner quads'
    # areas: the budget tol·A takes A from the pixel's sampled polygon too (with the quad's A
    # alone these erred by 1.8x and 1.5x tol), in torch and in the compiled count stage alike
    layout = lw.EllipticLayout(theta, dtype=F64)
    ref = lw.pixel_mesh(layout, size, subdivisions=16384).areas()
    for tol in (1e-2, 1e-3):
        mesh = lw.pixel_mesh(layout, size, tol=tol, cache=False)
        assert float(((mesh.areas() - ref).abs() / ref).max()) <= tol, tol
        if lw.kernels.available():
            spec, th = lw.kernels.mesh.mesh_spec(layout), layout.theta.detach().numpy()
            compiled = lw.kernels.mesh.build_mesh(spec, size, th, tol, with_grad=False)
            assert np.array_equal(compiled.edge_offsets, mesh.edge_offsets.numpy()), tol


def test_the_tolerance_holds_on_random_elliptic_strips_near_the_bounds(gen):
    # strips of 2-9 pixels at θ in [-0.97, -0.88]² (with the quad's area alone 7 of 200 such
    # meshes erred, by up to 1.12x tol: this test failed in about half its seeds)
    for _ in range(12):
        theta = -(torch.rand(2, generator=gen, dtype=F64) * 0.09 + 0.88)
        k = int(torch.randint(2, 10, (), generator=gen))
        size = (k, 1) if bool(torch.rand((), generator=gen) < 0.5) else (1, k)
        layout = lw.EllipticLayout(theta.tolist(), dtype=F64)
        ref = lw.pixel_mesh(layout, size, subdivisions=8192).areas()
        for tol in (1e-2, 1e-3):
            got = lw.pixel_mesh(layout, size, tol=tol, cache=False).areas()
            assert float(((got - ref).abs() / ref).max()) <= tol, (theta.tolist(), size, tol)


@pytest.mark.parametrize("family", ["curv", "elliptic", "fovea"])
def test_the_tolerance_holds_on_random_strips_up_to_099(family, gen):
    # strips of 1-20 pixels at |θ| in [0.95, 0.99], either sign: a sweep beside STRIPS (sampled
    # at the quarters of a piece only, 4 of 240 such meshes erred, by up to 1.65x tol; the 24
    # here catch that in some seeds, STRIPS's four in every one)
    for _ in range(8):
        sign = torch.randint(0, 2, (2,), generator=gen) * 2 - 1
        theta = (torch.rand(2, generator=gen, dtype=F64) * 0.04 + 0.95) * sign
        k = int(torch.randint(1, 21, (), generator=gen))
        size = (k, 1) if bool(torch.rand((), generator=gen) < 0.5) else (1, k)
        layout = lw.make_layout(family, theta.tolist(), dtype=F64)
        ref = lw.pixel_mesh(layout, size, subdivisions=8192).areas()
        for tol in (1e-2, 1e-3):
            got = lw.pixel_mesh(layout, size, tol=tol, cache=False).areas()
            assert float(((got - ref).abs() / ref).max()) <= tol, (theta.tolist(), size, tol)


class TestTopology:
    @pytest.mark.parametrize("size", [(1, 1), (2, 3), (5, 4)])
    def test_every_interior_edge_is_shared_with_opposite_signs(self, size):
        topo = MeshTopology(size)
        h, w = size
        pix = topo.edge_pixels()
        assert pix.shape == (topo.num_edges, 2) and topo.num_edges == (h + 1) * w + h * (w + 1)
        # each pixel appears in exactly 4 edges: twice with +, twice with −
        plus = np.bincount(pix[:, 0][pix[:, 0] >= 0], minlength=h * w)
        minus = np.bincount(pix[:, 1][pix[:, 1] >= 0], minlength=h * w)
        assert (plus == 2).all() and (minus == 2).all()
        border = (pix < 0).any(1).sum()
        assert border == 2 * (h + w)
        edges = topo.pixel_edges()
        for i in range(h):
            for j in range(w):
                top, right, bottom, left = edges[i, j]
                assert pix[top, 0] == pix[right, 0] == pix[bottom, 1] == pix[left, 1] == i * w + j

    def test_combine_matches_pixel_edges(self, gen):
        topo = MeshTopology((3, 4))
        vals = torch.randn(topo.num_edges, generator=gen, dtype=F64)
        e = torch.from_numpy(topo.pixel_edges())
        expected = vals[e[..., 0]] + vals[e[..., 1]] - vals[e[..., 2]] - vals[e[..., 3]]
        assert torch.allclose(topo.combine(vals), expected, rtol=0, atol=1e-15)

    def test_edge_ends_follow_the_numbering(self):
        topo = MeshTopology((2, 3))
        a, b = topo.edge_ends()
        corners = lw.coords.uniform_corners((2, 3))
        assert torch.equal(a[topo.horizontal(1, 2)], corners[1, 2]) and torch.equal(
            b[topo.horizontal(1, 2)], corners[1, 3]
        )
        assert torch.equal(a[topo.vertical(1, 3)], corners[1, 3]) and torch.equal(
            b[topo.vertical(1, 3)], corners[2, 3]
        )


def test_polygon_area_against_shapely(gen):
    for _ in range(20):
        n = int(torch.randint(5, 13, (1,), generator=gen))
        # jittered, evenly spaced angles: every gap < π, so the polygon is simple (star-shaped)
        ang = (torch.arange(n, dtype=F64) + 0.9 * torch.rand(n, generator=gen, dtype=F64)) * (2 * np.pi / n)
        rad = 0.5 + torch.rand(n, generator=gen, dtype=F64)
        poly = torch.stack([rad * ang.cos(), rad * ang.sin()], -1)  # star-shaped, counter-clockwise in (x, y)
        ref = shapely.Polygon(poly.numpy()).area
        assert abs(float(polygon_area(poly)) - ref) < 1e-12
        assert abs(float(polygon_area(poly.numpy())) - ref) < 1e-12  # numpy too
        assert abs(float(segment_area(poly, poly.roll(-1, 0)).sum()) - ref) < 1e-12


def test_smooth_pieces_cut_at_the_unit_circle(gen):
    a = torch.tensor([[-1.0, 0.3], [-1.0, 0.9], [0.2, 0.1]], dtype=F64)
    b = torch.tensor([[1.0, 0.3], [1.0, 0.9], [0.3, 0.1]], dtype=F64)
    edge, t0, t1 = smooth_pieces(lw.CurvLayout(rand_theta(gen), dtype=F64), a, b)
    assert edge.tolist() == [0, 0, 0, 1, 1, 1, 2]  # two chords cross the circle twice, a segment inside never
    crossing = a[edge[1:3]] + t0[1:3, None] * (b - a)[edge[1:3]]
    assert torch.allclose(crossing.norm(dim=-1), torch.ones(2, dtype=F64), atol=1e-14)
    u = a[1] + t0[4] * (b[1] - a[1])
    assert abs(float(u.norm()) - 1) < 1e-14
    # pieces of an edge are consecutive and cover [0, 1]
    for e in range(3):
        sel = edge == e
        assert float(t0[sel][0]) == 0 and float(t1[sel][-1]) == 1 and torch.equal(t0[sel][1:], t1[sel][:-1])


def test_meshes_of_fixed_layouts_are_cached_and_learnable_ones_never(gen):
    from layoutwarp.mesh import MESHES

    MESHES.clear()
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    mesh = lw.pixel_mesh(layout, (5, 6), tol=1e-4)
    assert lw.pixel_mesh(layout, (5, 6), tol=1e-4) is mesh  # same θ: built once
    assert lw.pixel_mesh(copy.deepcopy(layout), (5, 6), tol=1e-4) is mesh  # equal θ, another object
    assert lw.pixel_mesh(layout, (5, 6), tol=1e-3) is not mesh
    layout.set_theta(-layout.theta)
    moved = lw.pixel_mesh(layout, (5, 6), tol=1e-4)
    assert moved is not mesh and not torch.equal(moved.vertices, mesh.vertices)
    learn = lw.CurvLayout(rand_theta(gen), dtype=F64, learn=True)
    first = lw.pixel_mesh(learn, (5, 6), tol=1e-4)
    assert first.vertices.requires_grad and lw.pixel_mesh(learn, (5, 6), tol=1e-4) is not first
    theta = rand_theta(gen, 0.5)  # unregistered families are never cached, even at equal θ
    assert lw.pixel_mesh(Cubic(theta, dtype=F64), (5, 6)) is not lw.pixel_mesh(
        Cubic(theta, dtype=F64), (5, 6)
    )
    registered = lw.CurvLayout(theta, dtype=F64)  # while a registered family at that θ is
    assert lw.pixel_mesh(registered, (5, 6)) is lw.pixel_mesh(lw.CurvLayout(theta, dtype=F64), (5, 6))
    # cache=False: a mesh it builds is not kept, a kept one is still returned
    unkept = lw.pixel_mesh(registered, (5, 7), cache=False)
    assert lw.pixel_mesh(registered, (5, 7), cache=False) is not unkept
    kept = lw.pixel_mesh(registered, (5, 7))
    assert kept is not unkept and torch.equal(kept.vertices, unkept.vertices)
    assert lw.pixel_mesh(registered, (5, 7), cache=False) is kept


def test_an_area_resampler_keeps_no_mesh_and_its_areas_are_the_meshes(gen):
    from layoutwarp.mesh import MESHES
    from layoutwarp.weights import area_weights

    MESHES.clear()
    layout = lw.CurvLayout(rand_theta(gen), dtype=F64)
    res = lw.AreaResampler(layout, (5, 6), (40, 50), tol=1e-4)
    mesh = lw.pixel_mesh(layout, (5, 6), tol=1e-4, dtype=F64, cache=False)
    assert lw.pixel_mesh(layout, (5, 6), tol=1e-4, dtype=F64, cache=False) is not mesh  # none kept
    # the polygons the weights are built on: torch's mesh, or the compiled one (the same polygons
    # to rounding) where this process has the mesh unit loaded
    assert torch.allclose(res.areas, mesh.areas(), rtol=1e-13, atol=0)
    ref = area_weights(layout, (5, 6), (40, 50), tol=1e-4, weights_dtype=np.float32, mesh=mesh)
    assert (abs(res.weights - ref)).max() <= 2**-23 * abs(ref).max()


class Cubic(lw.Layout):
    family = "cubic-test"

    def phi(self, p, theta):
        return p + theta.to(p.dtype) * p * (1 - p * p) / 2


class Swirl(lw.Layout):
    """A user layout that writes only φ (curved edges, θ-gradients by the autograd fallbacks):
    a rotation by ``θ (1 − ‖p‖²)²`` inside the unit disc."""

    family = "swirl-test"
    num_params = 1

    def phi(self, p, theta):
        a = theta.to(p.dtype) * (1 - (p * p).sum(-1, keepdim=True)).clamp(min=0) ** 2
        c, s = torch.cos(a), torch.sin(a)
        return torch.cat([c * p[..., :1] - s * p[..., 1:], s * p[..., :1] + c * p[..., 1:]], -1)


def test_learnable_user_layout_gets_accurate_theta_gradients(gen):
    # the adaptive mesh bounds ∂φ/∂θ through the generic autograd fallback, which must work
    # inside the mesh's gradient-free count stage
    theta = float(torch.rand((), generator=gen, dtype=F64)) * 1.6 - 0.8
    img = torch.rand(2, 40, 56, generator=gen, dtype=F64)
    layout = Swirl((theta,), dtype=F64, learn=True)
    th = torch.tensor([theta], dtype=F64, requires_grad=True)
    mesh = lw.pixel_mesh(layout, (5, 7), tol=1e-6, theta=th)
    assert mesh.num_segments > MeshTopology((5, 7)).num_edges  # it did subdivide
    (g,) = torch.autograd.grad(lw.integrators.integrate_exact(img, layout, (5, 7), mesh=mesh).sum(), th)
    h = 1e-6

    def value(t: float) -> float:
        fixed = Swirl((t,), dtype=F64)
        mesh = lw.pixel_mesh(fixed, (5, 7), subdivisions=600)  # smooth in θ, for differences
        return float(lw.integrators.integrate_exact(img, fixed, (5, 7), mesh=mesh).sum())

    fd = (value(theta + h) - value(theta - h)) / (2 * h)
    assert abs(float(g) - fd) <= 1e-4 * max(1.0, abs(fd))


def test_a_float32_mesh_whose_pixels_float32_cannot_hold_is_refused_in_one_line():
    """θ = (−0.999999, −0.999999) is a valid layout whose border pixels are narrower than float32
    resolves: its float32 mesh is refused in one line (it had pixels of negative area); its
    float64 mesh has every area positive, and the integrators (float64 meshes) run."""
    layout = lw.CurvLayout((-0.999999, -0.999999))
    with pytest.raises(ValueError, match="narrower than float32") as err:
        lw.pixel_mesh(layout, (16, 16))
    assert "\n" not in str(err.value)
    assert bool((lw.pixel_mesh(layout, (16, 16), dtype=torch.float64).areas() > 0).all())
    assert torch.isfinite(lw.simulate(torch.rand(1, 1, 64, 64), layout, (16, 16))).all()


def _graded_areas(layout, size):
    """Every pixel's area from its boundary sampled along φ: a 2000-step grid on each edge and
    3000 points graded geometrically from 1e-13 to each of its ends (where φ bends as θ nears ±1)."""
    h, w = size
    t = np.linspace(0, 1, 2001)
    t = torch.tensor(np.unique(np.r_[t, np.geomspace(1e-13, 0.5, 3000), 1 - np.geomspace(1e-13, 0.5, 3000)]))
    gx, gy = torch.linspace(-1, 1, w + 1, dtype=F64), torch.linspace(-1, 1, h + 1, dtype=F64)
    out = np.zeros((h, w))
    for i in range(h):
        for j in range(w):
            (x0, x1), (y0, y1) = gx[j : j + 2], gy[i : i + 2]
            sides = [((x0, y0), (x1, y0)), ((x1, y0), (x1, y1)), ((x1, y1), (x0, y1)), ((x0, y1), (x0, y0))]
            pts = torch.cat(
                [
                    torch.stack([a[0] + (b[0] - a[0]) * t[:-1], a[1] + (b[1] - a[1]) * t[:-1]], -1)
                    for a, b in sides
                ]
            )
            with torch.no_grad():
                out[i, j] = abs(float(polygon_area(layout.phi(pts, layout.theta_as(F64)))))
    return out


@pytest.mark.xfail(
    strict=True,
    reason="known: nearer the bound than ±0.99 a bend held by the last millionth of an edge is "
    "narrower than the count stage's samples, which miss it without a word (curv (0.999999, "
    "0.999999) on 1x5: one segment an edge, 3900x tol), or needs more equal steps than max_subdiv "
    "(elliptic (0.9999, 0.9999) on 6x6: 65x tol, with a warning); python examples/near_bound.py",
)
@pytest.mark.parametrize(
    ("family", "theta", "size"),
    [("curv", (0.999999, 0.999999), (5, 1)), ("elliptic", (0.9999, 0.9999), (6, 6))],
)
def test_pixel_areas_nearer_the_bound_than_099_hold_the_tolerance(family, theta, size):
    layout, tol = lw.make_layout(family, theta, dtype=F64), 2.0**-12
    ref = _graded_areas(layout, size)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # the cap's, where it binds
        areas = lw.pixel_mesh(layout, size, tol=tol, dtype=F64).areas().numpy()
    assert float((np.abs(areas - ref) / ref).max()) <= tol


@pytest.mark.parametrize(
    ("family", "theta", "size"), [("curv", (0.99, -0.99), (5, 1)), ("elliptic", (0.99, 0.99), (6, 6))]
)
def test_pixel_areas_at_099_hold_the_tolerance_against_graded_boundaries(family, theta, size):
    # the reference of the xfail above, where the count stage's samples resolve the bend
    layout, tol = lw.make_layout(family, theta, dtype=F64), 2.0**-12
    ref = _graded_areas(layout, size)
    areas = lw.pixel_mesh(layout, size, tol=tol, dtype=F64).areas().numpy()
    assert float((np.abs(areas - ref) / ref).max()) <= 0.5 * tol
