"""``tactiled record``, ``recover``, ``replay`` and ``export``: recordings in and out."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from tactiled.cli import common as c
from tactiled.cli.common import EXIT_FAIL, EXIT_OK, EXIT_USAGE, Sub, command, config_of, say
from tactiled.config import Config
from tactiled.errors import TactiledError

if TYPE_CHECKING:
    from tactiled.core.events import SlideResult
    from tactiled.files.recording import Recording
    from tactiled.learn.choose import ModelChoice


def _choice(args: argparse.Namespace, config: Config) -> ModelChoice:
    """The model choice of a command with --model / --no-model (and --force): --model, else the config's ``model.path``
    (as ``run`` takes it: replay --config my.toml labels with the daemon's model), else the shipped one."""
    from tactiled.learn.choose import ModelChoice

    from_config = not args.model and not args.no_model and config.model.path
    return ModelChoice(config, args.model or (config.model.path if from_config else None), explicit=args.no_model,
                       force=getattr(args, "force", False), warn=say, set_by=c.set_in_config(args, "model.path", not from_config))


def cmd_record(args: argparse.Namespace) -> int:
    """Record the port into a recording (``--format mcap``: the .npz beside it too, converted at the end).

    Everything the end needs is checked before the port opens: the outputs, and with ``--format mcap`` the ``mcap`` extra
    and the model (``--model``: it loads, fits the sensor's rate and channels, and keeps up). A recording of no sample
    writes no file and exits 1 (:meth:`~tactiled.service.recorder.RecordSummary.nothing_line`)."""
    from tactiled.extras import need
    from tactiled.files.outputs import check_output
    from tactiled.service.mcap_export import export_recording
    from tactiled.service.recorder import record

    config = config_of(args, {"sensor.port": args.port, "sensor.fs": args.fs, "sensor.volts_per_count": args.volts_per_count,
                              "sensor.channels": args.channels})
    npz = args.output if args.format == "npz" else str(Path(args.output).with_suffix(".npz"))
    check_output(args.output, args.force, (f".{args.format}",))
    choice = None
    if args.format == "mcap":
        check_output(npz, args.force)
        need("mcap.writer", "mcap")  # before the recording, not after it
        choice = _choice(args, config)
        if args.model:  # an explicit model that cannot be used is refused now (the shipped one that does not fit is said at the end)
            choice.for_stream(config.sensor.fs, config.sensor.channels, args.model)
    summary = record(config, args.seconds, npz, label=args.label, force=args.force)
    if summary.error is not None:  # a full disk: the capture stopped, the journal keeps what was written
        say(f"error: {summary.error}")
        return EXIT_FAIL
    if not summary.samples:  # the port gave nothing to record: no file, said in one line
        say(f"error: {summary.nothing_line(args.output)}")
        return EXIT_FAIL
    if choice is not None:
        counts = export_recording(npz, args.output, config, choice, force=args.force)
        print(f"{args.output}: {summary.line()}; {counts['roughness']} roughness messages; the recording stays in {npz}")
    else:
        print(f"{args.output}: {summary.line()}")
    return EXIT_OK


def cmd_recover(args: argparse.Namespace) -> int:
    """What a killed recorder left, as a recording."""
    from tactiled.files.journal import recover
    from tactiled.files.outputs import check_output

    check_output(args.output, args.force, (".npz",), [args.journal])
    try:
        result = recover(args.journal, args.output, {"recovered_from": str(args.journal)})
    except TactiledError:
        raise
    except OSError as exc:  # a full disk, an I/O error: a failure, not bad input; the journal is left as it was
        say(f"error: {exc.filename or args.output}: {exc.strerror or exc}; nothing written, the journal {args.journal} is kept")
        return EXIT_FAIL
    print(f"{args.output}: {result.line()}")
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    """A recording as an MCAP file."""
    from tactiled.service.mcap_export import export_recording

    config = config_of(args)
    counts = export_recording(args.file, args.output, config, _choice(args, config), batch=args.batch, profile=args.profile, force=args.force)
    marks = f", {counts['disconnected']} disconnections" if counts["disconnected"] else ""  # the port lost while recording
    print(f"{args.output}: {counts['samples']} samples messages, {counts['slides']} slides, {counts['roughness']} roughness messages{marks}")
    return EXIT_OK


def cmd_replay(args: argparse.Namespace) -> int:
    """Recordings and captures through the daemon's pipeline: a line (or a JSON object) per slide, a summary per file.

    Paced (``--speed``), each slide is printed as its final result stands, while the file plays; Ctrl-C there prints the
    summary of the file so far (the slides ended by then already printed) and exits 1, as a command interrupted does
    (:func:`tactiled.cli.main.main`). As fast as possible, a file's slides are printed once it has played (possibly in a
    worker process)."""
    from tactiled.run.replay import by_slide, result_record, summary_line
    from tactiled.service.replay_files import interrupted_line, replay_files

    config = config_of(args)
    summaries = sys.stderr if args.json else sys.stdout

    def show(path: str, rec: Recording, r: SlideResult, provisional: list[SlideResult], model: str) -> None:
        obj = result_record(path, rec, r, provisional, config.sensor.id, model)
        if args.json:
            print(json.dumps(obj.to_map()), flush=True)
            return
        conf = "" if r.confidence is None else f" ({r.confidence:.2f})"
        why = f" [{r.reason}]" if r.reason else ""
        truth = f", truth {obj.truth}" if obj.truth else ""
        early = f", provisional {provisional[0].label or '-'} at {provisional[0].used_s:.2f} s" if provisional else ""
        print(f"{path}: slide {r.slide_id}: {r.start}-{r.stop} ({obj.duration_s:.2f} s), {r.quality.get('windows', 0)} windows: "
              f"{r.label or '-'}{conf}{why}{early}{truth}", flush=True)

    paced = args.speed is not None
    failed = 0
    for done in replay_files(args.files, config, _choice(args, config), block=args.block, speed=args.speed, publish=args.publish,
                             wait_subscriber_s=args.wait_subscriber, samples=args.samples, jobs=args.jobs, on_slide=show if paced else None):
        if done.error is not None or done.rec is None:
            say(f"error: {done.error}")
            failed += 1
            continue
        path, rec = done.path, done.rec
        if done.interrupted_at is not None:  # Ctrl-C: what was done in this file, and no file after it
            size = rec.samples.shape[0] or None  # a capture's: not known (its recording has no samples yet)
            print(f"{path}: {interrupted_line(done.results, rec, done.interrupted_at, size, done.classes)}", file=summaries, flush=True)
            return EXIT_FAIL
        if not paced:  # paced, each slide was printed as it stood
            for r, provisional in by_slide(done.results):
                show(path, rec, r, provisional, done.model)
        print(f"{path}: {summary_line(done.results, rec, done.classes)}", file=summaries, flush=True)
    return EXIT_USAGE if failed else EXIT_OK


def add_commands(sub: Sub) -> None:
    """record, recover, export, replay."""
    p = command(sub, "record", "record serial frames into a .npz recording", cmd_record,
                "tactiled record --port /dev/ttyACM0 --seconds 60 --label P120 -o p120_01.npz")
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--port", help="serial device path " + c.overrides("sensor.port"))
    p.add_argument("--seconds", type=c.positive, required=True,
                   help="sensor time to record, s (a port that gives nothing to record is said after 5 s, and given up after "
                        "--seconds plus 30 s; if nothing was recorded when it stops, no file is written and the exit code is 1)")
    p.add_argument("-o", "--output", required=True, help="recording file to write (.npz, or .mcap with --format mcap)")
    p.add_argument("--label", help="surface of the whole file (its ground truth for train and score; default: none, the file is unlabelled)")
    p.add_argument("--fs", type=c.positive, help="sample rate, Hz " + c.overrides("sensor.fs"))
    p.add_argument("--channels", type=c.channels, help="channels " + c.overrides("sensor.channels"))
    p.add_argument("--volts-per-count", type=c.positive, help="ADC scale, V per count " + c.overrides("sensor.volts_per_count"))
    p.add_argument("--format", choices=("npz", "mcap"), default="npz",
                   help="npz recording, or MCAP: the .npz is recorded beside it (same name, kept) and converted at the end, as export does")
    p.add_argument("--model", help="with --format mcap: " + c.MODEL_HELP)
    p.add_argument("--no-model", action="store_true", help="with --format mcap: slides only, no classification")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")

    p = command(sub, "recover", "turn the journal a killed recorder left (OUTPUT.journal) into a .npz recording", cmd_recover,
                "tactiled recover p120_01.npz.journal -o p120_01.npz")
    p.add_argument("journal", help="the journal (what record -o OUT.npz or run --record OUT.npz leave as OUT.npz.journal)")
    p.add_argument("-o", "--output", required=True, help="output .npz")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")

    p = command(sub, "export", "a recording as an MCAP file (samples, ground-truth slides, labels) for Foxglove / PlotJuggler", cmd_export,
                "tactiled export p120_01.npz -o p120_01.mcap")
    p.add_argument("file", help="recording .npz")
    p.add_argument("-o", "--output", required=True, help="output .mcap")
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--model", help=c.MODEL_HELP)
    p.add_argument("--no-model", action="store_true", help="slides only, no classification")
    p.add_argument("--batch", type=c.count, default=None, help="samples per message (default 20: one board frame; 500 with --profile ros2)")
    p.add_argument("--profile", choices=("json", "ros2"), default="json",
                   help="json: JSON messages for Foxglove and PlotJuggler; ros2: a ROS 2 bag (CDR, the topics of tactiled ros2) for ros2 bag "
                        "play and rosbags (tactiled[ros2bag])")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")

    p = command(sub, "replay", "run recordings through the daemon's pipeline", cmd_replay,
                "tactiled replay --model my_model.npz data/sim/hand_Ra0.44_00.npz")
    p.add_argument("files", nargs="+", help="recordings (.npz), or raw serial captures (.bin, as run --raw writes: decoded with the "
                                            "config's sensor), one after the other")
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--json", action="store_true", help="one JSON object per slide")
    p.add_argument("--speed", type=c.positive, default=None,
                   help="pace at X times real time, each slide printed as its final result stands (Ctrl-C: the file's summary so far, "
                        "exit 1) (default: as fast as possible)")
    p.add_argument("--model", help=c.MODEL_HELP)
    p.add_argument("--no-model", action="store_true", help="no classification (labels are null)")
    p.add_argument("--publish", help="also publish the daemon's messages on this ZeroMQ endpoint: slides, labels and status (and the "
                                     "raw samples with --samples), so bridges and the monitor work on a replay as on a live sensor (default: publish nothing)")
    p.add_argument("--wait-subscriber", type=c.wait_s, default=1.0, metavar="S",
                   help="with --publish: wait up to S s for a first subscriber before sending, so that one already started misses "
                        "nothing (0: send at once)")
    p.add_argument("--samples", action="store_true", help="with --publish: also publish the raw samples on samples/<id>, as run --samples")
    p.add_argument("--block", type=c.count, default=None,
                   help="samples per block fed to the pipeline (default 65536; with --speed, about 40 ms of wall time each, as the daemon's batches)")
    p.add_argument("--jobs", type=c.jobs, default=0, metavar="N", help=c.JOBS_HELP + "; not with --speed or --publish, which play the files in turn")
    p.add_argument("--force", action="store_true", help="run a model whose analysis cannot keep up with real time (below 5x on this machine)")
