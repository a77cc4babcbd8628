#!/usr/bin/env python3
"""OpenCV's StereoBM on the pairs `harmonic-sim bench-stereo --out DIR` wrote, with the same
metrics as the bench (Middlebury bad-1.0 / bad-2.0 on non-occluded pixels with a disparity,
density), so the core's matcher can be compared on identical inputs.

    harmonic-sim bench-stereo --out out/bench-stereo
    python3 scripts/stereo_opencv.py out/bench-stereo

Each DIR/SCENARIO-K/ holds left.png, right.png, gt.pfm (pixels, inf = no surface), mask.png
(255 = visible in both views) and calib.txt (ndisp). StereoBM runs with the bench's defaults:
64 disparities, a 13 x 13 window (the footprint of the core's five 7 x 7 windows), its XSOBEL
prefilter, uniqueness 10 %, left-right check (disp12MaxDiff 1), speckle removal. Needs
opencv-python-headless (pip) and numpy.
"""
import argparse
import pathlib
import sys
import time

import cv2
import numpy as np


def read_pfm(path):
    with open(path, "rb") as f:
        magic = f.readline().strip()
        if magic != b"Pf":
            raise ValueError(f"{path}: not a single-channel PFM")
        w, h = map(int, f.readline().split())
        scale = float(f.readline())
        data = np.fromfile(f, dtype="<f4" if scale < 0 else ">f4", count=w * h)
    return np.flipud(data.reshape(h, w))


def evaluate(estimate, truth, mask):
    sel = np.isfinite(truth) & (mask == 255)
    evaluated = int(sel.sum())
    valid = sel & np.isfinite(estimate)
    err = np.abs(estimate[valid] - truth[valid])
    n = max(int(valid.sum()), 1)
    return {
        "bad1": 100.0 * (err > 1.0).sum() / n,
        "bad2": 100.0 * (err > 2.0).sum() / n,
        "density": 100.0 * valid.sum() / max(evaluated, 1),
        "bad2_holes": 100.0 * ((err > 2.0).sum() + evaluated - valid.sum()) / max(evaluated, 1),
        "mae": float(err.mean()) if err.size else 0.0,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("dir", type=pathlib.Path)
    ap.add_argument("--ndisp", type=int, default=64)
    ap.add_argument("--block", type=int, default=13)
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    pairs = sorted(p for p in args.dir.iterdir() if (p / "left.png").is_file())
    if not pairs:
        sys.exit(f"no pairs in {args.dir} (run harmonic-sim bench-stereo --out {args.dir})")
    cv2.setNumThreads(1)
    bm = cv2.StereoBM_create(numDisparities=args.ndisp, blockSize=args.block)
    bm.setUniquenessRatio(10)
    bm.setDisp12MaxDiff(1)
    bm.setSpeckleWindowSize(156)
    bm.setSpeckleRange(16)
    print(f"OpenCV {cv2.__version__} StereoBM, {args.ndisp} disparities, block {args.block}, 1 thread")
    print("| scenario | pairs | bad-1.0 % | bad-2.0 % | density % | bad-2.0 with holes % | mean error px | ms per pair | ns per pixel-disparity |")
    print("|---|---|---|---|---|---|---|---|---|")
    groups = {}
    for p in pairs:
        left = cv2.imread(str(p / "left.png"), cv2.IMREAD_GRAYSCALE)
        right = cv2.imread(str(p / "right.png"), cv2.IMREAD_GRAYSCALE)
        truth = read_pfm(p / "gt.pfm")
        mask = cv2.imread(str(p / "mask.png"), cv2.IMREAD_GRAYSCALE)
        best = float("inf")
        for _ in range(max(args.repeat, 1)):
            t0 = time.perf_counter()
            raw = bm.compute(left, right)
            best = min(best, time.perf_counter() - t0)
        disp = raw.astype(np.float32) / 16.0
        disp[raw < 0] = np.inf
        m = evaluate(disp, truth, mask)
        m["ms"] = best * 1e3
        m["ns"] = best * 1e9 / (left.size * args.ndisp)
        groups.setdefault(p.name.rsplit("-", 1)[0], []).append(m)
    rows = [(name, ms) for name, ms in groups.items()] + [("**all**", [m for ms in groups.values() for m in ms])]
    for name, ms in rows:
        mean = {k: sum(m[k] for m in ms) / len(ms) for k in ms[0]}
        print(
            f"| {name} | {len(ms)} | {mean['bad1']:.2f} | {mean['bad2']:.2f} | {mean['density']:.1f} | "
            f"{mean['bad2_holes']:.2f} | {mean['mae']:.3f} | {mean['ms']:.2f} | {mean['ns']:.2f} |"
        )


if __name__ == "__main__":
    main()
