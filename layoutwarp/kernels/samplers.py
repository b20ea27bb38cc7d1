"""Counter-based random streams and exact samplers for the compiled kernels: SplitMix64
streams ([`mix`][]), standard normals by a 1024-layer ziggurat ([`normal`][]), exact Poisson
draws ([`poisson`][]: multiplication of uniforms below a mean of 10, Ahrens and Dieter's PD
above) and their branch-free first tries ([`first_tries`][]), for
[`layoutwarp.kernels.noise`][]'s measurement on the CPU and on CUDA devices."""

from __future__ import annotations

import math

import numpy as np

from .base import inline

try:  # numba's own code generator, present wherever numba is
    from numba import types as numba_types
    from numba.extending import intrinsic
except ImportError:  # pragma: no cover - depends on the environment
    numba_types = intrinsic = None

__all__ = ["ELEMENT_G", "GOLDEN", "STREAM_G", "first_tries", "mix", "normal", "poisson", "stream_origin"]

GOLDEN = np.uint64(0x9E3779B97F4A7C15)
#: Element ``i``'s noise streams are disjoint blocks of one SplitMix64 sequence: its shot stream
#: from the state ``state0 + i·2³³·G``, its read stream ``2³²·G`` on (2³² draws each, so up to
#: 2³¹ elements a call never share a state).
STREAM_G = np.uint64((0x9E3779B97F4A7C15 << 32) % 2**64)
ELEMENT_G = np.uint64((0x9E3779B97F4A7C15 << 33) % 2**64)
_U53 = 1.0 / 9007199254740992.0


def _ziggurat_tables(layers: int = 1024) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The normal ziggurat's layer edges ``x`` (``layers + 1``; ``x[0]`` the base strip's
    equivalent width, ``x[1]`` the tail's start ``R``, ``x[layers] = 0``), ratios
    ``x[i+1] / x[i]`` and heights ``exp(−x²/2)``: Marsaglia and Tsang's construction for 1024
    equal-area layers of area ``V`` (``R`` and ``V`` solved in 40-digit arithmetic so the top
    layer closes; the same solve gives their published 128-layer and Doornik's 256-layer
    values). A first try is accepted 99.6 % of the time."""
    r, v = 4.038849846109505, 0.001226324646353088
    x = np.zeros(layers + 1)
    x[0], x[1] = v / math.exp(-0.5 * r * r), r
    for i in range(1, layers - 1):
        x[i + 1] = math.sqrt(-2.0 * math.log(v / x[i] + math.exp(-0.5 * x[i] * x[i])))
    return x, x[1:] / x[:-1], np.exp(-0.5 * x * x)


_ZIG_X, _ZIG_R, _ZIG_Y = _ziggurat_tables()
#: The first try's table ([`_first_try_table`][]): its bases and masks.
_X_BASE = np.float64(0.125).view(np.uint64)
_X_MASK = np.uint64((1 << 55) - 1)
_D_BASE = np.float64(2.0**-11).view(np.uint64)
_D_MASK = np.uint64(0x1FF << 47)


def _first_try_table() -> np.ndarray:
    """Each layer's edge ``x[i]`` and a lower bound of its ratio ``x[i+1]/x[i]`` in one 64-bit
    word, so a first try gathers one value instead of two: the edge's bits exactly, less those of
    0.125 (its six binades, 0.135 to 4.27, need 55 bits), and in the top 9 bits ``c`` with
    ``1 − d`` at most the ratio, ``d`` the double of bits ``bits(2⁻¹¹) + c·2⁴⁷`` (four exponent
    and five mantissa bits: ``1 − ratio`` rounded up by at most 1/32 of itself). A try between the
    bound and the ratio is flagged and rerun by the full sampler, which tests the exact ratio, so
    every draw is unchanged; the bound costs four tries in 10⁵ such a rerun (the ziggurat rejects
    430)."""
    x, ratio = _ZIG_X[:1024], _ZIG_R[:1024]
    edge = x.view(np.uint64) - _X_BASE
    gap = np.maximum(1.0 - ratio, 2.0**-11).view(np.uint64) - _D_BASE
    code = (gap + np.uint64((1 << 47) - 1)) >> np.uint64(47)  # rounded up
    while True:  # and up again where 1 − d rounds above the ratio
        over = 1.0 - ((code << np.uint64(47)) + _D_BASE).view(np.float64) > ratio
        if not over.any():
            break
        code[over] += np.uint64(1)
    assert (edge >> np.uint64(55) == 0).all() and (code < 512).all()
    return edge | (code << np.uint64(55))


_ZIG_P = _first_try_table()

if intrinsic is not None:

    @intrinsic
    def _as_float(typingctx, bits):
        """The float64 whose bits are the uint64 ``bits`` (a bit cast: free in a vector)."""

        def codegen(context, builder, signature, args):
            return builder.bitcast(args[0], context.get_value_type(numba_types.float64))

        return numba_types.float64(numba_types.uint64), codegen

else:  # pragma: no cover - without numba the kernels are not compiled

    def _as_float(bits: np.uint64) -> float:
        return float(np.uint64(bits).view(np.float64))


@inline
def _first_try_layer(i: int) -> tuple[float, float]:
    """Layer ``i``'s edge ``x[i]`` (exact) and a lower bound of its ratio, from one look-up of
    [`_first_try_table`][]."""
    word = _ZIG_P[i]
    edge = _as_float((word & _X_MASK) + _X_BASE)
    return edge, 1.0 - _as_float(((word >> np.uint64(8)) & _D_MASK) + _D_BASE)


@inline
def mix(z: np.uint64) -> np.uint64:
    """SplitMix64's finaliser: a counter to 64 well-mixed bits."""
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@inline
def _uniform(state: np.uint64) -> tuple[float, np.uint64]:
    """The next double in ``(0, 1)`` of a SplitMix64 stream, and the advanced state."""
    state = state + GOLDEN
    return ((mix(state) >> np.uint64(11)) + 0.5) * _U53, state


@inline
def _strip(bits: np.uint64) -> tuple[float, int]:
    """A ziggurat try from 64 bits: a uniform in ``(-1, 1)`` (the top 53 bits) and a layer
    (the lowest 10, which the uniform does not use)."""
    return ((bits >> np.uint64(11)) + 0.5) * (2.0 * _U53) - 1.0, np.int64(bits & np.uint64(1023))


@inline
def normal(state: np.uint64) -> tuple[float, np.uint64]:
    """A standard normal draw (the ziggurat: one 64-bit draw and a table look-up 99.6 % of the
    time; the wedges by rejection under the density, the tail beyond ``R`` by Marsaglia's
    exponential method), and the advanced state."""
    while True:
        state = state + GOLDEN
        u, i = _strip(mix(state))
        if abs(u) < _ZIG_R[i]:
            return u * _ZIG_X[i], state
        if i == 0:  # the tail |z| > R
            r = _ZIG_X[1]
            while True:
                a, state = _uniform(state)
                b, state = _uniform(state)
                t = -math.log(a) / r
                if -2.0 * math.log(b) > t * t:
                    return (r + t) if u > 0.0 else -(r + t), state
        z = u * _ZIG_X[i]
        v, state = _uniform(state)
        if _ZIG_Y[i] + v * (_ZIG_Y[i + 1] - _ZIG_Y[i]) < math.exp(-0.5 * z * z):
            return z, state


@inline
def _log_poisson(mu: float, k: float) -> float:
    """``log p_k`` of a Poisson of mean ``mu`` (``k ≥ 0`` whole, a float: an integer's ``k⁵``
    overflows int64 above 6208, and wraps to 0 at multiples of 8192): ``lgamma`` below 10, above the
    cancellation-free Stirling form ``k·(log1p(v) − v) − δ(k) − ½·log(2πk)``, ``v = (mu − k)/k``,
    with ``δ`` to its ``k⁻⁵`` term (relative error below 1e-12 at ``k = 10``)."""
    if k < 10.0:
        return -mu + k * math.log(mu) - math.lgamma(k + 1.0)
    v = (mu - k) / k
    d = 1.0 / (12.0 * k)
    d = d - 4.8 * d * d * d + 1.0 / (1260.0 * k**5)
    return k * (math.log1p(v) - v) - d - 0.5 * math.log(2.0 * math.pi * k)


@inline
def _modified_normal(mu: float, s: float, k: float) -> tuple[float, float]:
    """Ahrens and Dieter's modified normal at ``k`` (their procedure F): its exponent ``fx`` and
    factor ``fy`` (``fy·exp(fx)`` approximates ``p_k``)."""
    b1 = 0.041666666666666664 / mu
    b2 = 0.3 * b1 * b1
    c3 = 0.14285714285714285 * b1 * b2
    c2 = b2 - 15.0 * c3
    c1 = b1 - 6.0 * b2 + 45.0 * c3
    c0 = 1.0 - b1 + 3.0 * b2 - 15.0 * c3
    x = (k - mu + 0.5) / s
    x2 = x * x
    return -0.5 * x2, 0.3989422804014327 / s * (((c3 * x2 + c2) * x2 + c1) * x2 + c0)


@inline
def _pd_step_i(mu: float, k: float) -> bool:
    """PD's immediate acceptance of the normal's ``k = ⌊mu + √mu z⌋`` (step I)."""
    return k >= np.floor(mu - 1.1484)


@inline
def _pd_step_s(mu: float, k: float, u: float) -> bool:
    """PD's squeeze (step S) with the uniform ``u``: ``6 mu² u ≥ (mu − k)³``."""
    dm = mu - k
    return 6.0 * mu * mu * u >= dm * dm * dm


@inline
def poisson(mu: float, state: np.uint64) -> tuple[float, np.uint64]:
    """An exact Poisson draw, and the advanced state: multiplication of uniforms below 10, above
    Ahrens and Dieter's algorithm PD (1982; a normal draw accepted outright or by a squeeze
    about 99 % of the time at large means, else their exponential hat), its acceptance tests on
    the exact ``p_k`` of [`_log_poisson`][]."""
    if mu <= 0.0:
        return 0.0, state
    if not mu < math.inf:  # NaN or inf (allow_nonfinite): passed through, no count to draw
        return mu, state
    if mu < 10.0:
        limit, k = math.exp(-mu), 0.0
        prod, state = _uniform(state)
        while prod > limit:
            u, state = _uniform(state)
            prod *= u
            k += 1.0
        return k, state
    s = math.sqrt(mu)
    z, state = normal(state)
    g = mu + s * z
    if g >= 0.0:
        k = np.floor(g)  # a float, as _log_poisson needs (numba's math.floor gives an integer)
        if _pd_step_i(mu, k):
            return k, state
        u, state = _uniform(state)
        if _pd_step_s(mu, k, u):
            return k, state
        fx, fy = _modified_normal(mu, s, k)
        if fy * (1.0 - u) <= math.exp(_log_poisson(mu, k) - fx):  # step Q
            return k, state
    while True:  # steps E and H
        u, state = _uniform(state)
        e = -math.log(u)
        u, state = _uniform(state)
        u = 2.0 * u - 1.0
        t = 1.8 + (e if u >= 0.0 else -e)
        if t <= -0.6744:
            continue
        k = np.floor(mu + s * t)
        fx, fy = _modified_normal(mu, s, k)
        if 0.1069 / mu * abs(u) <= math.exp(_log_poisson(mu, k) + e) - fy * math.exp(fx + e):
            return k, state


@inline
def first_tries(mu: float, shot: np.uint64, read: np.uint64) -> tuple[float, float, float, bool, bool, bool]:
    """What [`poisson`][] and [`normal`][] return when their first tries succeed, without a
    branch (so whole runs of pixels vectorise), for a mean ``mu ≥ 0``: the Poisson draw
    (steps N, I, S), the shot stream's normal draw scaled to ``mu + √mu·z``, the read stream's
    normal, and whether each is valid (the normals', the Poisson's given its normal's; never for
    an infinite mean, whose floor is no count; a normal's try tests a lower bound of its layer's
    ratio, [`_first_try_layer`][]); where one is not, the caller runs the full algorithms,
    which return exactly these values where they are."""
    u1, i1 = _strip(mix(shot + GOLDEN))
    x1, r1 = _first_try_layer(i1)
    g = mu + math.sqrt(mu) * (u1 * x1)
    k = np.floor(g)  # a float: no round trip through an integer
    u2, _ = _uniform(shot + GOLDEN)  # the draw after the normal's
    ok_k = (mu >= 10.0) & (mu < math.inf) & (g >= 0.0) & (_pd_step_i(mu, k) | _pd_step_s(mu, k, u2))
    u3, i3 = _strip(mix(read + GOLDEN))
    x3, r3 = _first_try_layer(i3)
    return k, g, u3 * x3, abs(u1) < r1, ok_k, abs(u3) < r3


@inline
def stream_origin(seed: int) -> np.uint64:
    """The state the noise streams of a call seeded by ``seed`` start from: element ``i``'s shot
    stream at ``origin + i·`` [`ELEMENT_G`][], its read stream [`STREAM_G`][] on."""
    return mix(np.uint64(seed) * GOLDEN + np.uint64(0x632BE59BD9B4E019))
