"""The prefix tables of Green's theorem for the exact integrator's kernels: each image row's
running sums, in blocks of [`BLOCK`][] columns with float64 offsets between blocks, built in
bands of rows (a whole image at once, [`prefix_tables`][], or a band at a time,
[`band_prefix`][]), or an item at a time on a device."""

from __future__ import annotations

import numpy as np

from .base import inline, run_shares, serial, threads

__all__ = ["BLOCK", "band_prefix", "prefix_block_item", "prefix_offsets_item", "prefix_tables"]

#: Columns per block of the prefix tables (see [`prefix_tables`][]).
BLOCK = 16


@inline
def _block_prefix(image: np.ndarray, r: int, rr: int, b: int, k: int, block: int, incl: np.ndarray) -> None:
    """Inclusive sums of block ``b`` of row ``r``, channel ``k``, into ``incl[rr, :, k]``."""
    w = image.shape[2]
    acc = image[k, r, b * block] * 0  # zero in the image's dtype
    for c in range(b * block, min(w, (b + 1) * block)):
        acc += image[k, r, c]
        incl[rr, c, k] = acc


@inline
def _row_offsets(rr: int, k: int, block: int, incl: np.ndarray, offsets: np.ndarray) -> None:
    """The float64 sums of the whole blocks before each block of ``incl[rr, :, k]``."""
    w = incl.shape[1]
    total = 0.0
    for b in range(offsets.shape[1]):
        offsets[rr, b, k] = total
        total += incl[rr, min(w, (b + 1) * block) - 1, k]


@inline
def prefix_block_item(image: np.ndarray, i: int, block: int, incl: np.ndarray) -> None:
    """Item ``i`` (row × block × channel) of the prefix table's blocks, [`_block_prefix`][], for
    one device thread (an ``i`` past the last does nothing)."""
    n, h, w = image.shape
    nb = (w + block - 1) // block
    if i < h * nb * n:
        r = i // (nb * n)
        _block_prefix(image, r, r, (i // n) % nb, i % n, block, incl)


@inline
def prefix_offsets_item(i: int, block: int, incl: np.ndarray, offsets: np.ndarray) -> None:
    """Item ``i`` (row × channel) of the prefix table's block offsets, [`_row_offsets`][], for one
    device thread (an ``i`` past the last does nothing)."""
    h, _, n = incl.shape
    if i < h * n:
        _row_offsets(i // n, i % n, block, incl, offsets)


@inline
def band_prefix(
    image: np.ndarray, ra: int, rb: int, block: int, incl: np.ndarray, offsets: np.ndarray
) -> None:
    """The prefix tables (see [`prefix_tables`][]) of rows ``ra .. rb − 1`` into ``incl``/
    ``offsets`` (row ``ra`` at index 0); [`_block_prefix`][] and [`_row_offsets`][] are
    the one home of their arithmetic."""
    n, _, w = image.shape
    nb = (w + block - 1) // block
    for rr in range(rb - ra):
        for k in range(n):
            for b in range(nb):
                _block_prefix(image, ra + rr, rr, b, k, block, incl)
            _row_offsets(rr, k, block, incl, offsets)


@serial
def _prefix_share(
    t: int, nt: int, image: np.ndarray, block: int, incl: np.ndarray, offsets: np.ndarray
) -> None:
    h = image.shape[1]
    r0, r1 = t * h // nt, (t + 1) * h // nt
    band_prefix(image, r0, r1, block, incl[r0:r1], offsets[r0:r1])


def prefix_tables(image: np.ndarray, block: int, nt: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Row prefix sums of ``image (N, H, W)``, safe in float32, channels last.

    Returns ``(incl, offsets)``: ``incl[r, c, n]`` is the inclusive prefix sum of row ``r`` of
    channel ``n`` within the ``block``-column block of ``c`` (in the image's dtype) and
    ``offsets[r, k, n]`` the float64 sum of the whole blocks before block ``k``, so a prefix
    never carries more than one block's rounding. Channels last puts everything one piece
    reads in one or two cache lines. ``nt``: threads (default [`threads`][layoutwarp.kernels.base.threads]
    of the image's size), each a band of rows.
    """
    n, h, w = image.shape
    nb = (w + block - 1) // block
    incl = np.empty((h, w, n), dtype=image.dtype)
    offsets = np.empty((h, nb, n), dtype=np.float64)
    run_shares(_prefix_share, min(h, threads(image.size) if nt is None else nt), image, block, incl, offsets)
    return incl, offsets
