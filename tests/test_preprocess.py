"""Dataset preprocessing: exact area weights, the folder walk, resuming, labels, workers."""

from __future__ import annotations

import json
import re
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import shapely
import torch
from conftest import SAMPLES, rand_theta

import layoutwarp as lw
from layoutwarp.backwarp import sensor_index_maps
from layoutwarp.checks import ArgumentError
from layoutwarp.cli import main
from layoutwarp.preprocess import preprocess_folder
from layoutwarp.resampler import AreaResampler
from layoutwarp.weights import area_weights

F64 = torch.float64


def fixed(family, theta=None):
    return (
        lw.make_layout(family, theta, learn=False, dtype=F64) if family != "uniform" else lw.UniformLayout()
    )


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_area_weights_equal_exact_integrator(family, gen):
    layout = fixed(family, rand_theta(gen, 0.9))
    for src, size in [((37, 53), (7, 9)), ((64, 48), (13, 11)), ((12, 20), (17, 23))]:
        img = torch.rand(3, *src, generator=gen, dtype=F64)
        w = area_weights(layout, size, src, tol=1e-6)
        got = (w @ img.reshape(3, -1).T.numpy()).T.reshape(3, *size)
        with torch.no_grad():
            ref = lw.simulate(img, layout, size, tol=1e-6).numpy()
        assert np.abs(got - ref).max() < 1e-12
        assert np.abs(np.asarray(w.sum(1)).ravel() - 1).max() < 1e-12
        assert (w.data > 0).all()


@pytest.mark.parametrize("family", ["rect", "curv", "fovea"])
def test_area_weights_built_in_blocks_of_any_height_are_the_same_matrix(family, gen, monkeypatch):
    # the build takes blocks of sensor rows, each from the edges bounding its pixels: one row a
    # block, a few rows, and the whole sensor in one block give one matrix (and the integral)
    import layoutwarp.weights as res

    layout = fixed(family, rand_theta(gen, 0.9))
    src, size = (41, 67), (tuple(int(v) for v in torch.randint(5, 15, (2,), generator=gen)))
    built = {}
    for pieces in (1, 300, 1 << 40):
        monkeypatch.setattr(res, "PIECES_PER_BLOCK", pieces)
        built[pieces] = area_weights(layout, size, src, tol=1e-6)
    one = built[1 << 40]
    for w in (built[1], built[300]):
        assert np.array_equal(w.indptr, one.indptr) and np.array_equal(w.indices, one.indices)
        assert np.abs(w.data - one.data).max() < 1e-15
    img = torch.rand(2, *src, generator=gen, dtype=F64)
    with torch.no_grad():
        ref = lw.simulate(img, layout, size, tol=1e-6).numpy()
    got = (built[1] @ img.reshape(2, -1).T.numpy()).T.reshape(2, *size)
    assert np.abs(got - ref).max() < 1e-12


def test_a_long_weights_build_shows_its_progress_on_a_terminal_only(monkeypatch):
    # a build that runs past PROGRESS_AFTER_S draws a bar (rows done, the time left) on a
    # terminal's stderr, and nothing where stderr is a file or a pipe
    import io
    import sys

    import layoutwarp.weights as res

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setattr(res, "PROGRESS_AFTER_S", 0.0)
    monkeypatch.setattr(res, "PIECES_PER_BLOCK", 50)  # a block a row or so: the bar moves
    for stream, shown in ((Terminal(), True), (io.StringIO(), False)):
        monkeypatch.setattr(sys, "stderr", stream)
        area_weights(lw.CurvLayout((0.3, -0.2)), (12, 16), (40, 60))
        text = stream.getvalue()
        assert ("area weights 12x16" in text and "/12 [" in text and "row/s" in text) == shown, text


def test_the_compiled_weights_build_shows_its_progress_on_a_terminal_only(monkeypatch):
    # the compiled walk's two passes over the sensor rows, block by block, move one bar
    import io
    import sys

    import layoutwarp.kernels.weights as kw
    import layoutwarp.weights as res

    class Terminal(io.StringIO):
        def isatty(self) -> bool:
            return True

    monkeypatch.setattr(res, "PROGRESS_AFTER_S", 0.0)
    monkeypatch.setattr(kw, "BLOCK_PIXELS", 40)  # blocks of 2 rows: the bar moves
    with lw.jit.use_mode("wait"):
        for stream, shown in ((Terminal(), True), (io.StringIO(), False)):
            monkeypatch.setattr(sys, "stderr", stream)
            runs, _ = res.fixed_runs(lw.CurvLayout((0.3, -0.2)), (12, 16), (40, 60), 1e-4)
            text = stream.getvalue()
            assert ("area weights 12x16" in text and "/24 [" in text and "row/s" in text) == shown, text
            assert runs.shape == (12 * 16, 40 * 60)


def test_area_weights_rows_are_cell_overlaps(gen):
    # independent: shapely clipping of one curved pixel (fine polygon) with every source cell
    layout = fixed("curv", rand_theta(gen, 0.8))
    src, size = (10, 14), (3, 4)
    w = area_weights(layout, size, src, tol=1e-9).toarray()
    polys = lw.pixel_mesh(layout, size, tol=1e-9).polygons()
    for k in (0, 5, 11):
        px = shapely.Polygon((polys[k] + 1) / 2 * np.array([src[1], src[0]]))
        cells = np.array(
            [
                shapely.box(c, r, c + 1, r + 1).intersection(px).area
                for r in range(src[0])
                for c in range(src[1])
            ]
        )
        assert np.abs(w[k] - cells / px.area).max() < 1e-9


def _images(root: Path) -> dict[str, np.ndarray]:
    rng = np.random.default_rng(7)
    imgs = {
        "gray8.png": rng.integers(0, 256, (45, 61), dtype=np.uint8),
        "sub/colour8.png": rng.integers(0, 256, (50, 40, 3), dtype=np.uint8),
        "sub/deep/colour16.tif": rng.integers(0, 65536, (33, 47, 3), dtype=np.uint16),
        "alpha.png": rng.integers(0, 256, (45, 61, 4), dtype=np.uint8),
        "gray16.png": rng.integers(0, 65536, (45, 61), dtype=np.uint16),
    }
    for rel, arr in imgs.items():
        (root / rel).parent.mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(root / rel), arr)
    (root / "photo.jpg").parent.mkdir(exist_ok=True)
    cv2.imwrite(str(root / "photo.jpg"), imgs["sub/colour8.png"])
    (root / "broken.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not a png")
    (root / "empty.jpg").write_bytes(b"")
    (root / "notes.txt").write_text("not an image")
    return imgs


def test_preprocess_folder_matches_simulate_and_reports_failures(tmp_path):
    src, dst = tmp_path / "src", tmp_path / "dst"
    imgs = _images(src)
    layout, size = fixed("curv", (0.6, -0.4)), (9, 13)
    res = preprocess_folder(src, dst, layout, size, progress=False)
    assert res.processed == 6 and res.skipped == 0
    assert sorted(f["file"] for f in res.failed) == ["broken.png", "empty.jpg"]
    for rel, arr in imgs.items():
        out = cv2.imread(str(dst / rel), cv2.IMREAD_UNCHANGED)
        assert out.dtype == arr.dtype and out.shape == (*size, *arr.shape[2:])
        chw = torch.from_numpy(arr.astype(np.float64)).reshape(*arr.shape[:2], -1).permute(2, 0, 1)
        with torch.no_grad():
            ref = lw.simulate(chw, layout, size, tol=1e-7).permute(1, 2, 0).reshape(out.shape).numpy()
        # integer output: the exact value within a quarter level, rounded (so within 1/255 at 8 bit)
        assert np.abs(out - ref).max() <= 0.75 + 1e-9
    assert (dst / "photo.jpg").exists()
    manifest = json.loads((dst / "manifest.json").read_text())
    assert manifest["files_done"] == 6 and len(manifest["failed"]) == 2
    assert "broken.png" in manifest["failed"][0]["file"] + manifest["failed"][1]["file"]
    saved, info = lw.load_layout(dst / "layout.json")
    assert saved.family == "curv" and info["size_hw"] == [9, 13]
    assert not list(dst.rglob(".*"))  # no temporary files left behind


def test_preprocess_on_a_device_matches_the_cpu(tmp_path, device, gen):
    layout, size = fixed("curv", rand_theta(gen)), (7, 11)
    img = torch.rand(40, 52, 3, generator=gen, dtype=torch.float64).mul(255).numpy()
    cpu = AreaResampler(layout, size, img.shape[:2], tol=1e-6)
    dev = AreaResampler(layout, size, img.shape[:2], tol=1e-6, device=device)
    assert dev.device.type == device.type
    ref = cpu(img)
    # float32 sums in another order on CUDA; the CPU is the same code path
    np.testing.assert_allclose(dev(img), ref, rtol=0, atol=0 if device.type == "cpu" else 1e-4)
    src = tmp_path / "src"
    _images(src)
    preprocess_folder(src, tmp_path / "cpu", layout, size, progress=False)
    res = preprocess_folder(src, tmp_path / "dev", layout, size, progress=False, device=device)
    assert json.loads(res.manifest.read_text())["device"] == str(device)
    for f in (tmp_path / "cpu").rglob("*.png"):
        a = cv2.imread(str(f), cv2.IMREAD_UNCHANGED).astype(int)
        b = cv2.imread(str(tmp_path / "dev" / f.relative_to(tmp_path / "cpu")), cv2.IMREAD_UNCHANGED).astype(
            int
        )
        assert np.abs(a - b).max() <= (0 if device.type == "cpu" else 1)


def test_preprocess_resumes_and_checks_layout(tmp_path):
    src, dst = tmp_path / "src", tmp_path / "dst"
    _images(src)
    layout, size = fixed("rect", (0.3, 0.2)), (8, 8)
    first = preprocess_folder(src, dst, layout, size, progress=False)
    again = preprocess_folder(src, dst, layout, size, progress=False)
    assert again.processed == 0 and again.skipped == first.processed
    # a changed source, a deleted output and a torn last line of the done-list are redone
    cv2.imwrite(str(src / "gray8.png"), np.zeros((45, 61), np.uint8))
    (dst / "sub" / "colour8.png").unlink()
    with (dst / "done.jsonl").open("a") as f:
        f.write('{"file": "alpha.pn')
    third = preprocess_folder(src, dst, layout, size, progress=False)
    assert third.processed == 2 and third.skipped == first.processed - 2
    assert cv2.imread(str(dst / "gray8.png"), cv2.IMREAD_UNCHANGED).max() == 0
    with pytest.raises(ValueError, match="another layout"):
        preprocess_folder(src, dst, fixed("rect", (0.3, 0.25)), size, progress=False)
    # the files were made at the default tolerance: a resumed run at another would mix the two
    with pytest.raises(ValueError, match=r"made with tol none \(the default\), not 0.001"):
        preprocess_folder(src, dst, layout, size, tol=1e-3, progress=False)


def test_a_changed_label_rule_is_refused_and_two_outputs_to_one_file_too(tmp_path):
    rng = np.random.default_rng(0)
    src, lab = tmp_path / "img", tmp_path / "lab"
    for folder in (src, src / "labels", lab):
        folder.mkdir()
    cv2.imwrite(str(src / "a.png"), rng.integers(0, 256, (20, 24, 3), dtype=np.uint8))
    cv2.imwrite(str(lab / "a.png"), rng.integers(0, 3, (20, 24), dtype=np.uint8))
    layout, size = fixed("curv", (0.3, -0.2)), (4, 5)
    preprocess_folder(src, tmp_path / "out", layout, size, labels=lab, label_rule="majority", progress=False)
    with pytest.raises(ValueError, match="made with label_rule 'majority', not 'nearest'"):
        preprocess_folder(
            src, tmp_path / "out", layout, size, labels=lab, label_rule="nearest", progress=False
        )
    # a source under src/labels/ would be written where a.png's label map goes
    cv2.imwrite(str(src / "labels" / "a.png"), rng.integers(0, 256, (20, 24, 3), dtype=np.uint8))
    with pytest.raises(ValueError, match="two outputs of the run would be one file"):
        preprocess_folder(src, tmp_path / "new", layout, size, labels=lab, progress=False)
    assert not (tmp_path / "new").exists()


def test_parallel_workers_give_identical_files_and_share_weights(tmp_path, monkeypatch, seed):
    src = tmp_path / "src"
    imgs = _images(src)
    rng = np.random.default_rng(seed)
    (src / "same").mkdir()
    for k in range(12):  # many files of one size: the pool must build their weights once
        assert cv2.imwrite(str(src / f"same/{k}.png"), rng.integers(0, 256, (30, 38, 3), dtype=np.uint8))
    builds = []

    class Counting(AreaResampler):  # each build of a weights' resampler
        def __init__(self, layout, size, src_size, **kw):
            builds.append((tuple(src_size), kw["tol"], kw["dtype"]))
            super().__init__(layout, size, src_size, **kw)

    monkeypatch.setattr("layoutwarp.preprocess.AreaResampler", Counting)
    layout, size = fixed("curv", (0.5, 0.5)), (7, 11)
    a = preprocess_folder(src, tmp_path / "a", layout, size, progress=False)
    assert len(builds) == len(set(builds)) == 5  # (size, dtype) pairs of the inputs
    builds.clear()
    b = preprocess_folder(src, tmp_path / "b", layout, size, workers=4, progress=False)
    assert len(builds) == len(set(builds)) == 5
    assert a.processed == b.processed == 18 and len(b.failed) == 2
    for rel in [*imgs, *(f"same/{k}.png" for k in range(12))]:
        assert (tmp_path / "a" / rel).read_bytes() == (tmp_path / "b" / rel).read_bytes()


def test_label_rules(tmp_path, gen):
    rng = np.random.default_rng(3)
    src_size, size = (40, 52), (6, 8)
    blocks = rng.integers(0, 5, (5, 4)).astype(np.uint8)
    label = cv2.resize(blocks, (52, 40), interpolation=cv2.INTER_NEAREST)
    layout = fixed("curv", rand_theta(gen, 0.8))
    res = AreaResampler(layout, size, src_size, tol=1e-7)
    # nearest: the label under each deformed pixel centre
    q = layout.phi(lw.coords.pixel_centers(size), layout.theta)
    col = np.floor((q[..., 0].numpy() + 1) / 2 * src_size[1] + 1e-9).astype(int)  # a centre on a
    row = np.floor((q[..., 1].numpy() + 1) / 2 * src_size[0] + 1e-9).astype(int)  # border: right/below
    near = res.labels(label, "nearest")
    assert near.dtype == np.uint8 and (near == label[row, col]).all()
    # majority: argmax of the exact area shares of the one-hot classes
    onehot = torch.from_numpy(np.stack([label == k for k in range(5)]).astype(np.float64))
    with torch.no_grad():
        share = lw.simulate(onehot, layout, size, tol=1e-7).numpy()
    maj = res.labels(label, "majority")
    top2 = np.sort(share, 0)[-2:]
    clear = top2[1] - top2[0] > 1e-4
    assert (maj[clear] == share.argmax(0)[clear]).all() and clear.mean() > 0.8
    # inverse: label kept, back-warp maps stored once
    (tmp_path / "img").mkdir()
    (tmp_path / "lab").mkdir()
    cv2.imwrite(str(tmp_path / "img" / "a.png"), rng.integers(0, 256, (40, 52, 3), dtype=np.uint8))
    cv2.imwrite(str(tmp_path / "lab" / "a.png"), label)
    out = tmp_path / "out"
    preprocess_folder(tmp_path / "img", out, layout, size, labels=tmp_path / "lab", label_rule="inverse")
    assert (cv2.imread(str(out / "labels" / "a.png"), cv2.IMREAD_UNCHANGED) == label).all()
    maps = np.load(out / "backwarp" / "52x40.npz")
    c, r = sensor_index_maps(layout, size, src_size)
    assert (maps["col"] == c.numpy()).all() and (maps["row"] == r.numpy()).all()
    with pytest.raises(ValueError, match="label_rule"):
        preprocess_folder(tmp_path / "img", out, layout, size, label_rule="mode")


def test_cli_preprocess_with_benchmark(tmp_path, capsys):
    dst = tmp_path / "cam"
    argv = ["preprocess", str(SAMPLES / "camvid" / "val"), str(dst), "--family", "rect", "--theta", "0.4,0.2"]
    argv += ["--size", "60x45", "--labels", str(SAMPLES / "camvid" / "valannot"), "--label-rule", "majority"]
    assert main([*argv, "--benchmark", "--no-progress"]) == 0
    text = capsys.readouterr().out
    assert "images/s" in text and "ratio" in text
    assert "where the workers' time went: decode" in text and "integrate" in text
    manifest = json.loads((dst / "manifest.json").read_text())
    assert manifest["benchmark"]["ratio"] > 0 and manifest["files_done"] == 3
    stages = manifest["benchmark"]["stage_seconds"]  # every stage timed, together within the run
    assert set(stages) == {"decode", "weights", "integrate", "encode"} and min(stages.values()) > 0
    assert sum(stages.values()) <= manifest["seconds"] * 1.05
    lab = cv2.imread(str(next((dst / "labels").glob("*.png"))), cv2.IMREAD_UNCHANGED)
    assert lab.shape == (45, 60) and lab.max() <= 11
    assert main(["preprocess", str(SAMPLES / "camvid" / "val"), str(tmp_path / "x")]) == 2
    assert "argument --layout: give a layout file, or --family" in capsys.readouterr().err


def _tree(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.mark.slow
@pytest.mark.heavy
def test_dask_engine_writes_the_same_bytes_and_reports_the_same_failures(tmp_path, monkeypatch):
    pytest.importorskip("distributed")
    import tempfile

    scratch = tmp_path / "tmp"  # the system's temporary folder: the cluster leaves nothing there
    scratch.mkdir()
    monkeypatch.setattr(tempfile, "tempdir", str(scratch))
    monkeypatch.setenv("TMPDIR", str(scratch))
    src = tmp_path / "src"
    _images(src)  # mixed dtypes and sizes, plus two unreadable files
    layout, size = fixed("grid", None), (9, 13)
    a = preprocess_folder(src, tmp_path / "local", layout, size, workers=2, progress=False)
    b = preprocess_folder(src, tmp_path / "dask", layout, size, workers=2, engine="dask", progress=False)
    assert (a.processed, b.processed) == (6, 6)
    assert sorted(f["file"] for f in a.failed) == sorted(f["file"] for f in b.failed)
    skip = {"done.jsonl", "manifest.json", "layout.json"}  # record order and timings differ
    local, dask = _tree(tmp_path / "local"), _tree(tmp_path / "dask")
    assert {k: v for k, v in local.items() if k not in skip} == {
        k: v for k, v in dask.items() if k not in skip
    }
    done = [json.loads(x) for x in (tmp_path / "dask" / "done.jsonl").read_text().splitlines()]
    assert (
        len(done) == 6 and json.loads((tmp_path / "dask" / "manifest.json").read_text())["engine"] == "dask"
    )
    assert list(scratch.iterdir()) == []  # Dask's scratch folder (its lock files) went with it


@pytest.mark.slow
def test_dask_engine_joins_a_cluster_builds_weights_once_per_worker_and_resumes(tmp_path):
    distributed = pytest.importorskip("distributed")
    from layoutwarp.preprocess import worker_weight_builds

    src, labels = SAMPLES / "camvid" / "train", SAMPLES / "camvid" / "trainannot"
    layout, size = fixed("curv", (0.5, 0.3)), (18, 24)
    with (
        distributed.LocalCluster(
            n_workers=2, threads_per_worker=2, processes=True, dashboard_address=None
        ) as cluster,
        distributed.Client(cluster) as client,
    ):
        kw = {"labels": labels, "engine": "dask", "address": cluster.scheduler_address, "progress": False}
        res = preprocess_folder(src, tmp_path / "d", layout, size, **kw)
        assert res.processed == 6 and not res.failed
        builds = client.run(worker_weight_builds)  # one source size (480x360): at most one each
        assert sum(builds.values()) >= 1 and max(builds.values()) <= 1
        again = preprocess_folder(src, tmp_path / "d", layout, size, **kw)
        assert (again.processed, again.skipped) == (0, 6)  # resumed from done.jsonl
    ref = preprocess_folder(src, tmp_path / "l", layout, size, labels=labels, progress=False)
    assert ref.processed == 6
    skip = {"done.jsonl", "manifest.json", "layout.json"}
    assert {k: v for k, v in _tree(tmp_path / "l").items() if k not in skip} == {
        k: v for k, v in _tree(tmp_path / "d").items() if k not in skip
    }


def _snapshot(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _photo(path: Path, seed: int, hw=(40, 60)) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = np.random.default_rng(seed)
    cv2.imwrite(str(path), rng.integers(0, 256, (*hw, 3), dtype=np.uint8))


def test_preprocess_refuses_a_destination_that_would_overwrite_what_it_reads(tmp_path, seed):
    layout, size = fixed("curv", (0.5, 0.3)), (6, 8)
    src = tmp_path / "src"
    _photo(src / "a.png", seed)
    _photo(src / "b.png", seed + 1)
    _photo(src / "src" / "b.png", seed + 2)  # rel src/b.png: into dst = tmp it goes over src/b.png
    before = _snapshot(tmp_path)
    cases = {
        "the source folder": (src, "is the source folder"),
        "a folder whose outputs are sources": (tmp_path, "would overwrite the source file '.*b.png'"),
    }
    for what, (dst, needle) in cases.items():
        with pytest.raises(ArgumentError, match=needle) as info:
            preprocess_folder(src, dst, layout, size, progress=False)
        assert info.value.argument == "dst" and "\n" not in str(info.value), what
        assert _snapshot(tmp_path) == before, what  # nothing written, nothing overwritten
    # the labels' own case: with dst = tmp, labels must be tmp/labels to collide
    (tmp_path / "labels").mkdir()
    _photo(tmp_path / "labels" / "x.png", seed + 3)
    _photo(tmp_path / "only" / "x.png", seed + 4)
    before = _snapshot(tmp_path)
    with pytest.raises(ArgumentError, match=re.escape("labels/x.png")):
        preprocess_folder(
            tmp_path / "only", tmp_path, layout, size, labels=tmp_path / "labels", progress=False
        )
    assert _snapshot(tmp_path) == before
    # a link in the destination to a source file is replaced by the output, never written through
    out = tmp_path / "out"
    out.mkdir()
    (out / "a.png").hardlink_to(src / "a.png")
    (out / "b.png").symlink_to(src / "b.png")
    (out / "layout.json").write_text("{}")  # as an earlier run left it, so its outputs are ours
    (out / "layout.json").unlink()
    with pytest.raises(ArgumentError, match="holds files of its own"):  # not a run's: refused
        preprocess_folder(src, out, layout, size, progress=False, files=[src / "a.png"])
    lw.save_layout(layout, out / "layout.json", size)
    preprocess_folder(src, out, layout, size, progress=False, files=[src / "a.png", src / "b.png"])
    assert (src / "a.png").read_bytes() == before["src/a.png"] and (src / "b.png").read_bytes() == before[
        "src/b.png"
    ]
    assert not (out / "b.png").is_symlink() and cv2.imread(str(out / "a.png")).shape == (6, 8, 3)
    # a destination inside the source is fine: it is left out of the walk
    res = preprocess_folder(src, src / "sensor", layout, size, progress=False)
    assert res.processed == 3 and not res.failed
    assert (src / "a.png").read_bytes() == before["src/a.png"]


def test_preprocess_refuses_a_missing_labels_folder_before_writing(tmp_path, seed):
    _photo(tmp_path / "src" / "a.png", seed)
    with pytest.raises(ArgumentError, match=r"labels must be a folder of label maps, got '.*nowhere'"):
        preprocess_folder(
            tmp_path / "src", tmp_path / "dst", fixed("rect", (0.2, 0.1)), (4, 4), labels=tmp_path / "nowhere"
        )
    assert not (tmp_path / "dst").exists()


def test_a_run_refused_at_its_dask_scheduler_writes_nothing_and_locks_no_settings(tmp_path, seed):
    pytest.importorskip("distributed")
    _photo(tmp_path / "src" / "a.png", seed)
    layout, dst = fixed("curv", (0.2, 0.1)), tmp_path / "dst"
    # a free port: nobody listens there (the connection is refused at once, no timeout waited)
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ArgumentError, match="no Dask scheduler reached"):
        preprocess_folder(
            tmp_path / "src", dst, layout, (4, 4), engine="dask", address=f"tcp://127.0.0.1:{port}"
        )
    assert not dst.exists()  # nothing written: not even the folder
    # a folder whose run finished no file (stopped before its first) holds no dataset: a run with
    # other settings takes it, where one with a finished file is refused (the test above)
    dst.mkdir()
    lw.save_layout(layout, dst / "layout.json", (4, 4), tol=None, label_rule=None, source="x")
    (dst / "done.jsonl").write_text("")
    res = preprocess_folder(tmp_path / "src", dst, layout, (4, 4), tol=1e-3, progress=False)
    assert res.processed == 1
    assert lw.load_layout(dst / "layout.json")[1]["extra"]["tol"] == 1e-3
    with pytest.raises(ValueError, match=r"made with tol 0.001, not none \(the default\)"):
        preprocess_folder(tmp_path / "src", dst, layout, (4, 4), progress=False)


def test_a_stretched_source_is_warned_about_once(tmp_path, seed):
    for k in range(3):
        _photo(tmp_path / "src" / f"{k}.png", seed + k, hw=(60, 30))  # portrait
    with pytest.warns(
        UserWarning, match=r"another aspect ratio .* \(60, 30\).*stretched 4.00x along x"
    ) as rec:
        preprocess_folder(
            tmp_path / "src", tmp_path / "dst", fixed("rect", (0.2, 0.1)), (10, 20), progress=False
        )
    assert len([w for w in rec if "aspect ratio" in str(w.message)]) == 1
    # with the file it came with (the first of its size), in the manifest too: on two threads
    with pytest.warns(UserWarning, match=r"\(60, 30\): .*stretched 2.00x along x \(first: [012].png\)"):
        res = preprocess_folder(
            tmp_path / "src",
            tmp_path / "dst1",
            fixed("rect", (0.2, 0.1)),
            (10, 10),
            workers=2,
            progress=False,
        )
    assert len(res.warnings) == 1 and "stretched 2.00x" in res.warnings[0]
    assert json.loads((tmp_path / "dst1" / "manifest.json").read_text())["warnings"] == res.warnings
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # within 10 %: no warning
        preprocess_folder(
            tmp_path / "src", tmp_path / "dst2", fixed("rect", (0.2, 0.1)), (21, 10), progress=False
        )


def test_a_dask_workers_warning_is_told_by_the_run_once_as_a_local_runs_is(tmp_path, seed):
    pytest.importorskip("distributed")
    for k in range(4):
        _photo(tmp_path / "src" / f"{k}.png", seed + k, hw=(60, 30))  # portrait
    with pytest.warns(UserWarning, match=r"another aspect ratio .* \(60, 30\).*stretched 4.00x") as rec:
        res = preprocess_folder(
            tmp_path / "src", tmp_path / "dst", fixed("rect", (0.2, 0.1)), (10, 20), workers=2,
            engine="dask", progress=False,
        )  # fmt: skip
    assert res.processed == 4
    assert len([w for w in rec if "aspect ratio" in str(w.message)]) == 1  # two workers built one each


def test_a_dask_worker_with_threads_returns_each_files_warnings_with_that_file(monkeypatch):
    # a `dask worker` runs a thread per core: warnings.catch_warnings (the process's) lost one
    # thread's warning and gave it to no file, while the other's went to the worker's log
    import threading
    import warnings

    import layoutwarp.preprocess as pp

    def fake(spec, task):
        time.sleep(task["d"])
        warnings.warn(f"stretched {task['file']}", UserWarning, stacklevel=2)
        time.sleep(task["d"])
        return {"ok": False, "file": task["file"], "error": ""}

    monkeypatch.setattr(pp, "_remote_process", fake)
    got = {}

    def run(name, d):
        got[name] = pp._remote_process_many("{}", [{"file": name, "d": d}])[0]["warnings"]

    threads = [
        threading.Thread(target=run, args=("a.png", 0.05)),
        threading.Thread(target=run, args=("b.png", 0.2)),
    ]
    for t in threads:
        t.start()
        time.sleep(0.01)
    for t in threads:
        t.join()
    assert got == {name: [(UserWarning, f"stretched {name}")] for name in ("a.png", "b.png")}
    with pytest.warns(UserWarning, match="outside a file"):  # the worker's own warnings as before
        warnings.warn("outside a file", UserWarning, stacklevel=2)


def test_truncated_images_are_refused_in_our_words(tmp_path, seed):
    from layoutwarp.preprocess import read_image

    _photo(tmp_path / "a.png", seed)
    _photo(tmp_path / "a.jpg", seed)
    for name, why in [("a.png", "truncated PNG file"), ("a.jpg", "truncated JPEG file")]:
        data = (tmp_path / name).read_bytes()
        assert read_image(tmp_path / name).shape == (40, 60, 3)
        cut = tmp_path / f"cut_{name}"
        cut.write_bytes(data[: len(data) * 2 // 3])
        with pytest.raises(ValueError, match=why):
            read_image(cut)
    (tmp_path / "padded.jpg").write_bytes((tmp_path / "a.jpg").read_bytes() + b"\0" * 100)
    assert read_image(tmp_path / "padded.jpg").shape == (40, 60, 3)  # trailing padding is not a cut
    trailer = b"\x00\x00\x00\x18ftypmp42" + bytes(range(256)) * 40  # a motion photo's video after it
    (tmp_path / "motion.jpg").write_bytes((tmp_path / "a.jpg").read_bytes() + trailer)
    assert read_image(tmp_path / "motion.jpg").shape == (40, 60, 3)
    (tmp_path / "tail.png").write_bytes((tmp_path / "a.png").read_bytes() + trailer)
    assert read_image(tmp_path / "tail.png").shape == (40, 60, 3)


def test_reading_works_with_the_oldest_opencvs_log_functions(tmp_path, monkeypatch, seed):
    # OpenCV 4.8 has setLogLevel/getLogLevel on cv2 itself and no cv2.utils.logging
    from layoutwarp.preprocess import read_image

    calls = []
    monkeypatch.delattr(cv2.utils, "logging", raising=False)
    monkeypatch.setattr(cv2, "getLogLevel", lambda: calls.append("get") or 3, raising=False)
    monkeypatch.setattr(cv2, "setLogLevel", lambda level: calls.append(level), raising=False)
    _photo(tmp_path / "a.png", seed)
    assert read_image(tmp_path / "a.png").shape == (40, 60, 3)
    assert calls == ["get", 0, 3]  # silent while decoding, then as it was


def test_preprocess_refuses_to_overwrite_a_folders_own_files(tmp_path, seed):
    # a destination no earlier run wrote (no layout.json) keeps its files: a same-named output is refused
    layout, size = fixed("rect", (0.2, 0.1)), (4, 4)
    _photo(tmp_path / "src" / "a.png", seed)
    _photo(tmp_path / "mine" / "a.png", seed + 1)
    before = _snapshot(tmp_path / "mine")
    with pytest.raises(ArgumentError, match="holds files of its own that the run would overwrite"):
        preprocess_folder(tmp_path / "src", tmp_path / "mine", layout, size, progress=False)
    assert _snapshot(tmp_path / "mine") == before
    res = preprocess_folder(tmp_path / "src", tmp_path / "ours", layout, size, progress=False)
    again = preprocess_folder(tmp_path / "src", tmp_path / "ours", layout, size, progress=False)
    assert res.processed == 1 and again.skipped == 1  # a run's own destination resumes


def test_a_fine_sensor_says_when_its_area_weights_are_built(tmp_path, monkeypatch, capfd):
    """With progress shown, a sensor of at least ``ANNOUNCE_PIXELS`` pixels says, above the bar,
    that it builds its area weights (once per source size) and how long that took, and the build's
    own bar shows (stderr need not be a terminal: the command's is a pipe while it runs); with
    progress off it says nothing."""
    import layoutwarp.preprocess as pre
    import layoutwarp.weights as weights

    src = tmp_path / "src"
    src.mkdir()
    for k in range(2):  # one source size: the weights built once
        assert cv2.imwrite(str(src / f"{k}.png"), np.full((30, 38), 100 + k, np.uint8))
    monkeypatch.setattr(pre, "ANNOUNCE_PIXELS", 20)  # a 5x6 sensor counts as fine here
    monkeypatch.setattr(weights, "PROGRESS_AFTER_S", 0.0)
    preprocess_folder(src, tmp_path / "out", fixed("curv", (0.3, -0.2)), (5, 6), progress=True)
    err = capfd.readouterr().err
    assert err.count("building the area weights of the 5x6 sensor for 30x38 images") == 1, err
    assert re.search(r"built in \d+\.\d s", err), err
    assert "area weights 5x6" in err, err
    preprocess_folder(src, tmp_path / "quiet", fixed("curv", (0.3, -0.2)), (5, 6), progress=False)
    assert "area weights" not in capfd.readouterr().err


@pytest.mark.parametrize("workers", [1, 3])
def test_a_stopped_run_writes_its_manifest_and_leaves_the_rest_unbegun(tmp_path, monkeypatch, workers):
    # Ctrl-C after the second image: the manifest says what was finished and that the run did
    # not end, the thread pool begins no further image, and a rerun finishes the same files
    src, dst = tmp_path / "src", tmp_path / "dst"
    _images(src)
    layout, size = fixed("curv", (0.3, -0.2)), (6, 7)
    calls, real = [], lw.preprocess.read_image

    def stopping(path, *args, **kwargs):
        calls.append(path)
        if len(calls) == 2:
            raise KeyboardInterrupt
        time.sleep(0.5)  # the other images in hand outlast the stop, however busy the machine
        return real(path, *args, **kwargs)

    monkeypatch.setattr("layoutwarp.preprocess.read_image", stopping)
    with pytest.raises(KeyboardInterrupt):
        preprocess_folder(src, dst, layout, size, workers=workers, progress=False)
    manifest = json.loads((dst / "manifest.json").read_text())
    written = [p for p in dst.rglob("*") if p.is_file() and p.parent.name != "backwarp"]
    written = [p for p in written if p.name not in ("layout.json", "done.jsonl", "manifest.json")]
    # every image finished before or while the stop came is recorded (a rerun does not do it again)
    assert manifest["finished"] is False and manifest["files_done"] == len(written) >= 1
    assert len(calls) <= workers + 1  # the images in hand (and the stopped thread's next), no more
    monkeypatch.setattr("layoutwarp.preprocess.read_image", real)
    again = preprocess_folder(src, dst, layout, size, workers=workers, progress=False)
    whole = preprocess_folder(src, tmp_path / "whole", layout, size, progress=False)
    assert json.loads((dst / "manifest.json").read_text())["finished"] is True
    assert again.processed + manifest["files_done"] == whole.processed
    for rel in ("gray8.png", "sub/colour8.png", "alpha.png"):
        assert (dst / rel).read_bytes() == (tmp_path / "whole" / rel).read_bytes()


def test_an_image_its_suffix_cannot_keep_fails_and_is_not_written(tmp_path):
    # 16-bit data in a file named .jpg, float data named .png: OpenCV's encoders wrote them as
    # 8-bit, saturated, without an error (every value 255), and the run counted them as done
    src, dst = tmp_path / "src", tmp_path / "dst"
    src.mkdir()
    rng = np.random.default_rng(4)
    (src / "scan16.jpg").write_bytes(
        cv2.imencode(".png", rng.integers(0, 65536, (48, 64), dtype=np.uint16))[1]
    )
    (src / "depth.png").write_bytes(cv2.imencode(".tif", rng.random((48, 64), dtype=np.float32))[1])
    _photo(src / "fine.png", 1)
    res = preprocess_folder(src, dst, lw.UniformLayout(), (12, 16), progress=False)
    failed = {f["file"]: f["error"] for f in res.failed}
    assert res.processed == 1 and sorted(failed) == ["depth.png", "scan16.jpg"]
    assert "a uint16 image cannot be written as .jpg, which keeps uint8 only" in failed["scan16.jpg"]
    assert (
        "a float32 image cannot be written as .png, which keeps uint8 or uint16 only" in failed["depth.png"]
    )
    assert sorted(p.name for p in dst.iterdir()) == ["done.jsonl", "fine.png", "layout.json", "manifest.json"]
    rgba = rng.integers(0, 255, (5, 7, 4)).astype(np.uint8)  # a JPEG dropped the alpha without a word
    with pytest.raises(
        ValueError, match=r"^an image of 4 channels cannot be written as \.jpg, which keeps 1 or 3"
    ):
        lw.imagefiles.encode_image(Path("a.jpg"), rgba)
    with pytest.raises(ValueError, match=r"^OpenCV cannot encode a uint8 \(5, 7, 2\) image as \.png$"):
        lw.imagefiles.encode_image(Path("a.png"), rgba[..., :2])  # OpenCV's own error: many lines
    for suffix, keeps in lw.imagefiles.KEEPS.items():  # what OpenCV's encoder of each suffix keeps
        for dtype in ("uint8", "uint16", "int16", "float32"):
            arr = rng.integers(0, 200, (5, 7)).astype(dtype)
            if dtype in keeps:
                back = cv2.imdecode(
                    np.frombuffer(lw.imagefiles.encode_image(Path("a" + suffix), arr), np.uint8), -1
                )
                assert back.dtype == arr.dtype
            else:
                article = "an" if dtype.startswith("int") else "a"
                with pytest.raises(
                    ValueError, match=f"^{article} {dtype} image cannot be written as {suffix}"
                ):
                    lw.imagefiles.encode_image(Path("a" + suffix), arr)


def test_links_in_the_source_folder_are_followed_once_and_a_broken_one_fails_alone(tmp_path):
    import os

    src, elsewhere = tmp_path / "src", tmp_path / "elsewhere"
    for rel in ("real/a.png", "real/b.png"):
        _photo(src / rel, 2)
    _photo(elsewhere / "c.png", 3)
    (src / "linked").symlink_to(elsewhere)  # a folder link: its images are the source's too
    (src / "again").symlink_to(elsewhere)  # the same folder by a second link: walked once
    (src / "real" / "loop").symlink_to(src)  # a link back up: not walked again
    (src / "real" / "up").symlink_to(tmp_path)  # up to src's parent: not followed (its siblings)
    _photo(tmp_path / "sibling" / "d.png", 4)
    (src / "real" / "gone.png").symlink_to(tmp_path / "nowhere.png")  # broken
    os.mkfifo(src / "real" / "pipe.png")  # a pipe: never opened (it would wait for a writer)
    res = preprocess_folder(src, tmp_path / "dst", lw.UniformLayout(), (10, 15), progress=False)
    assert sorted(f["file"] for f in res.failed) == ["real/gone.png", "real/pipe.png"]
    assert all("not a file (a broken link, a pipe or a device)" in f["error"] for f in res.failed)
    written = sorted(str(p.relative_to(tmp_path / "dst")) for p in (tmp_path / "dst").rglob("*.png"))
    assert written == ["again/c.png", "real/a.png", "real/b.png"]  # "again" sorts before "linked"
    manifest = json.loads((tmp_path / "dst" / "manifest.json").read_text())
    assert len(manifest["failed"]) == 2 and manifest["files_done"] == 3


def test_label_maps_palette_changed_or_not_fitting_their_image(tmp_path):
    from PIL import Image

    img, lab, dst = tmp_path / "img", tmp_path / "lab", tmp_path / "dst"
    _photo(img / "a.png", 4, hw=(48, 64))
    _photo(img / "b.jpg", 5, hw=(48, 64))
    _photo(img / "c.png", 6, hw=(48, 64))
    classes = np.zeros((48, 64), np.uint8)
    classes[:, 32:] = 1
    classes[24:] += 2
    lab.mkdir()
    palette = Image.fromarray(classes, "P")  # Pascal VOC's kind: the pixels hold class indices
    palette.putpalette([0, 0, 0, 128, 0, 0, 0, 128, 0, 128, 128, 0] + [0] * 756)
    palette.save(lab / "a.png")
    cv2.imwrite(str(lab / "b.png"), classes)  # a JPEG image's label map: the .png of its stem
    cv2.imwrite(str(lab / "c.png"), cv2.resize(classes, (128, 96), interpolation=cv2.INTER_NEAREST))
    layout, size = lw.UniformLayout(), (6, 8)
    res = preprocess_folder(img, dst, layout, size, labels=lab, label_rule="nearest", progress=False)
    assert [f["file"] for f in res.failed] == ["c.png"]  # a label map of another size than its image
    assert "must be single-channel and 64x48 as its image, has shape (96, 128)" in res.failed[0]["error"]
    assert not (dst / "c.png").exists() and not (dst / "labels" / "c.png").exists()  # nothing of it
    want = AreaResampler(layout, size, (48, 64)).labels(classes, "nearest")
    for name in ("a.png", "b.png"):
        assert (cv2.imread(str(dst / "labels" / name), cv2.IMREAD_UNCHANGED) == want).all()
    # label maps of int16 or int32 indices go to the sensor grid as a PNG keeps them (uint8 here)
    wide, wimg = tmp_path / "wide", tmp_path / "wimg"
    (wide / "lab").mkdir(parents=True)
    wimg.mkdir()
    for dtype in ("int16", "int32"):
        cv2.imwrite(str(wimg / f"{dtype}.tif"), np.zeros((48, 64), np.uint8))
        cv2.imwrite(str(wide / "lab" / f"{dtype}.tif"), classes.astype(dtype))
    res = preprocess_folder(wimg, wide / "out", layout, size, labels=wide / "lab", progress=False)
    assert res.failed == [] and res.processed == 2
    from layoutwarp.preprocess import _png_classes

    with pytest.raises(ValueError, match="holds float32 values; class indices are integers"):
        _png_classes(np.array([[0.0, 1.7]], np.float32), Path("x.tif"))  # not truncated to 0, 1
    for name in ("int16.png", "int32.png"):
        got = cv2.imread(str(wide / "out" / "labels" / name), cv2.IMREAD_UNCHANGED)
        assert got.dtype == np.uint8 and (got == want).all()
    # a corrected label map is taken on the next run (its image unchanged)
    time.sleep(0.01)
    cv2.imwrite(str(lab / "b.png"), 3 - classes)
    res = preprocess_folder(img, dst, layout, size, labels=lab, label_rule="nearest", progress=False)
    assert res.processed == 1 and res.skipped == 1 and [f["file"] for f in res.failed] == ["c.png"]
    assert (cv2.imread(str(dst / "labels" / "b.png"), cv2.IMREAD_UNCHANGED) == 3 - want).all()
    # inverse: each label map copied in its own format (b.jpg's label map is a PNG file)
    inv = tmp_path / "inv"
    res = preprocess_folder(img, inv, layout, size, labels=lab, label_rule="inverse", progress=False)
    assert [f["file"] for f in res.failed] == ["c.png"]
    assert sorted(p.name for p in (inv / "labels").iterdir()) == ["a.png", "b.png"]
    assert (inv / "labels" / "b.png").read_bytes() == (lab / "b.png").read_bytes()


def test_a_jpeg_is_read_as_its_exif_orientation_shows_it(tmp_path):
    from PIL import Image

    src = tmp_path / "src"
    src.mkdir()
    stored = np.zeros((48, 64, 3), np.uint8)
    stored[:, :32] = 255  # stored landscape, left half white; shown portrait (turned 90° clockwise)
    im = Image.fromarray(stored)
    exif = im.getexif()
    exif[0x0112] = 6
    im.save(src / "phone.jpg", exif=exif.tobytes(), quality=95)
    shown = cv2.imread(str(src / "phone.jpg"))  # OpenCV's own reader applies the orientation
    assert shown.shape == (64, 48, 3)
    assert np.array_equal(lw.imagefiles.read_image(src / "phone.jpg"), shown)
    preprocess_folder(src, tmp_path / "dst", lw.UniformLayout(), (16, 12), progress=False)
    out = cv2.imread(str(tmp_path / "dst" / "phone.jpg"), cv2.IMREAD_UNCHANGED)
    assert out.shape == (16, 12, 3) and out[:8].mean() > 200 and out[8:].mean() < 50  # white on top
