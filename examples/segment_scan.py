#!/usr/bin/env python3
"""Segments one LiDAR scan with the Python module: segment_scan.py WEIGHTS SCAN OUT [DEVICE]
prints how many cells each class got and writes the label map (class ids, height x width) as
OUT.png, a palette PNG whose pixel values are the ids, where Pillow is installed, else OUT.npy.
SCAN: any file read_points reads (.bin, .pcd, .ply, .npy, .pcd.bin). DEVICE: cpu (default),
cuda or emu."""
import colorsys
import sys

import numpy as np

import pillarseg


def main(weights, scan, out, device="cpu"):
    points = pillarseg.read_points(scan)
    with pillarseg.Segmenter(weights, device=device) as segmenter:
        labels = segmenter.segment(points)
        print(f"{scan}: {len(points)} points -> {labels.shape[0]} x {labels.shape[1]} cells on "
              f"{segmenter.device_name}")
    counts = np.bincount(labels.ravel(), minlength=pillarseg.NUM_CLASSES + 1)
    for class_id in np.argsort(-counts, kind="stable"):
        if counts[class_id] > 0:
            print(f"{pillarseg.class_names[class_id]:>12} {counts[class_id]:6d} cells")
    try:
        from PIL import Image
    except ImportError:
        np.save(f"{out}.npy", labels)
        print(f"wrote {out}.npy (Pillow is not installed: no PNG)")
        return
    image = Image.fromarray(labels, mode="P")
    # Unlabeled black, the 12 classes at evenly spaced hues.
    colours = [(0.0, 0.0, 0.0)] + [colorsys.hsv_to_rgb(k / 12, 0.8, 0.95) for k in range(12)]
    image.putpalette([round(255 * c) for rgb in colours for c in rgb])
    image.save(f"{out}.png")
    print(f"wrote {out}.png")


if __name__ == "__main__":
    if len(sys.argv) not in (4, 5):
        sys.exit(__doc__)
    try:
        main(*sys.argv[1:])
    except pillarseg.Error as e:
        sys.exit(str(e))
