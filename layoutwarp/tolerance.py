"""The curved-edge tolerance a dtype's data needs: the policy every integrator's and the
sensor's default ``tol`` follows."""

from __future__ import annotations

import numpy as np
import torch

__all__ = ["data_tolerance"]


def data_tolerance(dtype: torch.dtype | np.dtype | type) -> tuple[float, str]:
    """The curved-edge tolerance the data needs, relative to the image's value range, and why.

    Integer images: a quarter of one quantisation step of the dtype's range (``0.25/255``
    for uint8, ``0.25/65535`` for uint16), so an exact integral rounds to the right level.
    float16/bfloat16: a quarter of their precision at 1.0 (``2⁻¹²``, ``2⁻⁹``). Other floats:
    ``2⁻¹²`` (a quarter of a 10-bit step, for the 8–10-bit data most float images hold; pass
    ``tol`` for finer).

    Examples:
        >>> data_tolerance(torch.uint8)[0] == 0.25 / 255
        True
    """
    if isinstance(dtype, torch.dtype):
        if dtype in (torch.float16, torch.bfloat16):
            eps = torch.finfo(dtype).eps
            return eps / 4, f"{dtype}: a quarter of its precision at 1.0"
        if not (dtype.is_floating_point or dtype.is_complex or dtype == torch.bool):
            top = torch.iinfo(dtype).max  # no tensor made: a compiled graph reads it as a constant
            name = str(dtype).removeprefix("torch.")
            return 0.25 / top, f"{name} input: a quarter of one step (1/{top} of the range)"
    else:
        dtype = np.dtype(dtype)
        if np.issubdtype(dtype, np.integer):
            step = 1 / np.iinfo(dtype).max
            return 0.25 * step, f"{dtype} input: a quarter of one step (1/{np.iinfo(dtype).max} of the range)"
        if dtype == np.float16:
            return float(np.finfo(dtype).eps) / 4, f"{dtype}: a quarter of its precision at 1.0"
    return 2.0**-12, "float input: a quarter of a 10-bit step (2^-12) of the value range"
