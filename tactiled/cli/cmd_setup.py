"""``tactiled config``, ``check-config`` and ``curve-keys``: setting a sensor up."""

from __future__ import annotations

import argparse

from tactiled.cli.common import EXIT_OK, Sub, command, say
from tactiled.config import ipc_folder_problem, load_config
from tactiled.errors import ConfigError, ModelError, WindowError

TTY_READ_BUFFER = 4096  # bytes a tty's line discipline holds for its reader before it throttles the driver


def cmd_config(args: argparse.Namespace) -> int:
    """Print the example config (every key, its default and what it does), shipped inside the package."""
    from importlib import resources

    print(resources.files("tactiled").joinpath("data/tactiled.toml").read_text(encoding="utf-8"), end="")
    return EXIT_OK


def cmd_check_config(args: argparse.Namespace) -> int:
    """Load and validate a config file: ok, or one line naming the key. An ipc:// endpoint whose folder does not exist is an
    error, or a note under /run (systemd makes the unit's RuntimeDirectory, /run/tactiled, when the unit starts: a check
    before that must pass). Then the model ``tactiled run`` would use with it:
    a ``model.path`` or ``model.shadow`` that does not fit the sensor's rate and channels is an error (one line), as it is
    for ``run``; the shipped model not fitting is a note (a config for ``record`` needs no model)."""
    from tactiled.board.frames import frame_size
    from tactiled.core.analysis import AnalysisSettings
    from tactiled.learn.choose import ModelChoice

    config = load_config(args.file)
    s = config.sensor
    where = f"sensor {s.id}"
    notes: list[str] = []
    for key, endpoint in (("publish.endpoint", config.publish.endpoint), ("control.endpoint", config.control.endpoint)):
        folder = ipc_folder_problem(endpoint)  # auto: the daemon makes its runtime folder itself
        if folder is not None and folder[0]:
            raise ConfigError(f"{args.file}: {key}: {folder[1]}")
        if folder is not None:
            notes.append(f"{key}: {folder[1]}")
    key = "model.path"
    try:
        model = ModelChoice(config, config.model.path or None, check_cost=False, warn=notes.append).for_stream(s.fs, s.channels, where)
        key = "model.shadow"
        if config.model.shadow:
            ModelChoice(config, config.model.shadow, explicit=True, check_cost=False).for_stream(s.fs, s.channels, where)
    except ModelError as exc:
        raise ModelError(f"{args.file}: {key}: {exc}") from None
    print(f"{args.file}: ok")
    waiting = config.serial.read_interval_s * s.fs * frame_size(s.channels, 20) / 20  # bytes between two reads, 20-sample frames
    if waiting > TTY_READ_BUFFER:
        notes.append(f"serial.read_interval_s = {config.serial.read_interval_s:g} s lets ~{waiting / 1024:.1f} KiB of frames wait between reads, "
                     f"more than the {TTY_READ_BUFFER // 1024} KiB a tty's line discipline holds: safe on a board that buffers them itself "
                     "(USB CDC-ACM) or with flow control; a USB-serial bridge without it loses the rest (docs/benchmarks.md)")
    for note in notes:
        say(f"note: {note}")
    if model is None:
        try:  # run --no-model analyses with the config's own windows and features
            AnalysisSettings.from_config(config, s.channels, s.fs)
            no_model = "or --no-model"
        except WindowError as exc:
            no_model = f"(--no-model cannot analyse with this config: {exc})"
        say(f"note: tactiled run needs a model that fits this sensor (train one with tactiled train and set model.path) {no_model}")
    return EXIT_OK


def cmd_curve_keys(args: argparse.Namespace) -> int:
    """Create a CURVE certificate pair and print the two paths."""
    from tactiled.service.publish import create_curve_pair

    public, secret = create_curve_pair(args.dir, args.name, args.force)
    print(f"{public}\n{secret}")
    return EXIT_OK


def add_commands(sub: Sub) -> None:
    """config, check-config, curve-keys."""
    p = command(sub, "config", "print the example config (every key explained)", cmd_config, "tactiled config --example")
    p.add_argument("--example", action="store_true", required=True, help="print the example config, shipped inside the package")
    p = command(sub, "check-config", "validate a config file", cmd_check_config, "tactiled check-config configs/tactiled.toml")
    p.add_argument("file", help="TOML config file to check")

    p = command(sub, "curve-keys", "create a ZeroMQ CURVE certificate pair (NAME.key, NAME.key_secret) in DIR", cmd_curve_keys,
                "tactiled curve-keys keys/ daemon")
    p.add_argument("dir", help="folder for the certificates (created if missing)")
    p.add_argument("name", help="certificate name: NAME.key (public) and NAME.key_secret")
    p.add_argument("--force", action="store_true", help="replace an existing pair of that name")
