"""layoutwarp's torch operators (``torch.ops.layoutwarp.*``), one module an operator and its
backward: its schema, fake kernel, autograd formula, ``vmap`` rule and the choice of
implementation. [`base`][layoutwarp.operators.base] holds what they share (how a layout and a
camera travel into one, which backend runs it, seeds, the refusal of second derivatives);
importing this package registers [`exact`][layoutwarp.operators.exact],
[`separable`][layoutwarp.operators.separable], [`flux`][layoutwarp.operators.flux],
[`areas`][layoutwarp.operators.areas] and [`draws`][layoutwarp.operators.draws]. The fixed
layout's product (``area``), the measurement (``measure``, ``draws``) and the maps
(``map_points``, ``raster_index_map``) are registered by [`layoutwarp.resampler`][],
[`layoutwarp.physics`][] and [`layoutwarp.maps`][]."""

from __future__ import annotations

from . import areas, base, draws, exact, flux, separable
from .base import OPERATORS, SECOND_ORDER, TRANSFORMS, backend, layout_of, layout_token

__all__ = [
    "OPERATORS",
    "SECOND_ORDER",
    "TRANSFORMS",
    "areas",
    "backend",
    "base",
    "draws",
    "exact",
    "flux",
    "layout_of",
    "layout_token",
    "separable",
]
