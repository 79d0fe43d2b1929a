"""Coverage-guided fuzzing (atheris) of the frame decoder and the file and config loaders.

    python fuzz/fuzz_targets.py decoder -max_total_time=600
    python fuzz/fuzz_targets.py recording -runs=100000
    python fuzz/fuzz_targets.py model ...
    python fuzz/fuzz_targets.py config ...

Each target asserts the property that must hold for any input; a crash is a bug: fix it and
commit the crashing input under tests/fuzz_cases/<target>/ (tests/test_fuzz.py replays them).
"""

from __future__ import annotations

import os
import sys
import tempfile

import atheris

with atheris.instrument_imports(include=["tactiled"]):  # our code only: instrumenting SciPy costs ~50 s
    from tactiled.board.frames import FrameDecoder
    from tactiled.config import parse_config
    from tactiled.errors import ConfigError, ModelError, RecordingError
    from tactiled.files.recording import load_recording
    from tactiled.learn.model import load_model


def _input_file() -> str:
    """A path the loaders can open, for each input in turn: an anonymous in-memory file on Linux (freed however the fuzzer
    exits: libFuzzer leaves by C ``exit``, which runs no Python cleanup), else a file in a temporary folder."""
    if hasattr(os, "memfd_create"):
        return f"/proc/self/fd/{os.memfd_create('tactiled-fuzz-input')}"
    return os.path.join(tempfile.mkdtemp(prefix="tactiled-fuzz-"), "input.npz")


_PATH = _input_file()


def decoder(data: bytes) -> None:
    """Chunking never changes the frames; frames are well formed; indices only grow."""
    whole = FrameDecoder()
    frames = whole.feed(data) + whole.flush()
    step = 1 + (data[0] % 97 if data else 0)
    chunked = FrameDecoder()
    parts = []
    for i in range(0, len(data), step):
        parts += chunked.feed(data[i:i + step])
    parts += chunked.flush()
    assert [(f.index, f.samples.tobytes()) for f in frames] == [(f.index, f.samples.tobytes()) for f in parts]
    last = -1
    for f in frames:
        assert f.samples.ndim == 2 and 1 <= f.samples.shape[1] <= 8 and 1 <= f.samples.shape[0] <= 1024
        assert f.index >= last
        last = f.index + f.samples.shape[0]
    assert whole.stats.bytes_discarded <= len(data)


def _file(data: bytes) -> str:
    with open(_PATH, "wb") as fh:  # truncates: the file holds this input only
        fh.write(data)
    return _PATH


def recording(data: bytes) -> None:
    try:
        rec = load_recording(_file(data))
    except RecordingError:
        return
    assert rec.samples.ndim == 2 and rec.fs > 0


def model(data: bytes) -> None:
    try:
        load_model(_file(data))
    except ModelError:
        return


def config(data: bytes) -> None:
    try:
        parse_config(data.decode("utf-8", "replace"), "fuzz.toml")
    except ConfigError:
        return


TARGETS = {"decoder": decoder, "recording": recording, "model": model, "config": config}

if __name__ == "__main__":
    target = TARGETS[sys.argv.pop(1)]
    atheris.Setup(sys.argv, target)
    atheris.Fuzz()
