"""How many slides does ``tactiled enrol`` need to teach a model one more surface, against a full retrain?

Per scene: a training set of 15 surfaces (3 files per surface, 3 slides per file, seed 100); one surface (``--new``,
inside the range) is left out and a model is trained on the other 14 with ``train``'s defaults. The left-out surface
is then enrolled from 1, 3, 5, 10 and 20 slides (files of one slide each, seed 300), and every model is replayed on a
test set of all 15 surfaces (2 files per surface, 3 slides per file, seed 200), every true slide counted: the new
surface's accuracy, and the 14 known surfaces' accuracy against the model before enrolment. The full retrain is
``train`` on all 15 surfaces' training files.

``--new`` picks the case. A grade inside the range (the default, Ra1.40, between two taught grades 18 % apart) is the
hardest: a confusable class. An end-of-range grade (Ra0.44, Ra4.43) has a taught neighbour on one side only. A
grating of the other surface family (``G0.32mm``, docs/simulator.md; recorded with the same scene's kinematics and
fingertip) is the field case: a surface unlike every taught one. Then nothing is left out: the model before enrolment
is trained on all 15 grades, the grating's training, pool and test files are simulated alike (seeds 101, 300 and
201, so that no file shares another's seed), and the full retrain is ``train`` on the 15 grades plus the grating.
The row "enrolled from the retrain's training slides" enrols the new surface's slides of the full retrain's training
set: the same data as the retrain, with the model's candidate kept (no search), which tells what the new class costs
the known surfaces from what enrolling few slides costs. The last column is the share of true slides flagged as an
unknown surface (new surface / known ones).

Then, with ``--units``, a fingertip swap: the model trained on unit 0 (all 15 surfaces) meets units 1 and 2 (new
specimens too; docs/simulator.md); one recording of 5 slides per surface made with the new unit is enrolled under the
recordings' own labels, and the model is replayed on other recordings of that unit (2 files × 3 slides per surface),
beside the plain whole-slide spectral baseline of bench/labels.py trained on unit 0.

``--ensemble always`` trains every model with ``train --ensemble always`` (enrolment then refits both members).

Usage: python bench/enrol.py [--scenes robot,hand] [--new Ra1.40|Ra4.43|G0.32mm] [--out DIR] [--units] [--ensemble off|always|guarded]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

from scratch import scratch

from tactiled.config import Config
from tactiled.files.recording import Recording
from tactiled.learn.dataset import load_recordings
from tactiled.learn.enrol import enrol
from tactiled.learn.model import Model
from tactiled.learn.train import train
from tactiled.run.replay import pair_results, replay_recording
from tactiled.sim.physics import default_surfaces, grating_surfaces
from tactiled.sim.simulate import write_dataset

COUNTS = (1, 3, 5, 10, 20)


def accuracy(recs: list[tuple[str, Recording]], config: Config, model: Model, new: str,
             label: str) -> tuple[float, float, float, float]:
    """(accuracy on the new surface's true slides, on the others', share of the new surface's true slides flagged as an
    unknown surface, of the others'), every true slide counted; ``label`` is the new one's name."""
    hits = {True: [0, 0, 0], False: [0, 0, 0]}
    for _, rec in recs:
        truth, paired, _ = pair_results(rec, replay_recording(rec, config, model))
        for t, r in zip(truth, paired, strict=True):
            is_new = t == new
            hits[is_new][0] += r is not None and r.label == (label if is_new else t)
            hits[is_new][1] += 1
            hits[is_new][2] += r is not None and r.reason == "unknown_surface"
    n_new, n_known = max(1, hits[True][1]), max(1, hits[False][1])
    return hits[True][0] / n_new, hits[False][0] / n_known, hits[True][2] / n_new, hits[False][2] / n_known


def main() -> None:
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
    ap = argparse.ArgumentParser()
    ap.add_argument("--scenes", default="robot,hand")
    ap.add_argument("--new", default="Ra1.40", help="the surface left out of training and enrolled")
    ap.add_argument("--out", default=None)
    ap.add_argument("--units", action="store_true", help="the fingertip-swap table instead")
    ap.add_argument("--ensemble", default="off", help="train --ensemble for every model (off, always, guarded)")
    args = ap.parse_args()
    config, root = Config(), scratch(args.out, "tactiled-enrol-")
    opts: dict[str, Any] = {"ensemble": args.ensemble}
    if args.units:
        unit_swap(args.scenes.split(","), root, config, opts)
        return
    grades = [g.name for g in default_surfaces()]
    other_family = args.new not in grades
    if other_family and args.new not in [g.name for g in grating_surfaces()]:
        ap.error(f"--new: {args.new!r} is neither a grade ({grades[0]} ... {grades[-1]}) nor a grating (G0.10mm ... G1.00mm)")
    known = len(grades) - (not other_family)
    print(f"| scene | model | new surface | {known} known surfaces | unknown (new / known) | seconds |")
    print("|---|---|---|---|---|---|")
    for scene in args.scenes.split(","):
        new_scene = f"{scene},grating" if other_family else scene  # the new surface's family, same kinematics and fingertip
        tr = write_dataset(root / scene / "train", scene=scene, seed=100, files_per_surface=3, slides_per_file=3)
        pool = write_dataset(root / scene / "pool", scene=new_scene, seed=300, surfaces=args.new, files_per_surface=max(COUNTS), slides_per_file=1)
        test_paths = write_dataset(root / scene / "test", scene=scene, seed=200, files_per_surface=2, slides_per_file=3)
        if other_family:
            tr_known = tr
            tr = tr + write_dataset(root / scene / "train-new", scene=new_scene, seed=101, surfaces=args.new, files_per_surface=3, slides_per_file=3)
            test_paths += write_dataset(root / scene / "test-new", scene=new_scene, seed=201, surfaces=args.new, files_per_surface=2, slides_per_file=3)
        else:
            tr_known = [p for p in tr if f"_{args.new}_" not in p.name]
        test = load_recordings(test_paths)
        rows: list[tuple[str, Any, float]] = []
        t0 = time.perf_counter()
        base = train(tr_known, config, **opts).model
        rows.append((f"trained on {known} (before enrolment)", base, time.perf_counter() - t0))
        base_path = root / scene / "base.npz"
        base.save(base_path)
        for n in COUNTS:
            t0 = time.perf_counter()
            done = enrol(base_path, pool[:n], config, label="NEW", min_slides=1)
            rows.append((f"enrolled from {n} slide{'s' * (n > 1)}", done.model, time.perf_counter() - t0))
        t0 = time.perf_counter()  # the full retrain's slides of the new surface, enrolled: its data with the model's candidate
        done = enrol(base_path, [p for p in tr if f"_{args.new}_" in p.name], config, label="NEW", min_slides=1)
        rows.append((f"enrolled from the retrain's {sum(done.added.values())} training slides", done.model, time.perf_counter() - t0))
        t0 = time.perf_counter()
        rows.append((f"full retrain on {known + 1}", train(tr, config, **opts).model, time.perf_counter() - t0))
        for name, model, seconds in rows:
            label = args.new if name.startswith("full") else "NEW"
            new_acc, known_acc, new_unknown, known_unknown = accuracy(test, config, model, args.new, label)
            print(f"| {scene} | {name} | {100 * new_acc:.1f} % | {100 * known_acc:.1f} % | "
                  f"{100 * new_unknown:.0f} / {100 * known_unknown:.1f} % | {seconds:.1f} |", flush=True)


def unit_swap(scenes: list[str], root: Path, config: Config, opts: dict[str, Any]) -> None:
    """The fingertip-swap table (see the module docstring)."""
    from labels import plain_baseline

    print("| scene | unit | trained on unit 0 | after enrolling 5 slides per surface of the unit | plain baseline (unit 0) |")
    print("|---|---|---|---|---|")
    for scene in scenes:
        tr = write_dataset(root / scene / "train", scene=scene, seed=100, files_per_surface=3, slides_per_file=3)
        model = train(tr, config, **opts).model
        model.save(root / scene / "m.npz")
        for u in (1, 2):
            new = write_dataset(root / scene / f"enrol{u}", scene=scene, seed=500 + u, files_per_surface=1, slides_per_file=5, unit=u, specimen=u)
            test = load_recordings(write_dataset(root / scene / f"test{u}", scene=scene, seed=200 + 100 * u, files_per_surface=2,
                                                 slides_per_file=3, unit=u, specimen=u))
            enrolled = enrol(root / scene / "m.npz", new, config).model
            plain = plain_baseline(load_recordings(tr), {"test": test})["test"]
            print(f"| {scene} | {u} | {100 * overall(test, config, model):.1f} % | {100 * overall(test, config, enrolled):.1f} % | "
                  f"{100 * plain:.1f} % |", flush=True)


def overall(recs: list[tuple[str, Recording]], config: Config, model: Model) -> float:
    """Accuracy over every true slide of ``recs`` (an abstention is wrong)."""
    right = total = 0
    for _, rec in recs:
        truth, paired, _ = pair_results(rec, replay_recording(rec, config, model))
        right += sum(r is not None and r.label == t for t, r in zip(truth, paired, strict=True))
        total += len(truth)
    return right / max(1, total)


if __name__ == "__main__":
    main()
