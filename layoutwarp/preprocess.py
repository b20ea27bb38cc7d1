"""Dataset preprocessing: a folder of images to their sensor images for a fixed layout.

Each source size gets one [`AreaResampler`][] (the exact integrator as a sparse
matrix), shared by every file of that size; OpenCV reads and writes the files.

[`preprocess_folder`][] walks a folder tree (PNG, JPEG, TIFF, BMP; 8/16-bit or float,
gray, colour or with alpha: every channel is integrated alike, straight alpha) and writes
each sensor image under the same relative path of the destination. It is resumable (a
re-run skips files the done-list records with an unchanged source and a complete output),
writes atomically (a temporary file renamed into place), reports unreadable inputs at the
end and in the manifest without stopping, and runs in parallel worker threads (decoding,
encoding, file I/O and the sparse product release the GIL; the weights are shared).

Destination layout::

    DST/layout.json            the layout (family, θ, bound, sensor size) and options
    DST/done.jsonl             one line per finished file (appended as they finish)
    DST/manifest.json          counts, failures, timing (rewritten at the end of a run, a stopped one too)
    DST/<rel path>             the sensor images
    DST/labels/<rel path>      label maps (``label_rule`` "nearest" or "majority": on the
                               sensor grid; "inverse": the full-resolution copy)
    DST/backwarp/<W>x<H>.npz   ("inverse") int32 ``row``, ``col``: the sensor pixel of each
                               full-resolution pixel, so ``pred[row, col]`` back-warps
"""

from __future__ import annotations

import functools
import hashlib
import json
import os
import sys
import tempfile
import threading
import time
import warnings
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor, as_completed
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from . import jit
from .backwarp import sensor_index_maps
from .checks import (
    ArgumentError,
    check_choice,
    check_device,
    check_int,
    check_number,
    check_size,
    warn_if_finer,
    warn_if_stretched,
)
from .doctor import run_info
from .files import atomic_write, file_in_the_way
from .imagefiles import IMAGE_SUFFIXES, encode_image, list_images, read_image, read_label, to_dtype
from .labels import LABEL_RULES as SENSOR_RULES
from .layoutfile import layout_from_spec, layout_spec, load_layout, same_spec, save_layout
from .layouts import Layout, check_layout
from .measurement import measure
from .physics import SensorPhysics, apply_psf, as_physics
from .resampler import AreaResampler

__all__ = [
    "LABEL_RULES",
    "PreprocessResult",
    "check_destination",
    "check_no_overwrite",
    "file_seed",
    "preprocess_folder",
    "read_image",
]

#: Sensors of at least this many pixels say when their area weights are built, and how long it
#: took (with progress shown): a 4000x4000 sensor's take a minute or more.
ANNOUNCE_PIXELS = 1 << 20

#: The most worker threads (or Dask processes) a run takes.
MAX_WORKERS = 256
#: Label rules: the sensor-grid rules of [`layoutwarp.labels`][], or full-size copies with back-warp maps.
LABEL_RULES = (*SENSOR_RULES, "inverse")


# ----------------------------------------------------------------------------------------
# Folder processing
# ----------------------------------------------------------------------------------------
@dataclass
class PreprocessResult:
    """What a [`preprocess_folder`][] run did."""

    processed: int = 0
    skipped: int = 0
    failed: list[dict] = field(default_factory=list)
    seconds: float = 0.0
    manifest: Path | None = None
    #: Seconds the workers spent per stage, summed over the images written: ``decode`` (read and
    #: decode the file), ``weights`` (build the area weights, once per source size),
    #: ``integrate`` (the sensor image), ``encode`` (encode and write it, its label map too).
    stages: dict[str, float] = field(default_factory=dict)
    #: The warnings of the run (a stretched source, say), each told once, naming the first file
    #: that raised it.
    warnings: list[str] = field(default_factory=list)

    @property
    def images_per_second(self) -> float:
        return self.processed / self.seconds if self.seconds > 0 else float("nan")


class _Job:
    """One preprocessing run: the layout and one shared resampler per source size.

    Worker threads share it: decoding, encoding, file I/O and the sparse product release
    the GIL, and the weights of a source size are built once (under a lock) for all.
    """

    def __init__(
        self,
        layout: Layout,
        size: tuple[int, int],
        tol: float | None,
        label_rule: str,
        device: str = "cpu",
        physics: SensorPhysics | None = None,
        say: Callable[[str], None] | None = None,
    ):
        self.layout, self.size, self.tol, self.label_rule = layout, size, tol, label_rule
        self.device, self.physics, self.say = device, physics, say
        self._cache: dict[tuple, AreaResampler] = {}
        self._lock = threading.Lock()

    def record(self, img: np.ndarray, res: AreaResampler, rel: str) -> np.ndarray:
        """The sensor image of ``img`` (HW or HWC): the pixel means, or with physics what the sensor
        records (the PSF on the source, then photons and noise; values in the image's units, noise
        seeded from the file's relative path so a rerun writes the same bytes)."""
        if self.physics is None:
            return res(img)
        scale = float(np.iinfo(img.dtype).max) if np.issubdtype(img.dtype, np.integer) else 1.0
        src = torch.from_numpy(np.ascontiguousarray(img, np.float32) / scale)
        src = src[None] if src.ndim == 2 else src.permute(2, 0, 1)
        blurred = apply_psf(src.contiguous(), self.physics).permute(1, 2, 0).numpy()
        mean = torch.from_numpy(res(blurred)).to(torch.float64)
        mean = mean[None] if mean.ndim == 2 else mean.permute(2, 0, 1)
        gen = torch.Generator().manual_seed(file_seed(self.physics.seed, rel))
        with torch.no_grad():
            out = measure(mean, res.areas.cpu(), self.physics, generator=gen)  # the weights' polygons
        out = out.permute(1, 2, 0).numpy() * scale
        return out[..., 0] if img.ndim == 2 else out

    def resampler(self, src_size: tuple[int, int], dtype: np.dtype) -> AreaResampler:
        """The shared resampler of a source size (and, with ``tol=None``, of a dtype's tolerance)."""
        key = (src_size, None if self.tol is not None else np.dtype(dtype).str)
        with self._lock:
            if key not in self._cache:
                warn_if_finer(self.size, src_size)  # once a source size (and once a calling line)
                warn_if_stretched(self.size, src_size)
                fine = self.say is not None and self.size[0] * self.size[1] >= ANNOUNCE_PIXELS
                if fine:  # minutes for a fine sensor: said, so a long first image reads as work
                    h, w = self.size
                    self.say(f"preprocess: building the area weights of the {h}x{w} sensor for "
                             f"{src_size[0]}x{src_size[1]} images (once per source size) ...")  # fmt: skip
                t0 = time.perf_counter()
                # the compiled build and product loaded (or compiled) first, so every image takes
                # them: the same bytes whenever a file is processed, and their load counted with
                # the weights
                jit.ready("fixed", torch.float32, wait=True)
                shown = self.say is not None  # the bar as the command's own (stderr is a pipe here)
                self._cache[key] = AreaResampler(
                    self.layout, self.size, src_size, tol=self.tol, dtype=dtype, device=self.device,
                    progress=shown,
                )  # fmt: skip
                if fine:
                    self.say(f"preprocess: ... built in {time.perf_counter() - t0:.1f} s")
            return self._cache[key]

    def process(self, task: dict) -> dict:
        """Process one file; never raises, reports errors instead."""
        rel = task["rel"]
        try:
            t = [time.perf_counter()]
            img = read_image(Path(task["src"]))
            t.append(time.perf_counter())
            res = self.resampler(img.shape[:2], img.dtype)
            t.append(time.perf_counter())
            out = to_dtype(self.record(img, res, rel), img.dtype)
            t.append(time.perf_counter())
            dst = Path(task["dst"])
            image = encode_image(dst, out)
            label = self._label(task, img.shape[:2], res) if task.get("label_src") else None
            atomic_write(dst, image)  # after the label map: a file refused for it writes nothing
            entry = {"file": rel, "src_bytes": task["src_bytes"], "src_mtime_ns": task["src_mtime_ns"]}
            entry |= {"src_hw": list(img.shape[:2]), "out_bytes": dst.stat().st_size}
            if label is not None:
                entry |= self._write_label(task, label, res)
            t.append(time.perf_counter())
            stages = dict(zip(STAGES, np.diff(t).tolist(), strict=True))
            return {"ok": True, "entry": entry, "stages": stages}
        except Exception as exc:  # reported, never fatal
            return {"ok": False, "file": rel, "error": f"{type(exc).__name__}: {exc}"}

    def _label(self, task: dict, src_hw: tuple[int, int], res: AreaResampler) -> bytes:
        """The bytes of a file's sensor-grid label map (``"inverse"``: its label map's own);
        ``ValueError`` for a label map that is not one class index a pixel of its image."""
        src, dst = Path(task["label_src"]), Path(task["label_dst"])
        label = read_label(src)
        if label.shape != src_hw:
            h, w = src_hw
            raise ValueError(f"label map {src} must be single-channel and {w}x{h} as its image, has shape "
                             f"{label.shape}")  # fmt: skip
        if self.label_rule == "inverse":
            return src.read_bytes()
        return encode_image(dst, _png_classes(res.labels(label, self.label_rule), src))

    def _write_label(self, task: dict, label: bytes, res: AreaResampler) -> dict:
        """Write a file's label map (and, for ``"inverse"``, its source size's back-warp maps, once);
        its entry in ``done.jsonl``."""
        dst = Path(task["label_dst"])
        atomic_write(dst, label)
        if self.label_rule == "inverse":
            maps = Path(task["backwarp_dir"]) / f"{res.src_size[1]}x{res.src_size[0]}.npz"
            with self._lock:
                if not maps.exists():
                    col, row = sensor_index_maps(res.layout, res.size, res.src_size)
                    buf = _npz_bytes(row=row.numpy().astype(np.int32), col=col.numpy().astype(np.int32))
                    atomic_write(maps, buf)
        entry = {"label": str(dst), "label_bytes": dst.stat().st_size}
        return entry | {k: task[k] for k in ("label_src_bytes", "label_src_mtime_ns")}


def _png_classes(labels: np.ndarray, src: Path) -> np.ndarray:
    """Sensor-grid class indices as a PNG keeps them: uint8 or uint16, the smallest that holds
    them (a label map of int16 or int32 indices, say); ``ValueError`` naming the label map ``src``
    where an index is negative or above 65535."""
    if labels.dtype in (np.uint8, np.uint16):
        return labels
    if not (np.issubdtype(labels.dtype, np.integer) or labels.dtype == np.bool_):
        raise ValueError(f"label map {src} holds {labels.dtype} values; class indices are integers")
    lo, hi = (int(labels.min()), int(labels.max())) if labels.size else (0, 0)
    if lo < 0 or hi > np.iinfo(np.uint16).max:
        raise ValueError(f"label map {src} holds class indices {lo} .. {hi}; a PNG keeps 0 .. 65535")
    return labels.astype(np.uint8 if hi <= np.iinfo(np.uint8).max else np.uint16)


#: The stages of one image, as [`PreprocessResult.stages`][] sums them.
STAGES = ("decode", "weights", "integrate", "encode")

#: Where preprocessing runs: threads of this process, or the workers of a Dask cluster.
ENGINES = ("local", "dask")
_WORKER_JOBS: dict[str, _Job] = {}
_WORKER_LOCK = threading.Lock()


def _remote_process(spec: str, task: dict) -> dict:
    """A Dask task: process one file with this worker process's job for ``spec`` (a JSON layout
    description), built on the worker's first task and kept, so every worker builds the area
    weights of a source size once, however many files it gets."""
    with _WORKER_LOCK:
        job = _WORKER_JOBS.get(spec)
        if job is None:
            d = json.loads(spec)
            layout = layout_from_spec(d["layout"], dtype=torch.float64)
            physics = SensorPhysics.from_dict(d["physics"]) if d.get("physics") else None
            job = _Job(layout, tuple(d["size"]), d["tol"], d["label_rule"], d["device"], physics)
            _WORKER_JOBS[spec] = job
    return job.process(task)


def _remote_process_many(spec: str, tasks: list[dict]) -> list[dict]:
    """A Dask task of several files (fewer round trips to the scheduler). The warnings a file
    raises on the worker come back with its result (``"warnings"``: category and text), so the
    run's own process tells them as a local run does, not the worker's log."""
    return [_telling(functools.partial(_remote_process, spec), task) for task in tasks]


def _telling(process: Callable[[dict], dict], task: dict) -> dict:
    """``process(task)``'s result with the warnings it raised in this thread (``"warnings"``:
    category and text), for the run to tell once and keep in its manifest."""
    with _told_to_the_run() as said:
        r = process(task)
    return r | {"warnings": said}


_SAID = threading.local()  # per worker thread: the warnings of the file it is on


@contextmanager
def _told_to_the_run() -> Iterator[list[tuple[type[Warning], str]]]:
    """The warnings this thread shows meanwhile, as ``(category, text)``, instead of showing them
    (a worker's other threads, and everything else, show theirs as before: `warnings.catch_warnings`
    is the whole process's, and lost or mixed up the warnings of a worker's threads)."""
    with _WORKER_LOCK:
        if getattr(warnings.showwarning, "__name__", "") != "_show_or_tell":
            shown = warnings.showwarning

            def _show_or_tell(
                message: Warning | str, category: type[Warning], filename: str, lineno: int,
                file: Any = None, line: str | None = None,
            ) -> None:  # fmt: skip
                said = getattr(_SAID, "list", None)
                if said is None:
                    shown(message, category, filename, lineno, file, line)
                else:
                    said.append((category, str(message)))

            warnings.showwarning = _show_or_tell
    _SAID.list = said = []
    try:
        yield said
    finally:
        _SAID.list = None


def worker_weight_builds() -> int:
    """How many area-weight matrices this process's Dask jobs have built (for tests and logs)."""
    return sum(len(job._cache) for job in _WORKER_JOBS.values())


def _npz_bytes(**arrays: np.ndarray) -> bytes:
    import io

    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return buf.getvalue()


def file_seed(seed: int | None, rel: str | Path) -> int:
    """The noise seed of one file: its relative path (as POSIX text) hashed with ``seed`` (0 when
    ``None``), the same on every machine, run and engine."""
    digest = hashlib.blake2b(f"{seed or 0}:{Path(rel).as_posix()}".encode(), digest_size=8).digest()
    return int.from_bytes(digest, "little") >> 1


def _read_done(path: Path) -> dict[str, dict]:
    done = {}
    if path.exists():
        for line in path.read_text().splitlines():
            try:
                entry = json.loads(line)
                done[entry["file"]] = entry
            except (json.JSONDecodeError, KeyError, TypeError):
                continue  # a line cut short by a kill
    return done


def _done_before(prev: dict | None, task: dict) -> bool:
    """Whether a file's entry ``prev`` in ``done.jsonl`` (or ``None``) says that ``task`` was done
    and its outputs stand: the same source file (and label map) by size and modification time, and
    the outputs of the sizes written. (Entries of an earlier version, without the label map's
    size and time, leave those out.)"""
    if prev is None:
        return False
    keys = ["src_bytes", "src_mtime_ns"] + [k for k in ("label_src_bytes", "label_src_mtime_ns") if k in prev]
    label = task.get("label_dst")
    return (
        all(prev.get(k) == task.get(k) for k in keys)
        and _has_size(Path(task["dst"]), prev.get("out_bytes"))
        and (label is None or _has_size(Path(label), prev.get("label_bytes")))
    )


def _has_size(path: Path, size: int | None) -> bool:
    return path.exists() and path.stat().st_size == size


def _find_label(labels: Path, rel: Path) -> Path | None:
    for cand in (labels / rel, (labels / rel).with_suffix(".png")):
        if cand.exists():
            return cand
    return None


def check_destination(dst: Path, src: Path | None = None) -> None:
    """Refuse a destination that is a file or lies under one, or that is the source folder
    ``src`` itself, before anything is written."""
    blocker = file_in_the_way(dst)
    if blocker is not None:
        what = "is a file" if blocker == dst else f"lies under {str(blocker)!r}, which is a file"
        raise ArgumentError("dst", f"dst must be a folder; {str(dst)!r} {what}")
    if src is not None and dst.exists() and dst.resolve() == src.resolve():
        raise ArgumentError(
            "dst", f"dst {str(dst)!r} is the source folder: its images would be overwritten; choose another"
        )


#: The records every run writes in its destination.
RECORDS = ("layout.json", "done.jsonl", "manifest.json")


def _label_paths(dst: Path, labels: Path | None, rel: Path, label_rule: str) -> tuple[Path | None, Path]:
    """A source file's label map (``None`` if it has none) and where its sensor-grid label goes."""
    label_src = _find_label(labels, rel) if labels is not None else None
    if label_src is None:
        return None, dst / "labels" / rel
    return label_src, dst / "labels" / rel.with_suffix(
        label_src.suffix if label_rule == "inverse" else ".png"
    )


def check_no_overwrite(
    src: Path, dst: Path, sources: Iterable[Path], labels: Path | None, label_rule: str
) -> None:
    """Refuse a run that would write over a file it reads: a sensor image, label map or record in
    ``dst`` whose path is a source image's under ``src`` or a label map's (folders resolved, so
    a folder link into the source counts; a file link or hard link does not: every output is
    written to a new file renamed over the name, which replaces the link, not what it points to);
    or over any file already in a ``dst`` that no earlier run wrote (it has no ``layout.json``).
    Before anything is written.

    Raises:
        ArgumentError: naming ``dst``, the file that would be overwritten and the output, in one line.
    """

    def identity(path: Path) -> Path | None:
        """The directory entry ``path`` names (its folder resolved), where it exists."""
        return path.parent.resolve() / path.name if os.path.lexists(path) else None

    reads: dict[Path, Path] = {}
    writes = [dst / name for name in RECORDS]
    made: dict[Path, Path] = {}  # each output of this run, and the source it comes from
    for path in list_images(src, dst):  # every image under src, not only the files of this run
        key = identity(path)
        if key is not None:
            reads[key] = path
    for path in sources:
        rel = path.relative_to(src)
        label_src, label_dst = _label_paths(dst, labels, rel, label_rule)
        outs = [dst / rel] + ([label_dst] if label_src is not None else [])
        for out in outs:
            other = made.setdefault(out, path)
            if other != path:  # e.g. a source under src/labels/ and a label map of the same name
                raise ArgumentError(
                    "dst", f"two outputs of the run would be one file, {str(out)!r}: from "
                    f"{str(other)!r} and from {str(path)!r}; rename or move one of them",
                )  # fmt: skip
        writes += outs
        if label_src is not None and (key := identity(label_src)) is not None:
            reads[key] = label_src
    ours = (dst / "layout.json").is_file()  # a destination of an earlier run: its outputs are ours
    for out in writes:
        key = identity(out)
        if key is not None and key in reads:
            raise ArgumentError(
                "dst",
                f"dst {str(dst)!r} would overwrite the source file {str(reads[key])!r} "
                f"(as {str(out)!r}); choose a folder that holds none of the inputs",
            )
        if key is not None and not ours:
            raise ArgumentError(
                "dst",
                f"dst {str(dst)!r} holds files of its own that the run would overwrite ({str(out)!r}); "
                "use an empty folder, or one an earlier run of this command wrote",
            )


def preprocess_folder(
    src: str | Path,
    dst: str | Path,
    layout: Layout,
    size: tuple[int, int],
    *,
    labels: str | Path | None = None,
    label_rule: str = "nearest",
    workers: int = 1,
    tol: float | None = None,
    progress: bool | None = None,
    files: Iterable[Path] | None = None,
    engine: str = "local",
    address: str | None = None,
    device: str | torch.device = "cpu",
    physics: SensorPhysics | None = None,
) -> PreprocessResult:
    """Write the sensor image of every image under ``src`` to the same relative path in ``dst``.

    Args:
        src: source folder (walked recursively; ``dst`` is skipped if it lies inside).
        dst: destination folder (created); a folder where the run would write over any file it
            reads (``src`` itself, or a folder whose outputs are source images or label maps) is
            refused before anything is written (`check_no_overwrite`).
        layout: the pixel layout (θ fixed).
        size: sensor size ``(h, w)``.
        labels: folder of class-index label maps with the same relative paths (a ``.png``
            of the same stem is also accepted), or None.
        label_rule: ``"nearest"``, ``"majority"`` (sensor-grid labels) or ``"inverse"``
            (full-resolution copies plus back-warp maps); see [`layoutwarp.labels`][].
        workers: worker threads (1: no pool).
        tol: bound on each pixel's error relative to the value range, spent on curved edges
            (default ``None``: what each file's dtype resolves,
            [`data_tolerance`][layoutwarp.tolerance.data_tolerance]:
            a quarter of a level for integer images, i.e. 9.8e-4 at 8 bit and 3.8e-6 at 16 bit,
            and 2^-12 for float images); with rounding, integer outputs stay within 0.75 levels
            of the exact integral.
        progress: show a progress bar (default: when stderr is a terminal).
        files: process only these files (paths under ``src``).
        engine: ``"local"`` (``workers`` threads here) or ``"dask"`` (the optional extra
            ``layoutwarp[dask]``): every file is a task on a Dask cluster, each worker process
            builds the area weights of a source size once; the outputs are the same bytes, and
            ``done.jsonl``/the manifest are written here as they arrive. Without ``address`` a
            local cluster of ``workers`` single-threaded processes is started and stopped.
        address: a running Dask scheduler to join (``"tcp://host:8786"``); its workers must see
            ``src`` and ``dst`` at the same paths (a shared file system).
        device: where the sparse products run (``"cpu"``, ``"cuda"``; on a Dask cluster, the
            device of each worker). The CPU's outputs are the reference; see
            [`AreaResampler`][] for CUDA's.
        physics: record the images as a real sensor would ([`layoutwarp.physics`][]: the image's
            full range is ``photons_per_um2``; outputs in the image's units, the ISP's estimate);
            each file's noise is seeded from ``physics.seed`` (0 when ``None``) and its relative
            path ([`file_seed`][]), so a rerun, or another engine, writes the same bytes.

    Returns:
        a [`PreprocessResult`][]; failures (unreadable files) are listed, not raised.

    Raises:
        ValueError: for a bad ``label_rule``, ``workers`` or sensor ``size``, a ``labels`` that is
            not a folder, a ``dst`` that would overwrite an input or write two outputs to one
            file, or one that already holds a dataset made with a different layout, physics,
            ``tol`` or ``label_rule``.
    """
    check_layout(layout)
    size = check_size(size)
    check_choice(label_rule, LABEL_RULES, "label_rule")
    check_int(workers, "workers", 1, MAX_WORKERS)
    check_choice(engine, ENGINES, "engine")
    tol = None if tol is None else check_number(tol, "tol", 0, lo_open=True)
    device = check_device(device)
    physics = as_physics(physics)
    if address is not None and engine != "dask":
        raise ArgumentError("address", f"address needs engine='dask', got engine={engine!r}")
    src, dst = Path(src), Path(dst)
    if not src.is_dir():
        raise ArgumentError("src", f"src must be a folder, got {str(src)!r}")
    if labels is not None and not Path(labels).is_dir():
        raise ArgumentError("labels", f"labels must be a folder of label maps, got {str(labels)!r}")
    labels = Path(labels) if labels is not None else None
    check_destination(dst, src)
    sources = [Path(f) for f in files] if files is not None else list_images(src, dst)
    if not sources:
        what = "files is empty" if files is not None else f"src {str(src)!r} holds no images"
        raise ArgumentError("src", f"{what} ({', '.join(IMAGE_SUFFIXES)})")
    for path in sources:
        if files is not None and (not path.is_relative_to(src) or not path.is_file()):
            raise ArgumentError(
                "files", f"files must be image files under src {str(src)!r}, got {str(path)!r}"
            )
    # what the walk found that is no file (a broken link, a pipe): listed as failed, never opened
    odd = [path for path in sources if not path.is_file()]
    sources = [path for path in sources if path.is_file()]
    if labels is not None and not any(_find_label(labels, p.relative_to(src)) for p in sources):
        raise ArgumentError(
            "labels",
            f"labels {str(labels)!r} holds no label map for any image (same relative paths, or .png)",
        )
    check_no_overwrite(src, dst, sources, labels, label_rule)
    config = layout_spec(layout) | {"size_hw": list(size)}
    layout_file, done_file = dst / "layout.json", dst / "done.jsonl"
    done = _read_done(done_file)
    if layout_file.exists() and done:  # a folder where no file was finished holds no dataset yet
        old_layout, old = load_layout(layout_file, dtype=torch.float64)
        prev = layout_spec(old_layout) | {"size_hw": old["size_hw"]}
        if not same_spec(prev, config):
            raise ArgumentError(
                "dst", f"{dst} holds a dataset made with another layout ({prev}); use an empty folder"
            )
        before = old.get("extra") or {}
        if before.get("physics") != (physics.to_dict() if physics else None):
            raise ArgumentError(
                "dst", f"{dst} holds a dataset recorded with other sensor physics; use an empty folder"
            )
        for name, now in (("tol", tol), ("label_rule", label_rule if labels else None)):
            then = before.get(name)
            if then != now:  # its files were made so: a resumed run would mix the two
                blank = "none (the default)" if name == "tol" else "none (no label maps)"
                said = {v: blank if v is None else repr(v) for v in (then, now)}
                raise ArgumentError(
                    name, f"{dst} holds a dataset made with {name} {said[then]}, not {said[now]}; "
                    f"use an empty folder, or {name} {said[then]} to resume it",
                )  # fmt: skip
    tasks, skipped = [], 0
    for path in sources:
        rel = path.relative_to(src)
        st = path.stat()
        out = dst / rel
        label_src, label_dst = _label_paths(dst, labels, rel, label_rule)
        task = {"rel": str(rel), "src": str(path), "dst": str(out), "src_bytes": st.st_size}
        task |= {"src_mtime_ns": st.st_mtime_ns, "backwarp_dir": str(dst / "backwarp")}
        if label_src is not None:
            lst = label_src.stat()
            task |= {"label_src": str(label_src), "label_dst": str(label_dst)}
            task |= {"label_src_bytes": lst.st_size, "label_src_mtime_ns": lst.st_mtime_ns}
        if _done_before(done.get(str(rel)), task):
            skipped += 1
        else:
            tasks.append(task)
    with ExitStack() as stack:  # the cluster reached before anything is written: a run refused
        # there leaves dst as it was
        client = stack.enter_context(_dask_client(workers, address)) if engine == "dask" and tasks else None
        dst.mkdir(parents=True, exist_ok=True)
        extra = {"physics": physics.to_dict()} if physics else {}
        save_layout(
            layout, layout_file, size, tol=tol, label_rule=label_rule if labels else None, source=str(src),
            **extra,
        )  # fmt: skip
        config |= {"tol": tol, "label_rule": label_rule}
        result = PreprocessResult(skipped=skipped)
        for path in odd:
            error = "ValueError: not a file (a broken link, a pipe or a device)"
            result.failed.append({"file": str(path.relative_to(src)), "error": error})
        show = sys.stderr.isatty() if progress is None else progress
        from tqdm.auto import tqdm

        bar = tqdm(total=len(tasks), desc="preprocess", unit="img", disable=not show)
        t0 = time.perf_counter()
        finished = False
        try:
            told: set[tuple[type[Warning], str]] = set()
            with done_file.open("a") as log:

                def record(r: dict) -> None:
                    for said in r.get("warnings", ()):  # a worker's (a thread's or a Dask
                        if said not in told:  # worker's), told here once a run, with its file
                            told.add(said)
                            result.warnings.append(f"{said[1]} (first: {r.get('entry', r).get('file')})")
                            warnings.warn(result.warnings[-1], said[0], stacklevel=2)
                    if r["ok"]:
                        log.write(json.dumps(r["entry"]) + "\n")
                        log.flush()
                        result.processed += 1
                        for stage, sec in r.get("stages", {}).items():
                            result.stages[stage] = result.stages.get(stage, 0.0) + sec
                    else:
                        result.failed.append({"file": r["file"], "error": r["error"]})
                    bar.update(1)

                fixed = layout_from_spec(config, dtype=torch.float64)
                job = _Job(
                    fixed, size, tol, label_rule, str(device), physics, say=_above(bar) if show else None
                )
                if client is not None:
                    spec = {"layout": config, "size": list(size), "tol": tol, "label_rule": label_rule}
                    spec |= {"physics": physics.to_dict() if physics else None}
                    spec = json.dumps(spec | {"device": str(device)})
                    _run_on_dask(client, spec, tasks, record)
                elif workers == 1 or len(tasks) <= 1:
                    for task in tasks:
                        record(_telling(job.process, task))
                else:
                    pool = ThreadPoolExecutor(workers)
                    futures, seen = [pool.submit(_telling, job.process, t) for t in tasks], set()
                    try:
                        for fut in as_completed(futures):
                            seen.add(fut)
                            record(fut.result())
                    finally:  # stopped (Ctrl-C): the images in hand are finished, the rest not begun
                        pool.shutdown(cancel_futures=True)  # (it waits: every future not cancelled is done)
                        for fut in futures:  # and those finished meanwhile are recorded: not done again
                            if fut not in seen and not fut.cancelled() and fut.exception() is None:
                                record(fut.result())
            finished = True
        finally:  # the manifest of a stopped run too: what it finished, and that it did not end
            bar.close()
            result.seconds = time.perf_counter() - t0
            manifest = {
                "layout": config,
                "source": str(src),
                "labels": str(labels) if labels else None,
                "files_done": len(_read_done(done_file)),
                "processed_this_run": result.processed,
                "skipped_this_run": result.skipped,
                "failed": result.failed,
                "warnings": result.warnings,
                "finished": finished,
                "seconds": round(result.seconds, 3),
                "workers": workers,
                "engine": engine if address is None else f"{engine} at {address}",
                "device": str(device),
                "physics": physics.to_dict() if physics else None,
                "run": run_info(device),
            }
            result.manifest = dst / "manifest.json"
            atomic_write(result.manifest, json.dumps(manifest, indent=2).encode())
        return result


def _above(bar: Any) -> Callable[[str], None]:
    """A line written above the progress bar, on standard error with it."""
    return lambda line: bar.write(line, file=sys.stderr)


# How long a run waits for the Dask scheduler at its ``address`` before it gives up.
_CONNECT_TIMEOUT_S = 10


@contextmanager
def _dask_client(workers: int, address: str | None) -> Iterator[Any]:
    """A client of the Dask scheduler at ``address``, or of a new local cluster of ``workers``
    single-threaded processes (closed with it, its scratch folder too: Dask's own, in the system's
    temporary folder, kept its lock files after every run); refused in one line (``engine`` or
    ``address``) where Dask is not installed or no scheduler answers."""
    try:
        from dask.distributed import Client, LocalCluster
    except ImportError:
        raise ArgumentError(
            "engine", "engine='dask' needs the optional extra: pip install 'layoutwarp[dask]'"
        ) from None
    import dask

    cluster, stack = None, ExitStack()
    try:
        if address is None:
            scratch = stack.enter_context(
                tempfile.TemporaryDirectory(prefix="layoutwarp-dask-", ignore_cleanup_errors=True)
            )
            stack.enter_context(dask.config.set({"temporary-directory": scratch}))
            cluster = LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                local_directory=scratch,
            )  # fmt: skip
        try:
            client = Client(address or cluster, timeout=_CONNECT_TIMEOUT_S)
        except (OSError, ValueError) as exc:  # no port, no such host, nobody listening
            raise ArgumentError(
                "address", f"address {address!r}: no Dask scheduler reached ({str(exc).splitlines()[0]})"
            ) from None
        with client:
            yield client
    finally:
        if cluster is not None:
            cluster.close()
        stack.close()  # Dask's settings as they were, then its scratch folder removed


def _run_on_dask(client: Any, spec: str, tasks: list[dict], record: Callable[[dict], None]) -> None:
    """Run every task on the cluster of ``client`` (chunks of files, about four a worker thread)
    and record the results here as they complete."""
    from dask.distributed import as_completed as completed

    n = max(1, sum(client.nthreads().values()))
    per = max(1, min(16, len(tasks) // (4 * n)))  # about four chunks per worker thread
    chunks = [tasks[k : k + per] for k in range(0, len(tasks), per)]
    futures = client.map(_remote_process_many, [spec] * len(chunks), chunks, pure=False)
    for fut in completed(futures):
        for r in fut.result():
            record(r)
