"""``tactiled simulate dataset|figure|serial``: the simulated fingertip."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from tactiled.cli import common as c
from tactiled.cli.common import EXIT_OK, Sub, command

MODE_HELP = "older spelling of --scene hand / --scene robot (default: the scene's)"


def cmd_dataset(args: argparse.Namespace) -> int:
    """Labelled recordings of a scene into a folder (more scenes may go beside them; the same names need --force)."""
    from tactiled.files.outputs import check_folder
    from tactiled.run.pool import map_files
    from tactiled.sim.simulate import write_dataset

    check_folder(args.out, force=True)
    paths = write_dataset(Path(args.out), scene=args.scene, seed=args.seed, surfaces=args.surfaces, files_per_surface=args.files_per_surface,
                          slides_per_file=args.slides_per_file, mode=args.mode, fs=args.fs, channels=args.channels,
                          progress=lambda msg: print(msg, file=sys.stderr), unit=args.unit, specimen=args.specimen, force=args.force,
                          mapper=lambda fn, tasks, signal_s: map_files(fn, tasks, args.jobs, signal_s=signal_s))
    print(f"{args.out}: wrote {len(paths)} recordings")
    return EXIT_OK


def cmd_figure(args: argparse.Namespace) -> int:
    """A PNG of one slide per surface class."""
    from tactiled.files.outputs import check_output
    from tactiled.sim.simulate import write_figure

    check_output(args.output, args.force, (".png",))
    write_figure(Path(args.output), args.scene, args.seed, args.mode)
    print(args.output)
    return EXIT_OK


def cmd_serial(args: argparse.Namespace) -> int:
    """A virtual board on a pty until stopped (or for --seconds)."""
    from tactiled.errors import OutputError
    from tactiled.files.outputs import check_output
    from tactiled.sim.simulate import run_virtual_board

    if args.link:  # checked before the pty opens: the link replaces only a link (a stale one of an earlier board)
        link = Path(args.link)
        if not link.parent.is_dir():
            raise OutputError(f"{link}: folder {link.parent} does not exist")
        if link.exists() and not link.is_symlink():
            raise OutputError(f"{link}: exists and is not a symlink (--link makes a symlink and replaces only a symlink)")
    if args.log:
        check_output(args.log, args.force)
    return run_virtual_board(args)


def add_commands(sub: Sub) -> None:
    """simulate dataset, simulate figure, simulate serial."""
    sim = command(sub, "simulate", "the simulated fingertip", lambda args: EXIT_OK, "tactiled simulate dataset --out data/sim --surfaces 5")
    group = sim.add_subparsers(dest="what", required=True, metavar="WHAT", help="what to simulate (each has --help)")

    p = command(group, "dataset", "write labelled recordings", cmd_dataset,
                "tactiled simulate dataset --scene robot --out data/sim --surfaces Ra0.44,Ra1.00,Ra4.43 --files-per-surface 2")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--force", action="store_true", help="replace recordings of the same names in the output folder")
    p.add_argument("--scene", type=c.scene, default=None, help=c.SCENE_HELP)
    p.add_argument("--seed", type=c.seed, default=0, help=c.SEED_HELP)
    p.add_argument("--surfaces", default=None, help=c.SURFACES_HELP)
    p.add_argument("--files-per-surface", type=c.count, default=4, help="recordings per surface")
    p.add_argument("--slides-per-file", type=c.count, default=5, help="slides per file (continuous scenes: one long slide)")
    p.add_argument("--mode", choices=("manual", "robot"), default=None, help=MODE_HELP)
    p.add_argument("--fs", type=c.positive, default=None, help="sample rate, Hz (default: the scene's, 20000 or 2200)")
    p.add_argument("--channels", type=c.channels, default=None, help="channels (default: the scene's, 2 or 1)")
    p.add_argument("--unit", type=c.seed, default=0,
                   help="which unit of the fingertip: 0 the nominal one, N another of the same model with its films' resonance, damping, "
                        "gain, cross-talk, high-pass and noise drawn within the manufacturing tolerance (docs/simulator.md)")
    p.add_argument("--specimen", type=c.seed, default=0,
                   help="which specimens of the grades: 0 the nominal ones, N new ones of the same grades (same names and nominal Ra "
                        "labels; their own Ra, correlation length and Hurst exponent drawn within the grade's tolerance; docs/simulator.md)")
    p.add_argument("--jobs", type=c.jobs, default=0, metavar="N", help=c.JOBS_HELP + " (the same files whatever N)")

    p = command(group, "figure", "PNG of one slide per surface class: signal and spectrum", cmd_figure, "tactiled simulate figure -o slides.png")
    p.add_argument("-o", "--output", required=True, help="PNG file to write")
    p.add_argument("--force", action="store_true", help=c.FORCE_HELP)
    p.add_argument("--scene", type=c.scene, default=None, help=c.SCENE_HELP)
    p.add_argument("--mode", choices=("manual", "robot"), default=None, help=MODE_HELP)
    p.add_argument("--seed", type=c.seed, default=0, help=c.SEED_HELP)

    p = command(group, "serial", "a virtual board streaming frames on a pty", cmd_serial,
                "tactiled simulate serial --link /tmp/tactile0 --drop 0.01 --unplug-at 30")
    p.add_argument("--link", help="keep this symlink pointing at the pty (removed on exit; default: none, the pty's path is printed)")
    p.add_argument("--scene", type=c.scene, default=None, help=c.SCENE_HELP)
    p.add_argument("--surfaces", default=None, help=c.SURFACES_HELP)
    p.add_argument("--mode", choices=("manual", "robot"), default=None, help=MODE_HELP)
    p.add_argument("--speed", type=c.positive, default=1.0, help="times real time")
    p.add_argument("--corrupt", type=c.probability, default=0.0, help="probability a frame is corrupted")
    p.add_argument("--drop", type=c.probability, default=0.0, help="probability a frame is dropped")
    p.add_argument("--garbage", type=c.probability, default=0.0, help="probability of garbage before a frame")
    p.add_argument("--unplug-at", default="", help="comma-separated sensor times (s) at which to unplug for --unplug-s (default: never)")
    p.add_argument("--unplug-s", type=c.positive, default=0.3, help="how long each unplug lasts, s of sensor time")
    p.add_argument("--reset-at", default="", help="comma-separated sensor times (s) at which the board resets: its index starts "
                   "again at 0 (the daemon counts a restart; default: never)")
    p.add_argument("--seconds", type=c.positive, default=None, help="stop after this much sensor time, s (default: run until stopped)")
    p.add_argument("--rest-first", type=c.number_in(0.0, 3600.0, "seconds"), default=0.0,
                   help="start with this long at rest, s, before the scene's own rests and slides (a finger put down after the "
                        "daemon is up; default: 0)")
    p.add_argument("--seed", type=c.seed, default=0, help=c.SEED_HELP)
    p.add_argument("--fs", type=c.positive, default=None, help="sample rate, Hz (default: the scene's)")
    p.add_argument("--channels", type=c.channels, default=None, help="channels (default: the scene's)")
    p.add_argument("--log", help="write one JSON line per event sent (slides, faults) to this file (default: no log)")
    p.add_argument("--force", action="store_true", help="replace an existing --log file")
