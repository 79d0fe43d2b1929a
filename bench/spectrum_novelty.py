"""The measurement that led to ``train --novelty spectrum`` (built since, with each surface on its own scale): the
far-surface distance on the whole-slide spectrum, not on the classifier's features, computed here outside the product.

``train``'s unknown-surface tests measure a slide's distance to the taught surfaces in the chosen classifier's own
standardised features: 4 to 8 of them on most scenes, picked to tell the *taught* surfaces apart. This script measures
the same kind of distance on the plain baseline's whole-slide spectrum instead (bench/labels.py's ``plain_features``:
per channel the log energy in 24 log-spaced bands, 20 Hz to 0.45 fs), as ``levels`` or as ``shape`` (each channel's
band levels less their mean: a film's gain moves every band of its channel alike and leaves the shape), standardised
on the training slides; the distance to a surface is the mean over its 3 nearest training slides
(tactiled.learn.model.nearest_surface_distances), from the nearest surface.

Two thresholds, from the training slides alone: ``far``, the rule ``train --novelty far`` uses (the larger of the 95 %
quantiles of each slide's distance to the nearest *other* surface and to its own surface's other recordings), and
``loro``, the second of those alone (at most 5 % of a new recording's known slides rejected). Per scene, the share of
slides over each: known slides of the same unit and of units 1-4 (a reference of all 15 surfaces), and, with 3 of the
15 left out of the reference (bench/labels.py's LEAVE_OUT), their slides and the known ones, on the same unit and units
1 and 2; with neighbouring grades, also the 15 gratings (``<scene>,grating``, 1 file x 3 slides each, seed 400).
Recordings as bench/labels.py makes them (train seed 100, 3 files x 3 slides per surface; tests 2 x 3).

Usage: python bench/spectrum_novelty.py [--scenes "robot;hand"] [--mixed] [--out DIR]
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from labels import LEAVE_OUT, dataset, plain_rows, ra
from scratch import scratch

from tactiled.learn.dataset import load_recordings
from tactiled.learn.model import nearest_surface_distances
from tactiled.sim.simulate import write_dataset

BANDS = 24  # plain_features: per channel 24 band levels, then the log centroid and the kurtosis


def slide_rows(paths: list[Path]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(plain features (s, 26 C), surfaces (s,), recording index (s,)) of every true slide of ``paths`` (``plain_rows``)."""
    per_file = [rows for rows in (plain_rows([rec]) for rec in load_recordings(paths)) if len(rows[1])]
    return (np.vstack([x for x, _ in per_file]), np.concatenate([y for _, y in per_file]).astype(np.str_),
            np.concatenate([np.full(len(y), i) for i, (_, y) in enumerate(per_file)]))


def view(x: np.ndarray, name: str) -> np.ndarray:
    """The band levels (s, 24 C) of plain features ``x``, as they are (``levels``) or less each channel's mean (``shape``)."""
    bands = x.reshape(len(x), -1, BANDS + 2)[:, :, :BANDS]
    if name == "shape":
        bands = bands - bands.mean(axis=2, keepdims=True)
    return bands.reshape(len(x), -1)


def thresholds(z: np.ndarray, y: np.ndarray, g: np.ndarray) -> dict[str, float]:
    """``far`` and ``loro`` (see the module docstring) of standardised training rows ``z`` of surfaces ``y``, recordings ``g``."""
    other_surface = np.array([nearest_surface_distances(z[i:i + 1], z[y != y[i]], y[y != y[i]], 3)[0, 0] for i in range(len(z))])
    other_file = np.array([nearest_surface_distances(z[i:i + 1], z[g != g[i]], y[g != g[i]], 3)[0, 0] for i in range(len(z))])
    loro = float(np.quantile(other_file, 0.95, method="higher"))
    return {"far": max(float(np.quantile(other_surface, 0.95, method="higher")), loro), "loro": loro}


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="robot;hand;one-channel;continuous")
    ap.add_argument("--mixed", action="store_true", help="8 grades spread over the range and 7 gratings per scene (bench/labels.py --mixed)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    root = scratch(args.out, "tactiled-spectrum-novelty-")
    print("| scene | view | threshold | known slides over it: same unit / units 1-4 (%) | 3 left out, theirs / known: same unit; "
          "unit 1; unit 2 (%) | gratings (%) |")
    print("|---|---|---|---|---|---|")
    for spec in args.scenes.split(";"):
        d = root / spec.replace(",", "+")
        train = slide_rows(dataset(d / "train", spec, 100, 3, 3, args.mixed))
        tests = {"same": slide_rows(dataset(d / "same", spec, 200, 2, 3, args.mixed))}
        for u in (1, 2, 3, 4):
            tests[f"unit {u}"] = slide_rows(dataset(d / f"other{u}", spec, 200 + 100 * u, 2, 3, args.mixed, unit=u, specimen=u))
        far = None if args.mixed or "grating" in spec else slide_rows(
            write_dataset(d / "gratings", scene=f"{spec},grating", seed=400, files_per_surface=1, slides_per_file=3))
        gone = sorted({s for i, s in enumerate(sorted(set(train[1]), key=ra)) if i in LEAVE_OUT})
        for name in ("levels", "shape"):
            full, taught = np.ones(len(train[1]), dtype=bool), ~np.isin(train[1], gone)
            cells: dict[str, list[str]] = {"far": ["", "", ""], "loro": ["", "", ""]}
            for part, keep in (("all", full), ("twelve", taught)):
                ref = view(train[0][keep], name)
                mu, sd = ref.mean(axis=0), ref.std(axis=0) + 1e-9
                z, y = (ref - mu) / sd, train[1][keep]
                limits = thresholds(z, y, train[2][keep])

                def dist(rows: tuple[np.ndarray, np.ndarray, np.ndarray], z: np.ndarray = z, y: np.ndarray = y,
                         mu: np.ndarray = mu, sd: np.ndarray = sd, name: str = name) -> np.ndarray:
                    out: np.ndarray = nearest_surface_distances((view(rows[0], name) - mu) / sd, z, y, 3)[:, 0]
                    return out

                for key, limit in limits.items():
                    if part == "all":
                        cells[key][0] = " / ".join(f"{100 * np.mean(dist(tests[k]) > limit):.0f}" for k in tests)
                        cells[key][2] = f"{100 * np.mean(dist(far) > limit):.0f}" if far is not None else "-"
                    else:
                        parts = []
                        for k in ("same", "unit 1", "unit 2"):
                            over, unseen = dist(tests[k]) > limit, np.isin(tests[k][1], gone)
                            parts.append(f"{100 * np.mean(over[unseen]):.0f} / {100 * np.mean(over[~unseen]):.0f}")
                        cells[key][1] = "; ".join(parts)
            for key in ("far", "loro"):
                print(f"| {spec} | {name} | {key} | {cells[key][0]} | {cells[key][1]} | {cells[key][2]} |", flush=True)


if __name__ == "__main__":
    main()
