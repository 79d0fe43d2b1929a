"""Coverage-guided fuzzing (atheris), time-bounded, seeded with valid inputs; and the crash cases found so far.

The timed runs are marked ``fuzz`` and left out of the unit suite (``pytest -m fuzz`` runs them);
the committed crash cases run in the unit suite (tests/test_fuzz.py::test_committed_fuzz_cases).
"""

from __future__ import annotations

import io
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tactiled.board.frames import encode_frames
from tactiled.learn.model import default_model_path
from tests.conftest import REPO

CASES = REPO / "tests" / "fuzz_cases"
SECONDS = 8


def _seeds(target: str, corpus: Path) -> None:
    corpus.mkdir()
    rng = np.random.default_rng(0)
    if target == "decoder":
        for i, (c, n) in enumerate([(2, 20), (1, 3), (8, 2)]):
            (corpus / f"s{i}").write_bytes(encode_frames(2**32 - 30 + i, rng.integers(-900, 900, (60, c)).astype(np.int16), count=n))
    elif target == "recording":
        buf = io.BytesIO()
        np.savez(buf, samples=np.zeros((40, 2), dtype=np.int16), fs=np.float64(20000), slide_start=np.array([1]), slide_stop=np.array([9]),
                 surface=np.array(["Ra1.00"]), lost=np.array([[3, 2]]), meta=np.str_("{}"))
        (corpus / "s0").write_bytes(buf.getvalue())
    elif target == "model":
        (corpus / "s0").write_bytes(default_model_path().read_bytes())
    else:
        (corpus / "s0").write_bytes((REPO / "configs" / "tactiled.toml").read_bytes())
    for case in (CASES / target).glob("*"):
        (corpus / case.name).write_bytes(case.read_bytes())


TARGETS = ["decoder", "recording", "model", "config"]


@pytest.mark.fuzz
@pytest.mark.parametrize("target", TARGETS)
def test_fuzz_target_for_a_few_seconds(tmp_path: Path, target: str) -> None:
    corpus = tmp_path / "corpus"
    _seeds(target, corpus)
    res = subprocess.run([sys.executable, str(REPO / "fuzz" / "fuzz_targets.py"), target, str(corpus), f"-max_total_time={SECONDS}",
                          "-rss_limit_mb=2048", f"-artifact_prefix={tmp_path}/"], capture_output=True, text=True, timeout=SECONDS + 120, cwd=tmp_path)
    crashes = list(tmp_path.glob("crash-*")) + list(tmp_path.glob("oom-*")) + list(tmp_path.glob("timeout-*"))
    assert res.returncode == 0 and not crashes, res.stderr[-3000:]
    assert "Done" in res.stderr or "interrupted" in res.stderr or "exiting" in res.stderr
