#!/usr/bin/python3
"""Statistics of LiDAR scans (KITTI .bin, optional SemanticKITTI .label), to compare simulated
scans with real HDL-64E ones (docs/simulator.md).

Per scan: points, rings (a ring ends where the azimuth wraps, as KITTI's and the simulator's
files are beam by beam), returns per ring, the share of returns by elevation, range
percentiles, the ground's height (per-2 m-cell lowest point within 20 m of the sensor) and
roughness (spread of the lowest points of 0.5 m cells within a 2 m cell), the plane of the
ground 3-15 m around the sensor (its pitch and roll in the sensor's frame), and reflectance
percentiles. With labels: per class (DESIGN.md's table) the point count, z, reflectance and
range percentiles, how much the reflectance of road, sidewalk, terrain and vegetation overlap,
the reflectance by range band (share of zeros, median of the others) of six classes, and the
ground cells: per 0.4 m cell of road, sidewalk or terrain within 20 m its height against
the road's and its mean reflectance, the share of sidewalk cells 5 m or more from a road cell,
and which of the three lies beside which (the street's cross-section); with several
labelled scans, the ground cells of all of them pooled as well.

Usage: scripts/scan_stats.py SCAN.bin [--labels SCAN.label] [SCAN.bin [--labels ...]] ...
       scripts/scan_stats.py --sequence ROOT/sequences/SS [--scans N]   (each scan with labels)
Needs python3-numpy.
"""
import argparse
import os
import sys

try:
    import numpy as np
except ImportError:
    sys.exit("scan_stats.py needs numpy (Debian: apt-get install python3-numpy)")

CLASSES = ["unlabeled", "vehicle", "person", "two-wheel", "rider", "road", "sidewalk",
           "other-ground", "building", "object", "vegetation", "trunk", "terrain"]
RAW_TO_CLASS = {}
for cls, ids in {1: [10, 13, 16, 18, 20, 252, 256, 257, 258, 259], 2: [30, 254], 3: [11, 15],
                 4: [31, 32, 253, 255], 5: [40, 60], 6: [48], 7: [44, 49], 8: [50],
                 9: [51, 80, 81], 10: [70], 11: [71], 12: [72]}.items():
    for raw in ids:
        RAW_TO_CLASS[raw] = cls


def load_points(path):
    size = os.path.getsize(path)
    if size % 16:
        sys.exit(f"{path}: size {size} is not a multiple of 16 (x y z r float32 records)")
    pts = np.fromfile(path, dtype="<f4").reshape(-1, 4)
    finite = np.isfinite(pts).all(axis=1)
    return pts[finite]


def load_classes(path, count):
    raw = np.fromfile(path, dtype="<u4")
    if raw.size != count:
        sys.exit(f"{path}: {raw.size} labels for {count} points")
    lut = np.zeros(65536, dtype=np.uint8)
    for r, c in RAW_TO_CLASS.items():
        lut[r] = c
    return lut[raw & 0xFFFF]


def pct(values, qs):
    if values.size == 0:
        return "-"
    return " ".join(f"{v:6.2f}" for v in np.percentile(values, qs))


def rings(pts):
    az = np.arctan2(pts[:, 1], pts[:, 0])
    jumps = np.abs(np.diff(az)) > np.pi
    return np.concatenate([[0], np.cumsum(jumps)])


def ground_profile(pts):
    """Lowest point per 2 m cell within 20 m, and the spread of the 0.5 m cells' lowest points
    inside each 2 m cell (only cells with at least 4 filled sub-cells)."""
    r = np.hypot(pts[:, 0], pts[:, 1])
    near = pts[(r < 20) & (r > 3)]
    if near.size == 0:
        return np.array([]), np.array([])
    big = np.floor(near[:, :2] / 2.0).astype(np.int64)
    small = np.floor(near[:, :2] / 0.5).astype(np.int64)
    low_small = {}
    for (sx, sy), z in zip(map(tuple, small), near[:, 2]):
        if z < low_small.get((sx, sy), np.inf):
            low_small[(sx, sy)] = z
    per_big = {}
    for (sx, sy), z in low_small.items():
        per_big.setdefault((sx // 4, sy // 4), []).append(z)
    lows = np.array([min(v) for v in per_big.values()])
    spread = []
    for v in per_big.values():
        v = np.array(v)
        # Only ground-like cells: the sub-cells within 0.4 m of the cell's lowest.
        v = v[v < v.min() + 0.4]
        if v.size >= 4:
            spread.append(v.std())
    del big
    return lows, np.array(spread)


def ground_plane(pts):
    """Plane z = h + a x + b y through the lowest point of each 1 m cell 3-15 m from the sensor,
    refitted five times to the cells within 0.15 m of it (kerbs, objects and ditches drop
    out). Returns h, the pitch (deg; positive: the ground rises ahead, the sensor looks down),
    the roll (deg; positive: the ground rises to the left) and the share of cells kept."""
    r = np.hypot(pts[:, 0], pts[:, 1])
    near = pts[(r > 3) & (r < 15)]
    if len(near) < 10:
        return None
    key = np.floor(near[:, 0]).astype(np.int64) * 100000 + np.floor(near[:, 1]).astype(np.int64)
    order = np.lexsort((near[:, 2], key))
    _, first = np.unique(key[order], return_index=True)
    low = near[order][first]
    design = np.c_[np.ones(len(low)), low[:, 0], low[:, 1]]
    keep = np.ones(len(low), bool)
    for _ in range(5):
        coef = np.linalg.lstsq(design[keep], low[keep, 2], rcond=None)[0]
        keep = np.abs(low[:, 2] - design @ coef) < 0.15
    return (coef[0], np.degrees(np.arctan(coef[1])), np.degrees(np.arctan(coef[2])),
            keep.mean())


GROUND_CELL_CLASSES = {5: "road", 6: "sidewalk", 12: "terrain"}


def ground_cells(pts, cls):
    """The 0.4 m cells within 20 m of the sensor whose points (at least 3) are all road, all
    sidewalk or all terrain: their indices, class, median height, range, for terrain cells
    the distance to the nearest sidewalk cell and the height against it (NaN otherwise), the
    mean reflectance, and the distance to the nearest road cell (NaN without one)."""
    near = np.hypot(pts[:, 0], pts[:, 1]) < 20
    p, c = pts[near], cls[near]
    ij = np.floor(p[:, :2] / 0.4).astype(np.int64)
    key = ij[:, 0] * 1000 + ij[:, 1]
    order = np.argsort(key, kind="stable")
    key, p, c, ij = key[order], p[order], c[order], ij[order]
    _, start, count = np.unique(key, return_index=True, return_counts=True)
    cells = []
    for s, n in zip(start, count):
        cc = c[s:s + n]
        if n >= 3 and cc[0] in GROUND_CELL_CLASSES and (cc == cc[0]).all():
            cells.append((ij[s, 0], ij[s, 1], cc[0], np.median(p[s:s + n, 2]),
                          np.hypot(*p[s, :2]), np.nan, np.nan, p[s:s + n, 3].mean(), np.nan))
    cells = np.array(cells, dtype=float).reshape(-1, 9)
    walk, grass = cells[cells[:, 2] == 6], np.flatnonzero(cells[:, 2] == 12)
    if len(walk) and len(grass):
        d = np.hypot(cells[grass, 0, None] - walk[None, :, 0],
                     cells[grass, 1, None] - walk[None, :, 1])
        nearest = d.argmin(axis=1)
        cells[grass, 5] = 0.4 * d[np.arange(len(grass)), nearest]
        cells[grass, 6] = cells[grass, 3] - walk[nearest, 3]
    road = cells[cells[:, 2] == 5]
    if len(road):
        for k in range(len(cells)):
            cells[k, 8] = 0.4 * np.hypot(road[:, 0] - cells[k, 0], road[:, 1] - cells[k, 1]).min()
    return cells


def ground_cell_report(cells):
    """Per ground class the cells' heights relative to the median road cell within 15 m, and
    which ground class lies beside which: the shares of each class's 8-neighbour contacts with
    the other two (the street's cross-section: road | sidewalk | grass, or road | grass |
    sidewalk)."""
    road = cells[(cells[:, 2] == 5) & (cells[:, 4] < 15)]
    if len(road) == 0:
        return
    z0 = np.median(road[:, 3])
    print("ground cells (0.4 m, within 20 m, one class, at least 3 points), height relative to "
          f"the median road cell within 15 m ({z0:.2f}):")
    for c, name in GROUND_CELL_CLASSES.items():
        mine = cells[cells[:, 2] == c]
        print(f"  {name:9s} {len(mine):5d} cells, height p10 p50 p90 "
              f"{pct(mine[:, 3] - z0, [10, 50, 90])}, mean reflectance p10 p50 p90 "
              f"{pct(mine[:, 7], [10, 50, 90])}")
    walk, grass = cells[cells[:, 2] == 6], cells[cells[:, 2] == 12]
    if len(walk) and len(grass):
        ratio = np.median(grass[:, 7]) / np.median(walk[:, 7])
        far = (walk[:, 8] >= 5).mean()
        print(f"  terrain / sidewalk median reflectance {ratio:.2f}; sidewalk cells 5 m or more "
              f"from a road cell {far:.2f}")
    grass = cells[np.isfinite(cells[:, 5])]
    bands = []
    for lo, hi in [(0, 1.5), (1.5, 3), (3, 6), (6, 12)]:
        dz = grass[(grass[:, 5] >= lo) & (grass[:, 5] < hi), 6]
        if dz.size:
            bands.append(f"{lo:g}-{hi:g} m {pct(dz, [10, 50, 90]).strip()}")
    if bands:
        print("  terrain against the nearest sidewalk cell, by distance to it, height p10 p50 "
              "p90: " + "; ".join(bands))
    where = {(int(c[0]), int(c[1])): int(c[2]) for c in cells}
    contacts = {}
    for (i, j), c in where.items():
        for di in (-1, 0, 1):
            for dj in (-1, 0, 1):
                o = where.get((i + di, j + dj))
                if o is not None and o != c:
                    contacts[(c, o)] = contacts.get((c, o), 0) + 1
    parts = []
    for c, name in GROUND_CELL_CLASSES.items():
        total = sum(n for (a, _), n in contacts.items() if a == c)
        if total:
            parts.append(f"{name}: " + ", ".join(
                f"{GROUND_CELL_CLASSES[o]} {contacts.get((c, o), 0) / total:.2f}"
                for o in GROUND_CELL_CLASSES if o != c))
    print("  contacts (share of each class's neighbours of another ground class): " +
          "; ".join(parts))


def ground_cell_report_pooled(pooled):
    """ground_cell_report over several scans: each scan's cells shifted to its own road level
    and kept apart (cell indices offset per scan) so that no contact joins two scans."""
    parts = []
    for n, (cells, z0) in enumerate(pooled):
        shifted = cells.copy()
        shifted[:, 3] -= z0
        shifted[:, 0] += 100000 * (n + 1)
        parts.append(shifted)
    ground_cell_report(np.concatenate(parts))


def overlap(a, b):
    """Overlap of two reflectance histograms (sum of the minimum of the normalised bins)."""
    if a.size == 0 or b.size == 0:
        return float("nan")
    bins = np.linspace(0, 1, 51)
    ha = np.histogram(a, bins)[0] / a.size
    hb = np.histogram(b, bins)[0] / b.size
    return float(np.minimum(ha, hb).sum())


def intensity_by_range(pts, cls):
    """Per class and horizontal range band: the share of returns that read 0 and the median of
    the others (the HDL-64E's intensity falls with the range; far dim returns read 0)."""
    bands = [0, 10, 20, 30, 40, 60]
    r = np.hypot(pts[:, 0], pts[:, 1])
    print("reflectance by range: share of zeros / median of the non-zero ones (points), bands " +
          " ".join(f"{lo}-{hi} m" for lo, hi in zip(bands[:-1], bands[1:])))
    for c in (5, 6, 12, 10, 8, 1):
        cells = []
        for lo, hi in zip(bands[:-1], bands[1:]):
            v = pts[(cls == c) & (r >= lo) & (r < hi), 3]
            if len(v) < 50:
                cells.append(f"{'-':>17s}")
                continue
            nonzero = v[v > 0]
            med = f"{np.median(nonzero):.2f}" if len(nonzero) else "  - "
            cells.append(f"{(v == 0).mean():.2f} / {med} ({len(v):5d})")
        print(f"  {CLASSES[c]:10s} " + "  ".join(cells))


def report(path, label_path):
    pts = load_points(path)
    print(f"== {path}{' + ' + label_path if label_path else ''}")
    print(f"points {len(pts)}")
    ring = rings(pts)
    per_ring = np.bincount(ring)
    print(f"rings {len(per_ring)}; returns per ring: median {np.median(per_ring):.0f}, "
          f"p10 {np.percentile(per_ring, 10):.0f}, p90 {np.percentile(per_ring, 90):.0f}, "
          f"max {per_ring.max()}")
    top = per_ring[: len(per_ring) // 2].sum() / max(1, per_ring.sum())
    print(f"share of returns in the upper half of the rings: {top:.3f}")
    r3 = np.linalg.norm(pts[:, :3], axis=1)
    rh = np.hypot(pts[:, 0], pts[:, 1])
    el = np.degrees(np.arctan2(pts[:, 2], rh))
    edges = [-25, -20, -15, -10, -8, -6, -4, -2, 0, 3]
    hist = np.histogram(el, edges)[0] / len(pts)
    print("share by elevation (deg): " +
          " ".join(f"[{a},{b}):{h:.3f}" for a, b, h in zip(edges[:-1], edges[1:], hist)))
    print(f"range p5 p25 p50 p75 p95 (m): {pct(r3, [5, 25, 50, 75, 95])}")
    print(f"share of returns beyond 40 m: {(r3 > 40).mean():.3f}, beyond 60 m: {(r3 > 60).mean():.3f}")
    print(f"reflectance p10 p25 p50 p75 p90: {pct(pts[:, 3], [10, 25, 50, 75, 90])}; "
          f"share == 0: {(pts[:, 3] == 0).mean():.3f}")
    lows, spread = ground_profile(pts)
    print(f"ground: lowest z per 2 m cell within 20 m, p5 p50 p95: {pct(lows, [5, 50, 95])}; "
          f"0.5 m cells' spread within a 2 m cell p50 p90: {pct(spread, [50, 90])}")
    plane = ground_plane(pts)
    if plane:
        print(f"ground plane 3-15 m: height {plane[0]:.2f} m, pitch {plane[1]:.2f} deg (rising "
              f"ahead), roll {plane[2]:.2f} deg (rising to the left), cells on it {plane[3]:.2f}")
    if not label_path:
        return None
    cls = load_classes(label_path, len(pts))
    print(f"{'class':13s} {'points':>7s} | {'z p5   p50   p95':>20s} | "
          f"{'refl p10 p50  p90':>20s} | {'range p10 p50 p90':>20s}")
    for c in range(len(CLASSES)):
        m = cls == c
        if not m.any():
            continue
        print(f"{CLASSES[c]:13s} {m.sum():7d} | {pct(pts[m, 2], [5, 50, 95])} | "
              f"{pct(pts[m, 3], [10, 50, 90])} | {pct(r3[m], [10, 50, 90])}")
    names = {5: "road", 6: "sidewalk", 7: "other-ground", 12: "terrain", 10: "vegetation"}
    keys = list(names)
    print("reflectance histogram overlap (1 = same distribution):")
    for i, a in enumerate(keys):
        for b in keys[i + 1:]:
            print(f"  {names[a]}/{names[b]}: {overlap(pts[cls == a, 3], pts[cls == b, 3]):.2f}")
    intensity_by_range(pts, cls)
    road = pts[cls == 5]
    if len(road):
        rr = np.hypot(road[:, 0], road[:, 1])
        near = road[rr < 20]
        print(f"road within 20 m: z p5 p50 p95 {pct(near[:, 2], [5, 50, 95])}, "
              f"std {near[:, 2].std():.3f}")
    cells = ground_cells(pts, cls)
    ground_cell_report(cells)
    return cells


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("scans", nargs="*")
    p.add_argument("--labels", action="append", default=[],
                   help="labels of the scan before it (in order)")
    p.add_argument("--sequence", help="a SemanticKITTI sequence directory")
    p.add_argument("--scans", dest="count", type=int, default=0, help="with --sequence: at most N")
    a = p.parse_intermixed_args()
    jobs = []
    if a.sequence:
        vel = os.path.join(a.sequence, "velodyne")
        if not os.path.isdir(vel):
            sys.exit(f"{a.sequence}: no velodyne/ directory")
        names = sorted(n for n in os.listdir(vel) if n.endswith(".bin"))
        if a.count > 0:
            names = names[: a.count]
        for n in names:
            lab = os.path.join(a.sequence, "labels", n[:-4] + ".label")
            jobs.append((os.path.join(vel, n), lab if os.path.exists(lab) else None))
    if len(a.labels) > len(a.scans):
        sys.exit("more --labels than scans")
    for i, s in enumerate(a.scans):
        jobs.append((s, a.labels[i] if i < len(a.labels) else None))
    if not jobs:
        p.error("no scans given")
    pooled = []
    for scan, lab in jobs:
        if not os.path.exists(scan):
            sys.exit(f"{scan}: no such file")
        cells = report(scan, lab)
        if cells is not None and len(cells):
            # Relative to each scan's own road, so that the scans pool.
            road = cells[(cells[:, 2] == 5) & (cells[:, 4] < 15), 3]
            if len(road):
                pooled.append((cells, np.median(road)))
        print()
    if len(pooled) > 1:
        print(f"== the {len(pooled)} labelled scans pooled")
        ground_cell_report_pooled(pooled)


if __name__ == "__main__":
    main()
