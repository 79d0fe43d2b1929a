"""Hostile input to the loaders: any bytes give the loader's own error, never a crash."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from tactiled.config import parse_config
from tactiled.errors import ConfigError, ModelError, RecordingError
from tactiled.files.recording import load_recording
from tactiled.learn.model import default_model_path, load_model

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


def _valid_recording() -> bytes:
    buf = io.BytesIO()
    np.savez(buf, samples=np.zeros((50, 2), dtype=np.int16), fs=np.float64(20000), slide_start=np.array([1]), slide_stop=np.array([9]),
             surface=np.array(["Ra1.00"]))
    return buf.getvalue()


RECORDING = _valid_recording()
MODEL = default_model_path().read_bytes()


def _mutate(data: bytes, cut: int, flips: list[tuple[int, int]]) -> bytes:
    b = bytearray(data[: max(1, cut % (len(data) + 1))])
    for at, x in flips:
        b[at % len(b)] ^= x
    return bytes(b)


@FUZZ
@given(cut=st.integers(0, 10**6), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=6))
def test_recording_loader_on_mutated_files(tmp_path: Path, cut: int, flips: list[tuple[int, int]]) -> None:
    path = tmp_path / "r.npz"
    path.write_bytes(_mutate(RECORDING, cut, flips))
    try:
        rec = load_recording(path)
    except RecordingError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
    else:
        assert rec.samples.ndim == 2


@FUZZ
@given(cut=st.integers(0, 10**6), flips=st.lists(st.tuples(st.integers(0, 10**6), st.integers(1, 255)), max_size=6))
def test_model_loader_on_mutated_files(tmp_path: Path, cut: int, flips: list[tuple[int, int]]) -> None:
    path = tmp_path / "m.npz"
    data = _mutate(MODEL, cut, flips)
    path.write_bytes(data)
    try:
        load_model(path)
    except ModelError as exc:
        assert str(path) in str(exc) and "\n" not in str(exc)
    else:
        assert data == MODEL or len(flips) > 0  # a flip in zip padding can leave the arrays intact


@pytest.mark.parametrize("shape", [(2**40, 2), (10**6, 2), (10,), (5, 0)])
def test_hostile_shapes_are_refused(tmp_path: Path, shape: tuple[int, ...]) -> None:
    path = tmp_path / "h.npz"
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": "<i2", "fortran_order": False, "shape": shape})
    import zipfile

    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("samples.npy", buf.getvalue())
        fs = io.BytesIO()
        np.save(fs, np.float64(20000))
        zf.writestr("fs.npy", fs.getvalue())
    with pytest.raises(RecordingError) as err:
        load_recording(path)
    assert str(path) in str(err.value)


@settings(max_examples=300, deadline=None)
@given(st.text(max_size=200))
def test_config_parser_on_any_text(text: str) -> None:
    try:
        parse_config(text, "x.toml")
    except ConfigError as exc:
        assert str(exc).startswith("x.toml: ") and "\n" not in str(exc).strip()


@settings(max_examples=200, deadline=None)
@given(st.dictionaries(st.sampled_from(["sensor", "detector", "window", "publish", "spikes"]),
                       st.dictionaries(st.sampled_from(["fs", "channels", "on_factor", "off_factor", "start_s", "endpoint", "method", "id"]),
                                       st.one_of(st.integers(-5, 10**6), st.floats(allow_nan=True), st.text(max_size=8), st.booleans()),
                                       max_size=3), max_size=3))
def test_config_values_of_any_type(tables: dict[str, dict[str, object]]) -> None:
    import tomllib

    lines = []
    for section, values in tables.items():
        lines.append(f"[{section}]")
        for k, v in values.items():
            lines.append(f"{k} = {v!r}".replace("True", "true").replace("False", "false").replace("nan", "nan"))
    text = "\n".join(lines)
    try:
        tomllib.loads(text)
    except tomllib.TOMLDecodeError:
        return
    try:
        parse_config(text, "x.toml")
    except ConfigError as exc:
        assert str(exc).startswith("x.toml: ")


CASES = Path(__file__).parent / "fuzz_cases"


def test_committed_fuzz_cases() -> None:
    """Every input a fuzzer ever crashed on, replayed through its target."""
    import runpy

    targets = runpy.run_path(str(Path(__file__).parents[1] / "fuzz" / "fuzz_targets.py"), run_name="cases")["TARGETS"]
    cases = sorted(p for p in CASES.glob("*/*") if p.is_file() and p.name != "README")
    assert cases, "the regression cases are committed under tests/fuzz_cases/"
    for case in cases:
        targets[case.parent.name](case.read_bytes())
