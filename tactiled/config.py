"""One config object: a TOML file read once into frozen dataclasses, validated at load.

An unknown key or a bad value is one :class:`~tactiled.errors.ConfigError` naming the key
path (``detector.on_factor: must be > detector.off_factor``). Every number is finite and
within documented bounds (the example config: ``tactiled config --example``), including the memory the ring buffer
would take; a file larger than :data:`MAX_CONFIG_BYTES` or nested too deeply is refused. CLI flags override fields
through :meth:`Config.override`; nothing else merges in.
"""

from __future__ import annotations

import dataclasses
import ipaddress
import math
import os
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

from tactiled.errors import ConfigError
from tactiled.readable import file_problem

DEFAULT_ENDPOINT = "auto"  # ipc://<runtime folder>/<sensor id>.sock (tactiled_client.endpoints); TCP is opt-in
MAX_CONFIG_BYTES = 1 << 20
MAX_KEY_FILE_BYTES = 64 << 10  # a CURVE certificate is a few hundred bytes
MAX_RING_BYTES = 1 << 30  # the ring buffer of raw samples (float64 in the worst case)
STAT_NAMES = ("mean", "sd", "energy", "rms", "skew", "kurt")


def _check(ok: bool, key: str, message: str) -> None:
    if not ok:
        raise ConfigError(f"{key}: {message}")


@dataclass(frozen=True)
class SensorConfig:
    """The sensor and its serial port."""

    id: str = "fingertip0"
    port: str = "/dev/ttyACM0"
    allow_url: bool = False
    baudrate: int = 1_000_000
    fs: float = 20_000.0
    channels: int = 2
    volts_per_count: float = 5.0 / 32768.0

    def validate(self, p: str) -> None:
        """Check id (1..64 printable, no '/'), port (a device path unless ``allow_url``), baudrate, fs (Hz), channels and volts_per_count.

        A bad value raises ConfigError naming the key (``p``: the section's name).
        """
        _check(bool(self.id) and "/" not in self.id and len(self.id.encode("utf-8")) <= 64 and self.id.isprintable(), f"{p}.id",
               "must be 1..64 printable characters (64 bytes in UTF-8), without '/'")
        _check(bool(self.port) and len(self.port) <= 4096 and "\0" not in self.port, f"{p}.port", "must be a non-empty path")
        _check(self.allow_url or "://" not in self.port, f"{p}.port",
               f"is a URL ({self.port.split('://')[0]}://), not a device path; set {p}.allow_url = true to read a pyserial URL")
        _check(50 <= self.baudrate <= 12_000_000, f"{p}.baudrate", "must be in 50..12000000")
        _check(100 <= self.fs <= 1e6, f"{p}.fs", "must be in [100, 1e6] Hz")
        _check(1 <= self.channels <= 8, f"{p}.channels", "must be in 1..8")
        _check(1e-12 <= self.volts_per_count <= 1e3, f"{p}.volts_per_count", "must be in [1e-12, 1e3]")


@dataclass(frozen=True)
class SerialConfig:
    """Reconnection of the serial source."""

    retry_initial_s: float = 0.05
    retry_max_s: float = 2.0
    read_interval_s: float = 0.01
    batch_s: float = 0.04  # the pipeline runs on batches of at least this much sensor time (CPU against latency)
    rest_batch_s: float = 0.2  # ... and of this much (at least batch_s) while no slide can be in progress (the daemon's loop wakes less)

    def validate(self, p: str) -> None:
        """Check read_interval_s, batch_s, rest_batch_s, retry_initial_s and retry_max_s (s, retry_max_s >= retry_initial_s) are in range.

        A bad value raises ConfigError naming the key (``p``: the section's name).
        """
        _check(0.001 <= self.read_interval_s <= 0.5, f"{p}.read_interval_s", "must be in [0.001, 0.5] s")
        _check(0.0 <= self.batch_s <= 1.0, f"{p}.batch_s", "must be in [0, 1] s")
        _check(0.0 <= self.rest_batch_s <= 1.0, f"{p}.rest_batch_s", "must be in [0, 1] s (below batch_s: batch_s)")
        _check(0.001 <= self.retry_initial_s <= 60, f"{p}.retry_initial_s", "must be in [0.001, 60] s")
        _check(self.retry_initial_s <= self.retry_max_s <= 600, f"{p}.retry_max_s", f"must be in [{p}.retry_initial_s, 600] s")


@dataclass(frozen=True)
class RingConfig:
    """The ring buffer of raw samples."""

    seconds: float = 20.0

    def validate(self, p: str) -> None:
        """Check seconds is in [1, 3600] s; a bad value raises ConfigError naming the key (``p``: the section's name)."""
        _check(1.0 <= self.seconds <= 3600, f"{p}.seconds", "must be in [1, 3600] s")


@dataclass(frozen=True)
class DetectorConfig:
    """Online slide detector: hysteresis on a short-time energy envelope over a tracked noise floor (tactiled/core/detect.py).

    Every threshold is a ratio of energies or a time; sample counts are derived from fs."""

    hop_ms: float = 5.0
    hop_min_samples: int = 32
    band_low_hz: float = 60.0
    band_high_hz: float = 4000.0
    band_high_frac: float = 0.45
    mains_hz: float = 50.0
    notch_q: float = 5.0  # accepted for old configs, not used (the comb replaced the notches)
    clamp_mads: float = 6.0  # accepted for old configs, not used (the median of sub-blocks replaced the clamp)
    on_factor: float = 6.0
    off_factor: float = 3.0
    off_hold_s: float = 0.3
    end_hold_s: float = 0.05  # a final label after this much quiet, withdrawn ("resumed") if the slide goes on within off_hold_s
    min_slide_s: float = 0.15
    max_slide_s: float = 0.0
    holdoff_s: float = 0.1
    floor_tau_s: float = 2.0
    initial_s: float = 0.4
    lookback_s: float = 0.2
    settle_s: float = 0.02

    def validate(self, p: str) -> None:
        """Check every time (ms, s), band edge (Hz), energy ratio and sample count is in range, band_high_hz > band_low_hz, on_factor > off_factor.

        A bad value raises ConfigError naming the key (``p``: the section's name).
        """
        _check(0.5 <= self.hop_ms <= 100, f"{p}.hop_ms", "must be in [0.5, 100] ms")
        _check(1 <= self.hop_min_samples <= 4096, f"{p}.hop_min_samples", "must be in 1..4096")
        _check(0.1 <= self.band_low_hz <= 10_000, f"{p}.band_low_hz", "must be in [0.1, 10000] Hz")
        _check(self.band_high_hz > self.band_low_hz and self.band_high_hz <= 1e6, f"{p}.band_high_hz", f"must be > {p}.band_low_hz")
        _check(0.05 <= self.band_high_frac <= 0.49, f"{p}.band_high_frac", "must be in [0.05, 0.49] (a fraction of fs)")
        _check(self.mains_hz == 0 or 40 <= self.mains_hz <= 70, f"{p}.mains_hz", "must be 0 (off) or in 40..70 Hz")
        _check(0.5 <= self.notch_q <= 100, f"{p}.notch_q", "must be in [0.5, 100]")
        _check(2 <= self.clamp_mads <= 100, f"{p}.clamp_mads", "must be in [2, 100]")
        _check(1.0 < self.off_factor <= 1e6, f"{p}.off_factor", "must be in (1, 1e6]")
        _check(self.off_factor < self.on_factor <= 1e6, f"{p}.on_factor", f"must be > {p}.off_factor (and <= 1e6)")
        _check(0 <= self.off_hold_s <= 60, f"{p}.off_hold_s", "must be in [0, 60] s")
        _check(0 <= self.end_hold_s <= 60, f"{p}.end_hold_s", "must be in [0, 60] s (0 or >= off_hold_s: labels only at the end)")
        _check(0 < self.min_slide_s <= 60, f"{p}.min_slide_s", "must be in (0, 60] s")
        _check(self.max_slide_s == 0 or self.min_slide_s < self.max_slide_s <= 86_400, f"{p}.max_slide_s",
               f"must be 0 (no limit) or in ({p}.min_slide_s, 86400] s")
        _check(0 <= self.holdoff_s <= 60, f"{p}.holdoff_s", "must be in [0, 60] s")
        _check(0.01 <= self.floor_tau_s <= 3600, f"{p}.floor_tau_s", "must be in [0.01, 3600] s")
        _check(0.005 <= self.initial_s <= 60, f"{p}.initial_s", "must be in [0.005, 60] s")
        _check(0 <= self.lookback_s <= 10, f"{p}.lookback_s", "must be in [0, 10] s")
        _check(0 <= self.settle_s <= 10, f"{p}.settle_s", "must be in [0, 10] s")


@dataclass(frozen=True)
class WindowConfig:
    """Analysis windows when no model is loaded (a model carries its own): ``duration_s`` long, the first
    ``start_s`` after the slide's start, one every ``hop_s`` (0: back to back), at most ``max_windows`` (0: all)."""

    start_s: float = 0.0
    duration_s: float = 0.5
    hop_s: float = 0.0
    max_windows: int = 0

    def validate(self, p: str) -> None:
        """Check start_s, duration_s, hop_s (s) and max_windows are in range; a bad value raises ConfigError naming the key (``p``: the section)."""
        _check(0 <= self.start_s <= 60, f"{p}.start_s", "must be in [0, 60] s")
        _check(0 < self.duration_s <= 60, f"{p}.duration_s", "must be in (0, 60] s")
        _check(0 <= self.hop_s <= 60, f"{p}.hop_s", "must be in [0, 60] s (0: hop = duration_s)")
        _check(0 <= self.max_windows <= 10_000, f"{p}.max_windows", "must be in 0..10000 (0: every window of the slide)")


@dataclass(frozen=True)
class SpikesConfig:
    """Spike (outlier) removal before feature extraction."""

    method: str = "mad"
    half_width: int = 5
    nsigma: float = 4.0

    def validate(self, p: str) -> None:
        """Check method (hampel, mad, none), half_width (samples) and nsigma; a bad value raises ConfigError naming the key (``p``: the section)."""
        _check(self.method in ("hampel", "mad", "none"), f"{p}.method", "must be one of hampel, mad, none")
        _check(1 <= self.half_width <= 1000, f"{p}.half_width", "must be in 1..1000")
        _check(0 < self.nsigma <= 1000, f"{p}.nsigma", "must be in (0, 1000]")


@dataclass(frozen=True)
class FeaturesConfig:
    """Feature families (dwt, psd, tex) computed without a model, and their settings (docs/features.md)."""

    wavelet: str = "coif5"
    level: int = 4
    mode: str = "symmetric"
    domains: tuple[str, ...] = ("time", "freq")
    stats: tuple[str, ...] = STAT_NAMES
    families: tuple[str, ...] = ("dwt", "psd", "tex")
    psd_low_hz: float = 20.0
    psd_high_frac: float = 0.45
    psd_bands_per_octave: float = 3.0

    def validate(self, p: str) -> None:
        """Check wavelet and mode (PyWavelets'), level, domains, stats, families, psd_low_hz (Hz), psd_high_frac (of fs), psd_bands_per_octave.

        A bad value raises ConfigError naming the key (``p``: the section's name).
        """
        import pywt

        _check(self.wavelet in pywt.wavelist(kind="discrete"), f"{p}.wavelet", "must be a discrete PyWavelets wavelet")
        _check(1 <= self.level <= 8, f"{p}.level", "must be in 1..8")
        _check(self.mode in pywt.Modes.modes, f"{p}.mode", f"must be one of {', '.join(pywt.Modes.modes)}")
        _check(bool(self.domains) and set(self.domains) <= {"time", "freq"}, f"{p}.domains", "must be a non-empty subset of time, freq")
        _check(bool(self.stats) and set(self.stats) <= set(STAT_NAMES), f"{p}.stats", f"must be a non-empty subset of {', '.join(STAT_NAMES)}")
        _check(bool(self.families) and set(self.families) <= {"dwt", "psd", "tex"}, f"{p}.families", "must be a non-empty subset of dwt, psd, tex")
        _check(0.1 <= self.psd_low_hz <= 10_000, f"{p}.psd_low_hz", "must be in [0.1, 10000] Hz")
        _check(0.05 <= self.psd_high_frac <= 0.5, f"{p}.psd_high_frac", "must be in [0.05, 0.5] (a fraction of fs)")
        _check(0.5 <= self.psd_bands_per_octave <= 24, f"{p}.psd_bands_per_octave", "must be in [0.5, 24]")


@dataclass(frozen=True)
class ClassifierConfig:
    """When the daemon publishes a provisional label, and when it abstains instead of publishing a label.

    ``max_saturated`` 1.0: clipped windows are labelled (their clipped fraction is in ``quality``)."""

    min_confidence: float = 0.0
    provisional_confidence: float = 0.5
    max_saturated: float = 1.0
    max_lost: float = 0.02

    def validate(self, p: str) -> None:
        """Check min_confidence, provisional_confidence, max_saturated and max_lost (fractions) are in range.

        A bad value raises ConfigError naming the key (``p``: the section's name).
        """
        _check(0.0 <= self.provisional_confidence <= 1.0, f"{p}.provisional_confidence", "must be in [0, 1] (1: no provisional labels)")
        _check(0.0 <= self.max_lost <= 0.5, f"{p}.max_lost", "must be in [0, 0.5]")
        _check(0.0 <= self.min_confidence <= 1.0, f"{p}.min_confidence", "must be in [0, 1]")
        _check(0.0 <= self.max_saturated <= 1.0, f"{p}.max_saturated", "must be in [0, 1]")


@dataclass(frozen=True)
class ModelConfig:
    """The model file; empty means the model shipped in the package. ``shadow``: a candidate model run in the shadow
    of the live one (its labels on ``shadow/<id>``, its agreement with the live ones in status); empty: none."""

    path: str = ""
    shadow: str = ""

    def validate(self, p: str) -> None:
        """Check path and shadow are paths (at most 4096 bytes, no NUL); a bad value raises ConfigError naming the key (``p``:
        the section). The files themselves are checked where a command loads them (:class:`tactiled.learn.choose.ModelChoice`,
        ``check-config``): a missing model must not stop ``record``, ``monitor``, ``run --model OTHER`` or ``--no-model``."""
        for key in ("path", "shadow"):
            value = getattr(self, key)
            _check(len(value) <= 4096 and "\0" not in value, f"{p}.{key}", "must be a path (at most 4096 bytes, no NUL)")


@dataclass(frozen=True)
class PublishConfig:
    """The ZeroMQ PUB socket."""

    endpoint: str = DEFAULT_ENDPOINT
    allow_remote: bool = False
    status_interval_s: float = 0.5
    curve_secret_key_file: str = ""
    curve_authorized_dir: str = ""
    samples: bool = False
    max_connections: int = 64  # subscriber connections at once; one more is disconnected as soon as it is accepted
    handshake_s: float = 5.0  # a connection that has not completed ZeroMQ's greeting by then is dropped (its place freed)
    socket_group: str = "tactiled"  # an ipc socket's group (mode 660), when that group exists and the daemon is in it

    def validate(self, p: str) -> None:
        """Check endpoint (``auto``, tcp://HOST:PORT or ipc://PATH, :func:`endpoint_problem`; loopback unless ``allow_remote``),
        status_interval_s and handshake_s (s), max_connections, and the CURVE key file and folder.

        The key file and folder are set together or not at all, and must exist. A bad value raises ConfigError naming the key.
        """
        _check(bool(self.curve_secret_key_file) == bool(self.curve_authorized_dir), f"{p}.curve_authorized_dir",
               f"must be set together with {p}.curve_secret_key_file")
        if self.endpoint != DEFAULT_ENDPOINT:
            problem = endpoint_problem(self.endpoint)
            _check(problem is None, f"{p}.endpoint", f"must be {DEFAULT_ENDPOINT!r}, tcp://HOST:PORT or ipc://PATH: {problem}")
        _check(0.01 <= self.status_interval_s <= 1.0, f"{p}.status_interval_s", "must be in [0.01, 1] s")
        _check(1 <= self.max_connections <= 512, f"{p}.max_connections", "must be in 1..512 (the unit's LimitNOFILE is 1024)")
        _check(0.1 <= self.handshake_s <= 60.0, f"{p}.handshake_s", "must be in [0.1, 60] s")
        _check(self.allow_remote or is_local_endpoint(self.endpoint), f"{p}.endpoint",
               "binds a non-loopback address; set publish.allow_remote = true to allow it")
        _readable_file(self.curve_secret_key_file, f"{p}.curve_secret_key_file", MAX_KEY_FILE_BYTES)
        _check(not self.curve_authorized_dir or Path(self.curve_authorized_dir).is_dir(), f"{p}.curve_authorized_dir",
               f"{self.curve_authorized_dir} is not a folder")


@dataclass(frozen=True)
class ControlConfig:
    """The daemon's control socket (``python -m tactiled_client control``): load a model, start or stop a shadow.

    Empty: none. Loopback or ipc only; with ``publish.curve_secret_key_file`` it admits the same certificates as the
    subscriptions.
    """

    endpoint: str = ""

    def validate(self, p: str) -> None:
        """Check endpoint is empty, ipc:// or a tcp:// loopback address with a port (:func:`endpoint_problem`); a bad value raises
        ConfigError naming the key (``p``: the section)."""
        if not self.endpoint:
            return
        _check(self.endpoint.startswith(("ipc://", "tcp://")) and is_local_endpoint(self.endpoint), f"{p}.endpoint",
               "must be empty, an ipc:// path or a tcp:// loopback address (the control socket is never remote)")
        problem = endpoint_problem(self.endpoint, any_port=False)
        _check(problem is None, f"{p}.endpoint", f"must be empty, ipc://PATH or tcp://HOST:PORT on loopback: {problem}")


MAX_IPC_PATH_BYTES = 107  # a Unix socket's path (sockaddr_un.sun_path less its closing NUL)
RUN_DIRS = ("/run/", "/var/run/")  # folders under these are made at boot or when a unit starts (systemd's RuntimeDirectory=)


def endpoint_problem(endpoint: str, any_port: bool = True, connect: bool = False) -> str | None:
    """Why ``endpoint`` is not one a daemon can bind (``connect``: a subscriber connect to) so that other processes reach
    it, or None: ``tcp://HOST:PORT`` with a port in 0..65535 (1..65535 to connect) (``*``: any free one, when ``any_port`` and not ``connect``;
    ZeroMQ would take a larger port modulo 65536) or ``ipc://PATH`` (at most :data:`MAX_IPC_PATH_BYTES` bytes).
    ``inproc://`` is refused: only the daemon's own process could reach it."""
    if endpoint.startswith("ipc://"):
        path = endpoint[len("ipc://"):]
        if not path:
            return "ipc:// needs a path"
        if len(path.encode("utf-8", "surrogateescape")) > MAX_IPC_PATH_BYTES:
            return f"the socket path is longer than the {MAX_IPC_PATH_BYTES} bytes a Unix socket's path may have"
        return None
    if endpoint.startswith("tcp://"):
        host, colon, port = endpoint[len("tcp://"):].rpartition(":")
        if not colon or not host or (host.endswith(":") and not host.startswith("[")):  # tcp://HOST, tcp://:7350, tcp://::1
            return "a tcp:// endpoint needs a host and a port (tcp://127.0.0.1:7350)"
        if connect and host == "*":
            return "* is every interface, where a daemon binds; a subscriber connects to one host (tcp://127.0.0.1:PORT)"
        if port == "*" and any_port and not connect:
            return None
        low = 1 if connect else 0
        if not (port.isascii() and port.isdigit() and low <= int(port) <= 65535):
            return f"port {port!r} is not a number in {low}..65535"
        return None
    if endpoint.startswith("inproc://"):
        return "an inproc:// endpoint is reachable from this process only (no subscriber could connect)"
    return f"{endpoint!r} is neither tcp:// nor ipc://"


def missing_ipc_folder(endpoint: str) -> Path | None:
    """The folder of an ``ipc://`` endpoint's socket when it does not exist, else None (not ipc, abstract, or it exists)."""
    if not endpoint.startswith("ipc://") or endpoint.startswith(("ipc://@", "ipc://*")):
        return None
    folder = Path(endpoint[len("ipc://"):]).absolute().parent
    return None if folder.is_dir() else folder


def ipc_folder_problem(endpoint: str) -> tuple[bool, str] | None:
    """For an ``ipc://`` endpoint whose folder does not exist: (fatal, why), or None (not ipc, abstract, or the folder
    exists). ``tactiled run`` cannot bind there; under /run the folder is fatal only if nothing makes it first, which
    systemd does when a unit with ``RuntimeDirectory=`` starts (``/run/tactiled``): not fatal there."""
    folder = missing_ipc_folder(endpoint)
    if folder is None:
        return None
    later = str(folder).startswith(RUN_DIRS)
    why = f"the folder {folder} does not exist: tactiled run cannot bind its socket there"
    return (not later, why + (" until something makes it (the systemd unit's RuntimeDirectory= makes /run/tactiled when it starts)"
                              if later else ""))


def same_ipc_socket(a: str, b: str) -> bool:
    """Whether two endpoints are the same ``ipc://`` socket file (a second bind would silently take the first one's over)."""
    if not (a.startswith("ipc://") and b.startswith("ipc://")):
        return False
    return os.path.normpath(os.path.abspath(a[6:])) == os.path.normpath(os.path.abspath(b[6:]))


def _readable_file(path: str, where: str, max_bytes: int) -> None:
    """A file the daemon will read must be a regular file of at most ``max_bytes`` ("" passes: not set).

    A device (``/dev/zero``) or a FIFO would be read without end, or block, when the daemon starts.
    """
    if not path:
        return
    problem = file_problem(path, max_bytes)
    _check(problem is None, where, f"{path}: {problem}")


def subscribe_endpoint(config: Config, sensor: str | None = None) -> str:
    """Where a subscriber on this machine finds the daemon of ``config``: its ``publish.endpoint``, or for ``auto`` the
    local socket of ``sensor`` (default: its sensor id; :func:`tactiled_client.endpoints.local_endpoint`)."""
    from tactiled_client.endpoints import local_endpoint

    endpoint = config.publish.endpoint
    return local_endpoint(sensor or config.sensor.id) if endpoint == DEFAULT_ENDPOINT else endpoint


def in_use(endpoint: str) -> bool:
    """Whether ``endpoint`` is an ``ipc://`` socket another process still listens on: ZeroMQ's bind would silently take it
    over (the other process's peers then reach this one). A stale socket, of a daemon that died, is not in use (the bind
    replaces it)."""
    if not (endpoint.startswith("ipc://") and Path(endpoint[6:]).is_socket()):
        return False
    import socket

    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        try:
            probe.connect(endpoint[6:])
        except OSError:
            return False  # nobody listens
    return True


def is_local_endpoint(endpoint: str) -> bool:
    """True for ``auto``, ipc://, inproc:// and tcp:// endpoints on a loopback address."""
    if endpoint == DEFAULT_ENDPOINT:
        return True
    if not endpoint.startswith("tcp://"):
        return True
    host = endpoint[len("tcp://"):].rsplit(":", 1)[0].strip("[]")
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


@dataclass(frozen=True)
class Config:
    """The whole configuration of one daemon (one sensor)."""

    sensor: SensorConfig = field(default_factory=SensorConfig)
    serial: SerialConfig = field(default_factory=SerialConfig)
    ring: RingConfig = field(default_factory=RingConfig)
    detector: DetectorConfig = field(default_factory=DetectorConfig)
    window: WindowConfig = field(default_factory=WindowConfig)
    spikes: SpikesConfig = field(default_factory=SpikesConfig)
    features: FeaturesConfig = field(default_factory=FeaturesConfig)
    classifier: ClassifierConfig = field(default_factory=ClassifierConfig)
    model: ModelConfig = field(default_factory=ModelConfig)
    publish: PublishConfig = field(default_factory=PublishConfig)
    control: ControlConfig = field(default_factory=ControlConfig)

    def validate(self) -> None:
        """Validate every section, and that the ring buffer (ring.seconds × fs × channels, float64) fits in 1 GiB.

        A bad value raises ConfigError naming the key.
        """
        for f in dataclasses.fields(self):
            getattr(self, f.name).validate(f.name)
        s = self.sensor
        if self.control.endpoint:
            _check(self.control.endpoint != self.publish.endpoint and not same_ipc_socket(self.control.endpoint, self.publish_address()),
                   "control.endpoint", f"is publish.endpoint's socket ({self.control.endpoint}): the control socket needs one of its own")
        ring_bytes = self.ring.seconds * s.fs * s.channels * 8
        _check(ring_bytes <= MAX_RING_BYTES, "ring.seconds",
               f"{self.ring.seconds:g} s of {s.channels} channels at {s.fs:g} Hz would take {ring_bytes / 2**20:.0f} MiB, more than {MAX_RING_BYTES >> 20} MiB")

    def publish_address(self) -> str:
        """The endpoint the daemon binds for ``publish.endpoint`` in this environment (``auto``: its local ipc socket)."""
        if self.publish.endpoint != DEFAULT_ENDPOINT:
            return self.publish.endpoint
        from tactiled_client.endpoints import local_socket

        return f"ipc://{local_socket(self.sensor.id)}"

    def override(self, values: dict[str, Any]) -> Config:
        """A copy with ``{"section.key": value}`` replaced (values already typed), validated."""
        sections: dict[str, dict[str, Any]] = {}
        for path, value in values.items():
            if value is None:
                continue
            section, _, key = path.partition(".")
            sections.setdefault(section, {})[key] = value
        new = dataclasses.replace(
            self, **{s: dataclasses.replace(getattr(self, s), **kv) for s, kv in sections.items()}
        )
        new.validate()
        return new


T = TypeVar("T")


def _coerce(value: Any, typ: Any, key: str) -> Any:
    if typ is bool:
        _check(isinstance(value, bool), key, "must be true or false")
        return value
    if typ is int:
        _check(isinstance(value, int) and not isinstance(value, bool) and abs(value) < 2**53, key, "must be an integer (|x| < 2**53)")
        return value
    if typ is float:
        _check(isinstance(value, (int, float)) and not isinstance(value, bool), key, "must be a number")
        _check(math.isfinite(value) and abs(value) < 1e300, key, "must be a finite number")
        return float(value)
    if typ is str:
        _check(isinstance(value, str), key, "must be a string")
        _check("\0" not in value, key, "holds a NUL character (\\u0000), which no path, endpoint or name may hold")
        return value
    if typing.get_origin(typ) is tuple:
        _check(isinstance(value, list) and len(value) <= 64 and all(isinstance(v, str) for v in value), key, "must be a list of at most 64 strings")
        return tuple(value)
    raise ConfigError(f"{key}: unsupported type")  # pragma: no cover - only our own dataclasses reach here


def _build(cls: type[T], table: Any, prefix: str) -> T:
    _check(isinstance(table, dict), prefix, "must be a table")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}  # type: ignore[arg-type]
    for key in table:
        _check(key in names, f"{prefix}.{key}" if prefix else key, "unknown key")
    kwargs = {}
    for name in names:
        if name in table:
            key = f"{prefix}.{name}" if prefix else name
            hint = hints[name]
            if isinstance(hint, type) and dataclasses.is_dataclass(hint):
                kwargs[name] = _build(hint, table[name], key)
            elif isinstance(hint, types.GenericAlias) or hint in (bool, int, float, str):
                kwargs[name] = _coerce(table[name], hint, key)
            else:
                kwargs[name] = _build(hint, table[name], key)
    return cls(**kwargs)


def parse_config(text: str, source: str = "<config>") -> Config:
    """Parse TOML text into a validated :class:`Config`; errors name ``source`` and the key path."""
    import tomllib  # here: the defaults (no --config) need no TOML parser (start-up)

    try:
        if len(text) > MAX_CONFIG_BYTES:
            raise ConfigError(f"larger than {MAX_CONFIG_BYTES} bytes")
        data = tomllib.loads(text)
        config = _build(Config, data, "")
        config.validate()
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:  # tomllib parses nested arrays and inline tables recursively
        raise ConfigError(f"{source}: not valid TOML: arrays or tables nested too deeply") from None
    except ConfigError as exc:
        raise ConfigError(f"{source}: {exc}") from None
    return config


def load_config(path: str | Path | None) -> Config:
    """Read a TOML config file (``None``: all defaults)."""
    if path is None:
        config = Config()
        config.validate()
        return config
    problem = file_problem(path, 1 << 62)  # a FIFO would block the open; the size is bounded by the read below
    if problem is not None:
        raise ConfigError(f"{path}: cannot read config: {problem}")
    try:
        with open(path, encoding="utf-8") as fh:
            text = fh.read(MAX_CONFIG_BYTES + 1)  # never more: a config path may be a device or a huge file
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read config: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path}: not UTF-8 text: {exc.reason} at byte {exc.start}") from None
    return parse_config(text, str(path))
