"""Sensor physics: photons, noise, full well, ADC, fixed patterns and optics, against references
(EMVA 1288 photon transfer, moments, finite differences, analytic PSF facts)."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch
from conftest import rand_theta, run_in_simulator

import layoutwarp as lw
from layoutwarp.checks import ArgumentError
from layoutwarp.physics import SensorPhysics, airy_profile, apply_psf, psf_kernels

F64 = torch.float64


def physics(**kw) -> SensorPhysics:
    return SensorPhysics(**({"sensor_um": (64.0, 64.0), "photons_per_um2": 100.0} | kw))


#: The camera of the photon-transfer tests (48 x 48 µm, 16-bit ADC): its gain K (DN/e⁻), read
#: noise (e⁻), full well and dark signal (per µm²) and quantum efficiency, and its fields.
K_TRUE, READ, FW, DARK_E, ETA = 0.35, 6.0, 800.0, 0.5, 0.6
CAMERA = {
    "sensor_um": (48.0, 48.0),
    "quantum_efficiency": ETA,
    "full_well_per_um2": FW,
    "read_noise_e": READ,
    "dark_e_per_um2": DARK_E,
    "adc_bits": 16,
    "gain_dn_per_e": K_TRUE,
    "black_level_dn": 64.0,
}


@pytest.mark.parametrize(
    ("field", "value", "needle"),
    [
        ("photons_per_um2", -1.0, "photons_per_um2 must be a finite number > 0, got -1.0"),
        ("photons_per_um2", float("nan"), "photons_per_um2 must be a finite number > 0, got nan"),
        ("fill_factor", 1.5, "fill_factor must be a finite number in (0, 1], got 1.5"),
        ("fill_factor", 0.0, "fill_factor must be a finite number in (0, 1], got 0.0"),
        ("quantum_efficiency", 0.0, "quantum_efficiency must be a finite number in (0, 1]"),
        ("read_noise_e", -0.1, "read_noise_e must be a finite number >= 0"),
        ("prnu", float("inf"), "prnu must be a finite number in [0, 1], got inf"),
        ("prnu", 5, "prnu must be a finite number in [0, 1], got 5"),
        ("psf", "bessel", "psf must be one of 'gaussian', 'airy'; got 'bessel'"),
        ("adc_bits", 0, "adc_bits must be an integer in [1, 32] or None, got 0"),
        ("sensor_um", (10.0, -2.0), "sensor_um[1] (width) must be a finite number in (0, 1e+09], got -2.0"),
        (
            "sensor_um",
            (1e300, 2.0),
            "sensor_um[0] (height) must be a finite number in (0, 1e+09], got 1e+300",
        ),
        ("noise", "shot", "noise must be one of 'auto', 'poisson', 'gaussian', 'none'; got 'shot'"),
        ("seed", -3, "seed must be an integer in [0, 9223372036854775807] or None, got -3"),
        ("seed", 2.0, "seed must be an integer in [0, 9223372036854775807] or None, got 2.0"),
        (
            "seed",
            2**64,
            "seed must be an integer in [0, 9223372036854775807] or None, got 18446744073709551616",
        ),
        ("pattern_seed", True, "pattern_seed must be an integer in [0, 9223372036854775807], got True"),
        ("psf_energy", 1.0, "psf_energy must be a finite number in [0.5, 1), got 1.0"),
    ],
)
def test_bad_values_are_refused_naming_field_value_and_range(field, value, needle):
    with pytest.raises(ArgumentError) as info:
        physics(**{field: value})
    assert needle in str(info.value) and "\n" not in str(info.value) and info.value.argument == field


def test_numpy_and_torch_numbers_are_kept_as_plain_numbers_that_write_to_json():
    ph = physics(
        photons_per_um2=np.float32(2.5),
        read_noise_e=torch.tensor(1.5, dtype=F64),
        full_well_per_um2=700,
        adc_bits=np.int64(10),
        seed=np.uint8(3),
    )
    values = (ph.photons_per_um2, ph.read_noise_e, ph.full_well_per_um2, ph.adc_bits, ph.seed)
    assert values == (2.5, 1.5, 700.0, 10, 3) and [type(v) for v in values] == [float] * 3 + [int] * 2
    back = SensorPhysics.from_json(ph.to_json())
    assert back == ph and hash(back) == hash(ph)


def test_electrons_and_digital_numbers_need_physics_and_snr_a_level_of_light(gen):
    img = torch.rand(1, 1, 16, 16, generator=gen)
    for output in ("dn", "electrons"):
        with pytest.raises(ArgumentError, match=f"output='{output}' needs physics"):
            lw.simulate(img, lw.CurvLayout((0.3, 0.1)), (4, 4), output=output)
        with pytest.raises(ArgumentError, match=f"output='{output}' needs physics"):
            lw.SensorLayer((4, 4), "curv", output=output)
    with pytest.raises(ArgumentError, match="level must be a finite number >= 0, got -1"):
        lw.physics.pixel_snr(torch.ones(2, 2), physics(), level=-1)


def test_a_full_well_below_the_read_noise_is_refused():
    ph = physics(full_well_per_um2=1.0, read_noise_e=20.0)  # the smallest pixel holds ~4 e⁻
    with pytest.raises(
        ValueError, match=r"full_well_per_um2 = 1 gives the smallest pixel a full well of .* e⁻, not"
    ):
        lw.simulate(torch.rand(1, 1, 32, 32), lw.RectLayout((0.5, 0.5)), (8, 8), physics=ph)


def test_physics_round_trips_through_json_and_layout_files(tmp_path):
    ph = physics(psf="airy", f_number=4.0, adc_bits=10, full_well_per_um2=900.0, prnu=0.01, seed=7)
    assert SensorPhysics.from_dict(ph.to_dict()) == ph
    assert SensorPhysics.from_json(ph.to_json()) == ph
    with pytest.raises(ValueError, match="sensor physics must be a JSON object, got list"):
        SensorPhysics.from_dict([1.0, 2.0])
    with pytest.raises(ValueError, match="missing 1 required positional argument: 'photons_per_um2'"):
        SensorPhysics.from_dict({"sensor_um": [1.0, 1.0]})
    with pytest.raises(ValueError, match=r"unknown sensor physics field\(s\) \['exposure'\]"):
        SensorPhysics.from_dict(ph.to_dict() | {"exposure": 1})
    layer = lw.SensorLayer((4, 4), "curv", physics=ph)
    layer.save_layout(tmp_path / "l.json")
    back = lw.SensorLayer.from_layout_file(tmp_path / "l.json")
    assert back.physics == ph


@pytest.mark.parametrize("method", ["exact", "separable", "montecarlo", "point"])
def test_without_physics_every_path_is_unchanged(method, gen):
    img = torch.rand(2, 3, 40, 48, generator=gen)
    layout = (
        lw.RectLayout(rand_theta(gen, 0.8)) if method == "separable" else lw.CurvLayout(rand_theta(gen, 0.8))
    )
    opts = {"seed": 3} if method == "montecarlo" else {}
    a = lw.simulate(img, layout, (5, 7), method, **opts)
    b = lw.simulate(img, layout, (5, 7), method, physics=None, **opts)
    assert torch.equal(a, b)


@pytest.mark.parametrize("family", ["rect", "curv"])
def test_noise_free_radiance_is_the_mean_and_electrons_scale_with_area(family, gen):
    img = torch.rand(1, 2, 48, 40, generator=gen, dtype=F64)
    layout = lw.make_layout(family, rand_theta(gen, 0.7), dtype=F64)
    ph = physics(
        quantum_efficiency=0.6, fill_factor=0.8, dark_e_per_um2=2.0, noise="none", sensor_um=(30.0, 50.0)
    )
    mean = lw.simulate(img, layout, (6, 5), tol=1e-8)
    out = lw.simulate(img, layout, (6, 5), tol=1e-8, physics=ph)
    assert float((out - mean).abs().max()) < 1e-12
    e = lw.simulate(img, layout, (6, 5), tol=1e-8, physics=ph, output="electrons")
    area_um2 = lw.pixel_mesh(layout, (6, 5), tol=1e-8).areas() * (30 * 50 / 4)
    expected = 0.6 * 0.8 * 100 * mean * area_um2 + 2.0 * area_um2
    assert float(((e - expected) / expected).abs().max()) < 1e-12


@pytest.mark.parametrize("compiled", [True, False])
def test_shot_and_read_noise_moments(compiled, gen, monkeypatch):
    # electrons: Poisson (variance = mean) plus Gaussian read noise, per pixel over many frames;
    # the fused kernel (CPU, no gradient) and the torch path (GPU, or numba missing) alike
    if not compiled:
        monkeypatch.setattr("layoutwarp.kernels.available", lambda: False)
    frames, size = 4000, (4, 4)
    layout = lw.RectLayout((0.6, 0.4), dtype=F64)  # pixel areas spanning more than 4x
    level = 0.2 + 0.6 * torch.rand((), generator=gen, dtype=F64)
    ph = physics(photons_per_um2=20.0, read_noise_e=2.0, quantum_efficiency=0.5, seed=int(level * 1e6))
    img = torch.full((frames, 1, 16, 16), float(level), dtype=F64)
    e = lw.simulate(img, layout, size, physics=ph, output="electrons")[:, 0]
    mu = lw.simulate(
        img[:1], layout, size, physics=SensorPhysics(**(ph.to_dict() | {"noise": "none"})), output="electrons"
    )[0, 0]
    assert float(mu.max() / mu.min()) > 4
    mean, var = e.mean(0), e.var(0)
    se_mean = torch.sqrt((mu + 4) / frames)
    assert bool(((mean - mu).abs() < 4.5 * se_mean).all())
    expected_var = mu + 4
    assert bool(((var / expected_var - 1).abs() < 4.5 * math.sqrt(2 / (frames - 1)) + 0.01).all())
    # Poisson is integer-valued before read noise: without it electrons are whole numbers
    whole = lw.simulate(
        img[:8],
        layout,
        size,
        physics=SensorPhysics(**(ph.to_dict() | {"read_noise_e": 0.0})),
        output="electrons",
    )
    assert torch.equal(whole, whole.round())


def test_the_fused_kernel_matches_the_torch_path_and_ignores_the_thread_count(gen):
    pytest.importorskip("numba")
    from layoutwarp.measurement import measure

    mean = torch.rand(3, 5, 7, generator=gen, dtype=F64)
    areas = (0.5 + torch.rand(5, 7, generator=gen, dtype=F64)) * (4 / 35)
    kw = {
        "photons_per_um2": 40.0,
        "prnu": 0.01,
        "dsnu": 2.0,
        "dark_e_per_um2": 0.3,
        "full_well_per_um2": 400.0,
    }
    kw |= {"adc_bits": 12, "black_level_dn": 8.0, "read_noise_e": 2.0}
    exact = physics(noise="none", **kw)
    for output in ("radiance", "electrons", "dn"):
        fused = measure(mean, areas, exact, output=output)
        traced = measure(mean.clone().requires_grad_(True), areas, exact, output=output).detach()
        assert torch.allclose(fused, traced, rtol=1e-12, atol=1e-9), output
    noisy = physics(seed=9, **kw)
    threads = torch.get_num_threads()  # the kernels' thread count follows torch's
    try:
        torch.set_num_threads(1)
        one = measure(mean, areas, noisy)
        torch.set_num_threads(3)
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(lw.kernels.base, "SMALL_WORK", 0)  # three shares however small
            many = measure(mean, areas, noisy)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, many) and not torch.equal(one, measure(mean, areas, exact))


def test_the_resampler_measures_in_one_call_what_measure_records(gen):
    # AreaResampler.apply(images, physics): on the CPU the product and the measurement in one
    # compiled call, the same bytes as the two steps; with image gradients, torch's product and
    # measure (Gaussian shot noise), whose gradient is the one of the two steps too
    from layoutwarp.measurement import measure

    res = lw.AreaResampler(lw.CurvLayout(rand_theta(gen, 0.7)), (9, 11), (40, 52))
    img = torch.rand(3, 40, 52, generator=gen)
    kw = {"read_noise_e": 2.0, "adc_bits": 10, "full_well_per_um2": 300.0, "prnu": 0.02, "dsnu": 0.5}
    seed = int(torch.randint(0, 2**31, (), generator=gen))
    for cam in (physics(seed=seed, **kw), physics(noise="none", **kw), physics(noise="gaussian", **kw)):
        for output in ("radiance", "electrons", "dn"):
            g1, g2 = torch.Generator().manual_seed(seed), torch.Generator().manual_seed(seed)
            one = res.apply(img, cam, output=output, generator=g1)
            two = measure(res.apply(img), res.areas, cam, output=output, generator=g2)
            assert one.dtype == torch.float32 and torch.equal(one, two), (cam.noise, output)
    assert not torch.equal(res.apply(img, physics(seed=seed, **kw)), res.apply(img))  # it measured
    with pytest.raises(ArgumentError, match="output must be one of 'radiance', 'electrons', 'dn'; got"):
        res.apply(img, physics(**kw), output="volts")
    cam = physics(seed=seed, **kw)
    x = img.clone().requires_grad_(True)
    y = img.clone().requires_grad_(True)
    a = res.apply(x, cam)
    b = measure(res.apply(y), res.areas, cam, generator=torch.Generator().manual_seed(seed))
    (a * img[:, :9, :11]).sum().backward()
    (b * img[:, :9, :11]).sum().backward()
    assert torch.equal(a, b) and torch.equal(x.grad, y.grad) and x.grad.abs().sum() > 0


def _kernel_electrons(
    mean: np.ndarray, noise: int, read: float, seed: int, in_place: bool = False, strided: bool = False
) -> np.ndarray:
    """The fused kernel's electrons for means ``mean`` (one plane; 1 e⁻ per unit, no patterns,
    no dark signal, full well or ADC): each element its own draw; ``in_place``: written over a
    copy of the means; ``strided``: read from every other element of a buffer twice as long."""
    from layoutwarp import kernels

    params = np.array([1.0, 1.0, 0.0, 0.0, 0.0, read, math.inf, 1.0, 0.0, math.inf])
    ones, zeros = np.ones(mean.size), np.zeros(mean.size)
    if strided:
        means = np.repeat(mean, 2)[None, ::2]
    else:
        means = mean[None].copy() if in_place else mean[None]
    out = means if in_place else np.empty((1, mean.size))
    kernels.sensor_measure(means, ones, zeros, zeros, params, seed, noise, 1, out, kernels.threads())
    return out[0]


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_the_plain_measurement_gives_the_fused_kernels_values_bit_for_bit(dtype, gen):
    # what a process measures with while the fused kernel compiles: every noise, output, fixed
    # pattern and ADC, means from below 0 through the Poisson methods' switch at 10 to 3e4, NaN and
    # inf passed through, in place or not, on 1 to 3 threads
    from layoutwarp import kernels

    rng = np.random.default_rng(int(torch.randint(0, 2**31, (), generator=gen)))
    n, p = 3, 4099
    mean = np.concatenate([rng.uniform(-0.5, 1.0, p - 3) ** 3 * 3.0e4, [np.nan, np.inf, 9.999]])
    means = np.stack([rng.permutation(mean) for _ in range(n)]).astype(dtype)
    area = rng.uniform(0.5, 2.0, p)
    prnu, dsnu = rng.standard_normal(p), rng.standard_normal(p)
    for noise in (0, 1, 2):
        for output in (0, 1, 2):
            for g_prnu, g_dsnu, read, top in ((0.0, 0.0, 0.0, math.inf), (0.01, 0.5, 2.5, 4095.0)):
                params = np.array([1.3, 0.6, g_prnu, g_dsnu, 0.4, read, 3.0e4, 0.1, 64.0, top])
                seed = int(rng.integers(0, 2**62))
                fast = np.empty_like(means)
                kernels.sensor_measure(means, area, prnu, dsnu, params, seed, noise, output, fast, 2)
                for threads, in_place in ((1, False), (3, True)):
                    plain = means.copy() if in_place else np.empty_like(means)
                    kernels.sensor_measure_plain(
                        plain if in_place else means,
                        area,
                        prnu,
                        dsnu,
                        params,
                        seed,
                        noise,
                        output,
                        plain,
                        threads,
                    )
                    assert np.array_equal(plain, fast, equal_nan=True), (noise, output, read, threads)
            assert not np.array_equal(fast, means, equal_nan=True)  # it measured


def test_the_compiled_measurement_sees_areas_changed_in_place(gen):
    # its per-sensor inputs are cached by the areas tensor: a change in place must not go stale
    from layoutwarp.measurement import measure

    mean = torch.rand(2, 4, 6, generator=gen, dtype=F64)
    areas = (0.5 + torch.rand(4, 6, generator=gen, dtype=F64)) * (4 / 24)
    cam = physics(noise="none", dark_e_per_um2=0.2)
    first = measure(mean, areas, cam, output="electrons")
    assert torch.equal(first, measure(mean, areas, cam, output="electrons"))
    areas.mul_(3.0)
    assert torch.allclose(measure(mean, areas, cam, output="electrons"), 3 * first, rtol=1e-14, atol=0)
    brighter = physics(noise="none", dark_e_per_um2=0.2, photons_per_um2=200.0)
    dark = 0.2 * areas * cam.um2_per_unit()  # the tripled areas
    assert torch.allclose(
        measure(mean, areas, brighter, output="electrons") - dark, 2 * (3 * first - dark), rtol=1e-13
    )


@pytest.mark.parametrize("lam", [0.7, 3.0, 9.99, 10.0, 12.3, 37.5, 1000.0, 3.0e4])
def test_the_kernels_poisson_draws_follow_the_poisson_law(lam, gen):
    # 3M draws against the exact pmf (χ², tails pooled): below 10 the multiplication method,
    # above Ahrens-Dieter PD, whose rarer steps (Q, E, H) carry about 1 % of the mass at 10-40
    stats = pytest.importorskip("scipy.stats")
    n = 3_000_000
    k = _kernel_electrons(np.full(n, lam), 1, 0.0, int(torch.randint(0, 2**62, (), generator=gen)))
    assert np.array_equal(k, np.round(k)) and k.min() >= 0
    values, counts = np.unique(k, return_counts=True)
    expected = stats.poisson.pmf(values, lam) * n
    keep = expected > 25
    observed = np.r_[counts[keep], n - counts[keep].sum()]
    expected = np.r_[expected[keep], n - expected[keep].sum()]
    chi2 = float(((observed - expected) ** 2 / expected).sum())
    assert stats.chi2.sf(chi2, observed.size - 1) > 1e-4, (chi2, observed.size)
    assert abs(k.mean() - lam) < 5 * math.sqrt(lam / n)


def test_the_kernels_normal_draws_follow_the_normal_law(gen):
    # the ziggurat through the shot stream (Gaussian mode at mean 1: e = 1 + z) and the read
    # stream (Poisson mode at mean 0: e = σ z): KS against Φ, and the tail beyond the 1024-layer
    # ziggurat's R = 4.0388 (its slow path) and beyond the first layer's edge at their exact masses
    stats = pytest.importorskip("scipy.stats")
    n = 3_000_000
    seed = int(torch.randint(0, 2**62, (), generator=gen))
    shot = _kernel_electrons(np.ones(n), 2, 0.0, seed) - 1.0
    read = _kernel_electrons(np.zeros(n), 1, 2.0, seed) / 2.0
    for z in (shot, read):
        assert stats.kstest(z, "norm").pvalue > 1e-4
        for edge in (4.038849846109505, 3.0, 0.1):  # the tail, a wedge's span, the top layers
            tail, p = float((np.abs(z) > edge).mean()), 2 * stats.norm.sf(edge)
            assert abs(tail - p) < 5 * math.sqrt(p * (1 - p) / n), (edge, tail, p)
        assert abs(float(z.mean())) < 5 / math.sqrt(n) and abs(float(z.var()) - 1) < 5 * math.sqrt(2 / n)
    assert abs(float(np.corrcoef(shot, read)[0, 1])) < 5 / math.sqrt(n)  # two independent streams


def test_the_first_try_table_holds_each_edge_exactly_and_a_close_lower_bound_of_its_ratio():
    # one 64-bit word per layer: decoded with numpy's bit views (not the kernels' bit cast), the
    # edges must be the ziggurat's bit for bit (a draw is u·x[i]), the ratio bounds at most the
    # ratios (else a try the exact test rejects would be accepted) and close (each bound's
    # 1 − ratio at most 1/32 above the exact one, so few accepted tries are rerun)
    from layoutwarp.kernels import samplers as noise

    words = noise._ZIG_P
    assert words.dtype == np.uint64 and words.shape == (1024,)
    edge = ((words & noise._X_MASK) + noise._X_BASE).view(np.float64)
    assert np.array_equal(edge, noise._ZIG_X[:1024])
    bound = 1.0 - (((words >> np.uint64(8)) & noise._D_MASK) + noise._D_BASE).view(np.float64)
    x = noise._ZIG_X
    ratio = x[1:] / x[:-1]  # recomputed from the edges
    assert (bound <= ratio).all() and bound[-1] == 0.0  # the top layer: every try to its wedge
    assert ((1.0 - bound) <= (1.0 - ratio) * (1 + 1 / 32)).all()
    assert float((ratio - bound).mean()) < 0.01 * float((1.0 - ratio).mean())  # < 1 % more reruns


@pytest.mark.parametrize("noise", [1, 2])
def test_the_kernels_first_tries_give_the_full_samplers_draws_bit_for_bit(noise, gen):
    # the vectorised first tries (and the partial reruns where one stream's try fails) must
    # return exactly what the full samplers draw from each element's two streams, also when the
    # kernel writes over its means (the rescan then reads the means its first tries left) or
    # reads them from a strided view (a signature of its own: each run's means copied into the
    # output, the cache hints stepping by the view's stride, which no result can show)
    numba = pytest.importorskip("numba")
    from layoutwarp.kernels import samplers as nk

    @numba.njit
    def reference(mu, seed, read, noise):
        state0 = nk.mix(np.uint64(seed) * nk.GOLDEN + np.uint64(0x632BE59BD9B4E019))
        out = np.empty(mu.size)
        for i in range(mu.size):
            key = state0 + np.uint64(i) * nk.ELEMENT_G
            if noise == 1:
                e, _ = nk.poisson(mu[i], key)
            else:
                z, _ = nk.normal(key)
                e = mu[i] + math.sqrt(mu[i]) * z
            z, _ = nk.normal(key + nk.STREAM_G)
            out[i] = e + read * z
        return out

    n = 200_000  # a few thousand failed first tries of each kind
    mu = np.exp(torch.empty(n, dtype=F64).uniform_(math.log(0.5), math.log(1e5), generator=gen).numpy())
    seed = int(torch.randint(0, 2**62, (), generator=gen))
    expected = reference(mu, seed, 2.5, noise)
    assert np.array_equal(_kernel_electrons(mu, noise, 2.5, seed), expected)
    assert np.array_equal(_kernel_electrons(mu, noise, 2.5, seed, in_place=True), expected)
    assert np.array_equal(_kernel_electrons(mu, noise, 2.5, seed, strided=True), expected)


def test_the_kernels_poisson_sampler_keeps_large_counts_finite_in_its_rare_steps():
    # a draw at mean 98946 whose normal gives k = 98304 = 12·8192, rejected by the squeeze, so
    # step Q evaluates log p_k: with k an int64, k⁵ wrapped to 0 and log p_k was -inf (that k
    # could never be accepted there); with numba's default error model in the sampler, that
    # division raised
    numba = pytest.importorskip("numba")
    stats = pytest.importorskip("scipy.stats")
    from layoutwarp.kernels import samplers as noise

    @numba.njit  # error_model="python": x / 0 raises
    def draw(mu, seed, i):
        state0 = noise.mix(np.uint64(seed) * noise.GOLDEN + np.uint64(0x632BE59BD9B4E019))
        return noise.poisson(mu, state0 + np.uint64(i) * noise.ELEMENT_G)[0]

    @numba.njit
    def log_p(mu, k):
        return noise._log_poisson(mu, k)

    k = draw(98946.46779494225, 515249225436444668, 131632)
    assert k == round(k) and abs(k - 98946.47) < 6 * math.sqrt(98946.47)
    for j in (1, 5, 12):  # whole multiples of 8192, where an integer k⁵ wraps to 0
        mu = 8192.0 * j + 0.37 * math.sqrt(8192.0 * j)
        assert math.isclose(log_p(mu, 8192.0 * j), stats.poisson.logpmf(8192 * j, mu), rel_tol=1e-10)


def test_quantiser_levels_and_full_well_clipping():
    layout = lw.RectLayout((0.5, 0.5), dtype=F64)
    ph = physics(
        photons_per_um2=1e4,
        full_well_per_um2=500.0,
        adc_bits=10,
        read_noise_e=3.0,
        black_level_dn=16.0,
        seed=1,
    )
    img = torch.linspace(0, 1, 8, dtype=F64).view(8, 1, 1, 1).expand(8, 1, 32, 32)
    dn = lw.simulate(img, layout, (4, 4), physics=ph, output="dn")
    assert torch.equal(dn, dn.round()) and float(dn.min()) >= 0 and float(dn.max()) <= 1023
    areas = lw.pixel_mesh(layout, (4, 4)).areas() * (64 * 64 / 4)
    k = ph.gain(float(areas.max()))
    assert k == pytest.approx((1023 - 16) / (500 * float(areas.max())))
    e = lw.simulate(img, layout, (4, 4), physics=ph, output="electrons")
    full = 500 * areas
    assert bool((e <= full + 1e-9).all()) and torch.allclose(e[-1, 0], full)  # the brightest frame saturates
    assert float(dn[-1].max()) == pytest.approx(round(k * float(full.max()) + 16), abs=0)
    assert float(dn[0].min()) >= 0  # read noise around the black level stays in range


def test_fixed_patterns_have_their_statistics_and_stay_fixed():
    size = (48, 48)
    layout = lw.UniformLayout()
    ph = physics(
        photons_per_um2=50.0, prnu=0.02, dsnu=3.0, noise="none", sensor_um=(96.0, 96.0), pattern_seed=5
    )
    one = torch.ones(1, 1, 96, 96, dtype=F64)
    e = lw.simulate(one, layout, size, physics=ph, output="electrons")[0, 0]
    dark = lw.simulate(0 * one, layout, size, physics=ph, output="electrons")[0, 0]
    signal = e - dark
    rel = signal / signal.mean() - 1
    assert float(rel.std()) == pytest.approx(0.02, rel=0.1)  # 2304 pixels: std within about 3 %
    assert float(dark.std()) == pytest.approx(3.0, rel=0.1)
    assert torch.equal(dark, lw.simulate(0 * one, layout, size, physics=ph, output="electrons")[0, 0])
    other = lw.simulate(
        0 * one,
        layout,
        size,
        physics=SensorPhysics(**(ph.to_dict() | {"pattern_seed": 6})),
        output="electrons",
    )
    assert not torch.equal(dark, other[0, 0])


def test_seeds_give_the_same_noise_and_every_image_its_own(gen):
    img = torch.rand(1, 3, 32, 32, generator=gen).expand(4, 3, 32, 32)
    ph = physics(read_noise_e=1.0, seed=11)
    layout = lw.CurvLayout(rand_theta(gen, 0.5))
    a = lw.simulate(img, layout, (6, 6), physics=ph)
    assert torch.equal(a, lw.simulate(img, layout, (6, 6), physics=ph))
    assert not torch.equal(a[0], a[1]) and not torch.equal(a[0, 0], a[0, 1])  # images and channels differ
    fresh = SensorPhysics(**(ph.to_dict() | {"seed": None}))
    assert not torch.equal(
        lw.simulate(img, layout, (6, 6), physics=fresh), lw.simulate(img, layout, (6, 6), physics=fresh)
    )
    layer = lw.SensorLayer((6, 6), layout, physics=ph)
    first, second = layer(img), layer(img)  # a seeded sequence: new noise every call, replayable
    assert not torch.equal(first, second)
    again = lw.SensorLayer((6, 6), layout, physics=ph)
    assert torch.equal(again(img), first) and torch.equal(again(img), second)


def test_gaussian_noise_in_training_and_poisson_elsewhere(gen):
    layout = lw.RectLayout(rand_theta(gen, 0.5), learn=True, dtype=F64)
    ph = physics(photons_per_um2=3.0, seed=2)
    img = torch.full((1, 1, 16, 16), 0.5, dtype=F64)
    with torch.no_grad():
        e = lw.simulate(img, layout, (4, 4), physics=ph, output="electrons")
    assert torch.equal(e, e.round())  # Poisson: whole electrons
    e = lw.simulate(img, layout, (4, 4), physics=ph, output="electrons")
    assert e.requires_grad and not torch.equal(e, e.round())  # reparameterised Gaussian


def test_theta_gradient_of_the_expectation_matches_central_differences(gen):
    # expected electrons depend on each pixel's area; their θ-gradient against differences (float64)
    img = torch.rand(1, 1, 30, 36, generator=gen, dtype=F64)
    ph = physics(noise="none", dark_e_per_um2=1.5, quantum_efficiency=0.7)
    w = torch.rand(1, 1, 5, 6, generator=gen, dtype=F64)
    theta = rand_theta(gen, 0.7)
    for family in ("rect", "curv"):
        layout = lw.make_layout(family, theta, learn=True, dtype=F64)
        mesh_opts = {} if family == "rect" else {"subdivisions": 2048}  # smooth in θ, areas to ~1e-7

        def loss(t: torch.Tensor, family=family, mesh_opts=mesh_opts) -> torch.Tensor:
            fixed = lw.make_layout(family, t, dtype=F64)
            mesh = lw.pixel_mesh(fixed, (5, 6), **mesh_opts)
            mean = lw.integrators.integrate_exact(img[0], fixed, (5, 6), mesh=mesh)
            from layoutwarp.measurement import measure

            return (measure(mean, mesh.areas(), ph, output="electrons") * w[0]).sum()

        out = lw.simulate(img, layout, (5, 6), physics=ph, output="electrons", tol=1e-9)
        (g,) = torch.autograd.grad((out * w).sum(), layout.rho)
        g_theta = g / (1 - layout.theta.detach() ** 2)
        h = 1e-6
        fd = torch.stack(
            [(loss(theta + h * e) - loss(theta - h * e)) / (2 * h) for e in torch.eye(2, dtype=F64)]
        )
        assert float((g_theta - fd).norm() / fd.norm()) < 1e-5, (family, g_theta, fd)


def test_reparameterised_gradient_is_unbiased(gen):
    # E[Σ w out²] = Σ w (m² + (μ_e + σ_d²) / s²) with s = η p a f: its θ-gradient is what the
    # mean over many noisy gradients must approach (within four standard errors)
    img = torch.rand(1, 1, 24, 24, generator=gen, dtype=F64) * 0.5 + 0.25
    ph = physics(photons_per_um2=2.0, read_noise_e=1.5, quantum_efficiency=0.8, noise="gaussian")
    w = torch.rand(1, 1, 4, 4, generator=gen, dtype=F64)
    layout = lw.RectLayout(rand_theta(gen, 0.6), learn=True, dtype=F64)
    mean = lw.simulate(img, layout, (4, 4))
    a_um2 = lw.pixel_mesh(layout, (4, 4)).areas() * (64 * 64 / 4)
    s = 0.8 * 2.0 * a_um2
    expected = (w * (mean**2 + (s * mean + 1.5**2) / s**2)).sum()
    (g_exp,) = torch.autograd.grad(expected, layout.rho)
    gens = torch.Generator().manual_seed(int(torch.randint(0, 2**31, (), generator=gen)))
    grads: list[torch.Tensor] = []
    # draws in rounds of 600 until the test has power (a standard error under a fifth of the
    # expected gradient; its terms can cancel to a small gradient for some layouts), at most 4800
    while len(grads) < 4800:
        for _ in range(600):
            out = lw.simulate(img, layout, (4, 4), physics=ph, generator=gens)
            grads.append(torch.autograd.grad((w * out**2).sum(), layout.rho)[0])
        se = torch.stack(grads).std(0) / math.sqrt(len(grads))
        if float(se.max()) < 0.2 * float(g_exp.abs().max()):
            break
    mean_grad = torch.stack(grads).mean(0)
    assert bool(((mean_grad - g_exp).abs() < 4 * se).all()), (mean_grad, g_exp, se, len(grads))
    assert float(se.max()) < 0.2 * float(g_exp.abs().max())  # the test has power


def test_psf_kernels_conserve_energy_and_the_airy_zero_is_at_1_22_lambda_n(gen):
    ph = physics(psf="airy", f_number=5.6, wavelength_um=0.55)
    r0 = 1.22 * 0.55 * 5.6
    assert ph.airy_zero_um() == pytest.approx(r0, rel=1e-3)
    r = torch.linspace(0.9 * r0, 1.1 * r0, 2001, dtype=F64)
    prof = airy_profile(r, 5.6, 0.55)
    assert float(r[prof.argmin()]) == pytest.approx(r0, rel=1e-3) and float(prof.min()) < 1e-7
    for kind in ("gaussian", "airy"):
        k = psf_kernels(physics(psf=kind, sensor_um=(100.0, 120.0)), (80, 60))
        for arr in (v for key, v in k.items() if key != "error"):
            assert arr.sum() == pytest.approx(1.0, abs=1e-12)
    k = psf_kernels(physics(psf="gaussian", psf_sigma_um=3.0, sensor_um=(40.0, 40.0)), (40, 40))
    x = np.arange(len(k["kx"])) - len(k["kx"]) // 2
    assert float((k["kx"] * x**2).sum()) == pytest.approx(9 + 1 / 12, rel=1e-3)  # σ² plus a pixel's box
    assert psf_kernels(physics(psf="airy", psf_energy=0.9), (64, 64))["error"] == pytest.approx(0.1)
    # kept per camera and size, read-only; another camera (here only its seed differs) builds anew
    ph = physics(psf="airy", sensor_um=(100.0, 120.0))
    k = psf_kernels(ph, (80, 60))
    assert psf_kernels(physics(psf="airy", sensor_um=(100.0, 120.0)), [80, 60]) is k
    assert not k["k2d"].flags.writeable
    again = psf_kernels(physics(psf="airy", sensor_um=(100.0, 120.0), seed=5), (80, 60))
    assert again is not k and np.array_equal(again["k2d"], k["k2d"])
    # a blob away from the border keeps its energy; OpenCV (CPU, no grad) and torch agree
    img = torch.zeros(2, 64, 64, dtype=torch.float32)
    img[:, 20:40, 25:35] = torch.rand(2, 20, 10, generator=gen)
    for kind in ("gaussian", "airy"):
        ph = physics(psf=kind, f_number=8.0)
        out = apply_psf(img, ph)
        assert torch.allclose(out.sum((1, 2)), img.sum((1, 2)), rtol=1e-5)
        via_torch = apply_psf(img.clone().requires_grad_(True), ph).detach()
        assert torch.allclose(out, via_torch, atol=1e-6)
    # light up to the border, and images narrower than the kernel: both paths reflect as OpenCV's
    # BORDER_REFLECT (scipy's "reflect"), and keep the light (torch's path lost 0.2 % of it, 40 %
    # of its edge column's, with BORDER_REFLECT_101)
    import scipy.ndimage

    for kind, hw in (("gaussian", (24, 20)), ("airy", (24, 20)), ("gaussian", (3, 2)), ("airy", (5, 1))):
        ph = physics(psf=kind, f_number=8.0, sensor_um=(20.0, 20.0))
        img = torch.rand(2, *hw, generator=gen, dtype=F64)
        k = psf_kernels(ph, hw)
        k2d = k["k2d"] if "k2d" in k else np.outer(k["ky"], k["kx"])
        ref = np.stack([scipy.ndimage.correlate(a, k2d, mode="reflect") for a in img.numpy()])
        for x in (img, img.clone().requires_grad_(True)):
            out = apply_psf(x, ph).detach()
            assert np.abs(out.numpy() - ref).max() < 1e-12, (kind, hw, x.requires_grad)
        if min(hw) > max(k2d.shape) // 2:  # a kernel within the image: the light is kept
            assert torch.allclose(out.sum((1, 2)), img.sum((1, 2)), rtol=1e-12)


def test_photon_transfer_recovers_gain_read_noise_and_saturation_per_pixel_class(gen):
    """EMVA 1288's photon transfer on a non-uniform sensor: flat fields at 24 exposures and dark
    frames; per class of pixel area, the variance-vs-mean slope is the system gain K, the dark
    variance gives the read noise, and the plateau the full well; the SNR follows √area where
    shot noise dominates and the EMVA formula everywhere."""
    size, frames = (12, 12), 6000
    layout = lw.RectLayout((0.55, 0.55), dtype=F64)
    k_true, read, fw, dark_e, eta = K_TRUE, READ, FW, DARK_E, ETA
    base = CAMERA | {"seed": int(torch.randint(0, 2**31, (), generator=gen))}
    area = lw.pixel_mesh(layout, size).areas() * (48 * 48 / 4)
    assert float(area.max() / area.min()) > 4
    classes = torch.bucketize(
        area, torch.quantile(area.flatten(), torch.tensor([0.25, 0.5, 0.75], dtype=F64))
    )

    def frames_dn(level: float, n: int = frames) -> torch.Tensor:
        ph = SensorPhysics(photons_per_um2=max(level, 1e-9), **base)
        flat = torch.full((n, 1, 24, 24), float(level > 0), dtype=F64)
        return lw.simulate(flat, layout, size, physics=ph, output="dn")[:, 0]

    dark = frames_dn(0.0, 4000)  # the dark variance to 1 %: many frames
    mu_dark, var_dark = dark.mean(0), dark.var(0)
    levels = np.geomspace(20, 400, 24)  # photons/µm²: the largest pixels stay below saturation
    means, variances = [], []
    for lv in levels:
        y = frames_dn(float(lv))
        means.append(y.mean(0) - mu_dark)
        variances.append(y.var(0) - var_dark)
    means, variances = torch.stack(means), torch.stack(variances)
    for c in range(4):
        sel = classes == c
        x, v = means[:, sel].flatten(), variances[:, sel].flatten()
        k_fit = float((x * v).sum() / (x * x).sum())  # through the origin, as the method's model
        assert k_fit == pytest.approx(k_true, rel=0.02), c
        sigma_d = math.sqrt(max(float(var_dark[sel].mean()) - 1 / 12, 0.0)) / k_fit
        # the dark noise σ_d (read noise and the dark signal's shot noise, as EMVA 1288 defines it)
        assert sigma_d == pytest.approx(math.sqrt(read**2 + dark_e * float(area[sel].mean())), rel=0.02), c
    saturated = frames_dn(1e6)  # every pixel at its full well
    e_sat = (saturated.mean(0) - 64.0) / k_true
    for c in range(4):
        sel = classes == c
        assert float(e_sat[sel].mean()) == pytest.approx(fw * float(area[sel].mean()), rel=0.02)
    # SNR: √area in the shot-noise regime, and the EMVA formula
    lv = 300.0
    y = frames_dn(lv, 4000)  # each pixel's SNR to about 1 %
    snr = (y.mean(0) - mu_dark) / y.std(0)
    slope = np.polyfit(np.log(area.flatten().numpy()), np.log(snr.flatten().numpy()), 1)[0]
    mu_e = eta * lv * area
    sigma_d2 = read**2 + dark_e * area
    expected = mu_e / torch.sqrt(sigma_d2 + (1 / 12) / k_true**2 + mu_e)
    assert slope == pytest.approx(0.5, abs=0.02)
    assert float(((snr / expected) - 1).abs().mean()) < 0.03


def test_the_emva1288_package_characterises_the_simulated_camera(gen, monkeypatch):
    """The standard's reference implementation (``emva1288``, a test extra) run on the simulated
    frames of each class of pixel area, as its loader would feed it (pairs of frames per
    exposure, a dark pair, the spatial sums): its system gain, quantum efficiency, dark noise and
    saturation capacity equal the configured camera's (the last as the standard defines it)."""
    pytest.importorskip("emva1288")
    from emva1288.process import Data1288, Results1288
    from emva1288.process.routines import get_int_imgs

    # its fits call np.asfarray, which NumPy 2 removed: the same function under its old name
    monkeypatch.setattr(np, "asfarray", lambda a, dtype=float: np.asarray(a, dtype=dtype), raising=False)
    size, frames = (16, 12), 1000
    layout = lw.RectLayout((0.7, 0.0), dtype=F64)  # rows alike, column widths spanning > 4x
    k_true, read, fw, dark_e, eta = K_TRUE, READ, FW, DARK_E, ETA
    base = CAMERA
    seeds = iter(torch.randint(0, 2**31, (64,), generator=gen).tolist())  # new noise every exposure
    area = (lw.pixel_mesh(layout, size).areas() * (48 * 48 / 4))[0]  # µm² per column
    classes = [(0, 11), (3, 8), (5, 6)]  # a column and its mirror image: equal areas
    assert float(area[0] / area[5]) > 4  # θ > 0: small pixels in the centre

    def pairs(level: float) -> list[np.ndarray]:
        ph = SensorPhysics(photons_per_um2=max(level, 1e-9), seed=next(seeds), **base)
        flat = torch.full((2 * frames, 1, 32, 24), float(level > 0))
        dn = lw.simulate(flat, layout, size, physics=ph, output="dn")[:, 0].numpy()
        return [
            np.stack([dn[f * frames : (f + 1) * frames, :, list(cols)] for f in (0, 1)]) for cols in classes
        ]

    sat = fw / eta  # photons/µm² at which every pixel reaches its full well
    levels = np.r_[np.geomspace(0.02, 0.7, 14), np.linspace(0.72, 1.1, 20)] * sat
    dark = pairs(0.0)
    bright = [pairs(float(lv)) for lv in levels]
    for c, cols in enumerate(classes):
        a = float(area[cols[0]])
        shape = dark[c][0].reshape(-1, 2).shape
        temporal: dict[float, dict] = {}
        for lv, imgs in [(0.0, dark), *zip(levels, bright, strict=True)]:
            d = get_int_imgs([img.reshape(shape) for img in imgs[c]])
            temporal[float(lv) * a] = {
                "sum": np.sum(d["sum"]),
                "pvar": np.sum(d["pvar"]),
                "dmean": d["dmean"],
            }
        spatial = {
            0.0: get_int_imgs(list(dark[c][0][:8])),
            float(levels[8]) * a: get_int_imgs(list(bright[8][c][0][:8])),
        }
        data = Data1288(
            {"width": shape[1], "height": shape[0], "temporal": {1.0: temporal}, "spatial": {1.0: spatial}},
            loglevel=40,
        )
        res = Results1288(data.data, pixel_area=a, loglevel=40)
        assert res.K == pytest.approx(k_true, rel=0.02), c
        assert res.QE == pytest.approx(100 * eta, rel=0.02), c
        assert res.sigma_d == pytest.approx(math.sqrt(read**2 + dark_e * a), rel=0.02), c
        # EMVA's saturation is the exposure of largest temporal variance: a few σ of noise below
        # the full well (clipping eats the upper tail first), on the exposure grid. Its capacity
        # u_e_sat is that exposure times the fitted QE, so it also carries the QE fit's error
        # (0.4 % low put it 25 e⁻ under these bounds, seed 4013862211): the exposure is checked
        full, step = fw * a, (levels[-1] - levels[-2]) * eta * a
        u_sat = res.u_p_sat * eta  # electrons at the chosen exposure, with the configured QE
        assert full - 4 * math.sqrt(full + read**2) - step <= u_sat <= full, (c, u_sat, full)
        assert res.u_e_sat == pytest.approx(u_sat, rel=0.02), c


def test_preprocessing_records_with_physics_and_reruns_to_the_same_bytes(tmp_path):
    from conftest import SAMPLES

    from layoutwarp.preprocess import file_seed

    ph = physics(sensor_um=(360.0, 480.0), photons_per_um2=3.0, read_noise_e=2.0, psf="gaussian", seed=4)
    layout, src = lw.CurvLayout((0.4, 0.2)), SAMPLES / "camvid" / "val"
    one = lw.preprocess_folder(src, tmp_path / "a", layout, (36, 48), physics=ph, progress=False)
    two = lw.preprocess_folder(src, tmp_path / "b", layout, (36, 48), physics=ph, workers=2, progress=False)
    assert one.processed == two.processed == 3 and not one.failed
    files = sorted(p.name for p in (tmp_path / "a").glob("*.png"))
    assert all((tmp_path / "a" / f).read_bytes() == (tmp_path / "b" / f).read_bytes() for f in files)
    clean = lw.preprocess_folder(src, tmp_path / "c", layout, (36, 48), progress=False)
    import cv2

    a, c = (cv2.imread(str(tmp_path / d / files[0])).astype(float) for d in ("a", "c"))
    assert 2 < np.abs(a - c).mean() < 60  # noisy at 3 photons/µm², around the clean image
    assert file_seed(4, files[0]) != file_seed(4, files[1]) and file_seed(4, "x/y.png") == file_seed(
        4, "x/y.png"
    )
    manifest = (tmp_path / "a" / "manifest.json").read_text()
    assert '"photons_per_um2": 3.0' in manifest and clean.processed == 3
    with pytest.raises(ValueError, match="other sensor physics"):
        lw.preprocess_folder(src, tmp_path / "a", layout, (36, 48), progress=False)


def test_the_preprocess_command_reads_a_physics_file_and_its_flags_override_it(tmp_path):
    import json

    from conftest import SAMPLES

    from layoutwarp.cli import main

    src = SAMPLES / "camvid" / "val"
    file = tmp_path / "camera.json"  # no light in the file: the flag gives it; the flag's read noise wins
    file.write_text(json.dumps({"sensor_um": [360.0, 480.0], "read_noise_e": 9.0, "seed": 4, "adc_bits": 10}))
    argv = ["preprocess", str(src), str(tmp_path / "cli"), "--family", "curv", "--theta", "0.4,0.2"]
    argv += ["--size", "48x36", "--physics", str(file), "--photons-per-um2", "3", "--read-noise-e", "2"]
    assert main([*argv, "--no-progress"]) == 0
    ph = physics(sensor_um=(360.0, 480.0), photons_per_um2=3.0, read_noise_e=2.0, seed=4, adc_bits=10)
    api = lw.preprocess_folder(
        src, tmp_path / "api", lw.CurvLayout((0.4, 0.2)), (36, 48), physics=ph, progress=False
    )
    files = sorted(p.relative_to(tmp_path / "api") for p in (tmp_path / "api").rglob("*.png"))
    assert api.processed == len(files) == 3
    assert all((tmp_path / "cli" / f).read_bytes() == (tmp_path / "api" / f).read_bytes() for f in files)
    recorded = json.loads((tmp_path / "cli" / "manifest.json").read_text())
    assert SensorPhysics.from_dict(recorded["physics"]) == ph


def test_export_report_gives_each_pixels_full_well_and_snr(tmp_path):
    ph = physics(photons_per_um2=40.0, full_well_per_um2=600.0, read_noise_e=4.0, dark_e_per_um2=1.0)
    layout = lw.RectLayout((0.5, 0.3))
    report = lw.export_layout(layout, (6, 8), tmp_path / "m.svg", (60.0, 80.0), physics=ph)
    areas = lw.pixel_mesh(layout, (6, 8)).areas().flatten().numpy() * (60 * 80 / 4)
    full = np.array(report.physics["full_well_e"])
    assert np.allclose(full, 600 * areas, rtol=1e-6)
    mu = 40 * areas
    assert np.allclose(report.physics["snr"], mu / np.sqrt(16 + areas + mu), rtol=1e-6)
    assert "SNR" in report.summary() and report.physics["sensor_um"] == [60.0, 80.0]


def test_the_physics_flags_reach_training_model_files_and_kornia(tmp_path, capsys):
    from layoutwarp.cli import main
    from layoutwarp.experiments.models import load_model

    argv = ["train", "mnist", "--quick", "--epochs", "1", "--family", "rect", "--no-progress"]
    assert main([*argv, "--photons-per-um2", "3", "--read-noise-e", "2", "--out", str(tmp_path)]) == 0
    model, info = load_model(tmp_path / "model_rect_4x4_seed0.pt")
    assert info["sensor"]["physics"]["photons_per_um2"] == 3.0 and model.sensor.physics.sensor_um == (
        28.0,
        28.0,
    )
    assert main([*argv, "--read-noise-e", "2", "--out", str(tmp_path / "x")]) == 2
    assert "argument --photons-per-um2: needed for sensor physics" in capsys.readouterr().err
    import kornia.augmentation as K

    aug = lw.SensorAugmentation((6, 6), "curv", physics=physics(photons_per_um2=5.0, seed=1))
    x = torch.rand(2, 1, 24, 24)
    out = K.AugmentationSequential(aug, data_keys=["input"])(x)
    clean = lw.simulate(x, aug.layout, (6, 6))
    noise = float((out - clean).detach().abs().mean())
    assert out.shape == (2, 1, 6, 6) and 0.01 < noise < 1  # noisy, around the mean


def test_the_quantiser_passes_gradients_straight_through(gen):
    # with the ADC on, training sees the rounded values but the gradient of the unrounded ones
    img = torch.rand(1, 1, 20, 20, generator=gen, dtype=F64)
    w = torch.rand(1, 1, 4, 4, generator=gen, dtype=F64)
    grads = []
    for bits in (None, 6):
        layout = lw.RectLayout((0.3, -0.2), learn=True, dtype=F64)
        ph = physics(noise="none", adc_bits=bits, full_well_per_um2=1e6, gain_dn_per_e=1e-3)
        out = lw.simulate(img, layout, (4, 4), physics=ph, output="dn")
        if bits:
            assert torch.equal(out.detach(), out.detach().round())
        grads.append(torch.autograd.grad((out * w).sum(), layout.rho)[0])
    assert torch.allclose(grads[0], grads[1], rtol=1e-12) and bool(grads[0].abs().sum() > 0)


@pytest.mark.parametrize("psf", [None, "gaussian"])
@pytest.mark.parametrize("learn", [False, True])
def test_nonfinite_input_raises_with_physics_naming_the_sources_count(psf, learn, gen):
    # a fixed layout's compiled product counts the bad means as it writes them, a learnable
    # one's are checked after; a PSF spreads the bad value, but the message counts the image's
    img = torch.rand(1, 2, 40, 60, generator=gen)
    r, c = (int(v) for v in torch.randint(10, 30, (2,), generator=gen))
    img[0, 1, r, c] = float("nan")
    ph = physics(photons_per_um2=200.0, seed=1, psf=psf, f_number=4.0, wavelength_um=0.55)
    layout = lw.CurvLayout(rand_theta(gen, 0.5), learn=learn)
    with pytest.raises(ValueError, match=r"image contains 1 non-finite value\(s\)"):
        lw.simulate(img, layout, (8, 12), physics=ph)
    out = lw.simulate(img, layout, (8, 12), physics=ph, allow_nonfinite=True)
    assert torch.isfinite(out[0, 0]).all() and not torch.isfinite(out[0, 1]).all()


def test_nonfinite_input_passes_through_the_measurement_with_allow_nonfinite(gen):
    # NaN/Inf in the image (allow_nonfinite=True) reach only the pixels they touch, as NaN/Inf
    # electrons: the samplers pass them through instead of looping on them
    img = torch.rand(2, 3, 40, 60, generator=gen)
    img[0, 1, 10:20, 10:20] = float("nan")
    img[1, 0, :5, :5] = float("inf")
    ph = physics(photons_per_um2=200.0, read_noise_e=2.0, seed=1)
    layout = lw.CurvLayout(rand_theta(gen, 0.5))
    touched = torch.isnan(lw.simulate(img, layout, (8, 12), allow_nonfinite=True))
    touched |= torch.isinf(lw.simulate(img, layout, (8, 12), allow_nonfinite=True))
    for output in ("radiance", "electrons"):
        out = lw.simulate(img, layout, (8, 12), physics=ph, allow_nonfinite=True, output=output)
        assert torch.equal(~torch.isfinite(out), touched) and 0 < int(touched.sum()) < touched.numel()
    for noise in (1, 2):  # every first try, whatever its normal, on many infinite and NaN means
        mean = np.repeat([np.inf, np.nan, 50.0], 2000)
        e = _kernel_electrons(mean, noise, 2.0, int(torch.randint(0, 2**62, (), generator=gen)))
        assert not np.isfinite(e[:4000]).any() and np.isfinite(e[4000:]).all()  # inf - inf: NaN, as in torch


@pytest.mark.parametrize("noise", ["poisson", "gaussian", "none"])
def test_the_differentiable_measurement_records_what_the_compiled_one_does_of_nonfinite_and_huge_means(
    noise,
):
    # the torch path (a gradient) and the compiled pass record the same of means the noise cannot
    # move (no read noise): ±inf, NaN and ±1e30 (the straight-through steps kept the value, not
    # inf − inf = NaN or 1e30 − 1e30 = 0; torch's Poisson overflowed its int64 counts and refused
    # NaN and inf)
    from layoutwarp.measurement import measure

    mean = torch.tensor([[[math.inf, math.nan, 1e30, -math.inf, -1e30]]], dtype=F64)
    areas = torch.ones(1, 5, dtype=F64)
    for output, full in (("dn", 1e4), ("electrons", None), ("radiance", 1e4)):
        cam = physics(noise=noise, adc_bits=10, full_well_per_um2=full, read_noise_e=0.0, seed=1)
        with torch.no_grad():
            compiled = measure(mean, areas, cam, output=output)
        x = mean.clone().requires_grad_(True)
        taped = measure(x, areas, cam, output=output)
        torch.testing.assert_close(taped.detach(), compiled, rtol=1e-12, atol=0, equal_nan=True)
        taped.nansum().backward()  # a gradient of the finite values' path, no error


def test_measure_checks_its_arguments_in_one_line_each():
    from layoutwarp.measurement import measure

    mean, areas = torch.rand(2, 9, 11, dtype=F64), torch.full((9, 11), 4 / 99, dtype=F64)
    cam = physics(seed=3)
    for grad in (False, True):
        m = mean.clone().requires_grad_(grad)
        for args, kw, match in (
            ((m, areas[:1], cam), {}, r"areas must be the pixels' floating-point \(h, w\) = \(9, 11\)"),
            ((m, areas.long(), cam), {}, "areas must be .* got .* torch.int64"),
            ((m[0, 0], areas[0], cam), {}, r"mean must have shape \(\.\.\., h, w\), got \(11,\)"),
            ((m, areas, None), {}, "physics must be a SensorPhysics or its dict, got None"),
            ((m, areas, cam), {"seed": 5}, "seed must be a 0-d int64 tensor"),
            ((m, areas, cam), {"output": "volts"}, "output must be one of"),
        ):
            with pytest.raises(ArgumentError, match=match):
                measure(*args, **kw)
    # a camera's dict is a camera, as simulate takes it
    assert torch.equal(measure(mean, areas, cam.to_dict()), measure(mean, areas, cam))


#: The measurement and a fixed layout's forward through the device path in numba's CUDA simulator,
#: written for the test to compare with the CPU kernels.
DEVICE_MEASURE = """
import json, sys
import numpy as np, torch
import layoutwarp as lw
from layoutwarp.testing import count_launches
case = dict(np.load(sys.argv[1]))
cam = json.loads(str(case["camera"]))
means, areas, img = (torch.from_numpy(case[k]) for k in ("means", "areas", "img"))
layout = lw.CurvLayout(tuple(case["theta"]))
out = {}
with torch.no_grad():
    for noise in ("poisson", "gaussian", "none"):
        for output in ("radiance", "electrons", "dn"):
            phys = lw.SensorPhysics(**cam, noise=noise)
            out[f"{noise}-{output}"] = lw.measurement.measure(means, areas, phys, output=output).numpy()
    phys = lw.SensorPhysics(**cam)
    out["fixed"] = lw.simulate(img, layout, (5, 6)).numpy()
    out["fixed-physics"] = lw.simulate(img, layout, (5, 6), physics=phys).numpy()
    launches = count_launches(lambda: lw.simulate(img, layout, (5, 6), physics=phys))
np.savez(sys.argv[2], launches=sum(launches.values()), **out)
"""


@pytest.mark.slow  # a process of its own, the kernels as plain Python
@pytest.mark.heavy
def test_the_measurement_on_the_device_path_draws_what_the_cpu_kernel_draws_in_numbas_simulator(
    gen, tmp_path
):
    """Without a GPU: the device path of the measurement (one thread per element, the full
    samplers) and of a fixed layout's forward with physics (one launch: the product and the
    measurement) in numba's CUDA simulator against the CPU kernels: the same noise draws, so the
    same values to the bit, for every noise model and output, and for a fixed layout's forward
    with and without the measurement."""
    import json

    seed = int(torch.randint(0, 2**31, (), generator=gen))
    camera = {
        "sensor_um": (280.0, 560.0), "photons_per_um2": 5.0, "read_noise_e": 2.0, "full_well_per_um2": 400.0,
        "adc_bits": 10, "prnu": 0.02, "dsnu": 0.5, "seed": seed,
    }  # fmt: skip
    means = torch.rand(2, 6, 7, generator=gen, dtype=torch.float64) * 3
    means[0, 0, :3] = torch.tensor([0.0, 1e-9, 300.0])  # no light, a trickle, past the full well
    areas = torch.rand(6, 7, generator=gen, dtype=torch.float64) * 0.2 + 0.05
    img = torch.rand(1, 3, 20, 26, generator=gen)
    theta = rand_theta(gen, 0.6)
    case = {"camera": json.dumps(camera), "means": means, "areas": areas, "img": img, "theta": theta}
    np.savez(tmp_path / "case.npz", **{k: np.asarray(v) for k, v in case.items()})
    run_in_simulator(DEVICE_MEASURE, tmp_path / "case.npz", tmp_path / "out.npz", wait=True)
    got = np.load(tmp_path / "out.npz")
    layout = lw.CurvLayout(tuple(theta))
    with torch.no_grad():
        for noise in ("poisson", "gaussian", "none"):
            for output in ("radiance", "electrons", "dn"):
                phys = SensorPhysics(**camera, noise=noise)
                ref = lw.measurement.measure(means, areas, phys, output=output).numpy()
                assert np.array_equal(got[f"{noise}-{output}"], ref), (noise, output)
        assert np.array_equal(got["fixed"], lw.simulate(img, layout, (5, 6)).numpy())
        recorded = lw.simulate(img, layout, (5, 6), physics=SensorPhysics(**camera)).numpy()
        assert np.array_equal(got["fixed-physics"], recorded)
    assert int(got["launches"]) <= 1  # the product and the measurement, one kernel (19 + 39 before)


def test_a_device_kernel_that_fails_warns_once_and_leaves_the_torch_path(monkeypatch, gen):
    """Where numba-cuda cannot compile or launch the measurement's kernel, the call warns once,
    names the kernel and the reason, and returns the other path's result; later calls go there
    without trying again."""
    from layoutwarp import measurement as ph
    from layoutwarp.kernels import device
    from layoutwarp.operators import base as ops

    calls = []

    def broken(*args):
        calls.append(1)
        raise RuntimeError("NVVM_ERROR_COMPILATION")

    lw.jit.ready("measure", torch.float64, wait=True)  # its warm-up done before the device is faked
    monkeypatch.setattr(device, "FAILED", {})
    monkeypatch.setattr(ops, "runs_on_device", lambda t: True)  # the one backend decision
    monkeypatch.setattr(ph.kernels, "cuda_available", lambda dtype="float32": True)
    monkeypatch.setattr(ph, "measure_on_device", broken)
    cam = SensorPhysics((100.0, 120.0), photons_per_um2=20.0, read_noise_e=1.0, seed=7)
    means = torch.rand(1, 4, 5, generator=gen, dtype=torch.float64)
    areas = torch.full((4, 5), 0.2, dtype=torch.float64)
    with pytest.warns(RuntimeWarning, match="CUDA kernel of the sensor's measurement does not run.*NVVM"):
        first = ph.measure(means, areas, cam)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = ph.measure(means, areas, cam)
    assert calls == [1] and torch.equal(first, second)
    monkeypatch.setattr(ops, "runs_on_device", lambda t: False)
    assert torch.equal(first, ph.measure(means, areas, cam))  # the path it fell back to


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_the_measurement_on_cuda_draws_the_cpus_noise(gen):
    """On a GPU: a fixed layout's forward with physics, and `measure` alone, from the same seed on
    CUDA and on the CPU: the same draws from the same streams, so nearly every value equal (the
    device's exp/log and fused multiply-adds may round a rare rejection test or a mean's last bit
    otherwise), and the rest within a few DN of the ADC."""
    if not lw.kernels.cuda_available("float32"):
        pytest.skip("numba's CUDA target does not run here")
    cam = SensorPhysics((280.0, 560.0), photons_per_um2=5.0, read_noise_e=2.0, adc_bits=10, prnu=0.02, seed=3)
    img = torch.rand(1, 3, 60, 80, generator=gen)
    layout = lw.CurvLayout(tuple(rand_theta(gen, 0.6)))
    with torch.no_grad():
        gpu = lw.simulate(img.cuda(), layout.cuda(), (15, 20), physics=cam, output="dn").cpu()
        cpu = lw.simulate(img, layout.cpu(), (15, 20), physics=cam, output="dn")
        means = torch.rand(3, 15, 20, generator=gen, dtype=torch.float64) * 40
        areas = torch.full((15, 20), 4 / 300, dtype=torch.float64)
        alone = lw.measurement.measure(means.cuda(), areas.cuda(), cam, output="electrons").cpu()
        alone_cpu = lw.measurement.measure(means, areas, cam, output="electrons")
    assert not lw.kernels.device.FAILED
    for a, b in ((gpu, cpu), (alone, alone_cpu)):
        assert float((a == b).double().mean()) >= 0.99
        assert float((a - b).abs().max()) <= 4.0


def test_a_psf_wider_than_the_sensor_is_refused_before_its_kernel_is_built():
    # f/1e9 made an Airy kernel of 220 GB: refused at once, naming the field that set its width
    for kwargs, field in (
        ({"psf": "airy", "f_number": 1e9}, "f_number"),
        ({"psf": "gaussian", "psf_sigma_um": 65.0}, "psf_sigma_um"),
    ):
        with pytest.raises(ArgumentError, match=f"^{field} .* over 4 times the sensor's 64 µm") as info:
            physics(**kwargs)
        assert info.value.argument == field
    assert physics(psf="airy", f_number=5.6).psf == "airy"


@pytest.mark.slow
def test_the_ranks_of_a_process_group_draw_noise_of_their_own(tmp_path):
    # under torchrun every rank's SensorLayer followed one seeded sequence: rank 1's k-th image got
    # rank 0's k-th image's noise, so a global batch held each draw once per rank
    import os
    import subprocess
    import sys
    import textwrap

    script = tmp_path / "ranks.py"
    script.write_text(
        textwrap.dedent("""
        import torch, torch.distributed as dist, layoutwarp as lw
        dist.init_process_group("gloo")
        phys = lw.SensorPhysics((28, 28), photons_per_um2=3.0, read_noise_e=1.0, seed=0)
        out = lw.SensorLayer((4, 4), "curv", physics=phys)(torch.full((2, 1, 28, 28), 0.5)).detach()
        outs = [torch.empty_like(out) for _ in range(2)]
        dist.all_gather(outs, out)
        if dist.get_rank() == 0:
            alone = lw.SensorLayer((4, 4), "curv", physics=phys)
            dist.destroy_process_group()
            same = torch.equal(alone(torch.full((2, 1, 28, 28), 0.5)), outs[0])  # rank 0: as one process
            print(same, len({tuple(s.flatten().tolist()) for s in torch.cat(outs)}))
        else:
            dist.destroy_process_group()
    """)
    )
    env = {k: v for k, v in os.environ.items() if k not in ("WORLD_SIZE", "RANK", "LOCAL_RANK")}
    torchrun = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc-per-node", "2"]
    res = subprocess.run([*torchrun, str(script)], capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 0, res.stderr[-3000:]
    assert res.stdout.split() == ["True", "4"]  # four images, four draws
