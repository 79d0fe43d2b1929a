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
    before that must pass). Then the model ``tactiled run`` would use with it: a ``model.path`` or ``model.shadow`` that does
    not fit the sensor's rate and channels is an error (one line), as it is for ``run``; so is no model at all (the shipped
    one not fitting and no ``model.path``), which ``run`` refuses too. With ``--no-model`` (a config for ``run --no-model``
    or for ``record``, which need none) the model is not checked, and the config's own windows and features not fitting the
    sensor (which only ``run --no-model`` uses) is a note."""
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
        model = ModelChoice(config, None if args.no_model else config.model.path or None, explicit=args.no_model, check_cost=False,
                            warn=notes.append).for_stream(s.fs, s.channels, where)
        key = "model.shadow"
        if config.model.shadow and not args.no_model:
            ModelChoice(config, config.model.shadow, explicit=True, check_cost=False).for_stream(s.fs, s.channels, where)
    except ModelError as exc:
        raise ModelError(f"{args.file}: {key}: {exc}") from None
    if model is None and not args.no_model:
        shipped = "".join(f" ({n.removeprefix('shipped model not used: ')})" for n in notes if n.startswith("shipped model not used"))
        raise ModelError(f"{args.file}: model.path: not set, and the shipped model does not fit this sensor{shipped}: tactiled run "
                         "would refuse it; train one (tactiled train) and set model.path, or check a config for record or "
                         "run --no-model with --no-model")
    if args.no_model:
        try:  # run --no-model analyses with the config's own windows and features; record needs none of them
            AnalysisSettings.from_config(config, s.channels, s.fs)
        except WindowError as exc:
            notes.append(f"run --no-model cannot analyse with this config (record can record with it): {exc}")
    print(f"{args.file}: ok" + (" (without a model)" if args.no_model else ""))
    waiting = config.serial.read_interval_s * s.fs * frame_size(s.channels, 20) / 20  # bytes between two reads, 20-sample frames
    if waiting > TTY_READ_BUFFER:
        notes.append(f"serial.read_interval_s = {config.serial.read_interval_s:g} s lets ~{waiting / 1024:.1f} KiB of frames wait between reads, "
                     f"more than the {TTY_READ_BUFFER // 1024} KiB a tty's line discipline holds: safe on a board that buffers them itself "
                     "(USB CDC-ACM) or with flow control; a USB-serial bridge without it loses the rest (docs/benchmarks.md)")
    for note in notes:
        say(f"note: {note}")
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
    p.add_argument("--no-model", action="store_true", help="a config for run --no-model or for record: check no model, only the "
                   "config's own windows and features (without it, no model that fits the sensor is an error, as for run)")

    p = command(sub, "curve-keys", "create a ZeroMQ CURVE certificate pair (NAME.key, NAME.key_secret) in DIR", cmd_curve_keys,
                "tactiled curve-keys keys/ daemon")
    p.add_argument("dir", help="folder for the certificates (created if missing)")
    p.add_argument("name", help="certificate name: NAME.key (public) and NAME.key_secret")
    p.add_argument("--force", action="store_true", help="replace an existing pair of that name")
