"""Selection rules judged on held-out data: which candidate each rule picks from the leaderboard, and its test accuracy.

Input: the JSON of ``python bench/scenes.py --all-candidates --json FILE`` (every candidate of the
default search refitted on the training set and scored end to end on the test set). For each scene
the script applies several rules to the training leaderboard (cross-validation only) and reports the
test accuracy of the candidate each rule picks, beside the papers' method and the best candidate in
hindsight (the oracle, which no rule can know).

Usage: python bench/selection.py FILE
"""

from __future__ import annotations

import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from tactiled.learn.search import Candidate, choose, default_candidates, standard_error, within_one_se

Row = dict[str, Any]


def best_mean(board: list[Row], cands: list[Candidate]) -> int:
    """The best mean over folds (ties: the earlier candidate)."""
    return int(np.argmax([r["mean"] for r in board]))


def one_se_list_order(board: list[Row], cands: list[Candidate]) -> int:
    """Within one standard error of the best mean, the earliest in the search's list."""
    return within_one_se([r["folds"] for r in board])[0]


def mean_minus_se(board: list[Row], cands: list[Candidate]) -> int:
    """The best mean less its own standard error."""
    return int(np.argmax([r["mean"] - standard_error(r["folds"]) for r in board]))


def mean_rank(board: list[Row], cands: list[Candidate]) -> int:
    """The best rank averaged over folds (ties: the better mean)."""
    folds = np.array([r["folds"] for r in board])
    ranks = (-folds).argsort(axis=0).argsort(axis=0).mean(axis=1)
    return int(np.lexsort((-np.array([r["mean"] for r in board]), ranks))[0])


def adopted(board: list[Row], cands: list[Candidate]) -> int:
    """``tactiled train``'s rule (:func:`tactiled.learn.search.choose`): the simplest within one standard error."""
    return choose(cands, [r["folds"] for r in board])


RULES: dict[str, Callable[[list[Row], list[Candidate]], int]] = {
    "best mean": best_mean, "1 SE, list order": one_se_list_order, "1 SE, simplest (adopted)": adopted,
    "mean - SE": mean_minus_se, "mean rank": mean_rank}


def main() -> None:
    rows = json.loads(Path(sys.argv[1]).read_text())
    by_name = {c.name: c for c in default_candidates()}
    order = list(by_name)
    print("| scene | papers' method | oracle | " + " | ".join(RULES) + " |")
    print("|---" * (3 + len(RULES)) + "|")
    totals: dict[str, list[float]] = {k: [] for k in RULES}
    papers = []
    for scene in rows:
        auto = scene["auto"]
        board = sorted(auto["leaderboard"], key=lambda r: order.index(r["candidate"]))  # the search's own order
        cands = [by_name[r["candidate"]] for r in board]
        test = auto["test_accuracy"]
        papers.append(scene["paper"]["accuracy"])
        cells = []
        for name, rule in RULES.items():
            pick = board[rule(board, cands)]["candidate"]
            totals[name].append(test[pick])
            cells.append(f"{100 * test[pick]:.1f} % ({pick})")
        print(f"| {scene['scene']} | {100 * papers[-1]:.1f} % | {100 * max(test.values()):.1f} % | " + " | ".join(cells) + " |")
    summary = [f"{100 * np.mean(v):.1f} %, ahead or equal on {sum(a >= p for a, p in zip(v, papers, strict=True))}/{len(papers)}"
               for v in totals.values()]
    print(f"| mean | {100 * np.mean(papers):.1f} % | | " + " | ".join(summary) + " |")


if __name__ == "__main__":
    main()
