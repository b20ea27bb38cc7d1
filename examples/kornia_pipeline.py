"""A learnable sensor inside a Kornia augmentation pipeline, with masks and the inverse.

Run from the repository root:  python examples/kornia_pipeline.py
"""

from pathlib import Path

import cv2
import kornia.augmentation as K
import torch

import layoutwarp as lw

ROOT = Path(__file__).resolve().parents[1]
name = sorted((ROOT / "data_samples" / "camvid" / "train").iterdir())[0].name
rgb = cv2.cvtColor(cv2.imread(str(ROOT / "data_samples" / "camvid" / "train" / name)), cv2.COLOR_BGR2RGB)
labels = cv2.imread(str(ROOT / "data_samples" / "camvid" / "trainannot" / name), cv2.IMREAD_GRAYSCALE)
image = torch.from_numpy(rgb).permute(2, 0, 1)[None].float() / 255
mask = torch.from_numpy(labels)[None, None].float()

sensor = lw.SensorAugmentation((90, 120), "rect", mask_rule="majority")
flip, jitter = K.RandomHorizontalFlip(p=0.5), K.ColorJitter(0.1, 0.1, 0.1, 0.0, p=1.0)
pipeline = K.AugmentationSequential(flip, jitter, sensor, data_keys=["input", "mask"])
low, low_mask = pipeline(image, mask)  # (1, 3, 90, 120), (1, 1, 90, 120)
loss = (low.mean() - 0.5) ** 2  # any loss: θ is a parameter of the pipeline
loss.backward()
print("sensor image", tuple(low.shape), "mask", tuple(low_mask.shape), "dθ", sensor.layout.rho.grad.tolist())
full, full_mask = pipeline.inverse(low, low_mask, data_keys=["input", "mask"])
print("back on the 480x360 grid:", tuple(full.shape), tuple(full_mask.shape))
