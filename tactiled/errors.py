"""The one exception tree of tactiled.

::

    TactiledError (Exception)
     ├── ConfigError (ValueError)        a config file or flag value is wrong
     ├── RecordingError (ValueError)     a .npz recording breaks docs/recordings.md
     ├── ModelError (ValueError)         a model file is malformed or does not fit the stream
     ├── WindowError (ValueError)        an analysis window cannot be analysed (too short, ...)
     ├── RingBufferError (LookupError)   a sample range is not in the ring buffer
     │    ├── OverwrittenError           ... because it was overwritten already
     │    └── NotYetWrittenError         ... because it has not been written yet
     ├── DeviceError (OSError)           the serial device cannot be opened or read
     └── OutputError (OSError)           an output file cannot be written there (checked before a capture)

Every message names *what* and *where* in one line, e.g.
``configs/x.toml: detector.on_factor: must be > detector.off_factor``.
Device faults are counted and recovered by the serial source, never fatal to the daemon.
"""

from __future__ import annotations


class TactiledError(Exception):
    """Base of every error tactiled raises on purpose."""


class ConfigError(TactiledError, ValueError):
    """A configuration value is missing, unknown or out of range."""


class RecordingError(TactiledError, ValueError):
    """A recording file is malformed (names the file and the key)."""


class ModelError(TactiledError, ValueError):
    """A model file is malformed, tampered with, or does not fit the stream."""


class WindowError(TactiledError, ValueError):
    """An analysis window cannot be analysed; ``reason`` is a short machine-readable code."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason

    def __reduce__(self) -> tuple[type[WindowError], tuple[str, str]]:  # raised again in the parent when a worker process raises it
        return WindowError, (self.reason, str(self))


class RingBufferError(TactiledError, LookupError):
    """A requested sample range is not available in the ring buffer."""


class OverwrittenError(RingBufferError):
    """The range was overwritten by newer samples."""


class NotYetWrittenError(RingBufferError):
    """The range lies beyond the newest sample written."""


class DeviceError(TactiledError, OSError):
    """The serial device cannot be opened or read."""


class OutputError(TactiledError, OSError):
    """An output path cannot be written (missing folder, not writable, exists, in use); names the path."""
