"""The benchmark's physics rows: what sensor physics and optics cost over the plain forward."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from .. import kernels
from ..integrators import data_tolerance
from ..layoutfile import layout_from_spec
from ..mesh import pixel_mesh
from ..sensor import simulate
from ..testing import count_ops
from .benchconfig import BenchConfig, bench_layouts
from .timing import Row, time_call, time_overhead

__all__ = ["BENCH_PHYSICS", "physics_rows"]


#: The camera of the physics rows: 12-bit, shot and read noise, a full well; the source image spans
#: the sensor with square 2.73 µm source pixels at 2048x1024.
BENCH_PHYSICS = {
    "photons_per_um2": 200.0,
    "quantum_efficiency": 0.6,
    "read_noise_e": 3.0,
    "dark_e_per_um2": 0.1,
    "full_well_per_um2": 2000.0,
    "adc_bits": 12,
    "seed": 0,
}


def physics_rows(cfg: BenchConfig, image_name: str, img: Tensor, anchors: dict[str, float]) -> list[Row]:
    """What sensor physics costs (fixed curv layout, the data tolerance, no gradient): the forward
    with noise, full well and ADC against the same forward without (``extra["over_plain"]``: the
    median of the rounds' ratios over ``200 × repeats`` rounds that call both), and the PSFs on the
    source image against INTER_AREA; the Airy row's error is the RMSE of its truncated kernel
    against one holding 99.9 % of the energy, relative to the image's range
    (``extra["truncated_energy"]``: what the kernel leaves out)."""
    from ..measurement import kernel_arguments
    from ..physics import SensorPhysics, apply_psf

    h, w = cfg.src
    extent = (2.734375 * h, 2.734375 * w)  # µm: 2.73 µm source pixels at 2048x1024
    layout = layout_from_spec(bench_layouts(cfg.theta)["curv"]).to(cfg.device)
    dev_img = img.to(cfg.device)
    ph = SensorPhysics(sensor_um=extent, **BENCH_PHYSICS)

    def plain():
        with torch.no_grad():
            return simulate(dev_img, layout, cfg.size)

    def measured():
        with torch.no_grad():
            return simulate(dev_img, layout, cfg.size, physics=ph)

    # a difference of a few percent between two times, on a machine whose speed drifts by 1.5x
    # within seconds: many pairs (1000 at the default repeats, about 5 s; the median moves by about
    # a point between runs of 200), and the overhead as the median of each round's ratio, both
    # calls of a round meeting the same machine state
    tp, tq, over = time_overhead(plain, measured, cfg.repeats * 200)
    noise = float((measured().cpu().double() - plain().cpu().double()).pow(2).mean().sqrt())
    extra = {"over_plain": over, "plain_ms": tp, "physics": ph.to_dict()}
    if cfg.device == "cpu" and kernels.available():
        # the measurement kernel alone on the forward's means, called in a row: the overhead's floor
        areas = pixel_mesh(
            layout, cfg.size, tol=data_tolerance(torch.float32)[0], dtype=torch.float64
        ).areas()
        args = kernel_arguments(ph, areas)
        mean = plain().reshape(-1, areas.numel()).numpy()
        out, nt = np.empty_like(mean), kernels.threads()
        extra["kernel_ms"] = time_call(lambda: kernels.sensor_measure(mean, *args, out, nt), cfg.repeats * 40)
        quiet = (*args[:-2], 0, args[-1])  # the same camera without noise: what the sampler costs
        extra["kernel_noise_free_ms"] = time_call(
            lambda: kernels.sensor_measure(mean, *quiet, out, nt), cfg.repeats * 40
        )
    rows = [Row(image_name, "curv", "exact + physics", "noise,FW,ADC", tq, rmse=noise, extra=extra)]
    # learning a layout under this camera: the training step of a learnable curv (mixed-sign θ)
    # with and without physics (the reparameterised noise; the areas from the compiled path)
    learnable = layout_from_spec({"family": "curv", "theta": [cfg.theta[0], -cfg.theta[1]]}, learn=True)
    learnable = learnable.to(cfg.device)

    def step(physics: SensorPhysics | None = None) -> None:
        simulate(dev_img, learnable, cfg.size, physics=physics).sum().backward()
        learnable.rho.grad = None

    t_plain, t_phys, over = time_overhead(step, lambda: step(ph), cfg.repeats * 4)
    extra = {"over_plain": over, "plain_ms": t_plain, "ops": count_ops(lambda: step(ph))}
    rows.append(Row(image_name, "curv ±", "physics train step", "noise,FW,ADC", t_phys, extra=extra))
    flat = dev_img.reshape(-1, h, w)
    for kind in ("gaussian", "airy"):
        psf = SensorPhysics(sensor_um=extent, photons_per_um2=1.0, psf=kind)
        t = time_call(lambda psf=psf: apply_psf(flat, psf), cfg.repeats)
        row = Row(
            image_name, "-", f"psf {kind}", "f/5.6", t, extra={"over_inter_area": t / anchors["inter_area"]}
        )
        if kind == "airy":
            ref = apply_psf(
                flat, SensorPhysics(sensor_um=extent, photons_per_um2=1.0, psf=kind, psf_energy=0.999)
            )
            err = (apply_psf(flat, psf).double() - ref.double()).cpu()
            row.rmse, row.max_err = float(err.pow(2).mean().sqrt()), float(err.abs().max())
            row.extra["truncated_energy"] = 1 - psf.psf_energy
        rows.append(row)
    return rows
