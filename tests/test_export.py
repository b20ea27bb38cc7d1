"""Fabrication masks read back with gdstk, ezdxf, an XML parser and OpenCV."""

from __future__ import annotations

import json
import re
import xml.etree.ElementTree as ET

import cv2
import numpy as np
import pytest
import shapely
import torch
from conftest import rand_theta

import layoutwarp as lw
from layoutwarp.cli import main
from layoutwarp.export import FORMATS, export_layout, pixel_polygons_um

SIZE = (9, 12)  # h, w
W_UM, H_UM = 1200.0, 900.0
UM = (H_UM, W_UM)  # the sensor extent in the order of size = (h, w)
XY = np.array([W_UM, H_UM])  # µm per unit of (x, y) / 2


def layout_of(family, gen):
    return lw.make_layout(family, None if family == "uniform" else rand_theta(gen, 0.8), dtype=torch.float64)


def read_back(path, fmt):
    """Polygons in image orientation (y down), µm, in file order."""
    if fmt == "gds":
        import gdstk

        lib = gdstk.read_gds(str(path))
        assert lib.unit == pytest.approx(1e-6) and lib.precision == pytest.approx(1e-9)
        polys = lib.cells[0].polygons
        assert {(p.layer, p.datatype) for p in polys} == {(3, 7)}
        return [np.stack([p.points[:, 0], H_UM - p.points[:, 1]], -1) for p in polys]
    if fmt == "dxf":
        import ezdxf

        doc = ezdxf.readfile(str(path))
        assert doc.header["$INSUNITS"] == 13  # micrometres
        ents = doc.modelspace().query("LWPOLYLINE")
        assert all(e.closed and e.dxf.layer == "PIXELS_3" for e in ents)
        return [np.array([(x, H_UM - y) for x, y in e.get_points("xy")]) for e in ents]
    root = ET.parse(path).getroot()
    assert root.get("width") == "1.2mm" and root.get("height") == "0.9mm"  # SVG/CSS units: 1:1
    assert root.get("viewBox") == "0 0 1200.0 900.0"  # user units: µm
    polys = root.iter("{http://www.w3.org/2000/svg}polygon")
    return [np.array([[float(v) for v in pt.split(",")] for pt in p.get("points").split()]) for p in polys]


def assert_tiles(polys, n):
    assert len(polys) == n
    shapes = [shapely.Polygon(p) for p in polys]
    assert all(s.is_valid for s in shapes)
    total = sum(s.area for s in shapes)
    union = shapely.union_all(shapes)
    sensor = W_UM * H_UM
    assert abs(total - sensor) < 1e-6 * sensor  # areas add up: no gap, no overlap ...
    assert abs(union.area - sensor) < 1e-6 * sensor  # ... and the union is the whole sensor
    assert union.geom_type == "Polygon" and len(union.interiors) == 0


@pytest.mark.parametrize("fmt", ["gds", "dxf", "svg"])
@pytest.mark.parametrize("family", ["rect", "curv"])
def test_vector_formats_read_back(fmt, family, gen, tmp_path):
    layout = layout_of(family, gen)
    path = tmp_path / f"mask.{fmt}"
    rep = export_layout(layout, SIZE, path, UM, layer=3, datatype=7, tol_um=0.05)
    polys = read_back(path, fmt)
    assert_tiles(polys, SIZE[0] * SIZE[1])
    # file order is row-major and matches the layout's pixels
    ref = lw.pixel_mesh(layout, SIZE, tol=1e-9).polygons()
    for k in (0, 17, len(ref) - 1):
        exact = shapely.Polygon((ref[k] + 1) / 2 * XY)
        assert shapely.Polygon(polys[k]).hausdorff_distance(exact) <= 0.05 + 1e-6
    assert rep.pixels == len(polys) and rep.max_deviation_um <= 0.05
    areas = [shapely.Polygon(p).area for p in polys]
    assert rep.min_area_um2 == pytest.approx(min(areas), rel=1e-12)
    assert rep.max_area_um2 == pytest.approx(max(areas), rel=1e-12)


@pytest.mark.slow
def test_tolerance_snapping_and_manhattan(gen):
    layout = layout_of("curv", gen)
    fine = lw.pixel_mesh(layout, SIZE, tol=1e-8).polygons()  # 6e-6 µm from the curves
    fine = [shapely.Polygon((p + 1) / 2 * XY) for p in fine]
    some = torch.randperm(len(fine), generator=gen)[: len(fine) // 4].tolist()  # a quarter: the
    # distances between outlines of thousands of vertices are most of the test's time

    def farthest(polys: list) -> float:
        return max(shapely.Polygon(polys[i]).hausdorff_distance(fine[i]) for i in some)

    for tol in (1.0, 0.01):
        polys, info = pixel_polygons_um(layout, SIZE, UM, tol_um=tol)
        assert info["max_deviation_um"] <= tol and len(polys) == len(fine)
        assert farthest(polys) <= tol * 1.01
    polys, info = pixel_polygons_um(layout, SIZE, UM, tol_um=0.5, manhattan=True)
    for p in polys:  # every edge axis-aligned
        d = np.diff(np.vstack([p, p[:1]]), axis=0)
        assert ((d[:, 0] == 0) | (d[:, 1] == 0)).all()
    # steep, thin pixels (θ near ±0.8) can give outlines that touch themselves (12 for seed
    # 1473107971, on v0.2 too): every invalid one is reported, and the areas still add up
    shapes = [shapely.Polygon(p) for p in polys]
    assert sum(not s.is_valid for s in shapes) <= info["self_touching"]
    assert abs(sum(s.area for s in shapes) - W_UM * H_UM) < 1e-6
    if info["self_touching"] == 0:
        assert_tiles(polys, SIZE[0] * SIZE[1])
    assert farthest(polys) <= 0.5
    # snapped to a grid: vertices on it, still a tiling; outlines valid unless reported
    grid = 0.25
    polys, info = pixel_polygons_um(layout, SIZE, UM, tol_um=0.5, grid_um=grid, manhattan=True)
    allv = np.concatenate(polys)
    assert np.abs(allv / grid - np.round(allv / grid)).max() < 1e-9
    shapes = [shapely.Polygon(p) for p in polys]
    assert sum(not s.is_valid for s in shapes) <= info["self_touching"]
    assert abs(sum(s.area for s in shapes) - W_UM * H_UM) < 1e-6
    if info["self_touching"] == 0:
        assert_tiles(polys, SIZE[0] * SIZE[1])
    polys, _ = pixel_polygons_um(layout, SIZE, UM, tol_um=0.01, grid_um=0.01)
    assert_tiles(polys, SIZE[0] * SIZE[1])


def test_png_boundaries_and_index(gen, tmp_path):
    layout = layout_of("curv", gen)
    rep = export_layout(layout, SIZE, tmp_path / "m.png", UM, px_per_um=0.5, line_width=2)
    lines = cv2.imread(str(tmp_path / "m.png"), cv2.IMREAD_UNCHANGED)
    index = cv2.imread(str(tmp_path / "m_index.png"), cv2.IMREAD_UNCHANGED)
    assert lines.shape == index.shape == (450, 600) and index.dtype == np.uint16
    assert rep.files[-1].endswith("m_index.png")
    assert set(np.unique(index)) == set(range(1, SIZE[0] * SIZE[1] + 1))
    assert 0.02 < (lines > 0).mean() < 0.3
    # the raster pixel at each deformed pixel centre holds that pixel's index
    q = layout.phi(lw.coords.pixel_centers(SIZE), layout.theta.detach())
    xy = ((q.numpy() + 1) / 2 * XY * 0.5).astype(int)
    assert (index[xy[..., 1], xy[..., 0]] == np.arange(1, SIZE[0] * SIZE[1] + 1).reshape(SIZE)).all()


def test_a_png_export_leaves_one_index_mask_beside_it(tmp_path):
    # over 65 534 pixels the index mask is a .npy: an export to the same path left the other
    # kind, an earlier export's, beside it (a stale mask that no longer matches the outlines)
    small, large = tmp_path / "m_index.png", tmp_path / "m_index.npy"
    for size, kept in [((4, 6), small), ((256, 257), large), ((3, 5), small)]:
        rep = export_layout(lw.UniformLayout(), size, tmp_path / "m.png", (size[0], size[1]), px_per_um=1)
        assert rep.files[-1] == str(kept) and sorted(tmp_path.iterdir()) == sorted([tmp_path / "m.png", kept])
        index = np.load(kept) if kept == large else cv2.imread(str(kept), cv2.IMREAD_UNCHANGED)
        assert index.max() == size[0] * size[1]


def test_report_pitch_and_warning(tmp_path):
    layout = lw.UniformLayout()
    rep = export_layout(layout, (4, 6), tmp_path / "u.svg", (400, 600), min_feature_um=120)
    assert rep.min_pitch_um == pytest.approx(100) and rep.max_pitch_um == pytest.approx(100)
    assert rep.min_area_um2 == pytest.approx(1e4) and rep.vertices == 96
    assert rep.warnings and "below the minimum feature size 120" in rep.warnings[0]
    assert "pitch 100 .. 100" in rep.summary()


def test_cli_export_and_errors(tmp_path, capsys):
    lw.save_layout(lw.make_layout("rect", (0.5, 0.3)), tmp_path / "l.json", (SIZE[0], SIZE[1]))
    out = tmp_path / "m.gds"
    argv = ["export", "--layout", str(tmp_path / "l.json"), "--sensor-um", "1200x900", "--out", str(out)]
    assert main([*argv, "--report", str(tmp_path / "r.json")]) == 0
    assert json.loads((tmp_path / "r.json").read_text())["pixels"] == SIZE[0] * SIZE[1]
    assert "108 pixels" in capsys.readouterr().out
    assert main([*argv[:-1], str(tmp_path / "m.jpg")]) == 2
    assert "argument --out: 'm.jpg' names no export format" in capsys.readouterr().err
    with pytest.raises(ValueError, match="grid_um"):
        pixel_polygons_um(lw.UniformLayout(), SIZE, UM, grid_um=-1)


def test_the_export_format_is_the_suffix_or_a_format_that_matches_it():
    from layoutwarp.checks import ArgumentError
    from layoutwarp.export import export_format

    assert [export_format(f"a/m.{f.upper()}") for f in FORMATS] == list(FORMATS)
    assert export_format("m.svg", "SVG") == "svg"
    for path, fmt, argument, needle in [
        ("m.svg", "png", "format", "'png' does not match the file name 'm.svg'"),
        ("m.svg", "jpg", "format", "format must be one of"),
        ("m", None, "path", "'m' names no export format"),
        ("m.jpg", None, "path", "name it *.gds, *.dxf, *.svg, *.png"),
    ]:
        with pytest.raises(ArgumentError, match=re.escape(needle)) as info:
            export_format(path, fmt)
        assert info.value.argument == argument


def test_gds_keeps_a_many_vertex_pixel_in_one_polygon(tmp_path):
    import gdstk

    layout = lw.CurvLayout((0.95, -0.9), dtype=torch.float64)
    polys, _ = pixel_polygons_um(layout, (3, 4), UM, tol_um=1e-4)
    assert max(len(p) for p in polys) > 199  # gdstk's default would fracture these
    rep = export_layout(layout, (3, 4), tmp_path / "m.gds", UM, tol_um=1e-4)
    back = gdstk.read_gds(str(tmp_path / "m.gds")).cells[0].polygons
    assert len(back) == 12 and not any("GDSII boundary" in w for w in rep.warnings)
    snapped, _ = pixel_polygons_um(layout, (3, 4), UM, tol_um=1e-4, grid_um=1e-3)  # what the file holds
    assert sorted(len(p.points) for p in back) == sorted(len(p) for p in snapped)
