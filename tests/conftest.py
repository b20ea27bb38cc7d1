"""Shared fixtures. Every test draws its random inputs from a seed of its own, fixed by its name,
so the same commit gets the same verdict; ``LAYOUTWARP_SEED=random`` draws fresh seeds (to
explore), a failing test prints its seed, and ``LAYOUTWARP_SEED=<seed>`` replays it."""

from __future__ import annotations

import ctypes
import fcntl
import gc
import hashlib
import math
import os
import platform
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

# pytest's workers (pytest-xdist, one a core) share the cores, so a thread waiting for work
# sleeps; the kernels compile once for all of them, before they start (pytest_configure)
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import numpy as np
import pytest
import shapely
import torch

import layoutwarp as lw

ROOT = Path(__file__).resolve().parents[1]
SAMPLES = ROOT / "data_samples"
SHARED = ROOT.parent / "shared" / "data"

torch.set_num_threads(min(2, torch.get_num_threads()))
# the suite compiles in process (results the same to the bit from the first call on, as the tests
# compare them); tests/test_jit.py tries the background compile in processes of its own
os.environ.setdefault("LAYOUTWARP_JIT", "wait")
if SHARED.is_dir():  # the full data sets, where this checkout has them (tests that need them skip else)
    os.environ.setdefault("LAYOUTWARP_DATA", str(SHARED))


def pytest_configure(config) -> None:
    """Before any test (in pytest's controller, before its workers start): the units of kernels
    missing from numba's cache, compiled two at a time in processes of their own, so that the
    workers load them rather than each compile them (a clean clone's run)."""
    from layoutwarp import jit

    if not os.environ.get("PYTEST_XDIST_WORKER"):
        jit.compile_missing(2, lambda line: print(line, file=sys.stderr, flush=True))


def seed_for(nodeid: str, setting: str | None = None) -> int:
    """A test's random seed: fixed by its id (``nodeid``), fresh with ``setting == "random"``, or
    ``setting`` itself when it is a number (the seed a failure printed)."""
    if setting is None or setting == "":
        return int.from_bytes(hashlib.blake2b(nodeid.encode(), digest_size=4).digest(), "little")
    if setting.strip().lower() == "random":
        return int.from_bytes(os.urandom(4), "little")
    try:
        return int(setting) % 2**32  # NumPy's legacy seeding takes 0 .. 2**32 - 1
    except ValueError:
        raise pytest.UsageError(f"LAYOUTWARP_SEED must be a number or 'random', got {setting!r}") from None


@pytest.fixture(autouse=True)
def seed(request) -> int:
    """Every test's random seed ([`seed_for`][]: from its id unless ``LAYOUTWARP_SEED`` says
    otherwise); torch's and NumPy's global generators start from it, so unseeded draws replay too."""
    s = seed_for(request.node.nodeid, os.environ.get("LAYOUTWARP_SEED"))
    request.node.user_properties.append(("seed", s))
    torch.manual_seed(s)
    np.random.seed(s)  # noqa: NPY002  (the legacy global generator, for unseeded draws)
    return s


@pytest.fixture
def gen(seed) -> torch.Generator:
    return torch.Generator().manual_seed(seed)


_LIBC = ctypes.CDLL(None) if platform.libc_ver()[0] == "glibc" else None
_PAGE_MB = os.sysconf("SC_PAGE_SIZE") / 2**20


def _resident_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * _PAGE_MB


_RESIDENT = pytest.StashKey[float]()


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_setup(item) -> None:
    item.stash[_RESIDENT] = _resident_mb() if _LIBC is not None else 0.0


def _hand_back_memory(start_mb: float) -> None:
    """Hand the heap a test freed back to the system (glibc keeps it otherwise, and the process
    would hold its largest test's peak to the end). A process 64 MB larger than at ``start_mb``
    is collected first: torch modules sit in reference cycles, their tensors wait for the
    collector (a full collection costs ~0.1-0.3 s, too much after every test)."""
    if _LIBC is not None:
        if _resident_mb() > start_mb + 64:
            gc.collect()
        _LIBC.malloc_trim(0)


@pytest.hookimpl(trylast=True)  # after the fixtures' own teardown
def pytest_runtest_teardown(item, nextitem) -> None:
    _hand_back_memory(item.stash.get(_RESIDENT, 0.0))


@pytest.fixture(autouse=True)
def _one_heavy_test_at_a_time(request, tmp_path_factory) -> Iterator[None]:
    """A test marked ``heavy`` waits until no other pytest worker of this run holds one (a lock
    file in the run's shared temporary folder): two side by side take the suite past 3 GB. It
    hands its memory back before it lets the next one start."""
    if request.node.get_closest_marker("heavy") and hasattr(request.config, "workerinput"):
        with open(tmp_path_factory.getbasetemp().parent / "heavy.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            yield
            _hand_back_memory(request.node.stash.get(_RESIDENT, 0.0))
    else:
        yield


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item, call):
    outcome = yield
    rep = outcome.get_result()
    if rep.failed:
        for k, v in item.user_properties:
            if k == "seed":  # in the failure's own message (and so in the summary line), and below it
                crash = getattr(rep.longrepr, "reprcrash", None)
                if crash is not None:
                    crash.message = f"[LAYOUTWARP_SEED={v}] {crash.message}"
                rep.sections.append(("random seed", f"LAYOUTWARP_SEED={v}"))


@pytest.fixture(params=["cpu", "cuda"] if torch.cuda.is_available() else ["cpu"])
def device(request) -> torch.device:
    """Every device test runs on the CPU, and on CUDA where a GPU is present."""
    return torch.device(request.param)


def rand_theta(gen: torch.Generator, limit: float = 0.95) -> torch.Tensor:
    return (torch.rand(2, generator=gen, dtype=torch.float64) * 2 - 1) * limit


def grad_tol(layout: lw.Layout, g: torch.Tensor) -> float:
    """How far two summation orders of the same θ-gradient ``g`` may differ in float64: rounding
    times the conditioning. Near |θ| = 1 the per-vertex terms reach ~1/(1 − |θ|)² of the sum and
    cancel in it: at θ = 0.95 two backends differed by 6e-12 of the gradient (seed 1296022901),
    at θ = 0.984 by 1.8e-11 (seed 949116650), where a 1-ulp change of θ moves either backend's
    gradient by up to 6e-11 and the two agree to 1e-13 averaged over such changes."""
    return 1e-12 * max(float(g.abs().max()), 1.0) / (1 - float(layout.theta.detach().abs().max())) ** 2


def near_boundaries(pts: np.ndarray, polys: list, within: float = 1e-6) -> np.ndarray:
    """Which of the shapely points ``pts`` lie within ``within`` of some polygon's boundary (where
    point-in-polygon cannot tell one pixel from its neighbour): a tree query, not a distance to
    the union of every boundary (seconds for a finely subdivided mesh)."""
    near = np.zeros(len(pts), dtype=bool)
    tree = shapely.STRtree([p.boundary for p in polys])
    near[tree.query(pts, predicate="dwithin", distance=within)[0]] = True
    return near


def clip_reference(img: torch.Tensor, polys: list[np.ndarray], size) -> np.ndarray:
    """Mean of a piecewise-constant image over each polygon by shapely clipping (float64)."""
    n, hs, ws = img.shape
    arr = img.numpy()
    out = np.zeros((n, len(polys)))
    for k, p in enumerate(polys):
        poly = shapely.Polygon(np.stack([(p[:, 0] + 1) * ws / 2, (p[:, 1] + 1) * hs / 2], 1))
        x0, y0, x1, y1 = poly.bounds
        acc = np.zeros(n)
        for r in range(max(0, math.floor(y0)), min(hs, math.ceil(y1))):
            for c in range(max(0, math.floor(x0)), min(ws, math.ceil(x1))):
                a = poly.intersection(shapely.box(c, r, c + 1, r + 1)).area
                acc += a * arr[:, r, c]
        out[:, k] = acc / poly.area
    return out.reshape(n, *size)


def ptx_or_skip(kernel, dtype: str = "float32", signature: str | None = None) -> str:
    """:func:`layoutwarp.kernels.cuda_ptx`, or a skip where NVIDIA's numba-cuda target or a
    library it compiles with (NVVM, NVRTC, the CUDA runtime) is missing; no GPU needed."""
    from layoutwarp import kernels

    try:
        from numba import cuda  # numba-cuda's import loads the CUDA runtime

        if getattr(cuda, "implementation", "") != "NVIDIA":
            pytest.skip("needs NVIDIA's numba-cuda (pip install 'layoutwarp[cuda]')")
        return kernels.cuda_ptx(kernel, dtype, signature=signature)
    except Exception as err:
        if "NotFound" in type(err).__name__ or "Support" in type(err).__name__:  # a library missing
            pytest.skip(f"no CUDA compiler libraries here ({type(err).__name__})")
        raise


def run_in_simulator(script: str, *args: object, wait: bool = False) -> None:
    """Run ``script`` (Python source) with ``args`` in a process of its own under numba's CUDA
    simulator (the device kernels as plain Python, no GPU), ``LAYOUTWARP_JIT=wait`` with
    ``wait``; fail with the end of its standard error where it fails."""
    env = {**os.environ, "NUMBA_DISABLE_JIT": "1", "NUMBA_ENABLE_CUDASIM": "1"}
    if wait:
        env["LAYOUTWARP_JIT"] = "wait"
    cmd = [sys.executable, "-c", script, *(str(a) for a in args)]
    run = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert run.returncode == 0, run.stderr[-3000:]
