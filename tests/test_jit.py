"""Compiled code without the wait (layoutwarp.jit) and the CUDA kernels on a newer numpy."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
import time

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
def test_the_first_call_answers_from_torch_while_a_worker_compiles_then_runs_compiled(tmp_path):
    """From an empty cache in the background mode: the first fixed-layout forward returns at
    once from the torch path, one line says what is compiling, the worker fills the cache, and a
    later call loads the compiled kernels (nothing of them compiled in the process itself) and
    gives the same values to float32 rounding; the sensor's noise, while the worker is on other
    groups, runs its kernel's quick build, so its draws are the compiled sampler's from the first
    call on (the same as in wait mode)."""
    code = """
        import json, torch, layoutwarp as lw
        from layoutwarp import jit
        g = torch.Generator().manual_seed(5)
        img = torch.rand(2, 3, 40, 60, generator=g)
        layout = lw.CurvLayout((0.4, -0.3))
        with torch.no_grad():  # the torch path answers: the state says the worker is compiling
            first = lw.simulate(img, layout, (7, 9))
        state = jit.status()["fixed/float32"]
        jit._WORKER.wait_for("fixed/float32")
        with torch.no_grad():
            later = lw.simulate(img, layout, (7, 9))
        phys = lw.SensorPhysics((300.0, 400.0), photons_per_um2=20, seed=3)
        noisy = lw.simulate(img, layout, (7, 9), physics=phys)
        jit.stop_worker()  # the test's cache is thrown away: no need to finish it
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
    # the product came from the worker's cache, never compiled here; the noise from the quick build
    # (the worker took the learnable layout's kernels after the fixed ones: it was not on them)
    assert not any(n.startswith("layoutwarp: compiling a fixed layout") for n in notices)
    assert any("quick build" in n and "sensor's measurement" in n for n in notices)
    # the same draws as a process that compiled everything before its first call (in this
    # installation's cache, which the rest of the suite compiles the same kernels into)
    res_wait = run_python(code.replace('jit._WORKER.wait_for("fixed/float32")', ""), {jit.ENV: "wait"})
    assert res_wait.returncode == 0, res_wait.stderr[-3000:]
    assert json.loads(res_wait.stdout.strip().splitlines()[-1])["noisy"] == out["noisy"]


@pytest.mark.slow
@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_quick_build_gives_the_full_builds_values_to_the_bit(dtype, seed):
    """jit.quick recompiles a kernel and its callees without IR inlining: the sensor's
    measurement (every noise model and output, fixed patterns, full well, ADC, negative means) and
    the fused product + measurement agree with the full build bit for bit, under a name of their
    own in numba's cache."""
    rng = np.random.default_rng(seed)
    p, seed = 3001, int(rng.integers(2**62))
    mean = rng.uniform(-0.2, 4.0, (3, p)).astype(dtype)
    area = rng.uniform(0.5, 1.5, p)
    prnu, dsnu = rng.standard_normal(p), rng.standard_normal(p)
    params = np.array([40.0, 0.6, 0.02, 0.5, 0.1, 2.5, 150.0, 1.3, 3.0, 1023.0])
    quick = jit.quick(lw.kernels.sensor_measure)
    assert (
        quick.py_func.__qualname__ == "sensor_measure_quick" and jit.quick(lw.kernels.sensor_measure) is quick
    )
    for noise in (0, 1, 2):
        for output in (0, 1, 2):
            full_out, quick_out = np.empty_like(mean), np.empty_like(mean)
            lw.kernels.sensor_measure(mean, area, prnu, dsnu, params, seed, noise, output, full_out, 2)
            quick(mean, area, prnu, dsnu, params, seed, noise, output, quick_out, 2)
            assert np.array_equal(full_out, quick_out, equal_nan=True), (noise, output)
    weights = lw.AreaResampler(lw.CurvLayout((0.3, -0.2)), (4, 5), (20, 30)).weights
    x = rng.uniform(0, 1, (2, 600)).astype(np.float32)
    outs = []
    for kernel in (lw.kernels.measured_csr_apply, jit.quick(lw.kernels.measured_csr_apply)):
        out = np.empty((2, 20), np.float32)
        args = (area[:20], prnu[:20], dsnu[:20], params, seed, 1, 2)
        kernel(weights.indptr, weights.indices, weights.data, x, out, *args, out, 2)
        outs.append(out)
    assert np.array_equal(*outs)


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
    assert not written, written  # no kernel was compiled into the cache (a timing said so, flakily)


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
        fn, sig = mk.CUDA_KERNELS["amin"]
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
    assert "cuda: torch (numba's CUDA kernels do not run here" in lw.files.run_info()["backends"]


@pytest.mark.heavy
def test_workers_on_one_cache_take_a_unit_in_turn():
    """Several processes on one cache (the ranks of a torchrun job) each start a worker: a worker
    compiles a unit only while no other does (a lock beside the cache), then loads it."""
    import select
    import time

    unit = "fixed/float32"
    jit.ready("fixed", torch.float32, wait=True)  # in this cache, as another worker would leave it
    with jit._unit_lock(unit):
        proc = subprocess.Popen(
            [sys.executable, "-c", "from layoutwarp.jit import serve; serve()"],
            stdin=subprocess.PIPE,
            stdout=subprocess.PIPE,
            text=True,
            cwd=ROOT,
            env={**os.environ, jit.ENV: "wait"},
        )
        proc.stdin.write(unit + "\n")
        proc.stdin.flush()
        time.sleep(4)
        assert proc.poll() is None and not select.select([proc.stdout], [], [], 0)[0]  # waits its turn
    assert proc.stdout.readline().strip() == f"done {unit}"
    proc.stdin.close()
    assert proc.wait(timeout=60) == 0


@pytest.mark.slow
@pytest.mark.heavy
def test_wait_mode_processes_on_one_cache_compile_a_group_once(tmp_path):
    """In wait mode, processes on one empty cache that need a group at the same moment (pytest's
    workers, the ranks of a torchrun job) take it in turn: one compiles it, the others wait and
    load it (one line says it compiled), and all compute the same values. The compile runs in a
    child process: both load the group's kernels from the cache (numba's cache statistics), so
    neither keeps the compiler's memory."""
    code = """
        import json, os, pathlib, sys, time, torch, layoutwarp as lw
        pathlib.Path(sys.argv[1] + ".ready").touch()
        while not os.path.exists(sys.argv[2]):  # all start together
            time.sleep(0.01)
        with torch.no_grad():
            img = torch.arange(2 * 30 * 40.0).reshape(2, 30, 40)
            out = lw.simulate(img, lw.CurvLayout((0.4, -0.3)), (5, 7))
        print(json.dumps(out.flatten().tolist()))
        print(sum(lw.kernels.csr_apply.stats.cache_hits.values()))  # loaded, not compiled here
    """
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "wait"}
    go = tmp_path / "go"
    args = [sys.executable, "-c", textwrap.dedent(code)]
    pipes = {"cwd": ROOT, "env": env, "stdout": subprocess.PIPE, "stderr": subprocess.PIPE, "text": True}
    procs = [subprocess.Popen([*args, f"{tmp_path}/p{i}", str(go)], **pipes) for i in range(2)]
    try:
        while not all((tmp_path / f"p{i}.ready").exists() for i in range(2)):
            ended = [p for p in procs if p.poll() is not None]
            assert not ended, ended[0].communicate()[1][-3000:]  # one died before the start
            time.sleep(0.05)
        go.touch()
        results = [p.communicate(timeout=600) for p in procs]
    finally:
        for p in procs:  # none left waiting for the start
            p.kill()
    assert all(p.returncode == 0 for p in procs), [err[-3000:] for _, err in results]
    lines = [line for _, err in results for line in err.splitlines()]
    notices = [line for line in lines if line.startswith("layoutwarp: compiling")]
    assert len(notices) == 1 and "fixed layout" in notices[0], notices
    values, loaded = zip(*(out.splitlines()[-2:] for out, _ in results), strict=True)
    assert values[0] == values[1] and loaded == ("1", "1")


@pytest.mark.slow
@pytest.mark.heavy
def test_wait_mode_compiles_in_the_process_where_no_child_can(tmp_path):
    """Where the child that compiles a group fails (here no Python to start), wait mode compiles
    the group in the calling process: the same compiled values, the kernel compiled (not
    loaded) there."""
    code = """
        import json, sys, torch, layoutwarp as lw
        if sys.argv[1] == "no-child":
            sys.executable = "/nonexistent/python"
        with torch.no_grad():
            img = torch.arange(2 * 30 * 40.0).reshape(2, 30, 40)
            out = lw.simulate(img, lw.CurvLayout((0.4, -0.3)), (5, 7))
        print(json.dumps(out.flatten().tolist()))
        print(sum(lw.kernels.csr_apply.stats.cache_hits.values()))
    """
    outs = []
    for case in ("no-child", "child"):
        env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / case), jit.ENV: "wait"}
        args = [sys.executable, "-c", textwrap.dedent(code), case]
        run = subprocess.run(args, cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
        assert run.returncode == 0, run.stderr[-3000:]
        outs.append(run.stdout.splitlines()[-2:])
    (values, hits), (values_child, hits_child) = outs
    assert values == values_child and (hits, hits_child) == ("0", "1")


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


def test_back_to_back_processes_share_one_background_worker(tmp_path):
    """A process that finds another process's worker filling the cache starts none of its own
    (three commands in a row once left three compiling side by side): it answers from the torch
    path, says so once, and its status says where the compile runs."""
    code = """
        import sys, time, torch, layoutwarp as lw
        from layoutwarp import jit
        with torch.no_grad():
            out = lw.simulate(torch.ones(1, 1, 20, 20), lw.CurvLayout((0.3, 0.1)), (4, 4))
        print("worker" if jit._WORKER is not None else "none", jit.status()["fixed/float32"],
              round(float(out.mean()), 6), flush=True)
        sys.stdin.readline()  # the first process stays, its worker with it, until told
        jit.stop_worker()
    """
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "cache"), jit.ENV: "background"}
    cmd = [sys.executable, "-c", textwrap.dedent(code)]
    first = subprocess.Popen(
        cmd, env=env, stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    try:
        assert first.stdout.readline().split() == ["worker", "compiling", "1.0"]
        second = subprocess.run(cmd, env=env, input="\n", capture_output=True, text=True, timeout=300)
        assert second.returncode == 0, second.stderr[-3000:]
        assert second.stdout.split() == ["none", "compiling", "elsewhere", "1.0"]
        notices = [line for line in second.stderr.splitlines() if line.startswith("layoutwarp:")]
        assert len(notices) == 1 and "another process's background compile" in notices[0], notices
    finally:
        first.communicate("\n", timeout=300)
    assert first.returncode == 0
