"""Simulate both paper layouts on a bundled photo, back-warp, and export the maps.

Run from the repository root:  python examples/quickstart.py
"""

from pathlib import Path

import cv2
import numpy as np
import torch

import layoutwarp as lw

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "results" / "examples"
OUT.mkdir(parents=True, exist_ok=True)

rgb = cv2.cvtColor(cv2.imread(str(ROOT / "data_samples" / "photos" / "kodim03.png")), cv2.COLOR_BGR2RGB)
image = torch.from_numpy(rgb).permute(2, 0, 1)[None]  # (1, 3, 500, 500) uint8 -> scaled to [0, 1]
size = (48, 64)  # sensor (H, W)

for layout in (lw.RectLayout((0.5, 0.3)), lw.CurvLayout((0.5, 0.3))):
    with torch.no_grad():
        sensor, plan = lw.simulate(image, layout, size, return_plan=True)  # exact box integration
        back = lw.backwarp(sensor, layout, rgb.shape[:2])  # nearest, on the photo's grid
    print(f"{layout.family}: {plan.method} ({plan.reason}); sensor {tuple(sensor.shape)}")
    for name, t in (("sensor", sensor), ("backwarped", back)):
        arr = (t[0].permute(1, 2, 0).numpy() * 255).round().astype(np.uint8)
        cv2.imwrite(str(OUT / f"{layout.family}_{name}.png"), cv2.cvtColor(arr, cv2.COLOR_RGB2BGR))
    # the same sampling positions as OpenCV maps (deformed pixel centres)
    map_x, map_y = lw.forward_maps(layout, size, rgb.shape[:2]).numpy()
    point = cv2.remap(rgb, map_x, map_y, cv2.INTER_LINEAR)
    cv2.imwrite(str(OUT / f"{layout.family}_point_sampled.png"), cv2.cvtColor(point, cv2.COLOR_RGB2BGR))
print(f"wrote {OUT}")
