"""Provisional labels: how often right, how sure, and whether their confidence is a probability.

Usage: python bench/provisional.py [--scenes hand,robot,fluctuating] [--model FILE] [--pooled] [--out DIR] [--seed 11]
                                   [--json FILE]

For each scene, labelled recordings are simulated into ``--out`` (kept, and reused when there): for training (seed S, 3
files per surface of 5 slides) and for testing (seed S + 1, 2 files per surface: other tracks of the same specimens, the
same unit). ``tactiled train`` with its defaults learns each scene's training files, unless ``--model`` names one model
for every scene (the shipped one, say). The test recordings are replayed through the daemon's pipeline
(``tactiled.run.replay.replay_recording``, the default config) and every label it publishes is paired with the truth:

- provisional labels (``final`` false) and final ones: how many, their mean confidence, how many are right, and the
  expected calibration error (10 equal-width bins of confidence);
- the first provisional label of each slide: its time from the slide's start (``used_s``; median);
- provisional labels whose windows reach past their slide's end (``window[1]`` after the final label's ``stop``; the
  detector reports a quiet one 5 ms hop after it began, so a window ending within that hop still gives one).

``--pooled``: the scenes' test labels counted together too (the shipped model learnt hand and robot sliding together).
The code measured is the one imported: ``PYTHONPATH=/other/checkout:/other/checkout/clients python -P bench/...``
measures another checkout (its ``tactiled train`` too).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np

from tactiled.config import Config
from tactiled.files.recording import load_recording
from tactiled.learn.model import load_model
from tactiled.run.replay import replay_recording, truth_of

TACTILED = [sys.executable, "-P", "-m", "tactiled"]


def simulate(scene: str, out: Path, seed: int, files: int) -> list[Path]:
    """The scene's labelled recordings in ``out`` (simulated unless already there)."""
    if not any(out.glob("*.npz")):
        subprocess.run([*TACTILED, "simulate", "dataset", "--scene", scene, "--out", str(out), "--seed", str(seed),
                        "--files-per-surface", str(files), "--slides-per-file", "5", "--jobs", str(os.cpu_count() or 1)],
                       check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    return sorted(out.glob("*.npz"))


def ece(confidence: np.ndarray, right: np.ndarray, bins: int = 10) -> float:
    """Expected calibration error: the mean over equal-width confidence bins of |mean confidence - accuracy|, by share."""
    which = np.minimum((confidence * bins).astype(int), bins - 1)
    return float(sum(np.mean(which == b) * abs(confidence[which == b].mean() - right[which == b].mean())
                     for b in range(bins) if np.any(which == b)))


def figures(rows: list[tuple[float, bool]]) -> dict[str, Any]:
    """Count, mean confidence, accuracy and ECE of (confidence, right) pairs."""
    if not rows:
        return {"n": 0}
    c, y = np.array([r[0] for r in rows]), np.array([r[1] for r in rows], dtype=np.float64)
    return {"n": len(rows), "confidence": round(float(c.mean()), 3), "accuracy": round(float(y.mean()), 3), "ece": round(ece(c, y), 3)}


def measure(files: list[Path], model_path: Path) -> dict[str, Any]:
    """Every published label of ``files`` replayed with ``model_path``, against the truth."""
    model, config = load_model(model_path), Config()
    provisional: list[tuple[float, bool]] = []
    final: list[tuple[float, bool]] = []
    first: list[float] = []
    past_end = 0
    for f in files:
        rec = load_recording(f)
        results = replay_recording(rec, config, model)
        stops = {r.slide_id: r.stop for r in results if r.final}
        seen: set[int] = set()
        for r in results:
            truth = truth_of(rec, r.start, r.stop)
            if not r.final:
                past_end += int(r.slide_id in stops and r.window[1] > stops[r.slide_id])
                if r.slide_id not in seen:
                    seen.add(r.slide_id)
                    first.append(r.used_s)
            if truth is None or r.label is None or r.confidence is None:
                continue
            (final if r.final else provisional).append((r.confidence, r.label == truth))
    return {"provisional": figures(provisional), "final": figures(final), "first_provisional_median_s": float(np.median(first)) if first else None,
            "provisional_past_slide_end": past_end, "rows": {"provisional": provisional, "final": final}}


def line(name: str, m: dict[str, Any]) -> str:
    p, f = m["provisional"], m["final"]
    return (f"{name:<12s} provisional n={p['n']} confidence {p.get('confidence')} right {p.get('accuracy')} ECE {p.get('ece')}"
            f" | final n={f['n']} confidence {f.get('confidence')} right {f.get('accuracy')} ECE {f.get('ece')}"
            f" | first provisional median {m['first_provisional_median_s']} s | past the slide's end {m['provisional_past_slide_end']}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="hand,robot,fluctuating")
    ap.add_argument("--model", help="one model for every scene (default: train one per scene)")
    ap.add_argument("--pooled", action="store_true", help="also count the scenes' test labels together")
    ap.add_argument("--out", default="bench-provisional", help="folder of the simulated recordings and trained models")
    ap.add_argument("--seed", type=int, default=11)
    ap.add_argument("--json", help="write the figures here too")
    args = ap.parse_args()
    out, report = Path(args.out), {}
    pooled: dict[str, list[tuple[float, bool]]] = {"provisional": [], "final": []}
    for scene in args.scenes.split(","):
        test = simulate(scene, out / scene / "test", args.seed + 1, 2)
        if args.model:
            model = Path(args.model)
        else:
            train = simulate(scene, out / scene / "train", args.seed, 3)
            model = out / scene / "model.npz"
            done = subprocess.run([*TACTILED, "train", *map(str, train), "-o", str(model), "--force"], capture_output=True, text=True)
            if done.returncode:
                sys.exit(f"train failed ({done.returncode}): {done.stderr.strip()}")
        m = measure(test, model)
        for k in pooled:
            pooled[k] += m["rows"][k]
        report[scene] = {k: v for k, v in m.items() if k != "rows"}
        print(line(scene, m), flush=True)
    if args.pooled:
        report["pooled"] = {k: figures(v) for k, v in pooled.items()}
        p, f = report["pooled"]["provisional"], report["pooled"]["final"]
        print(f"{'pooled':<12s} provisional n={p['n']} confidence {p.get('confidence')} right {p.get('accuracy')} ECE {p.get('ece')}"
              f" | final n={f['n']} confidence {f.get('confidence')} right {f.get('accuracy')} ECE {f.get('ece')}")
    if args.json:
        Path(args.json).write_text(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
