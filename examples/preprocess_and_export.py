"""Preprocess the bundled CamVid slice with a fixed layout and export that layout as masks.

Run from the repository root: ``python examples/preprocess_and_export.py [OUT_DIR]``. Without
OUT_DIR it works in a temporary folder and removes it at the end (file names are printed relative
to the output folder).
"""

from __future__ import annotations

import argparse
import tempfile
from pathlib import Path

import cv2

import layoutwarp as lw

ROOT = Path(__file__).resolve().parents[1]


def main(out: Path) -> None:
    layout, size = lw.CurvLayout((0.5, 0.3)), (72, 96)  # sensor 96x72 over 480x360 street scenes
    lw.save_layout(layout, out / "layout.json", size)

    camvid = ROOT / "data_samples" / "camvid"  # the bundled samples (a fresh clone has them)
    res = lw.preprocess_folder(
        camvid / "val", out / "sensor", layout, size, labels=camvid / "valannot", label_rule="majority"
    )
    print(f"preprocessed {res.processed} images ({res.images_per_second:.1f}/s), failures: {res.failed}")
    first = sorted((out / "sensor").glob("*.png"))[0]
    print(f"{first.name}: {cv2.imread(str(first)).shape[1::-1]} sensor image, labels in sensor/labels/")

    # back-warp a sensor-grid label map to full size with the OpenCV path
    labels = cv2.imread(str(out / "sensor" / "labels" / first.name), cv2.IMREAD_UNCHANGED)
    full = lw.backwarp_numpy(labels, layout, (360, 480))
    print(f"back-warped labels: {full.shape}, classes {sorted(set(full.ravel().tolist()))}")

    for fmt in ("gds", "svg", "png"):
        # the sensor is 4.8 x 3.6 mm: (H, W) in µm
        report = lw.export_layout(layout, size, out / f"mask.{fmt}", (3600, 4800), min_feature_um=30)
        print(report.summary().replace(str(out) + "/", ""))


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("out", nargs="?", type=Path, metavar="OUT_DIR", help="keep the files here")
    args = parser.parse_args()
    if args.out is not None:
        main(args.out)
    else:
        with tempfile.TemporaryDirectory() as tmp:
            print("writing to a temporary folder, removed at the end (pass OUT_DIR to keep the files)")
            main(Path(tmp))
