"""The one place that picks a file's reader by its name: ``open_recording(path)``.

- ``.bin``: a raw capture (the bytes as read from a port): :class:`~tactiled.files.capture.Capture`, decoded later
  with a config's sensor settings; a regular file of at most :data:`~tactiled.files.recording.MAX_RECORDING_BYTES`;
- ``.mcap``: a tactiled MCAP file (``tactiled export``, ``record --format mcap``; JSON profile) read back as the
  recording it holds (:func:`~tactiled.files.mcap_read.load_mcap_recording`; the ``mcap`` extra);
- anything else: an ``.npz`` recording (docs/recordings.md), checked as it loads.
"""

from __future__ import annotations

from pathlib import Path

from tactiled.errors import RecordingError
from tactiled.files.capture import Capture
from tactiled.files.recording import MAX_RECORDING_BYTES, Recording, load_recording
from tactiled.readable import file_problem


def open_recording(path: str | Path) -> Recording | Capture:
    """The recording or capture at ``path``, by its suffix (see the module docstring); :class:`RecordingError` names
    the file and what is wrong with it."""
    p = Path(path)
    suffix = p.suffix.lower()
    if suffix == ".bin":
        problem = file_problem(p, MAX_RECORDING_BYTES)
        if problem is not None:
            raise RecordingError(f"{p}: {problem}")
        return Capture(p)
    if suffix == ".mcap":
        from tactiled.files.mcap_read import load_mcap_recording

        return load_mcap_recording(p)
    return load_recording(p)
