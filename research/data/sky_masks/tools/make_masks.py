"""Semi-automatic held-out sky masks: grabcut seeded by the pseudo-labeller + manual fixes.
Usage: python make_masks.py OUTROOT set/stem ...  (writes OUTROOT/<set>/<stem>.png and a
review sheet)."""

import json
import os
import sys

import cv2
import numpy as np

sys.path.insert(0, str(__import__("pathlib").Path(__file__).resolve().parents[3]))
from rectified_colmap_research.training.sky import (
    sky_pseudo_label,
    SKY,
    NOT_SKY,
    above_line,
    gradient_energy,
    sky_colour,
    to_lab,
)

R = "/work/shared/data/real-pool"
HZ = json.load(open(f"{R}/eurasian-cities/gt/gt_horizon_zenith.json"))["images"]
FIX = json.load(open(os.path.join(os.path.dirname(__file__), "fixes.json")))


def image_path(key):
    st, stem = key.split("/")
    if st == "eurasian-cities":
        return f"{R}/eurasian-cities/images/{stem}.jpg"
    return f"/work/shared/data/strecha-dev/{st}/images/{stem}.jpg"


def make(key):
    rgb = cv2.imread(image_path(key))[..., ::-1].copy()
    H, W = rgb.shape[:2]
    st, stem = key.split("/")
    hz = HZ[f"{stem}.jpg"]["horizon_abc_out"] if st == "eurasian-cities" else None
    fx = FIX.get(key, {})
    # seeds: loose pseudo-labels (no bottom rule beyond the horizon, smaller margin)
    pl = sky_pseudo_label(rgb, hz, work_size=1024, margin=0.004, min_area=0.002, **fx.get("pl", {}))
    lab = to_lab(rgb)
    col = sky_colour(lab)
    gc = np.where(
        pl == SKY,
        cv2.GC_FGD,
        np.where(pl == NOT_SKY, cv2.GC_BGD, np.where(col, cv2.GC_PR_FGD, cv2.GC_PR_BGD)),
    ).astype(np.uint8)
    if hz is not None:
        gc[above_line(hz, (H, W)) < -2] = cv2.GC_BGD
    for poly in fx.get("bg", []):
        m = np.zeros((H, W), np.uint8)
        cv2.fillPoly(m, [np.array(poly, np.int32)], 1)
        gc[m > 0] = cv2.GC_BGD
    for poly in fx.get("fg", []):
        m = np.zeros((H, W), np.uint8)
        cv2.fillPoly(m, [np.array(poly, np.int32)], 1)
        gc[m > 0] = cv2.GC_FGD
    if (gc == cv2.GC_FGD).any() or (gc == cv2.GC_PR_FGD).any():
        bgd = np.zeros((1, 65), np.float64)
        fgd = np.zeros((1, 65), np.float64)
        cv2.grabCut(
            np.ascontiguousarray(rgb[..., ::-1]), gc, None, bgd, fgd, 5, cv2.GC_INIT_WITH_MASK
        )
    sky = (gc == cv2.GC_FGD) | (gc == cv2.GC_PR_FGD)
    if fx.get("prefix"):  # sky only as the top run of each column (thin gaps bridged)
        br = cv2.morphologyEx(sky.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((9, 1), np.uint8)) > 0
        sky &= np.logical_and.accumulate(br, axis=0)
    # clean: sky must connect to the top (or to a definite seed), no specks
    n, comp, stats, _ = cv2.connectedComponentsWithStats(sky.astype(np.uint8), connectivity=4)
    keep = stats[:, cv2.CC_STAT_AREA] >= fx.get("min_piece", 0.0005) * H * W
    keep[0] = False
    seeded = np.zeros(n, bool)
    seeded[np.unique(comp[pl == SKY])] = True
    keep &= seeded  # only pieces that hold confident (pseudo-label) sky
    sky = keep[comp]
    # fill tiny non-sky holes (noise) in the sky
    n, comp, stats, _ = cv2.connectedComponentsWithStats((~sky).astype(np.uint8), connectivity=4)
    small = stats[:, cv2.CC_STAT_AREA] < 30
    small[0] = False
    sky |= small[comp]
    out = np.where(sky, 1, 0).astype(np.uint8)
    # ignore: a 3 px band on both sides of the boundary
    k = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (7, 7))
    band = (cv2.dilate(sky.astype(np.uint8), k) > 0) & ~(cv2.erode(sky.astype(np.uint8), k) > 0)
    # ignore: mixed textured areas (trees / wires against the sky)
    e = gradient_energy(cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY), 5)
    frac = cv2.blur(sky.astype(np.float32), (15, 15))
    mixed = (frac > 0.03) & (frac < 0.97) & (e > 6)
    mixed = cv2.dilate(mixed.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    # ignore: thin dark structures (wires, poles' arms) inside the sky
    g = cv2.cvtColor(rgb, cv2.COLOR_RGB2GRAY)
    bh = cv2.morphologyEx(g, cv2.MORPH_BLACKHAT, np.ones((9, 9), np.uint8))
    wires = (bh > 10) & (cv2.dilate(sky.astype(np.uint8), k) > 0)
    wires = cv2.dilate(wires.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    out[band | mixed | wires] = 255
    for poly in fx.get("ignore", []):
        m = np.zeros((H, W), np.uint8)
        cv2.fillPoly(m, [np.array(poly, np.int32)], 1)
        out[m > 0] = 255
    return rgb, out


def overlay(rgb, m, size=640):
    o = rgb.astype(np.float32).copy()
    o[m == 1] = 0.5 * o[m == 1] + 0.5 * np.array([0, 255, 0])
    o[m == 255] = 0.3 * o[m == 255] + 0.7 * np.array([255, 0, 255])
    o = o.astype(np.uint8)
    s = size / max(o.shape[:2])
    return cv2.resize(
        o, (round(o.shape[1] * s), round(o.shape[0] * s)), interpolation=cv2.INTER_AREA
    )


if __name__ == "__main__":
    outroot, keys = sys.argv[1], sys.argv[2:]
    tiles = []
    for key in keys:
        rgb, m = make(key)
        p = os.path.join(outroot, key + ".png")
        os.makedirs(os.path.dirname(p), exist_ok=True)
        cv2.imwrite(p, m)
        t = overlay(rgb, m)
        c = np.full((640, 640, 3), 40, np.uint8)
        c[: t.shape[0], : t.shape[1]] = t
        cv2.putText(c, key, (4, 630), 0, 0.6, (255, 255, 0), 2)
        tiles.append(c)
    while len(tiles) % 2:
        tiles.append(np.zeros_like(tiles[0]))
    rows = [np.concatenate(tiles[i : i + 2], 1) for i in range(0, len(tiles), 2)]
    cv2.imwrite(
        os.path.join(outroot, "review_" + keys[0].replace("/", "_") + ".png"),
        np.concatenate(rows, 0)[..., ::-1],
    )
