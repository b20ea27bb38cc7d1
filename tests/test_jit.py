"""Compiled code without the wait (layoutwarp.jit) and the CUDA kernels on a newer numpy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from conftest import ROOT, ptx_or_skip

import layoutwarp as lw
from layoutwarp import jit

pytestmark = pytest.mark.skipif(not lw.kernels.available(), reason="needs numba")


def run_python(code: str, env: dict[str, str], timeout: float = 600) -> subprocess.CompletedProcess:
    full = {**os.environ, **env}
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)],
        cwd=ROOT,
        env=full,
        capture_output=True,
        text=True,
        timeout=timeout,
    )


def test_mode_comes_from_the_environment_and_is_checked(monkeypatch):
    monkeypatch.setenv(jit.ENV, "off")
    assert jit.mode() == "off"
    assert not jit.ready("learn", torch.float64)  # off: the torch path, nothing compiled
    monkeypatch.setenv(jit.ENV, "sometimes")
    with pytest.raises(
        ValueError, match="LAYOUTWARP_JIT must be one of background, wait, off, got 'sometimes'"
    ):
        jit.mode()
    with pytest.raises(ValueError, match="mode must be one of"):
        jit.set_mode("eventually")
    with pytest.raises(ValueError, match="group must be one of"):
        jit.ready("everything")
    with pytest.raises(ValueError, match=r"dtype must be one of float32, float64, got torch\.float16"):
        jit.ready("learn", torch.float16)


@pytest.mark.slow
def test_the_first_call_answers_from_torch_while_a_child_compiles_then_runs_compiled(tmp_path):
    """From an empty cache in the background mode: the first fixed-layout forward returns at
    once from the torch path, one line says what is compiling, the child fills the cache, and a
    later call loads the compiled kernels (nothing of them compiled in the process itself) and
    gives the same values to float32 rounding; the sensor's noise is drawn by its plain kernel,
    compiled in the process in seconds at its first call while the child has the fused one to
    do, so its draws are the compiled sampler's from the first call on (the same as in wait
    mode)."""
    code = """
        import json, torch, layoutwarp as lw
        from layoutwarp import jit
        g = torch.Generator().manual_seed(5)
        img = torch.rand(2, 3, 40, 60, generator=g)
        layout = lw.CurvLayout((0.4, -0.3))
        with torch.no_grad():  # the torch path answers: the state says the child is compiling
            first = lw.simulate(img, layout, (7, 9))
        state = jit.status()["fixed/float32"]
        if jit._WORKER is not None:
            jit._WORKER.wait_for("fixed/float32")
        with torch.no_grad():
            later = lw.simulate(img, layout, (7, 9))
        phys = lw.SensorPhysics((300.0, 400.0), photons_per_um2=20, seed=3)
        noisy = lw.simulate(img, layout, (7, 9), physics=phys)
        print(json.dumps({"state": state, "after": jit.status()["fixed/float32"],
            "diff": float((first - later).abs().max()), "scale": float(later.abs().max()),
            "noisy": noisy.flatten().tolist()}))
    """
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"}
    res = run_python(code, env)
    assert res.returncode == 0, res.stderr[-3000:]
    out = json.loads(res.stdout.strip().splitlines()[-1])
    assert out["state"] == "compiling" and out["after"] == "ready"
    assert 0 < out["diff"] <= 1e-6 * out["scale"]  # float32 sums in another order: rounding, no more
    notices = [line for line in res.stderr.splitlines() if line.startswith("layoutwarp:")]
    assert all("once per installation" in n for n in notices)
    assert any("compiling in the background" in n and "fixed layout" in n for n in notices)
    # the product came from the child's cache, never compiled here; the noise compiled here
    assert not any(n.startswith("layoutwarp: compiling a fixed layout") for n in notices)
    assert any(
        n.startswith("layoutwarp: compiling the plain version (seconds) of the sensor's") for n in notices
    )
    # the same draws as a process that compiled everything before its first call (in this
    # installation's cache, which the rest of the suite compiles the same kernels into)
    res_wait = run_python(code, {jit.ENV: "wait"})
    assert res_wait.returncode == 0, res_wait.stderr[-3000:]
    assert json.loads(res_wait.stdout.strip().splitlines()[-1])["noisy"] == out["noisy"]


def _children_of(pid: int) -> list[int]:
    """The processes whose environment names ``pid`` as the parent of a background compile."""
    found = []
    for entry in os.listdir("/proc"):
        if entry.isdigit():
            try:
                with open(f"/proc/{entry}/environ", "rb") as f:
                    if f"LAYOUTWARP_PARENT={pid}".encode() in f.read().split(b"\0"):
                        found.append(int(entry))
            except OSError:  # gone meanwhile, or not ours to read
                pass
    return found


@pytest.mark.skipif(not os.path.isdir("/proc"), reason="lists processes through /proc")
@pytest.mark.parametrize("how", ["exits", "is killed"])
def test_no_process_outlives_the_command_that_started_it(tmp_path, how):
    """A command that starts a background compile from an empty cache and ends (normally, or
    killed with SIGKILL, which leaves it no chance to clean up) leaves no process behind: 2 s
    after it has gone, none of its background compile remains."""
    code = """
        import os, sys, torch, layoutwarp as lw
        torch.set_num_threads(2)
        with torch.no_grad():  # a fixed layout's first forward: the child starts compiling
            lw.simulate(torch.ones(1, 1, 20, 20), lw.CurvLayout((0.3, 0.1)), (4, 4))
        assert lw.jit._WORKER is not None and lw.jit._WORKER.busy()
        assert torch.get_num_threads() == 1  # a core left to the compile meanwhile
        print(os.getpid(), flush=True)
        sys.stdin.readline()  # ends when told (or is killed meanwhile)
    """
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"}
    cmd = [sys.executable, "-c", textwrap.dedent(code), how]
    pipes = dict.fromkeys(("stdin", "stdout", "stderr"), subprocess.PIPE)
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, text=True, **pipes)
    pid = int(proc.stdout.readline())
    assert _children_of(pid), "the command started no background compile"
    if how == "is killed":
        proc.kill()
    else:
        proc.stdin.write("\n")
        proc.stdin.flush()
    assert proc.wait(timeout=120) == (-9 if how == "is killed" else 0), proc.stderr.read()[-3000:]
    time.sleep(2)
    assert _children_of(pid) == []


def test_a_stopped_background_compile_gives_torch_its_threads_back(tmp_path):
    code = """
        import torch, layoutwarp as lw
        torch.set_num_threads(2)
        with torch.no_grad():
            lw.simulate(torch.ones(1, 1, 20, 20), lw.CurvLayout((0.3, 0.1)), (4, 4))
        during = torch.get_num_threads()
        lw.jit.stop_worker()
        print(during, torch.get_num_threads())
    """
    env = {"NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"}
    res = run_python(code, env)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.split() == ["1", "2"]


def test_a_look_at_the_cache_compiles_nothing(tmp_path):
    """:func:`jit.status` on an empty cache says 'not compiled' and compiles nothing (a look at
    the cache must not turn into the compile it was meant to avoid)."""
    code = """
        import layoutwarp as lw
        print(lw.jit.status())
    """
    res = run_python(code, {"NUMBA_CACHE_DIR": str(tmp_path / "cache")})
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.count("'not compiled'") == len(jit.UNITS)
    written = [p.name for p in (tmp_path / "cache").rglob("*") if p.is_file()]
    # no kernel was compiled into the cache (a timing said so, flakily); the sources' digest is kept
    assert written in ([], [lw.kernels.base.SOURCES_DIGEST]), written


@pytest.mark.slow
def test_after_the_warm_ups_the_entry_points_compile_nothing():
    """The warm-ups cover every type the entry points call the kernels with: after those of the
    groups they use, the README's example (a learnable curv step at 2048x1024 RGB, a fixed
    forward, a call with physics), the other learnable families and float64 compile nothing."""
    from numba.core import event

    for group, dtype in (
        ("learn", "float32"),
        ("fixed", "float32"),
        ("measure", "float32"),
        ("learn", "float64"),
    ):
        assert jit.ready(group, dtype, wait=True)  # compiled or loaded, as a first call would
    compiles = []

    class Count(event.Listener):
        def on_start(self, ev):
            compiles.append(ev.data["dispatcher"].py_func.__name__)

        def on_end(self, ev):
            pass

    g = torch.Generator().manual_seed(1)
    img = torch.rand(1, 3, 1024, 2048, generator=g)
    with event.install_listener("numba:compile", Count()):
        for layout in (
            lw.CurvLayout((0.3, -0.24), learn=True),
            lw.FoveaLayout((0.35, -0.25), center=(0.3, -0.2), learn=True),
            lw.EllipticLayout((0.2, 0.3), learn=True),
        ):
            lw.simulate(img, layout, (129, 257)).sum().backward()
        lw.simulate(
            img[:, :, :300, :500].double(), lw.CurvLayout((0.3, -0.2), learn=True), (33, 65)
        ).sum().backward()
        with torch.no_grad():
            lw.simulate(img, lw.CurvLayout((0.3, -0.1)), (129, 257))
            lw.simulate(img, lw.RectLayout((0.3, -0.1)), (129, 257))
        phys = lw.SensorPhysics((2800, 5600), photons_per_um2=50)
        lw.simulate(img, lw.CurvLayout((0.3, -0.1)), (129, 257), physics=phys)
    assert compiles == []


@pytest.mark.heavy
def test_the_cuda_kernels_compile_on_numpy_2_5_without_its_removed_aliases():
    """numpy 2.5 removed ``np.row_stack``, which numba-cuda 0.30.4 reads while registering its
    overloads: emulated here (the version string set, the alias deleted, before anything is
    imported), a CUDA kernel of each module compiles to PTX (the overloads register once, at the
    first compile; the other tests compile every kernel), and numpy is left without the alias.
    (On an H100 with numpy 2.5.2 itself the CUDA tests pass: examples/gpu/gpu_check_h100.json.)"""
    ptx_or_skip("edge_sums")  # skips where numba-cuda or the CUDA compilers are missing
    code = """
        import numpy
        numpy.__version__ = "2.5.0"
        if hasattr(numpy, "row_stack"):  # a numpy before 2.5 (on 2.5 itself this changes nothing)
            del numpy.row_stack
        numpy.__all__ = [n for n in numpy.__all__ if n != "row_stack"]
        from layoutwarp import kernels
        from layoutwarp.kernels import mesh as mk
        assert ".entry" in kernels.cuda_ptx("edge_sums", "float32")
        fn, sig = mk.CUDA_KERNELS["counts"]
        assert ".entry" in kernels.cuda_ptx(fn, signature=sig)
        print("compiled", hasattr(numpy, "row_stack"))
    """
    res = run_python(code, {})
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.strip().splitlines()[-1] == "compiled False"


def test_doctor_names_each_paths_backend_and_the_kernels_state(capsys, monkeypatch):
    from layoutwarp import cli

    assert cli.main(["doctor"]) == 0
    out = capsys.readouterr().out
    assert f"numpy {__import__('numpy').__version__}" in " ".join(out.split())
    assert "CPU:  compiled (numba" in out and "LAYOUTWARP_JIT=wait" in out
    for unit in jit.UNITS:
        assert any(line.split()[:1] == [unit] for line in out.splitlines()), unit
    monkeypatch.setenv(jit.ENV, "off")
    assert cli.main(["doctor"]) == 0
    assert "CPU:  torch (LAYOUTWARP_JIT=off)" in capsys.readouterr().out
    monkeypatch.setenv(jit.ENV, "later")
    assert cli.main(["doctor"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == "layoutwarp doctor: error: LAYOUTWARP_JIT must be one of background, wait, off, got 'later'"


def test_a_cuda_fallback_is_named_with_its_reason(monkeypatch):
    """Where the CUDA kernels do not run (numba-cuda fails to compile, as on numpy 2.5 before),
    doctor and every results file say the torch path runs, and why."""
    import warnings

    from layoutwarp import doctor, kernels

    def broken(dtype="float32"):
        reason = "layoutwarp: numba's CUDA kernels do not run here (AttributeError: row_stack)"
        warnings.warn(reason, RuntimeWarning, stacklevel=2)
        return False

    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda *a: "a test GPU")
    monkeypatch.setattr(kernels, "cuda_available", broken)
    assert doctor.cuda_backend() == "torch (numba's CUDA kernels do not run here (AttributeError: row_stack))"
    assert doctor.cuda_backend(probe=False) == "not used yet in this process (a test GPU)"
    monkeypatch.setattr(kernels, "cuda_checked", lambda: {"float32": False})
    assert "cuda: torch (numba's CUDA kernels do not run here" in lw.doctor.run_info()["backends"]


def test_a_look_at_the_cache_keeps_the_users_cached_weights():
    """The warm-ups go through simulate's cached area weights on tiny layouts; a look at the cache
    (or a compile) in a user's process leaves that cache as it found it."""
    from layoutwarp import resampler, warmups

    img = torch.rand(1, 3, 40, 60)
    with torch.no_grad():
        lw.simulate(img, lw.CurvLayout((0.4, -0.3)), (7, 9))
    before = resampler.RESAMPLERS.keys()
    assert before
    for group in ("fixed", "measure"):
        getattr(warmups, f"_warm_{group}")(torch.float32)
    assert resampler.RESAMPLERS.keys() == before


@pytest.mark.heavy
def test_the_first_cuda_compile_says_so_once(tmp_path):
    """A CUDA kernel with no compiled copy in numba's cache announces the compile in one line,
    once per process; a kernel whose copy is in the cache says nothing (no GPU needed: the
    kernels are not launched)."""
    pytest.importorskip("numba.cuda")
    code = """
        import pathlib
        from numba import cuda
        from layoutwarp.kernels import device
        device._import_cuda()
        kernels = [cuda.jit(cache=True)(device._kernel_source(n)) for n in ("edge_sums", "forward")]
        for k in kernels:
            device._announce_compile(k)
        index = pathlib.Path(kernels[0]._cache._cache_file._index_path)
        index.parent.mkdir(parents=True, exist_ok=True)
        index.write_bytes(b"")
        device._ANNOUNCED.clear()
        device._announce_compile(kernels[0])  # in the cache now: nothing to say
    """
    res = run_python(code, {"NUMBA_CACHE_DIR": str(tmp_path / "cache")})
    assert res.returncode == 0, res.stderr[-3000:]
    lines = [line for line in res.stderr.splitlines() if line.startswith("layoutwarp:")]
    assert lines == ["layoutwarp: compiling the CUDA kernels for this GPU (seconds; once per installation; "
                     "see layoutwarp doctor)"]  # fmt: skip


def test_the_compile_started_from_a_short_lived_thread_lives_as_long_as_its_process(tmp_path):
    """The kernel ends a child with the *thread* that started it (PR_SET_PDEATHSIG): a first call
    from a thread that ends (a web request's, a DataLoader's pin thread) must not take the
    background compile with it."""
    code = """
        import os, sys, threading, time, torch, layoutwarp as lw
        def call():
            with torch.no_grad():
                lw.simulate(torch.ones(1, 1, 20, 20), lw.CurvLayout((0.3, 0.1)), (4, 4))
        t = threading.Thread(target=call)
        t.start(); t.join()
        time.sleep(1)
        print(os.getpid(), lw.jit._WORKER.proc.poll(), flush=True)
        sys.stdin.readline()
    """
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"}
    pipes = dict.fromkeys(("stdin", "stdout", "stderr"), subprocess.PIPE)
    cmd = [sys.executable, "-c", textwrap.dedent(code)]
    proc = subprocess.Popen(cmd, cwd=ROOT, env=env, text=True, **pipes)
    try:
        pid, state = proc.stdout.readline().split()
        assert state == "None" and _children_of(int(pid))  # still compiling after its thread ended
    finally:
        proc.communicate("\n", timeout=120)
    time.sleep(2)
    assert _children_of(int(pid)) == []


def test_no_python_to_start_leaves_the_torch_path_and_one_line(tmp_path):
    """Where no child can start (an embedded interpreter: ``sys.executable`` is not Python), the
    call answers from the torch path, one line says why, and no later call tries again."""
    code = """
        import sys, torch, layoutwarp as lw
        sys.executable = "/nonexistent/python"
        img = torch.arange(2 * 30 * 40.0).reshape(1, 2, 30, 40)
        with torch.no_grad():
            outs = [lw.simulate(img, lw.CurvLayout((0.4, -0.3)), (5, 7)) for _ in range(3)]
        print(lw.jit._WORKER is None, all(torch.equal(outs[0], o) for o in outs))
    """
    res = run_python(code, {"NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"})
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.split() == ["True", "True"]
    notices = [line for line in res.stderr.splitlines() if line.startswith("layoutwarp:")]
    assert len(notices) == 1 and "no background compile" in notices[0], notices


@pytest.mark.skipif(not hasattr(os, "fork"), reason="needs fork")
def test_a_forked_child_of_a_compiling_process_starts_no_compile_of_its_own(tmp_path):
    """A DataLoader's fork workers inherit the parent's state: while the parent's background child
    fills the cache, a forked child answers from the torch path and starts no second compile."""
    code = """
        import os, sys, time, torch, layoutwarp as lw
        img = torch.ones(1, 1, 20, 20)
        with torch.no_grad():
            lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (4, 4))
        r, w = os.pipe()
        pid = os.fork()
        if pid == 0:
            with torch.no_grad():
                lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (4, 4))
            os.write(w, b"none" if lw.jit._WORKER is None else b"own")
            os._exit(0)
        os.waitpid(pid, 0)
        print(pid, os.read(r, 16).decode(), flush=True)
    """
    res = run_python(code, {"NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"})
    assert res.returncode == 0, res.stderr[-3000:]
    child, worker = res.stdout.split()
    assert worker == "none" and _children_of(int(child)) == []


def test_torch_threads_come_back_when_the_compile_ends_whatever_the_thread_calls_next(monkeypatch):
    """The calling thread's torch runs one thread fewer while the background child compiles, and as
    many as before once it has ended, even where the thread's later calls need no compile."""

    class Busy:
        running = True

        def busy(self):
            return self.running

        def has(self, unit):
            return False

    worker = Busy()
    monkeypatch.setattr(jit, "_WORKER", worker)
    monkeypatch.setattr(jit, "_READY", set(jit.UNITS))
    before = torch.get_num_threads()
    try:
        torch.set_num_threads(2)
        assert jit.ready("fixed", torch.float32) and torch.get_num_threads() == 1
        worker.running = False
        assert jit.ready("fixed", torch.float32) and torch.get_num_threads() == 2
        # and at a look at the units' state (a script that polls it, then runs torch alone)
        worker.running = True
        jit.ready("fixed", torch.float32)
        worker.running = False
        assert torch.get_num_threads() == 1
        jit.status()
        assert torch.get_num_threads() == 2
    finally:
        jit._SHARED.__dict__.clear()
        torch.set_num_threads(before)


def test_shares_from_several_threads_with_different_counts_all_run():
    """Threads calling kernels with different thread counts at once (the pool grows under them)
    each get every share run once."""
    import threading

    errors: list[BaseException] = []

    def caller(nt: int) -> None:
        try:
            for _ in range(200):
                seen = np.zeros(nt, dtype=np.int64)
                lw.kernels.run_shares(lambda t, n, out: out.__setitem__(t, out[t] + 1), nt, seen)
                assert (seen == 1).all()
        except BaseException as err:  # reported below
            errors.append(err)

    threads = [threading.Thread(target=caller, args=(nt,)) for nt in (2, 3, 5, 8)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert errors == []


def test_load_takes_a_unit_from_the_disk_cache_and_never_compiles(monkeypatch):
    """``jit.load``: a unit in the disk cache loads and stays loaded; one missing there is neither
    compiled nor handed to a background compile, and is looked for again only after
    ``LOOK_AGAIN_S``; the mode ``"off"`` loads nothing."""
    from layoutwarp import jit

    assert jit.load("mesh") and jit.loaded("mesh")  # the suite's cache holds every unit
    looks: list[str] = []
    monkeypatch.setattr(jit, "_READY", set())
    monkeypatch.setattr(jit, "_LOOKED", {})
    monkeypatch.setattr(jit, "_loads", lambda unit: looks.append(unit) or False)
    monkeypatch.setattr(jit, "_warm", lambda unit: pytest.fail(f"{unit} compiled"))
    monkeypatch.setattr(jit, "_start_worker", lambda *a: pytest.fail("a background compile started"))
    now = [1000.0]
    monkeypatch.setattr(jit.time, "monotonic", lambda: now[0])
    assert not jit.load("mesh") and not jit.load("mesh") and looks == ["mesh"]
    now[0] += jit.LOOK_AGAIN_S
    assert not jit.load("mesh") and looks == ["mesh", "mesh"]
    monkeypatch.setattr(jit, "_loads", lambda unit: True)
    now[0] += jit.LOOK_AGAIN_S
    with jit.use_mode("off"):
        assert not jit.load("mesh")
    assert jit.load("mesh") and jit.loaded("mesh")


@pytest.mark.parametrize("layout", ["pycache", "numba_cache_dir"])
def test_compiled_kernels_of_other_sources_are_deleted(layout, tmp_path, monkeypatch):
    # numba keys a kernel's cache on its own file: the mesh kernels inline phi.py's maps, and a
    # checkout that changed phi.py alone kept the old machine code (elliptic's θ = 0 fix undone)
    from layoutwarp.kernels import base

    if layout == "pycache":  # beside the sources: kernels/__pycache__, kernels/mesh/__pycache__
        folder, mesh = tmp_path / "kernels" / "__pycache__", tmp_path / "kernels" / "mesh" / "__pycache__"
    else:  # under NUMBA_CACHE_DIR: flat, each source folder's as numba names it (its name, a hash)
        from numba.core.caching import _CacheLocator

        here = Path(base.__file__).parent
        folder = tmp_path / "cache" / _CacheLocator.get_suitable_cache_subpath(str(here / "base.py"))
        mesh = tmp_path / "cache" / _CacheLocator.get_suitable_cache_subpath(str(here / "mesh" / "build.py"))
    sources = tmp_path / "src.py"
    sources.write_text("x = 1\n")
    monkeypatch.setattr(base, "kernel_sources", lambda: [str(sources)])

    def compiled() -> list[str]:
        for d in (folder, mesh):
            d.mkdir(parents=True, exist_ok=True)
            for name in ("k-1.py311.nbi", "k-1.py311.1.nbc"):
                (d / name).write_bytes(b"")
        (folder / "other.cpython-311.pyc").write_bytes(b"")  # not numba's: kept
        return sorted(p.name for d in (folder, mesh) for p in d.iterdir())

    compiled()
    assert base.renew_stale_caches(str(folder))  # kept before the digest was: deleted
    assert sorted(p.name for p in folder.iterdir() if p.is_file()) == [
        base.SOURCES_DIGEST,
        "other.cpython-311.pyc",
    ]
    assert list(mesh.iterdir()) == []
    compiled()
    assert not base.renew_stale_caches(str(folder))  # the same sources: kept
    assert len(list(mesh.iterdir())) == 2
    sources.write_text("x = 2\n")  # a source changed: every compiled kernel goes
    assert base.renew_stale_caches(str(folder)) and list(mesh.iterdir()) == []
    empty = tmp_path / "empty" / "__pycache__"
    assert not base.renew_stale_caches(str(empty)) and (empty / base.SOURCES_DIGEST).exists()
    assert not base.renew_stale_caches(None)
