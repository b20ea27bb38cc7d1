"""One command on a fresh GPU machine: every GPU figure the docs quote, then the CUDA tests, printed
and written to ``examples/gpu/gpu_check.json``. Keys: ``device``, ``torch``, ``numpy``;
``step_over_gs16`` per family (``step_over_gs16_dispatcher``: the curv ± step with every kernel
launched through numba's dispatcher instead of directly); ``captured_step_over_gs16`` (the step
captured in a CUDA graph and replayed); ``step_over_reference_b1``/``_b4`` (against the paper's
reference layer, a 16-sample step, where ``shared/refcode`` beside or inside the checkout
imports; else ``null``, and ``reference_missing`` says why); ``fixed_over_pool``;
``physics_overhead`` (a fraction); ``launches_per_step`` (the profiler's GPU activities;
``launches_counted``: `count_launches`, as the tests count them without a GPU;
``gpu_busy_ms_per_step``: the profiler's time of those); ``host_reads`` (`count_host_reads` of a
learnable step); ``numba_launch_us``, ``direct_launch_us`` and ``torch_launch_us`` (the host's
microseconds a launch of a numba kernel of 12 tensors costs through numba's dispatcher and
directly, and a torch operator's); ``first_call_s``; ``cuda_vs_cpu_f64_maxabs`` (the same
compiled mesh on both) and ``cuda_vs_cpu_fixed_f64_maxabs`` (a fixed layout: two meshes within
``fixed_f64_error_bound``); ``physics_cuda_equals_cpu`` (the share of recorded values equal on
both, same seed); ``cuda_tests``.

    python examples/gpu_check.py [--no-tests] [--out examples/gpu/gpu_check.json]

2048x1024 RGB float32 → 257x129; every ratio the median over interleaved rounds of the call and
its anchor in this process (synchronized calls). The first call runs in a fresh subprocess with
an empty numba cache (``NUMBA_CACHE_DIR``), so it includes compiling the CUDA kernels.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

import layoutwarp as lw
from layoutwarp.experiments.timing import interleaved_times
from layoutwarp.testing import count_host_reads, count_launches

lw.jit.set_mode("wait")  # time the compiled kernels, never the torch path while they compile
SIZE = (129, 257)
TESTS = "(cuda or device or gpu or numpy) and not simulator"  # the tests a GPU adds to, by name
FIRST_CALL = """
import time, torch, torch.nn.functional as F, layoutwarp as lw
img = F.interpolate(torch.rand(1, 3, 256, 512), size=(1024, 2048), mode="bilinear").cuda()
torch.cuda.synchronize()
t = time.perf_counter()
layout = lw.CurvLayout((0.3, -0.24), learn=True).cuda()
lw.simulate(img, layout, (129, 257)).sum().backward()
torch.cuda.synchronize()
print(time.perf_counter() - t)
"""


def paired_ms(fn, anchor, rounds: int = 15) -> tuple[float, float, float]:
    """Median ms of ``fn`` and of ``anchor`` in interleaved rounds, and the median of the rounds'
    ratios (the bench's way: both calls of a round meet the same machine state)."""
    t_fn, t_anchor = interleaved_times([fn, anchor], rounds)
    ratio = float(np.median(np.divide(t_fn, t_anchor)))
    return float(np.median(t_fn)), float(np.median(t_anchor)), ratio


def captured(fn):
    """``fn`` (a step: forward and backward) captured in a CUDA graph after three warm-up calls
    on a side stream; returns the graph's replay (gradients accumulate in place)."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(3):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        fn()
    return graph.replay


def reference_layer() -> tuple[object, str | None]:
    """The paper's reference layer (``FoveatedSensor`` with its curvilinear deformation, from
    ``../shared/refcode`` beside the checkout) and ``None``, or ``None`` and why not."""
    here = Path(__file__).resolve()
    roots = [here.parents[2] / "shared" / "refcode", here.parents[1] / "shared" / "refcode"]
    root = next((r for r in roots if (r / "sensor").is_dir()), None)
    if root is None:
        return None, f"no reference layer at {roots[0]} or {roots[1]}"
    sys.path.insert(0, str(root))
    try:
        from sensor.deformations import CurvilinearDeformation
        from sensor.sensor import FoveatedSensor
    except ImportError as err:  # it needs einops and jaxtyping
        return None, f"the reference layer does not import: {err}"
    return (lambda: FoveatedSensor(SIZE, t_init=[0.3, -0.24], spp=16, deform=CurvilinearDeformation())), None


def launches(fn, calls: int = 5) -> tuple[float, float]:
    """GPU activities (kernels, copies, memsets) per call, and the milliseconds the GPU spends
    in them per call, from torch's profiler."""
    from torch.profiler import ProfilerActivity, profile

    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize()
    events = [e for e in prof.events() if e.device_type == torch.autograd.DeviceType.CUDA]
    return len(events) / calls, sum(e.time_range.elapsed_us() for e in events) / calls / 1e3


cuda = None  # numba.cuda, bound by the first launch (layoutwarp.kernels.cuda_launch)


def _touch(a0, a1, a2, a3, a4, a5, a6, a7, a8, a9, a10, a11) -> None:
    """A kernel of twelve array arguments (as many as the mesh's kernels take) that does nothing
    but one write: what a launch costs the host."""
    if cuda.grid(1) == 0:
        a0[0] = a11[0]


def launch_us(device: str = "cuda", calls: int = 300) -> tuple[float, float, float]:
    """Host microseconds per launch, without waiting between them: a numba kernel of twelve
    tensor arguments through `cuda_launch` by numba's dispatcher and directly (as layoutwarp's
    kernels launch), and a torch operator (``add`` on the same tiny tensor)."""
    from layoutwarp.kernels import device as kd

    x = [torch.zeros(4, device=device) for _ in range(12)]
    stream = kd.stream_of(x[0])

    def through(fast: bool):
        def call():
            kd.FAST_LAUNCH = fast
            kd.cuda_launch(_touch, 1, stream, *x)

        return call

    out = []
    for fn in (through(False), through(True), lambda: torch.add(x[0], 1, out=x[1])):
        fn()  # compiles (numba) and warms up
        if device == "cuda":
            torch.cuda.synchronize()
        t = time.perf_counter()
        for _ in range(calls):
            fn()
        if device == "cuda":
            torch.cuda.synchronize()
        out.append((time.perf_counter() - t) / calls * 1e6)
    kd.FAST_LAUNCH = True
    return out[0], out[1], out[2]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--no-tests", action="store_true", help="skip the CUDA tests")
    ap.add_argument("--out", default=str(Path(__file__).parent / "gpu" / "gpu_check.json"))
    args = ap.parse_args()
    if not torch.cuda.is_available():
        print("gpu_check: no CUDA GPU here", file=sys.stderr)
        return 2
    res: dict = {"device": torch.cuda.get_device_name(), "torch": torch.__version__, "numpy": np.__version__}
    with tempfile.TemporaryDirectory() as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache}
        first = subprocess.run([sys.executable, "-c", FIRST_CALL], env=env, capture_output=True, text=True)
        res["first_call_s"] = float(first.stdout.split()[-1]) if first.returncode == 0 else None
        print(f"first learnable CUDA step from an empty cache: {res['first_call_s']} s", first.stderr[-300:])
    g = torch.Generator().manual_seed(0)
    img = F.interpolate(torch.rand(1, 3, 256, 512, generator=g), size=(1024, 2048), mode="bilinear").cuda()
    learnable = {
        "curv+-": lw.CurvLayout((0.3, -0.24), learn=True).cuda(),
        "fovea": lw.FoveaLayout((0.35, -0.25), center=(0.3, -0.2), learn=True).cuda(),
    }

    def step(layout):
        layout.zero_grad()
        lw.simulate(img, layout, SIZE).sum().backward()

    curv = learnable["curv+-"]

    def gs16_step():  # the paper's estimator, bare: 4x4 jittered samples a pixel through grid_sample
        u = lw.maps.sample_points(SIZE, 4, jitter=True, dtype=torch.float32, device="cuda")
        p = curv.phi(u, curv.theta.float())
        out = F.grid_sample(img, p[None], mode="bilinear", align_corners=False)
        out.reshape(1, 3, SIZE[0], 4, SIZE[1], 4).mean((3, 5)).sum().backward()
        curv.zero_grad()

    res["step_ms"], res["step_over_gs16"] = {}, {}
    for name, layout in learnable.items():
        ms, gs16, ratio = paired_ms(lambda layout=layout: step(layout), gs16_step)
        res["step_ms"][name], res["step_over_gs16"][name], res["gs16_ms"] = ms, ratio, gs16
        print(
            f"learnable {name} step {ms:.2f} ms = {ratio:.2f}x a bare grid_sample 16-sample step "
            f"({gs16:.2f} ms)"
        )

    from layoutwarp.kernels import device as kd

    kd.FAST_LAUNCH = False  # the same step, every kernel launched through numba's dispatcher
    ms, gs16, ratio = paired_ms(lambda: step(curv), gs16_step)
    kd.FAST_LAUNCH = True
    res["step_ms_dispatcher"], res["step_over_gs16_dispatcher"] = ms, ratio
    res["direct_launch_off"] = kd.DIRECT_OFF[:1]
    print(f"learnable curv+- step, numba's dispatcher launching: {ms:.2f} ms = {ratio:.2f}x grid_sample's")
    write(res, args.out)

    def accumulate(layout):  # a step whose gradient accumulates in place: what a graph replays
        lw.simulate(img, layout, SIZE).sum().backward()

    for name, layout in learnable.items():
        ms, gs16, ratio = paired_ms(captured(lambda layout=layout: accumulate(layout)), gs16_step)
        res.setdefault("captured_step_ms", {})[name] = ms
        res.setdefault("captured_step_over_gs16", {})[name] = ratio
        print(
            f"learnable {name} step captured in a CUDA graph {ms:.2f} ms = {ratio:.2f}x the grid_sample step"
        )
    make_reference, res["reference_missing"] = reference_layer()
    for batch in (1, 4):
        key = f"step_over_reference_b{batch}"
        res[key] = None
        if make_reference is None:
            continue
        ref, images = make_reference().cuda(), img.expand(batch, -1, -1, -1).contiguous()

        def ref_step(ref=ref, images=images):
            ref.zero_grad()
            ref(images).sum().backward()

        def our_step(images=images):
            curv.zero_grad()
            lw.simulate(images, curv, SIZE).sum().backward()

        ms, ref_ms, res[key] = paired_ms(our_step, ref_step)
        res[f"reference_ms_b{batch}"] = ref_ms
        print(f"curv ± step, batch {batch}: {ms:.2f} ms = {res[key]:.2f}x the reference ({ref_ms:.2f} ms)")
    if res["reference_missing"]:
        print("reference layer:", res["reference_missing"])
    res["host_reads"] = sum(count_host_reads(lambda: step(curv)).values())
    res["launches_per_step"], res["gpu_busy_ms_per_step"] = launches(lambda: step(curv))
    res["launches_counted"] = sum(count_launches(lambda: step(curv)).values())
    print(
        f"GPU activities per learnable curv step: {res['launches_per_step']:.0f} (profiler), "
        f"{res['launches_counted']} (count_launches, as tests count them without a GPU); "
        f"{res['host_reads']} values read back; the GPU busy {res['gpu_busy_ms_per_step']:.2f} ms of a step"
    )
    try:  # a diagnostic: its failure must not cost the figures after it
        res["numba_launch_us"], res["direct_launch_us"], res["torch_launch_us"] = launch_us()
        print(
            f"host cost of a launch: numba kernel of 12 tensors {res['numba_launch_us']:.1f} µs through "
            f"numba's dispatcher, {res['direct_launch_us']:.1f} µs direct; torch operator "
            f"{res['torch_launch_us']:.1f} µs"
        )
    except Exception as err:
        res["numba_launch_us"] = res["direct_launch_us"] = res["torch_launch_us"] = None
        res["launch_us_error"] = f"{type(err).__name__}: {err}"[:300]
        print("host cost of a launch: not measured:", res["launch_us_error"])
    fixed = lw.CurvLayout((0.3, -0.24)).cuda()
    phys = lw.SensorPhysics(
        (2800, 5600), photons_per_um2=50, read_noise_e=2.0, full_well_per_um2=1000.0, adc_bits=12
    )
    with torch.no_grad():
        t_fixed, t_pool, over_pool = paired_ms(
            lambda: lw.simulate(img, fixed, SIZE), lambda: F.adaptive_avg_pool2d(img, SIZE), 30
        )
        t_phys, _, over_fixed = paired_ms(
            lambda: lw.simulate(img, fixed, SIZE, physics=phys), lambda: lw.simulate(img, fixed, SIZE), 30
        )
    res.update(fixed_ms=t_fixed, pool_ms=t_pool, physics_ms=t_phys)
    res["fixed_over_pool"], res["physics_overhead"] = over_pool, over_fixed - 1
    print(
        f"fixed curv forward {t_fixed:.3f} ms = {over_pool:.2f}x adaptive_avg_pool2d "
        f"({t_pool:.3f} ms); "
        f"with physics {t_phys:.3f} ms (+{res['physics_overhead']:.0%})"
    )
    small = img[:, :, :256, :512].double()
    # the device kernels against the CPU kernels, float64, on the same compiled mesh (a learnable
    # layout's forward with autograd on: the CPU's fixed route builds its mesh in torch, whose
    # polylines differ within the tolerance)
    on = [
        lw.simulate(small.to(d), lw.CurvLayout((0.3, -0.24), learn=True).double().to(d), (33, 65))
        for d in ("cuda", "cpu")
    ]
    res["cuda_vs_cpu_f64_maxabs"] = float((on[0].detach().cpu() - on[1].detach()).abs().max())
    print("CUDA vs CPU, float64, the same compiled mesh, max abs difference:", res["cuda_vs_cpu_f64_maxabs"])
    with torch.no_grad():  # a fixed layout: the device's compiled mesh against the CPU's torch mesh
        a = lw.simulate(small, lw.CurvLayout((0.3, -0.24)).double().cuda(), (33, 65)).cpu()
        b, plan = lw.simulate(small.cpu(), lw.CurvLayout((0.3, -0.24)).double(), (33, 65), return_plan=True)
    res["cuda_vs_cpu_fixed_f64_maxabs"], res["fixed_f64_error_bound"] = (
        float((a - b).abs().max()),
        plan.error_bound,
    )
    print(
        f"a fixed float64 layout, CUDA vs CPU: {res['cuda_vs_cpu_fixed_f64_maxabs']:.2e} "
        f"(two polylines within the error bound {plan.error_bound:.2e})"
    )
    seeded = lw.SensorPhysics((2800, 5600), photons_per_um2=5, read_noise_e=2.0, adc_bits=12, seed=1)
    with torch.no_grad():  # the same noise draws on both: the same counter-based streams
        on_gpu = lw.simulate(img, fixed, SIZE, physics=seeded).cpu()
        on_cpu = lw.simulate(img.cpu(), lw.CurvLayout((0.3, -0.24)), SIZE, physics=seeded)
    res["physics_cuda_equals_cpu"] = float((on_gpu == on_cpu).double().mean())
    print(f"sensor physics, CUDA vs CPU, same seed: {res['physics_cuda_equals_cpu']:.4%} of values equal")
    if not args.no_tests:  # last: the figures come first where the device time runs short
        write(res, args.out)
        t = time.perf_counter()
        tests = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-n", "8", "tests", "-k", TESTS],
            cwd=Path(__file__).resolve().parents[1],
            capture_output=True,
            text=True,
        )
        summary = tests.stdout.strip().splitlines()[-1] if tests.stdout.strip() else tests.stderr[-500:]
        res["cuda_tests"] = {"rc": tests.returncode, "summary": summary, "seconds": time.perf_counter() - t}
        print("CUDA tests:", summary, flush=True)
        if tests.returncode:
            print(tests.stdout[-8000:], flush=True)
    write(res, args.out)
    return 0


def write(res: dict, out: str) -> None:
    """The figures so far, to ``out`` (and to ``$OUT/gpu_check.json`` on the device machine)."""
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(res, indent=1) + "\n")
    if os.environ.get("OUT"):
        Path(os.environ["OUT"], "gpu_check.json").write_text(json.dumps(res, indent=1) + "\n")


if __name__ == "__main__":
    sys.exit(main())
