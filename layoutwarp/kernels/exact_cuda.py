"""The exact integrator's CUDA kernels: the per-segment arithmetic of
[`layoutwarp.kernels.exact`][], one GPU thread per segment (or prefix-table row × block ×
channel, or pixel edge), by the names [`layoutwarp.kernels.device.cuda_launch`][] takes
([`CUDA_SOURCES`][])."""

from __future__ import annotations

import numpy as np

from .exact import edge_sum, segment_forward, segment_weights
from .prefix import prefix_block_item, prefix_offsets_item

__all__ = ["CUDA_SOURCES", "cuda_signature"]

cuda = None  # numba.cuda, bound by the first launch ([`layoutwarp.kernels.device.cuda_launch`][])


def _cuda_prefix_blocks(image: np.ndarray, block: int, incl: np.ndarray) -> None:
    """One thread per (row, block, channel):
    [`prefix_block_item`][layoutwarp.kernels.prefix.prefix_block_item]."""
    prefix_block_item(image, cuda.grid(1), block, incl)


def _cuda_prefix_offsets(block: int, incl: np.ndarray, offsets: np.ndarray) -> None:
    """One thread per (row, channel):
    [`prefix_offsets_item`][layoutwarp.kernels.prefix.prefix_offsets_item]."""
    prefix_offsets_item(cuda.grid(1), block, incl, offsets)


def _cuda_forward(
    verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, incl: np.ndarray, offsets: np.ndarray,
    block: int, per_seg: np.ndarray,
) -> None:  # fmt: skip
    """One thread per segment: [`segment_forward`][layoutwarp.kernels.exact.segment_forward] (its
    row of ``per_seg`` zeroed first: no zeroed buffer to launch for)."""
    s = cuda.grid(1)
    if s < seg_start.shape[0]:
        for k in range(per_seg.shape[1]):
            per_seg[s, k] = 0.0
        segment_forward(s, verts, seg_start, seg_end, incl, offsets, block, per_seg)


def _cuda_edge_sums(per_seg: np.ndarray, edge_offsets: np.ndarray, out: np.ndarray) -> None:
    """One thread per pixel edge: [`edge_sum`][layoutwarp.kernels.exact.edge_sum] (its column of
    ``out`` zeroed first)."""
    e = cuda.grid(1)
    if e < edge_offsets.shape[0] - 1:
        for k in range(out.shape[0]):
            out[k, e] = 0.0
        edge_sum(e, per_seg, edge_offsets, out)


def _cuda_backward(
    verts: np.ndarray, seg_start: np.ndarray, seg_end: np.ndarray, seg_edge: np.ndarray, incl: np.ndarray,
    block: int, grad: np.ndarray, wa: np.ndarray, wb: np.ndarray,
) -> None:  # fmt: skip
    """One thread per segment: [`segment_weights`][layoutwarp.kernels.exact.segment_weights]."""
    s = cuda.grid(1)
    if s < seg_start.shape[0]:
        wa[s], wb[s] = segment_weights(s, verts, seg_start, seg_end, seg_edge, incl, block, grad)


#: The CUDA kernels' sources by the names [`layoutwarp.kernels.device.cuda_launch`][] takes.
CUDA_SOURCES = {
    "prefix_blocks": _cuda_prefix_blocks,
    "prefix_offsets": _cuda_prefix_offsets,
    "forward": _cuda_forward,
    "edge_sums": _cuda_edge_sums,
    "backward": _cuda_backward,
}


def cuda_signature(name: str, dtype: str) -> str:
    """CUDA kernel ``name``'s argument types (numba's notation) for images of ``dtype``,
    C-contiguous arrays, as [`layoutwarp.kernels.device.cuda_launch`][] passes them."""
    img, idx, f64 = f"{dtype}[:, :, ::1]", "int64[::1]", "float64[::1]"
    f64_2, f64_3 = "float64[:, ::1]", "float64[:, :, ::1]"
    args = {
        "prefix_blocks": [img, "int64", img],
        "prefix_offsets": ["int64", img, f64_3],
        "forward": [f64_2, idx, idx, img, f64_3, "int64", f64_2],
        "edge_sums": [f64_2, idx, f64_2],
        "backward": [f64_2, idx, idx, idx, img, "int64", f64_2, f64, f64],
    }[name]
    return f"void({', '.join(args)})"
