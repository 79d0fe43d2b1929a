"""The ``tactiled`` command: a thin ``main(argv) -> int`` whose subcommands call library functions.

Exit codes: 0 ok, 1 failure, 2 usage or bad input (config, recording, model, device path).
Logging is configured here only.
"""

from __future__ import annotations

import argparse
import logging
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

from tactiled import __version__
from tactiled.config import Config, load_config
from tactiled.errors import TactiledError

log = logging.getLogger("tactiled")
EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2

Handler = Callable[[argparse.Namespace], int]


def _config(args: argparse.Namespace, overrides: dict[str, object] | None = None) -> Config:
    config = load_config(getattr(args, "config", None))
    return config.override(overrides or {})


# ---- commands ---------------------------------------------------------------------------------

def cmd_check_config(args: argparse.Namespace) -> int:
    load_config(args.file)
    print(f"{args.file}: ok")
    return EXIT_OK


def cmd_record(args: argparse.Namespace) -> int:
    from tactiled.record import record

    config = _config(args, {"sensor.port": args.port, "sensor.fs": args.fs, "sensor.volts_per_count": args.volts_per_count,
                            "sensor.channels": args.channels})
    if args.seconds <= 0:
        raise TactiledError("--seconds: must be > 0")
    summary = record(config.sensor.port, args.seconds, args.output, fs=config.sensor.fs, channels=config.sensor.channels,
                     volts_per_count=config.sensor.volts_per_count, label=args.label, baudrate=config.sensor.baudrate,
                     retry_max_s=config.serial.retry_max_s, meta={"sensor": config.sensor.id})
    print(f"{args.output}: {summary.line()}")
    return EXIT_OK


def cmd_simulate_dataset(args: argparse.Namespace) -> int:
    from tactiled.simulate import write_dataset

    paths = write_dataset(Path(args.out), seed=args.seed, surfaces=args.surfaces, files_per_surface=args.files_per_surface,
                          slides_per_file=args.slides_per_file, mode=args.mode, fs=args.fs, channels=args.channels,
                          progress=lambda msg: print(msg, file=sys.stderr))
    print(f"{args.out}: wrote {len(paths)} recordings")
    return EXIT_OK


def cmd_simulate_serial(args: argparse.Namespace) -> int:
    from tactiled.simulate import run_virtual_board

    return run_virtual_board(args)


# ---- parser -----------------------------------------------------------------------------------

def _positive_float(text: str) -> float:
    value = float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _probability(text: str) -> float:
    value = float(text)
    if not 0.0 <= value <= 1.0:
        raise argparse.ArgumentTypeError(f"must be in [0, 1], got {text}")
    return value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tactiled", description="Tactile roughness sensing daemon and toolkit.")
    parser.add_argument("--version", action="version", version=f"tactiled {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("check-config", help="validate a config file")
    p.add_argument("file")
    p.set_defaults(handler=cmd_check_config)

    p = sub.add_parser("record", help="record serial frames into a .npz recording")
    p.add_argument("--config", help="TOML config (default: built-in defaults)")
    p.add_argument("--port", help="serial device path (overrides sensor.port)")
    p.add_argument("--seconds", type=_positive_float, required=True, help="sensor time to record, s")
    p.add_argument("-o", "--output", required=True, help="output .npz")
    p.add_argument("--label", help="surface of the whole file")
    p.add_argument("--fs", type=_positive_float, help="sample rate, Hz (overrides sensor.fs)")
    p.add_argument("--channels", type=int, help="channels (overrides sensor.channels)")
    p.add_argument("--volts-per-count", type=_positive_float, help="ADC scale (overrides sensor.volts_per_count)")
    p.set_defaults(handler=cmd_record)

    sim = sub.add_parser("simulate", help="the simulated fingertip").add_subparsers(dest="what", required=True, metavar="WHAT")
    p = sim.add_parser("dataset", help="write labelled recordings")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--surfaces", default=None, help="N, or names Ra0.44,Ra1.04,… (default all 15)")
    p.add_argument("--files-per-surface", type=int, default=4)
    p.add_argument("--slides-per-file", type=int, default=5)
    p.add_argument("--mode", choices=("manual", "robot"), default="manual")
    p.add_argument("--fs", type=_positive_float, default=20_000.0)
    p.add_argument("--channels", type=int, default=2)
    p.set_defaults(handler=cmd_simulate_dataset)

    p = sim.add_parser("serial", help="a virtual board streaming frames on a pty")
    p.add_argument("--link", help="keep this symlink pointing at the pty")
    p.add_argument("--surfaces", default=None, help="N, or names (default all 15)")
    p.add_argument("--mode", choices=("manual", "robot"), default="manual")
    p.add_argument("--speed", type=_positive_float, default=1.0, help="times real time")
    p.add_argument("--corrupt", type=_probability, default=0.0, help="probability a frame is corrupted")
    p.add_argument("--drop", type=_probability, default=0.0, help="probability a frame is dropped")
    p.add_argument("--garbage", type=_probability, default=0.0, help="probability of garbage before a frame")
    p.add_argument("--unplug-at", default="", help="comma-separated sensor times (s) at which to unplug for --unplug-s")
    p.add_argument("--unplug-s", type=_positive_float, default=0.3)
    p.add_argument("--seconds", type=_positive_float, default=None, help="stop after this much sensor time")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--fs", type=_positive_float, default=20_000.0)
    p.add_argument("--channels", type=int, default=2)
    p.add_argument("--log", help="write one JSON line per event sent (slides, faults) to this file")
    p.set_defaults(handler=cmd_simulate_serial)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="tactiled: %(levelname)s: %(message)s", stream=sys.stderr)
    handler: Handler = args.handler
    try:
        return handler(args)
    except TactiledError as exc:
        print(f"tactiled: error: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt:
        return EXIT_FAIL
    except BrokenPipeError:
        return EXIT_FAIL


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
