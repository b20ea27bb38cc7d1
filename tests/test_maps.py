"""Dense remap maps: OpenCV and Kornia agree, forward maps look at the deformed centres,
inverse ∘ forward = identity."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import torch
from conftest import rand_theta
from kornia.geometry.transform import remap as kornia_remap

import layoutwarp as lw
from layoutwarp.coords import sensor_to_pixels

F64 = torch.float64
# sizes that break the reference code's arange(-1, 1, 2/n) (n + 1 cells), odd and even, 1xN
SIZES = [(1, 1), (1, 9), (9, 1), (49, 98), (98, 49), (7, 196), (196, 3), (4, 4), (5, 3)]


def smooth_image(gen, h, w, c=3):
    img = torch.rand(1, c, h // 4 + 2, w // 4 + 2, generator=gen)
    return torch.nn.functional.interpolate(img, size=(h, w), mode="bicubic", align_corners=False)[0]


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_cv2_and_kornia_remap_agree_with_forward_maps(family, gen):
    layout = lw.make_layout(family, None if family == "uniform" else rand_theta(gen, 0.8))
    src = smooth_image(gen, 60, 80)
    maps = lw.forward_maps(layout, (12, 20), (60, 80), samples=3)
    assert maps.map_x.shape == (36, 60) and maps.map_x.dtype == torch.float32
    mx, my = maps.numpy()
    np_src = src.permute(1, 2, 0).contiguous().numpy()
    for interp, mode in ((cv2.INTER_LINEAR, "bilinear"), (cv2.INTER_NEAREST, "nearest")):
        ref = cv2.remap(np_src, mx, my, interp, borderMode=cv2.BORDER_REPLICATE)
        got = (
            kornia_remap(
                src[None],
                maps.map_x[None],
                maps.map_y[None],
                mode=mode,
                padding_mode="border",
                align_corners=True,
            )[0]
            .permute(1, 2, 0)
            .numpy()
        )
        if mode == "bilinear":
            # cv2.remap quantises sample positions to 1/32 pixel: allow that, not more
            grad = np.abs(np.diff(np_src, axis=0)).max() + np.abs(np.diff(np_src, axis=1)).max()
            assert np.abs(ref - got).max() <= grad / 32 + 1e-6
        else:
            frac = np.abs(np.stack([mx, my]) % 1 - 0.5)
            safe = (frac > 1e-3).all(0)
            assert np.array_equal(ref[safe], got[safe])


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_forward_maps_look_at_the_deformed_centres(family, gen):
    layout = lw.make_layout(family, None if family == "uniform" else rand_theta(gen, 0.9), dtype=F64)
    maps = lw.forward_maps(layout, (7, 11), (50, 70))
    expected = sensor_to_pixels(layout(lw.coords.pixel_centers((7, 11))), (50, 70)) - 0.5
    assert torch.allclose(maps.map_x.double(), expected[..., 0], atol=1e-4)
    assert torch.allclose(maps.map_y.double(), expected[..., 1], atol=1e-4)


@pytest.mark.parametrize("family", ["uniform", "rect", "curv"])
def test_inverse_map_composed_with_forward_map_is_identity(family, seed):
    layout = lw.make_layout(
        family,
        None if family == "uniform" else rand_theta(torch.Generator().manual_seed(seed), 0.9),
        dtype=F64,
    )
    size, src = (10, 14), (40, 56)
    # inverse ∘ forward: jittered sensor samples -> float32 source coordinates -> back
    fwd = lw.forward_maps(
        layout, size, src, samples=2, jitter=True, generator=torch.Generator().manual_seed(seed)
    )
    u = lw.maps.sample_points(size, 2, jitter=True, generator=torch.Generator().manual_seed(seed))
    q = lw.coords.pixels_to_sensor(torch.stack([fwd.map_x.double(), fwd.map_y.double()], -1) + 0.5, src)
    back = sensor_to_pixels(layout.inverse(q), size)
    assert float((back - sensor_to_pixels(u, size)).abs().max()) < 1e-4
    # forward ∘ inverse: every target pixel centre -> float32 sensor coordinate -> back
    inv = lw.inverse_maps(layout, size, src)
    assert inv.map_x.shape == src and inv.map_x.dtype == torch.float32
    p = lw.coords.pixels_to_sensor(torch.stack([inv.map_x.double(), inv.map_y.double()], -1) + 0.5, size)
    again = sensor_to_pixels(layout(p), src) - 0.5
    grid = torch.stack(
        torch.meshgrid(torch.arange(src[1], dtype=F64), torch.arange(src[0], dtype=F64), indexing="xy"), -1
    )
    assert float((again - grid).abs().max()) < 1e-4
