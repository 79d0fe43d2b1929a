"""Feature files (``tactiled features``): every analysed window of every slide, for research. ``.npz`` + JSON header, no pickle.

Arrays: ``header`` (0-d unicode JSON: ``format`` "tactiled-features", ``version``, the analysis
settings, fs, channels), ``x`` (w, F) raw features (units in docs/features.md), ``names``
(F,), and per window ``label`` (w,) ("" when unlabelled), ``file`` (w,) file number,
``slide`` (w,) slide number, ``span`` (w, 2) sample positions in its file; ``files`` (m,)
the recordings' paths.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from tactiled.config import Config
from tactiled.core.analysis import AnalysisSettings
from tactiled.errors import RecordingError, WindowError
from tactiled.files.npzio import NpzError, load_json_bounded, read_npz
from tactiled.files.recording import Recording, atomic_savez
from tactiled.learn.dataset import Progress, WindowSet, collect_windows
from tactiled.learn.train import check_recordings

FORMAT, VERSION = "tactiled-features", 1
KEYS = ("header", "x", "names", "label", "file", "slide", "span", "files")
MAX_FEATURES_BYTES = 1 << 30  # inflated, all arrays together


def write_features(path: str | Path, recs: Sequence[tuple[str, Recording]], config: Config, jobs: int | None = None,
                   progress: Progress | None = None) -> WindowSet:
    """Analyse every slide of ``recs`` with the config's feature families and windows (on ``jobs`` processes, None: every
    core; ``progress``: a line every 10 files, as ``train`` says it); write the file; return the windows. Recordings of
    differing rates or channel counts, or one given twice, are a :class:`~tactiled.errors.TactiledError` (``train``'s
    check): the windows of all are analysed with one set of bands."""
    check_recordings(recs, len(recs), "its windows would be in the table twice")
    fs, channels = recs[0][1].fs, recs[0][1].channels
    try:
        settings = AnalysisSettings.from_config(config, channels, fs)
    except WindowError as exc:  # the rate is a property of the recordings: name the first
        raise WindowError(exc.reason, f"{recs[0][0]}: {exc}") from None
    ws = collect_windows(recs, config, settings, progress, require_labels=False, jobs=jobs)
    header = {"format": FORMAT, "version": VERSION, "settings": settings.to_dict(), "fs": fs, "channels": channels}
    atomic_savez(path, {"header": np.str_(json.dumps(header)), "x": ws.x, "names": np.array(ws.names, dtype=np.str_), "label": ws.y,
                        "file": ws.groups, "slide": ws.slide, "span": ws.spans, "files": np.array(ws.files, dtype=np.str_)})
    return ws


def load_features(path: str | Path) -> dict[str, Any]:
    """The arrays of a feature file and its parsed ``header``; :class:`RecordingError` naming file and key otherwise."""
    try:
        arrays: dict[str, Any] = read_npz(path, KEYS, MAX_FEATURES_BYTES)
        missing = [k for k in KEYS if k not in arrays]
        if missing:
            raise KeyError(", ".join(missing))
        if arrays["header"].shape != () or arrays["header"].dtype.kind != "U":
            raise ValueError("header: not a string")
        header = load_json_bounded(str(arrays["header"].item()), "header")
    except KeyError as exc:
        raise RecordingError(f"{path}: not a readable feature file: missing {exc.args[0]}") from None
    except NpzError as exc:
        raise RecordingError(f"{path}: {exc.key}: {exc}" if exc.key else f"{path}: not a readable feature file: {exc}") from None
    except ValueError as exc:
        raise RecordingError(f"{path}: not a readable feature file: {exc}") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT or header.get("version") != VERSION:
        raise RecordingError(f"{path}: header: not a {FORMAT} file of version {VERSION}")
    if arrays["x"].dtype.kind != "f" or any(arrays[k].dtype.kind not in "iu" for k in ("file", "slide", "span")):
        raise RecordingError(f"{path}: x, file, slide, span: x must be floats, the others integers")
    w, f = arrays["x"].shape if arrays["x"].ndim == 2 else (-1, -1)
    if w < 0 or arrays["names"].shape != (f,) or any(arrays[k].shape[:1] != (w,) for k in ("label", "file", "slide", "span")) or arrays["span"].shape != (w, 2):
        raise RecordingError(f"{path}: x, names, label, file, slide, span: shapes disagree")
    arrays["header"] = header
    return arrays
