"""Where unknown surfaces lie: the plain nearest-surface distance and the distance ratio of slides of each population.

Per scene, a model trained with ``tactiled train``'s defaults on 15 grades (unit 0; 3 files x 3 slides per surface,
seed 100, as bench/labels.py) scores every slide (the mean of its windows' features, standardised as its classifier
sees them, the way the daemon scores novelty) of:

- **train LORO**: each training slide against the other recordings' slides (leave one recording out; what
  training alone says of a new recording of a known surface);
- **train LOSO**: each training slide against the other surfaces' slides (leave one surface out; a grade one step away);
- **same unit**: test slides of the 15 grades, unit 0 (2 files x 3 slides, seed 200);
- **unit 1 / unit 2**: the same grades, another unit of the sensor and new specimens (seeds 300, 400; bench/labels.py);
- **left out**: a model trained on 12 grades (bench/labels.py's leave-out: Ra0.61, Ra1.40, Ra3.19), the left-out
  grades' same-unit test slides (and its known ones, ``left-out known``);
- **gratings**: the 15 gratings of the other surface family, same kinematics and fingertip (``<scene>,grating``,
  1 file x 3 slides each, seed 400): far from every grade.

Two numbers per slide: ``d``, the mean distance to the 3 nearest slides of the nearest taught surface (the ratio's
numerator), and ``ratio``, that over the same for the next surface. Printed as quantiles, ``d`` also in units of the
training LORO median, and the share of each population the gate flags (the model's own thresholds), by each test apart,
and by the distance test with its threshold 1.25 and 2 times as large.

``--mixed``: each scene's surfaces are 8 grades spread over the range and 7 gratings (bench/labels.py --mixed); no
gratings population then (they are taught).

Usage: python bench/novelty.py [--scenes "robot;hand;one-channel"] [--mixed] [--out DIR] [--json FILE]
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from labels import LEAVE_OUT, dataset, ra
from scratch import scratch

from tactiled.config import Config
from tactiled.files.recording import Recording
from tactiled.learn.dataset import collect_windows, find_slides, load_recordings
from tactiled.learn.model import Model, novelty_parts, over_thresholds
from tactiled.learn.train import train
from tactiled.sim.simulate import write_dataset


def slide_rows(recs: list[tuple[str, Recording]], config: Config, model: Model) -> tuple[np.ndarray, np.ndarray]:
    """(standardised mean features (s, F'), labels (s,)) of every slide of ``recs`` with a usable window."""
    ws = collect_windows(recs, config, model.settings, found=find_slides(recs, config)).averaged()
    return model.standardise(model.own(ws.x)), ws.y  # an ensemble: its first member's columns, as its novelty gate


def scores(model: Model, z: np.ndarray, train_z: np.ndarray | None = None, train_y: np.ndarray | None = None) -> dict[str, list[Any]]:
    """``d`` and ``ratio`` of rows ``z`` against the model's novelty slides (or ``train_z``, ``train_y``)."""
    tz = model.novelty_x if train_z is None else train_z
    ty = model.novelty_y if train_y is None else train_y
    assert tz is not None and ty is not None
    parts = novelty_parts(z, tz, ty, model.novelty_k, "combined")
    surfaces, codes = np.unique(ty, return_inverse=True)
    d = np.sqrt(np.maximum(((z[:, None, :] - tz[None, :, :]) ** 2).sum(axis=2), 0.0))
    nearest = [str(surfaces[codes[np.argmin(row)]]) for row in d]  # the surface of the nearest slide
    return {"d": parts[:, 1].tolist(), "ratio": parts[:, 0].tolist(), "nearest": nearest}


def training_scores(model: Model) -> dict[str, dict[str, list[Any]]]:
    """LORO and LOSO scores of the model's own novelty slides."""
    z, y, g = model.novelty_x, model.novelty_y, model.novelty_groups
    assert z is not None and y is not None and g is not None
    out: dict[str, dict[str, list[Any]]] = {"train LORO": {"d": [], "ratio": [], "nearest": [], "label": []},
                                            "train LOSO": {"d": [], "ratio": [], "nearest": [], "label": []}}
    for i in range(len(z)):
        for name, keep in (("train LORO", g != g[i]), ("train LOSO", y != y[i])):
            s = scores(model, z[i:i + 1], z[keep], y[keep])
            for key in ("d", "ratio", "nearest"):
                out[name][key] += s[key]
            out[name]["label"].append(str(y[i]))
    return out


def summary(v: list[float]) -> str:
    a = np.asarray(v)
    q = np.quantile(a, [0.05, 0.25, 0.5, 0.75, 0.95])
    return " / ".join(f"{x:.2f}" for x in (*q, a.max()))


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="robot;hand;one-channel")
    ap.add_argument("--out", default=None)
    ap.add_argument("--json", default=None)
    ap.add_argument("--novelty", default=None, help="train --novelty (default: train's)")
    ap.add_argument("--mixed", action="store_true", help="8 grades spread over the range and 7 gratings per scene (bench/labels.py --mixed)")
    args = ap.parse_args()
    opts: dict[str, Any] = {"novelty": args.novelty} if args.novelty else {}
    config = Config()
    root = scratch(args.out, "tactiled-novelty-")
    result: dict[str, Any] = {}
    for spec in args.scenes.split(";"):
        name = spec.replace(",", "+")
        tr = dataset(root / name / "train", spec, 100, 3, 3, args.mixed)
        sets = {"same unit": dataset(root / name / "same", spec, 200, 2, 3, args.mixed)}
        for u in (1, 2):
            sets[f"unit {u}"] = dataset(root / name / f"other{u}", spec, 200 + 100 * u, 2, 3, args.mixed, unit=u, specimen=u)
        if not args.mixed:
            sets["gratings"] = write_dataset(root / name / "gratings", scene=f"{spec},grating", seed=400, files_per_surface=1, slides_per_file=3)
        model = train(tr, config, progress=lambda m: None, **opts).model
        pops = training_scores(model)
        for key, paths in sets.items():
            z, _ = slide_rows(load_recordings(paths), config, model)
            pops[key] = scores(model, z)
        surfaces = sorted({str(s) for s in model.classes}, key=ra)
        gone = {surfaces[i] for i in LEAVE_OUT}
        keep = [p for p in tr if not any(f"_{g}_" in p.name for g in gone)]
        lo_model = train(keep, config, progress=lambda m: None, **opts).model
        z, y = slide_rows(load_recordings(sets["same unit"]), config, lo_model)
        unseen = np.isin(y, sorted(gone))
        pops["left out"] = scores(lo_model, z[unseen])
        pops["left-out known"] = scores(lo_model, z[~unseen])
        lo_train = training_scores(lo_model)
        scale = float(np.median(pops["train LORO"]["d"]))
        result[spec] = {"populations": pops, "ratio_threshold": model.novelty_threshold, "d_scale": scale,
                        "left_out_ratio_threshold": lo_model.novelty_threshold, "left_out_train": lo_train, "score": model.novelty_score,
                        "thresholds": {"ratio": model.novelty_threshold, "distance": model.novelty_distance_threshold},
                        "left_out_thresholds": {"ratio": lo_model.novelty_threshold,
                                                "distance": lo_model.novelty_distance_threshold}}
        print(f"\n{spec}: {model.kind} on {len(model.names)} features; novelty {model.novelty_score}, ratio threshold {model.novelty_threshold:.3f}, "
              f"distance threshold {model.novelty_distance_threshold / scale:.2f} LORO medians; "
              f"d in units of the training LORO median ({scale:.2f})")
        print("| population | slides | d / LORO median: q05 / q25 / median / q75 / q95 / max | ratio: q05 / q25 / median / q75 / q95 / max "
              "| flagged (by the ratio, by the distance; distance threshold x1.25, x2) |")
        print("|---|---|---|---|---|---|")
        for key, s in pops.items():
            m = lo_model if key.startswith("left") else model
            flagged = flags(m, s)
            print(f"| {key} | {len(s['d'])} | {summary([x / scale for x in s['d']])} | {summary(s['ratio'])} | {flagged} |", flush=True)
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1, default=float))


def flags(model: Model, s: dict[str, list[Any]]) -> str:
    """The share of slides whose novelty (the model's own gate) is above 1; then, apart, the share over the ratio's threshold
    and over the distance threshold, and over the distance threshold times 1.25 and 2 (how much slack the distance test has)."""
    parts = np.column_stack([s["ratio"], s["d"]])
    nov = over_thresholds(parts, model.novelty_threshold, model.novelty_distance_threshold)
    ratio, d, far = parts[:, 0], parts[:, 1], model.novelty_distance_threshold

    def share(hit: np.ndarray) -> str:
        return f"{100 * float(np.mean(hit)):.1f}"

    return (f"{share(nov > 1)} % (ratio {share(ratio > model.novelty_threshold)}, distance {share(d > far)}, "
            f"x1.25 {share(d > 1.25 * far)}, x2 {share(d > 2 * far)})")


if __name__ == "__main__":
    main()
