"""Write the synthetic, format-faithful samples of the data sets not bundled as such.

Usage: python data_samples/make_synthetic.py

Cityscapes and CelebA may not be redistributed; ``train cityscapes --quick`` and ``train celeba
--quick`` run on these instead: drawn scenes and faces (seeded, the same on every run) in the
real folder layouts, file names and encodings, not copies of either data set.

- ``cityscapes/``: 3 train (city ``aachen``) and 2 val (``frankfurt``) street scenes at
  2048x1024, ``leftImg8bit/SPLIT/CITY/CITY_SEQ_FRAME_leftImg8bit.png`` (RGB PNG) and
  ``gtFine/SPLIT/CITY/CITY_SEQ_FRAME_gtFine_labelIds.png`` (8-bit label ids of the official
  table: road, sidewalk, building, vegetation, sky, car, pole, traffic sign, person, and void:
  unlabeled, ego vehicle, static).
- ``celeba/``: 24 aligned 178x218 JPEG faces ``img_align_celeba/NNNNNN.jpg``,
  ``list_attr_celeba.txt`` (the count, the 40 attribute names, a ±1 row per image, spaced as the
  original) and ``list_eval_partition.txt`` (16 train, 4 val, 4 test); hair colour, baldness,
  eyeglasses, a smile, a moustache, a hat and the face's shade follow the drawn attributes.
"""

from __future__ import annotations

import sys
from pathlib import Path

import cv2
import numpy as np

HERE = Path(__file__).resolve().parent

#: CelebA's 40 attributes, in the order of ``list_attr_celeba.txt``.
CELEBA_ATTRIBUTES = (
    "5_o_Clock_Shadow Arched_Eyebrows Attractive Bags_Under_Eyes Bald Bangs Big_Lips Big_Nose Black_Hair "
    "Blond_Hair Blurry Brown_Hair Bushy_Eyebrows Chubby Double_Chin Eyeglasses Goatee Gray_Hair Heavy_Makeup "
    "High_Cheekbones Male Mouth_Slightly_Open Mustache Narrow_Eyes No_Beard Oval_Face Pale_Skin Pointy_Nose "
    "Receding_Hairline Rosy_Cheeks Sideburns Smiling Straight_Hair Wavy_Hair Wearing_Earrings Wearing_Hat "
    "Wearing_Lipstick Wearing_Necklace Wearing_Necktie Young"
).split()

# label id: RGB colour of its surfaces
_COLOURS = {
    0: (0, 0, 0),
    1: (40, 40, 40),
    4: (90, 80, 70),
    7: (110, 100, 110),
    8: (190, 170, 180),
    11: (120, 110, 100),
    17: (150, 150, 150),
    20: (220, 200, 40),
    21: (70, 120, 50),
    23: (120, 160, 210),
    24: (200, 60, 80),
    26: (40, 40, 120),
}


def street(rng: np.random.Generator, h: int = 1024, w: int = 2048) -> tuple[np.ndarray, np.ndarray]:
    """A drawn street scene: RGB ``(h, w, 3)`` uint8 and its label ids ``(h, w)`` uint8."""
    ids = np.full((h, w), 23, np.uint8)  # sky
    horizon = int(h * rng.uniform(0.38, 0.46))
    ids[horizon:] = 8  # sidewalk, the road drawn over it
    vx = int(w * rng.uniform(0.4, 0.6))
    road = np.array(
        [[vx - 20, horizon], [vx + 20, horizon], [int(w * 0.95), h], [int(w * 0.05), h]], np.int32
    )
    cv2.fillPoly(ids, [road], 7)
    x = 0
    while x < w:  # buildings and trees along the horizon, left and right of the road's end
        bw = int(rng.uniform(120, 320))
        top = int(horizon - rng.uniform(0.1, 0.35) * h)
        label = 11 if rng.random() < 0.7 else 21
        if abs(x + bw / 2 - vx) > 200:
            cv2.rectangle(ids, (x, top), (x + bw, horizon + 10), label, -1)
        x += bw + int(rng.uniform(0, 60))
    for _ in range(int(rng.integers(3, 7))):  # cars on the road, larger when nearer
        y = int(rng.uniform(horizon + 20, h - 160))
        size = (y - horizon) / (h - horizon)
        cw, ch = int(60 + 420 * size), int(30 + 200 * size)
        cx = int(vx + rng.uniform(-0.5, 0.5) * (w * 0.8) * size)
        cv2.rectangle(ids, (cx - cw // 2, y - ch), (cx + cw // 2, y), 26, -1)
    for _ in range(int(rng.integers(2, 5))):  # poles with signs, people on the sidewalks
        px = int(rng.choice([rng.uniform(0.02, 0.25), rng.uniform(0.75, 0.98)]) * w)
        cv2.rectangle(ids, (px, int(horizon - 0.25 * h)), (px + 12, int(horizon + 0.2 * h)), 17, -1)
        cv2.rectangle(ids, (px - 30, int(horizon - 0.25 * h)), (px + 40, int(horizon - 0.2 * h)), 20, -1)
        qx = px + int(rng.uniform(40, 120))
        cv2.ellipse(ids, (qx, int(horizon + 0.15 * h)), (18, 70), 0, 0, 360, 24, -1)
    cv2.rectangle(ids, (0, h - 90), (w, h), 1, -1)  # ego vehicle
    cv2.rectangle(ids, (0, horizon - 6), (40, horizon + 40), 4, -1)  # static
    ids[:4] = 0  # unlabeled border
    lut = np.array([_COLOURS.get(i, (0, 0, 0)) for i in range(256)], np.uint8)
    shade = np.linspace(1.08, 0.88, h)[:, None, None]  # light from above
    rgb = np.clip(lut[ids] * shade, 0, 255).astype(np.uint8)
    return rgb, ids


def face(rng: np.random.Generator, attrs: dict[str, int]) -> np.ndarray:
    """A drawn aligned face, RGB ``(218, 178, 3)`` uint8, following some of ``attrs`` (±1)."""
    img = np.full((218, 178, 3), rng.integers(150, 230, 3), np.uint8)
    skin = (
        (235, 205, 185)
        if attrs["Pale_Skin"] > 0
        else tuple(int(v) for v in rng.integers(120, 220, 3) * [1, 0.8, 0.7])
    )
    hair = {
        "Black_Hair": (30, 25, 20),
        "Blond_Hair": (230, 200, 120),
        "Brown_Hair": (110, 70, 40),
        "Gray_Hair": (170, 170, 170),
    }
    colour = next((c for k, c in hair.items() if attrs[k] > 0), (80, 60, 40))
    if attrs["Bald"] < 0:
        cv2.ellipse(img, (89, 100), (62, 78), 0, 180, 360, colour, -1)
    cv2.ellipse(img, (89, 118), (52, 66), 0, 0, 360, skin, -1)
    for ex in (68, 110):  # eyes, and glasses around them
        cv2.circle(img, (ex, 108), 5, (40, 30, 30), -1)
        if attrs["Eyeglasses"] > 0:
            cv2.circle(img, (ex, 108), 14, (20, 20, 20), 2)
    mouth = (89, 150)
    if attrs["Smiling"] > 0:
        cv2.ellipse(img, mouth, (20, 10), 0, 0, 180, (150, 40, 50), 3)
    else:
        cv2.line(img, (mouth[0] - 16, mouth[1]), (mouth[0] + 16, mouth[1]), (150, 40, 50), 3)
    if attrs["Mustache"] > 0:
        cv2.rectangle(img, (70, 138), (108, 143), colour, -1)
    if attrs["Wearing_Hat"] > 0:
        cv2.rectangle(img, (30, 20), (148, 52), (60, 60, 160), -1)
    return cv2.GaussianBlur(img, (3, 3), 0)


def make_cityscapes(root: Path) -> None:
    rng = np.random.default_rng(2016)
    for split, city, n in (("train", "aachen", 3), ("val", "frankfurt", 2)):
        for k in range(n):
            rgb, ids = street(rng)
            stem = f"{city}_{k:06d}_000019"
            img_dir, lab_dir = root / "leftImg8bit" / split / city, root / "gtFine" / split / city
            img_dir.mkdir(parents=True, exist_ok=True)
            lab_dir.mkdir(parents=True, exist_ok=True)
            cv2.imwrite(
                str(img_dir / f"{stem}_leftImg8bit.png"), rgb[..., ::-1], [cv2.IMWRITE_PNG_COMPRESSION, 9]
            )
            cv2.imwrite(str(lab_dir / f"{stem}_gtFine_labelIds.png"), ids, [cv2.IMWRITE_PNG_COMPRESSION, 9])


def make_celeba(root: Path, n: int = 24) -> None:
    rng = np.random.default_rng(2015)
    (root / "img_align_celeba").mkdir(parents=True, exist_ok=True)
    rows, parts = [], []
    for k in range(1, n + 1):
        attrs = {a: int(rng.choice([-1, 1], p=[0.7, 0.3])) for a in CELEBA_ATTRIBUTES}
        hair = rng.integers(0, 5)  # at most one hair colour
        for i, a in enumerate(("Black_Hair", "Blond_Hair", "Brown_Hair", "Gray_Hair")):
            attrs[a] = 1 if hair == i else -1
        name = f"{k:06d}.jpg"
        cv2.imwrite(
            str(root / "img_align_celeba" / name), face(rng, attrs)[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90]
        )
        rows.append(name + "".join(f" {v:2d}" for v in attrs.values()))
        parts.append(f"{name} {0 if k <= 16 else 1 if k <= 20 else 2}")
    header = [str(n), " ".join(CELEBA_ATTRIBUTES) + " "]
    (root / "list_attr_celeba.txt").write_text("\n".join(header + rows) + "\n")
    (root / "list_eval_partition.txt").write_text("\n".join(parts) + "\n")


if __name__ == "__main__":
    out = Path(sys.argv[1]) if len(sys.argv) > 1 else HERE
    make_cityscapes(out / "cityscapes")
    make_celeba(out / "celeba")
