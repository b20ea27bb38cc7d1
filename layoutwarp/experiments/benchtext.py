"""The benchmark's text: its table, the training steps, the cached weights, the physics, the first
calls and the scaling grid, with ratios against the anchors of the same run."""

from __future__ import annotations

__all__ = ["format_first_calls", "format_scaling", "format_table", "report_text"]


def _fmt(v: float | None, spec: str) -> str:
    return "" if v is None else format(v, spec)


def format_table(result: dict) -> str:
    """A plain-text table with ratios against the anchors of the same run."""
    a = result["anchors_ms"]
    lines = [
        f"source {result['src_hw'][1]}x{result['src_hw'][0]}x3 float32 -> sensor "
        f"{result['sensor_hw'][1]}x{result['sensor_hw'][0]}, θ={tuple(result['theta'])}, "
        f"{result['threads']} threads, {result.get('device', 'cpu')}; "
        f"anchors: INTER_AREA {a['inter_area']:.2f} ms, "
        f"grid_sample MC-16 {a['grid_sample_mc16']:.2f} ms",
        "errors: RMSE/max against float64 exact; 'scene' RMSE against the analytic pixel means "
        "(synthetic only); grad: relative error of dL/dθ against float64 finite differences"
        + (
            f" (along {k} random directions where θ has more entries)"
            if (k := result.get("fd_directions"))
            else ""
        ),
        "fwd ms: a fixed layout (its mesh is built once and reused); train ms: forward + backward "
        "of a learnable layout (mesh rebuilt every call, as in training); bwd/fwd within training",
    ]
    # the text columns as wide as their longest entry, so every number stays under its header
    w = {
        k: max([len(k), *(len(r[k]) for r in result["rows"])])
        for k in ("image", "layout", "method", "setting")
    }
    lines.append(
        f"{'image':{w['image']}s} {'layout':{w['layout']}s} {'method':{w['method']}s} "
        f"{'setting':{w['setting']}s} {'fwd ms':>8s} {'/AREA':>6s} "
        f"{'/GS16':>6s} {'train ms':>8s} {'bwd/fwd':>7s} {'RMSE':>8s} {'max err':>8s} {'scene':>8s} "
        f"{'grad':>8s} {'peak/in':>7s}"
    )
    for r in result["rows"]:
        fg = r["extra"].get("forward_with_grad_ms")
        bwd = None if r["backward_ms"] is None else r["backward_ms"] / fg
        train = None if r["backward_ms"] is None else r["backward_ms"] + fg
        peak = None if r["peak_mb"] is None else r["peak_mb"] / result["input_mb"]
        lines.append(
            f"{r['image']:{w['image']}s} {r['layout']:{w['layout']}s} {r['method']:{w['method']}s} "
            f"{r['setting']:{w['setting']}s} {r['forward_ms']:8.2f} "
            f"{r['forward_ms'] / a['inter_area']:6.2f} {r['forward_ms'] / a['grid_sample_mc16']:6.2f} "
            f"{_fmt(train, '8.1f'):>8s} {_fmt(bwd, '.2f'):>7s} {_fmt(r['rmse'], '.2e'):>8s} "
            f"{_fmt(r['max_err'], '.2e'):>8s} "
            f"{_fmt(r['scene_rmse'], '.2e'):>8s} {_fmt(r['grad_rel_err'], '.1e'):>8s} "
            f"{_fmt(peak, '.2f'):>7s}"
        )
    return "\n".join(lines)


def format_scaling(result: dict) -> str:
    """The scaling grid (ms) and fitted slopes as text."""
    sizes = [f"{w}x{h}" for h, w in result["sizes_hw"]]
    lines = [f"scaling: forward ms; rows = source, columns = sensor {', '.join(sizes)}"]
    for label, grid in result["times_ms"].items():
        s = result["slopes"][label]
        lines.append(
            f"  {label:26s} slope vs source px {s['vs_source_pixels']:.2f}, "
            f"vs sensor px {s['vs_sensor_pixels']:.2f}"
        )
        for (h, w), row in zip(result["srcs_hw"], grid, strict=True):
            lines.append(f"    {w}x{h}: " + "  ".join(f"{t:9.2f}" for t in row))
    return "\n".join(lines)


def format_first_calls(calls: dict) -> list[str]:
    """A line per entry point of [`first_calls`][]' result."""
    return [
        f"first call from an empty kernel cache, {name}: {c['first_s']:.1f} s "
        f"(warm {c['warm_s']:.1f} s, {c['first_s'] - c['warm_s']:+.1f} s)"
        + ("; " + ", ".join(f"{k} {v:.1f} s" for k, v in c["steps"].items()) if "steps" in c else "")
        for name, c in calls.items()
    ]


def report_text(result: dict) -> str:
    """Everything the benchmark prints: the table, the training steps, the cached weights, the
    physics, the compile time and the scaling grid; first, the backends it ran on."""
    backends = result.get("run", {}).get("backends")
    lines = ([f"backends: {backends}"] if backends else []) + [format_table(result)]
    for r in result["rows"]:
        if r["method"].startswith("train step"):
            lines.append(
                f"{r['layout']:8s} {r['method']:24s} {r['setting']:12s} {r['forward_ms']:8.1f} ms  "
                f"{r['extra']['ops']:5d} torch ops"
                + (
                    f"  (mesh build {r['extra']['mesh_ms']:.1f} ms; {r['extra']['over_mc16']:.2f}x the "
                    f"MC-16 step, {r['extra']['over_fixed_forward']:.1f}x the fixed forward; "
                    f"{r['extra'].get('in_a_row_ms', float('nan')):.1f} ms in a row)"
                    if "mesh_ms" in r["extra"]
                    else ""
                )
            )
    for r in result["rows"]:
        if r["method"] == "exact, cached weights":
            lines.append(
                f"a fixed layout's repeated exact forward: {r['forward_ms']:.2f} ms "
                f"({r['extra']['over_inter_area']:.2f}x INTER_AREA, "
                f"{r['extra'].get('over_interpolate', float('nan')):.2f}x F.interpolate(area), "
                f"{r['extra'].get('over_read', float('nan')):.1f}x one read of the image, x.sum() "
                f"{r['extra'].get('read_ms', float('nan')):.2f} ms; in rounds); its weights "
                f"{r['extra'].get('weights_over_plane', float('nan')):.2f}x a float32 plane; its first call, "
                f"which builds the area weights: {r['extra']['first_call_ms']:.1f} ms; with no weights "
                f"kept (resampler.RESAMPLERS.maxsize = 0), the compiled walk: {r['extra']['walk_ms']:.2f} ms"
                + (
                    f", its first call {r['extra']['walk_peak_mb'] / result['input_mb']:.2f} input copies "
                    "of memory"
                    if r["extra"].get("walk_peak_mb") is not None
                    else ""
                )
            )
        if r["method"] == "exact + physics":
            lines.append(
                f"sensor physics (noise, full well, 12-bit ADC): {r['forward_ms']:.2f} ms against "
                f"{r['extra']['plain_ms']:.2f} ms without, {100 * r['extra']['over_plain']:+.1f} % "
                "(the median of the rounds' ratios)"
                + (
                    f"; the measurement kernel alone {r['extra']['kernel_ms']:.3f} ms, "
                    f"{r['extra'].get('kernel_noise_free_ms', float('nan')):.3f} ms without noise"
                    if "kernel_ms" in r["extra"]
                    else ""
                )
            )
        if r["method"] == "physics train step":
            lines.append(
                f"learning a layout under that camera (curv ±, train step): {r['forward_ms']:.1f} ms "
                f"against {r['extra']['plain_ms']:.1f} ms without physics, "
                f"{100 * r['extra']['over_plain']:+.0f} %; {r['extra']['ops']} torch ops"
            )
    lines += format_first_calls(result.get("first_calls", {}))
    c = result.get("compile")  # results written before the first-call lines: their compile probe
    if c:
        lines.append(
            f"first exact forward+backward in a new process: {c['first_process']['first_call_s']:.2f} s "
            f"with an empty kernel cache (compiling), {c['second_process']['first_call_s']:.2f} s with the "
            "cache filled"
        )
    if "scaling" in result:
        lines.append(format_scaling(result["scaling"]))
    return "\n".join(lines)
