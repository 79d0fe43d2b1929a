"""The ``tactiled`` command: a thin ``main(argv) -> int`` whose subcommands call library functions.

Exit codes: 0 ok, 1 failure, 2 usage or bad input (config, recording, model, device path).
Logging is configured here only.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NoReturn

from tactiled import __version__
from tactiled.config import Config, load_config
from tactiled.errors import TactiledError

if TYPE_CHECKING:
    from tactiled.learn.model import Model

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
    from tactiled.run.ingest import max_gap_for
    from tactiled.service.record import record

    config = _config(args, {"sensor.port": args.port, "sensor.fs": args.fs, "sensor.volts_per_count": args.volts_per_count,
                            "sensor.channels": args.channels})
    if args.seconds <= 0:
        raise TactiledError("--seconds: must be > 0")
    # --format mcap: record the .npz as usual beside the output (kept: the recording itself), then convert it as tactiled export does
    npz = args.output if args.format == "npz" else str(Path(args.output).with_suffix(".npz"))
    from tactiled.service.record import check_output

    check_output(args.output, args.force, (f".{args.format}",))
    if args.format == "mcap":
        check_output(npz, args.force)
    summary = record(config.sensor.port, args.seconds, npz, fs=config.sensor.fs, channels=config.sensor.channels,
                     volts_per_count=config.sensor.volts_per_count, label=args.label, baudrate=config.sensor.baudrate,
                     retry_max_s=config.serial.retry_max_s, meta={"sensor": config.sensor.id}, force=args.force,
                     max_gap=max_gap_for(config.ring.seconds, config.sensor.fs))
    if summary.error is not None:  # a full disk: the capture stopped, the journal keeps what was written
        print(f"tactiled: error: {summary.error}", file=sys.stderr)
        return EXIT_FAIL
    if args.format == "mcap":
        counts = _export(npz, args.output, config, args.model, explicit_model=args.no_model)
        print(f"{args.output}: {summary.line()}; {counts['roughness']} roughness messages; the recording stays in {npz}")
        return EXIT_OK
    print(f"{args.output}: {summary.line()}")
    return EXIT_OK


def cmd_recover(args: argparse.Namespace) -> int:
    from tactiled.files.journal import recover
    from tactiled.service.record import check_output

    check_output(args.output, args.force, (".npz",))
    result = recover(args.journal, args.output, {"recovered_from": str(args.journal)})
    print(f"{args.output}: {result.line()}")
    return EXIT_OK


def _export(path: str, output: str, config: Config, model_path: str | None, explicit_model: bool, batch: int | None = None,
            profile: str = "json") -> dict[str, int]:
    """Recording ``path`` → MCAP ``output``, with the pipeline's results (by the model that fits, unless ``explicit_model`` and none given)."""
    from tactiled.files.recording import load_recording
    from tactiled.run.replay import replay_recording
    from tactiled.service.mcap_export import BATCH, ROS2_BATCH, export_mcap, export_ros2_mcap

    if profile == "ros2":
        from tactiled.extras import need

        need("rosbags.typesys", "ros2bag")  # before the replay, not after it
    rec = load_recording(path)
    model = _model_for(model_path, rec.fs, rec.channels, path, explicit=explicit_model)
    results = replay_recording(rec, config, model)
    write, default = (export_ros2_mcap, ROS2_BATCH) if profile == "ros2" else (export_mcap, BATCH)
    return write(rec, output, sensor=str(rec.meta.get("sensor", config.sensor.id)), results=results,
                 model=getattr(model, "fingerprint", ""), batch=batch or default, source=path)


def cmd_export(args: argparse.Namespace) -> int:
    from tactiled.service.record import check_output

    if Path(args.output).resolve() == Path(args.file).resolve():
        raise TactiledError(f"{args.output}: is the recording being exported; write the MCAP file elsewhere")
    check_output(args.output, args.force, (".mcap",))
    counts = _export(args.file, args.output, _config(args), args.model, explicit_model=args.no_model, batch=args.batch, profile=args.profile)
    print(f"{args.output}: {counts['samples']} samples messages, {counts['slides']} slides, {counts['roughness']} roughness messages")
    return EXIT_OK


def cmd_simulate_dataset(args: argparse.Namespace) -> int:
    from tactiled.service.record import check_folder
    from tactiled.sim.simulate import write_dataset

    check_folder(args.out, force=True)  # a dataset folder takes more scenes; files of the same names need --force
    paths = write_dataset(Path(args.out), scene=args.scene, seed=args.seed, surfaces=args.surfaces, files_per_surface=args.files_per_surface,
                          slides_per_file=args.slides_per_file, mode=args.mode, fs=args.fs, channels=args.channels,
                          progress=lambda msg: print(msg, file=sys.stderr), unit=args.unit, specimen=args.specimen, force=args.force)
    print(f"{args.out}: wrote {len(paths)} recordings")
    return EXIT_OK


def cmd_simulate_figure(args: argparse.Namespace) -> int:
    from tactiled.service.record import check_output
    from tactiled.sim.simulate import write_figure

    check_output(args.output, args.force, (".png",))
    write_figure(Path(args.output), args.scene, args.seed, args.mode)
    print(args.output)
    return EXIT_OK


def cmd_simulate_serial(args: argparse.Namespace) -> int:
    from tactiled.sim.simulate import run_virtual_board

    return run_virtual_board(args)


def _model_for(path: str | None, fs: float, channels: int, where: str, explicit: bool) -> Model | None:
    """The model to use on a stream: an explicit one must fit; the shipped one is used only if it fits."""
    from tactiled.errors import ModelError
    from tactiled.learn.model import default_model_path, load_model

    if path:
        model = load_model(path)
        model.check_stream(fs, channels, where)
        return model
    if not explicit and default_model_path().exists():
        model = load_model(None)
        try:
            model.check_stream(fs, channels, where)
        except ModelError as exc:
            log.warning("shipped model not used: %s", exc)
            return None
        return model
    return None


def _say_model_settings(config: Config, model: Model) -> None:
    """One warning when the config sets analysis sections that the loaded ``model`` replaces with its own."""
    from tactiled.core.analysis import sections_a_model_overrides

    unused = sections_a_model_overrides(config)
    if not unused:
        return
    st = model.settings
    log.warning("the model analyses with its own settings (windows of %g s from %g s, spikes %s, %d features); not used with a "
                "model, only without one (--no-model): the config's %s", st.duration_s, st.start_s, st.spikes, len(st.names),
                ", ".join(f"[{s}]" for s in unused))


def _replay_capture(path: str, config: Config, args: argparse.Namespace, publisher: Any) -> tuple[list[Any], Any, Any]:
    """``replay x.bin``: raw serial bytes through the daemon's ingest core (config.sensor: fs, channels, scale)."""
    from tactiled.files.player import capture_recording_stub, read_chunks
    from tactiled.run.replay import replay_bytes

    s = config.sensor
    model = _model_for(args.model, s.fs, s.channels, path, explicit=args.no_model)
    on_event = None
    if publisher is not None:
        stub = capture_recording_stub(path, s.fs, s.channels, s.volts_per_count)
        on_event = publisher.replay_handler(s.id, stub, getattr(model, "fingerprint", ""), args.speed)
    try:
        results, rec = replay_bytes(read_chunks(path), config, model, speed=args.speed, on_event=on_event, meta={"capture": path})
    except OSError as exc:
        raise TactiledError(f"{path}: cannot read: {exc.strerror or exc}") from None
    return results, rec, model


def cmd_replay(args: argparse.Namespace) -> int:
    import json

    from tactiled.errors import RecordingError, WindowError
    from tactiled.files.recording import load_recording
    from tactiled.run.replay import BLOCK, ReplayFeed, by_slide, replay_recording, result_record, summary_line

    config = _config(args)
    failed = 0
    said = False  # the model-settings warning, once
    publisher = None
    if args.publish:
        from tactiled.service.publish import Publisher

        publisher = Publisher(config.override({"publish.endpoint": args.publish}).publish, see_subscribers=True)
        publisher.wait_subscriber(args.wait_subscriber)
    try:
        for path in args.files:
            if path.endswith(".mcap"):
                print(f"tactiled: error: {path}: an MCAP file: replay reads .npz recordings and .bin captures "
                      f"(the MCAP's labels replay with python -m tactiled_client replay {path})", file=sys.stderr)
                failed += 1
                continue
            try:
                rec = load_recording(path) if not path.endswith(".bin") else None
            except RecordingError as exc:
                print(f"tactiled: error: {exc}", file=sys.stderr)
                failed += 1
                continue
            if rec is None:  # a raw capture: through the decoder, as the daemon read it
                results, rec, model = _replay_capture(path, config, args, publisher)
            else:
                model = _model_for(args.model, rec.fs, rec.channels, path, explicit=args.no_model)
                if model is not None and not said:
                    from tactiled.learn.cost import check_speed

                    check_speed(model, args.model or "the shipped model", args.force)
                    _say_model_settings(config, model)
                    said = True
                feed = None
                if publisher is not None:  # the daemon's messages: slides and labels, status, and the samples with --samples
                    feed = ReplayFeed(publisher, config, rec, getattr(model, "fingerprint", ""), args.speed, samples=args.samples)
                try:
                    results = replay_recording(rec, config, model, block=args.block or BLOCK, speed=args.speed,
                                               on_event=feed.event if feed else None, on_block=feed.block if feed else None)
                    if feed:
                        feed.finish(last=path == args.files[-1])
                except WindowError as exc:  # this file's rate or windows cannot be analysed: say which, go on with the others
                    print(f"tactiled: error: {path}: {exc}", file=sys.stderr)
                    failed += 1
                    continue
            for r, provisional in by_slide(results):
                obj = result_record(path, rec, r, provisional, config.sensor.id, getattr(model, "fingerprint", ""))
                if args.json:
                    print(json.dumps(obj.to_map()), flush=True)
                else:
                    conf = "" if r.confidence is None else f" ({r.confidence:.2f})"
                    why = f" [{r.reason}]" if r.reason else ""
                    truth = f", truth {obj.truth}" if obj.truth else ""
                    early = f", provisional {provisional[0].label or '-'} at {provisional[0].used_s:.2f} s" if provisional else ""
                    print(f"{path}: slide {r.slide_id}: {r.start}-{r.stop} ({obj.duration_s:.2f} s), {r.quality.get('windows', 0)} windows: "
                          f"{r.label or '-'}{conf}{why}{early}{truth}", flush=True)
            print(f"{path}: {summary_line(results, rec)}", file=sys.stderr if args.json else sys.stdout, flush=True)
    finally:
        if publisher is not None:
            publisher.close()
    return EXIT_USAGE if failed else EXIT_OK


def cmd_features(args: argparse.Namespace) -> int:
    from tactiled.learn.dataset import load_recordings
    from tactiled.learn.features_file import write_features
    from tactiled.service.record import check_output

    config = _config(args)
    check_output(args.output, args.force, (".npz",))  # before every window is analysed, not after
    recs = load_recordings(args.files, _stderr)
    if not recs:
        raise TactiledError("no readable recordings")
    ws = write_features(args.output, recs, config, args.jobs)
    print(f"{args.output}: {ws.x.shape[0]} windows of {len(ws.slides)} slides x {ws.x.shape[1]} features"
          + (f" (slides without a window: {ws.skipped})" if ws.skipped else ""))
    return EXIT_OK if len(recs) == len(args.files) else EXIT_USAGE


def _stderr(msg: str) -> None:
    print(f"tactiled: {msg}", file=sys.stderr, flush=True)


def _files_done(what: str) -> Callable[[int, int], None]:
    """Progress over files on one line of stderr (rewritten in place on a terminal; only the last count otherwise)."""
    tty = sys.stderr.isatty()

    def done(i: int, n: int) -> None:
        if tty or i == n:
            print(f"\r{what}: {i}/{n} files", end="\n" if i == n else "", file=sys.stderr, flush=True)
    return done


def cmd_train(args: argparse.Namespace) -> int:
    from tactiled.learn.train import train
    from tactiled.service.record import check_output

    config = _config(args)
    check_output(args.output, args.force, (".npz",))  # before minutes of search, not after
    result = train(args.files, config, method=args.method, folds=args.folds, seed=args.seed, min_slides=args.min_slides, drop_rare=args.drop_rare,
                   scheduler=args.scheduler, progress=lambda m: print(f"train: {m}", file=sys.stderr, flush=True), group_by=args.group_by)
    print("leaderboard (slide accuracy, grouped by file: mean ± sd over folds; * the choice, the simplest within one standard error of the best):")
    width = max(len(row["candidate"]) for row in result.leaderboard)
    for row in result.leaderboard:
        mark = "*" if row.get("chosen") else " "
        print(f"{mark} {row['candidate']:<{width}s} {100 * row['mean']:5.1f} ± {100 * row['sd']:4.1f} %")
    cal, nov = result.model.summary.get("calibration", {}), result.model.summary.get("novelty", {})
    if cal:
        print(f"confidence: calibrated ({cal['method']}) on {cal['slides']} out-of-fold slides")
    if nov.get("threshold") is not None:
        print(f"unknown surfaces: by cross-validation, {100 * nov['known_rejected']:.1f} % of slides of known surfaces are called unknown, "
              + (f"{100 * nov['unseen_flagged']:.1f} % of slides of a surface left out of training" if nov.get("unseen_flagged") is not None
                 else "and no surface could be left out to test it"))
    fingerprint = result.model.save(args.output)
    print(f"{args.output}: {result.model.describe()}; fingerprint {fingerprint}")
    return EXIT_OK


def cmd_score(args: argparse.Namespace) -> int:
    import json

    from tactiled.learn.dataset import load_recordings
    from tactiled.learn.model import load_model
    from tactiled.learn.score import score_recordings

    config = _config(args)
    model = load_model(args.model)
    recs = load_recordings(args.files, _stderr)
    for name, rec in recs:
        model.check_stream(rec.fs, rec.channels, name)
    scored = [(n, r) for n, r in recs if r.slides() or r.label is not None]
    if not scored:
        raise TactiledError("no recording with ground truth (per-slide surfaces or a file label) to score")
    report = score_recordings(scored, config, model, args.jobs, _files_done("score"))
    if args.json:
        print(json.dumps(report))
    else:
        print(f"accuracy {report['accuracy']:.4f} ({report['correct']} of {report['n']} true slides); coverage {report['coverage']:.4f} "
              f"({report['labelled']} labelled); accuracy of the labelled {report['accuracy_of_labelled']:.4f}")
        if report["abstained"]:
            print("no label: " + ", ".join(f"{k} {v}" for k, v in sorted(report["abstained"].items())))
        print(f"unknown surfaces: {report['unknown']} of {report['n']} true slides")
        if report["ece"] is not None:
            print(f"confidence: expected calibration error {report['ece']:.3f} (10 bins), Brier score {report['brier']:.3f}")
        if report["unpaired_detections"]:
            print(f"detections outside any true slide: {report['unpaired_detections']}")
        for c, r in report["recall"].items():
            print(f"  {c:>12s}: recall {r:.3f}")
    return EXIT_OK if len(recs) == len(args.files) else EXIT_USAGE


def cmd_run(args: argparse.Namespace) -> int:
    import asyncio

    from tactiled.service.daemon import Daemon

    config = _config(args, {"sensor.port": args.port, "sensor.id": args.sensor_id, "publish.endpoint": args.publish,
                            "model.path": args.model, "publish.samples": True if args.samples else None, "model.shadow": args.shadow})
    model = None
    if not args.no_model:
        model = _model_for(config.model.path or None, config.sensor.fs, config.sensor.channels, f"sensor {config.sensor.id}",
                           explicit=bool(config.model.path))
        if model is None:
            raise TactiledError("no model fits this sensor (train one with tactiled train, or pass --no-model)")
        _say_model_settings(config, model)
    from tactiled.learn.model import default_model_path

    model_path = None if model is None else (config.model.path or str(default_model_path()))  # what SIGHUP (systemctl reload) loads again
    shadow = _model_for(config.model.shadow, config.sensor.fs, config.sensor.channels, f"sensor {config.sensor.id}",
                        explicit=True) if config.model.shadow else None

    from tactiled.service.record import check_output

    for out, suffix in ((args.record, ".npz"), (args.raw, ".bin")):
        if out:
            check_output(out, args.force, (suffix,))  # before the port opens: never replace a file (or write a device) unasked
    if args.no_wait:
        from tactiled.board.serialsource import check_port

        check_port(config.sensor.port)

    async def main() -> None:
        daemon = Daemon(config, model, args.record, raw_to=args.raw, model_path=model_path, force=args.force,  # type: ignore[arg-type]
                        shadow=shadow)
        print(f"tactiled: sensor {config.sensor.id} on {config.sensor.port}, publishing on {daemon.endpoint}", file=sys.stderr, flush=True)
        await daemon.run()

    asyncio.run(main())
    return EXIT_OK


def cmd_monitor(args: argparse.Namespace) -> int:
    from tactiled.apps.monitor import run_monitor

    endpoint = args.connect or _config(args).publish.endpoint
    return run_monitor(endpoint, args.truth)


def cmd_lsl(args: argparse.Namespace) -> int:
    from tactiled.apps.bridges.cli import serve

    return serve("lsl", _config(args), args.connect, args.sensor_id, nan_lost=args.nan_lost)


def cmd_ros2(args: argparse.Namespace) -> int:
    from tactiled.apps.bridges.cli import serve

    return serve("ros2", _config(args), args.connect, args.sensor_id, ros_args=args.ros_args)


def cmd_demo(args: argparse.Namespace) -> int:
    """Virtual board on a pty + daemon with the shipped model + monitor (or, headless, label lines for ``--seconds``)."""
    import subprocess
    import tempfile

    from tactiled.apps.monitor import run_monitor
    from tactiled.sim.simulate import scene_for

    if args.seconds is not None and not args.headless:
        raise TactiledError("--seconds needs --headless")
    scene_for(args.scene)  # an unknown scene is one line now, not a board that never starts
    with tempfile.TemporaryDirectory(prefix="tactiled-demo-") as tmp:
        link, board_log = f"{tmp}/tty", f"{tmp}/board.jsonl"
        endpoint = args.publish or f"ipc://{tmp}/pub"
        exe = [sys.executable, "-m", "tactiled"]
        board = subprocess.Popen([*exe, "simulate", "serial", "--link", link, "--scene", args.scene, "--seed", str(args.seed), "--log", board_log],
                                 stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        assert board.stdout is not None
        board.stdout.readline()  # the device path: the pty exists from here on
        daemon = subprocess.Popen([*exe, "run", "--port", link, "--publish", endpoint, "--samples"], stderr=open(f"{tmp}/daemon.log", "w"))  # noqa: SIM115
        try:
            if args.headless:
                return _headless(endpoint, args.seconds if args.seconds is not None else 20.0, board_log, f"{tmp}/daemon.log")
            return run_monitor(endpoint, board_log)  # the simulator's log: the true surface of every slide
        finally:
            for proc in (daemon, board):
                proc.terminate()
                proc.wait(5)


def _headless(endpoint: str, seconds: float, board_log: str, daemon_log: str) -> int:
    """Print one line per label for ``seconds`` (wall time), with the true surface from the virtual board's log; 0 if labels came."""
    import time

    from tactiled_client import BlockingSubscriber, NoData, Roughness
    from tactiled_client.truth import overlapping

    from tactiled.apps.monitor import read_truth

    def truth(start: int, stop: int) -> str:
        return overlapping(read_truth(board_log), start, stop) or "?"

    labels = 0
    deadline = time.monotonic() + seconds
    with BlockingSubscriber(endpoint, topics=["roughness"], timeout=1.0) as sub:
        while time.monotonic() < deadline:
            try:
                msg = sub.receive(timeout=min(1.0, max(0.01, deadline - time.monotonic())))
            except NoData:
                continue
            if not isinstance(msg, Roughness):
                continue
            kind = "final" if msg.final else f"provisional after {msg.used_s:.2f} s"
            why = f" [{msg.reason}]" if msg.reason else ""
            print(f"slide {msg.slide_id}: {msg.label or '-'} ({msg.confidence or 0:.2f}, {kind}){why}, true surface {truth(msg.start, msg.stop)}",
                  flush=True)
            labels += bool(msg.final and msg.label)
    if not labels:
        print(f"tactiled: no label in {seconds:g} s; daemon log: {daemon_log}", file=sys.stderr)
        return EXIT_FAIL
    return EXIT_OK


def cmd_evaluate(args: argparse.Namespace) -> int:
    from tactiled.learn.dataset import load_recordings
    from tactiled.learn.evaluate import run_evaluation
    from tactiled.service.record import check_folder

    config = _config(args)
    check_folder(args.report, args.force)  # before minutes of experiments, not after
    readable = load_recordings(args.files, _stderr)
    recs = [(n, r) for n, r in readable if r.slides()]
    if len(recs) < 2:
        raise TactiledError("evaluation needs at least two readable recordings with ground-truth slides")
    if len({(r.fs, r.channels) for _, r in recs}) != 1:
        raise TactiledError("recordings differ in fs or channels; evaluate one kind at a time")
    results = run_evaluation(recs, config, Path(args.report), experiments=args.experiments, folds=args.folds, quick=args.quick, seed=args.seed,
                             progress=lambda m: print(f"evaluate: {m}", file=sys.stderr, flush=True))
    print(f"{Path(args.report) / 'report.md'}: {len(recs)} recordings, {results['seconds']:.0f} s")
    return EXIT_OK if len(readable) == len(args.files) else EXIT_USAGE  # as features and score: the skipped files were named


def cmd_curve_keys(args: argparse.Namespace) -> int:
    import zmq.auth

    from tactiled.service.record import check_folder, check_output

    out = Path(args.dir)
    check_folder(out, force=True)  # a folder of keys: another name goes beside the others
    if out.is_dir():
        for name in (f"{args.name}.key", f"{args.name}.key_secret"):
            check_output(out / name, args.force)
    try:
        out.mkdir(parents=True, exist_ok=True)
        public, secret = zmq.auth.create_certificates(str(out), args.name)
    except OSError as exc:
        raise TactiledError(f"{out}: cannot write the certificates: {exc.strerror or exc}") from None
    print(f"{public}\n{secret}")
    return EXIT_OK


# ---- parser -----------------------------------------------------------------------------------

class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help that shows each option's default (when it has a value worth showing) and keeps examples as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "default" in text or action.default is None or action.default is False or action.default in ("", argparse.SUPPRESS) \
                or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """An argument parser whose help shows defaults and whose errors are one line (subcommands inherit both)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}{_did_you_mean(message, self)} (see {self.prog} --help)\n")

    def parse_args(self, args: Sequence[str] | None = None, namespace: Any = None) -> Any:  # type: ignore[override]
        """As argparse, but an unknown option is reported by the subcommand it was given to, with the closest one it has."""
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            words = [a for a in (sys.argv[1:] if args is None else list(args)) if not a.startswith("-")]
            known = subcommands(self)
            chosen = max((k for k in known if k and words[:len(k.split())] == k.split()), key=len, default="")
            known[chosen].error(f"unrecognized argument{'s' if len(extras) > 1 else ''}: {' '.join(extras)}")
        return ns


def _did_you_mean(message: str, parser: argparse.ArgumentParser) -> str:
    """"; did you mean X?" for an unknown option or subcommand close to one that exists, else ""."""
    import difflib
    import re

    unknown = re.match(r"unrecognized arguments?: (\S+)", message)
    choice = re.match(r"argument \S+: invalid choice: '([^']*)' \(choose from (.*)\)", message)
    if unknown:
        word = unknown.group(1).split("=")[0]
        options = [o for a in parser._actions for o in a.option_strings]
    elif choice:
        word, options = choice.group(1), re.findall(r"'([^']*)'", choice.group(2))
    else:
        return ""
    close = difflib.get_close_matches(word, options, n=1, cutoff=0.6)
    return f"; did you mean {close[0]}?" if close else ""


EXPERIMENTS = "abcdefg"


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def _positive_float(text: str) -> float:
    value = _float(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def _float_in(low: float, high: float, name: str) -> Callable[[str], float]:
    """An argparse type: a number in ``[low, high]``."""

    def parse(text: str) -> float:
        value = _float(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in [{low:g}, {high:g}], got {text}")
        return value

    parse.__name__ = name
    return parse


def _int_in(low: int, high: int = 2**31) -> Callable[[str], int]:
    """An argparse type: an integer in ``low..high`` (an upper bound keeps every count and seed a machine integer)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be an integer {'>= ' + str(low) if value < low else '<= ' + str(high)}, got {text}")
        return value

    parse.__name__ = f"integer in {low}..{high}"
    return parse


def _scene(text: str) -> str:
    """A scene, or scenes joined by commas, that the simulator knows (checked when given: the simulator loads lazily)."""
    from tactiled.sim.sensor_model import parse_scene

    try:
        parse_scene(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--scene: ")) from None
    return text


def _experiments(text: str) -> str:
    unknown = sorted(set(text) - set(EXPERIMENTS))
    if unknown or not text:
        raise argparse.ArgumentTypeError(f"letters from {EXPERIMENTS} expected, got {text!r}")
    return text


_float.__name__ = "number"
_positive_float.__name__ = "number > 0"
_experiments.__name__ = "experiment letters"
_scene.__name__ = "scene"
_count, _seed, _channels = _int_in(1), _int_in(0, 2**32 - 1), _int_in(1, 8)
_probability, _wait_s = _float_in(0.0, 1.0, "probability"), _float_in(0.0, 3600.0, "seconds")

CONFIG_HELP = "TOML config file (every key is explained in configs/tactiled.toml; default: the built-in defaults)"
JOBS_HELP = "worker processes over the files (default 0: one per core; 1: in this process)"
SCENE_HELP = ("scene, or scenes joined by commas: hand (default), robot, continuous, fluctuating, hot-gain, one-channel, grating "
              "(docs/simulator.md), e.g. continuous,one-channel")
SURFACES_HELP = ("N surfaces spread over the range, or names such as Ra0.44,Ra4.43 (the grating scene: G0.10mm,G1.00mm) "
                 "(default: all 15)")
CONNECT_HELP = "daemon endpoint to subscribe to (default: publish.endpoint of --config, or the built-in default)"
SEED_HELP = "random seed"
MODEL_HELP = "model file (default: the shipped model, when it fits the recording's rate and channels)"

OUTPUT_POLICY = """\
Outputs: every command that writes checks, before any work, that the folder exists and is
writable, that a file's name ends as it should (.npz, .mcap, .bin, .png), and that it replaces
nothing: an existing file (a dataset's recordings of the same names, a certificate pair of the same
name), or a report folder that is not empty, needs --force. Each failure is one line and exit 2."""

# every command's example, shown at the end of its --help (keys: the command's words after "tactiled")
EXAMPLES: dict[str, str] = {
    "": "tactiled demo --headless --seconds 20",
    "check-config": "tactiled check-config configs/tactiled.toml",
    "record": "tactiled record --port /dev/ttyACM0 --seconds 60 --label P120 -o p120_01.npz",
    "recover": "tactiled recover p120_01.npz.journal -o p120_01.npz",
    "export": "tactiled export p120_01.npz -o p120_01.mcap",
    "simulate": "tactiled simulate dataset --out data/sim --surfaces 5",
    "simulate dataset": "tactiled simulate dataset --scene robot --out data/sim --surfaces Ra0.44,Ra1.00,Ra4.43 --files-per-surface 2",
    "simulate figure": "tactiled simulate figure -o slides.png",
    "simulate serial": "tactiled simulate serial --link /tmp/tactile0 --drop 0.01 --unplug-at 30",
    "run": "tactiled run --config my.toml --model my_model.npz",
    "curve-keys": "tactiled curve-keys keys/ daemon",
    "monitor": "tactiled monitor --connect tcp://127.0.0.1:7350",
    "lsl": "tactiled lsl --connect tcp://127.0.0.1:7350",
    "ros2": "tactiled ros2 --connect tcp://127.0.0.1:7350 --sensor-id fingertip0 --ros-args -r __ns:=/robot1",
    "demo": "tactiled demo --scene robot",
    "replay": "tactiled replay --model my_model.npz data/sim/hand_Ra0.44_00.npz",
    "features": "tactiled features data/sim/*.npz -o features.npz",
    "train": "tactiled train data/sim/*.npz -o my_model.npz",
    "evaluate": "tactiled evaluate data/sim/*.npz --report report/",
    "score": "tactiled score my_model.npz held_out/*.npz",
}


def build_parser() -> argparse.ArgumentParser:
    parser = Parser(prog="tactiled", description="Tactile roughness sensing daemon and toolkit.\n\n" + OUTPUT_POLICY)
    parser.add_argument("--version", action="version", version=f"tactiled {__version__}")
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output (-vv for debug)")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND", help="what to do (each command has --help)")

    p = sub.add_parser("check-config", help="validate a config file")
    p.add_argument("file", help="TOML config file to check")
    p.set_defaults(handler=cmd_check_config)

    p = sub.add_parser("record", help="record serial frames into a .npz recording")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--port", help="serial device path (overrides sensor.port)")
    p.add_argument("--seconds", type=_positive_float, required=True, help="sensor time to record, s")
    p.add_argument("-o", "--output", required=True, help="recording file to write (.npz, or .mcap with --format mcap)")
    p.add_argument("--label", help="surface of the whole file (its ground truth for train and score)")
    p.add_argument("--fs", type=_positive_float, help="sample rate, Hz (overrides sensor.fs)")
    p.add_argument("--channels", type=_channels, help="channels (overrides sensor.channels)")
    p.add_argument("--volts-per-count", type=_positive_float, help="ADC scale, V per count (overrides sensor.volts_per_count)")
    p.add_argument("--format", choices=("npz", "mcap"), default="npz",
                   help="npz recording, or MCAP: the .npz is recorded beside it (same name, kept) and converted at the end, as export does")
    p.add_argument("--model", help="with --format mcap: " + MODEL_HELP)
    p.add_argument("--no-model", action="store_true", help="with --format mcap: slides only, no classification")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(handler=cmd_record)

    p = sub.add_parser("recover", help="turn the journal a killed recorder left (OUTPUT.journal) into a .npz recording")
    p.add_argument("journal", help="the journal (what record -o OUT.npz or run --record OUT.npz leave as OUT.npz.journal)")
    p.add_argument("-o", "--output", required=True, help="output .npz")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(handler=cmd_recover)

    p = sub.add_parser("export", help="a recording as an MCAP file (samples, ground-truth slides, labels) for Foxglove / PlotJuggler")
    p.add_argument("file", help="recording .npz")
    p.add_argument("-o", "--output", required=True, help="output .mcap")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--model", help=MODEL_HELP)
    p.add_argument("--no-model", action="store_true", help="slides only, no classification")
    p.add_argument("--batch", type=_count, default=None, help="samples per message (default 20: one board frame; 500 with --profile ros2)")
    p.add_argument("--profile", choices=("json", "ros2"), default="json",
                   help="json: JSON messages for Foxglove and PlotJuggler; ros2: a ROS 2 bag (CDR, the topics of tactiled ros2) for ros2 bag "
                        "play and rosbags (tactiled[ros2bag])")
    p.add_argument("--force", action="store_true", help="overwrite an existing output file")
    p.set_defaults(handler=cmd_export)

    sim = sub.add_parser("simulate", help="the simulated fingertip").add_subparsers(dest="what", required=True, metavar="WHAT",
                                                                                   help="what to simulate (each has --help)")
    p = sim.add_parser("dataset", help="write labelled recordings")
    p.add_argument("--out", required=True, help="output folder")
    p.add_argument("--force", action="store_true", help="replace recordings of the same names in the output folder")
    p.add_argument("--scene", type=_scene, default=None, help=SCENE_HELP)
    p.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    p.add_argument("--surfaces", default=None, help=SURFACES_HELP)
    p.add_argument("--files-per-surface", type=_count, default=4, help="recordings per surface")
    p.add_argument("--slides-per-file", type=_count, default=5, help="slides per file (continuous scenes: one long slide)")
    p.add_argument("--mode", choices=("manual", "robot"), default=None, help="older spelling of --scene hand / --scene robot")
    p.add_argument("--fs", type=_positive_float, default=None, help="sample rate, Hz (default: the scene's, 20000 or 2200)")
    p.add_argument("--channels", type=_channels, default=None, help="channels (default: the scene's, 2 or 1)")
    p.add_argument("--unit", type=_seed, default=0,
                   help="which unit of the fingertip: 0 the nominal one, N another of the same model with its films' resonance, damping, "
                        "gain, cross-talk, high-pass and noise drawn within the manufacturing tolerance (docs/simulator.md)")
    p.add_argument("--specimen", type=_seed, default=0,
                   help="which specimens of the grades: 0 the nominal ones, N new ones of the same grades (same names and nominal Ra "
                        "labels; their own Ra, correlation length and Hurst exponent drawn within the grade's tolerance; docs/simulator.md)")
    p.set_defaults(handler=cmd_simulate_dataset)

    p = sim.add_parser("figure", help="PNG of one slide per surface class: signal and spectrum")
    p.add_argument("-o", "--output", required=True, help="PNG file to write")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--scene", type=_scene, default=None, help=SCENE_HELP)
    p.add_argument("--mode", choices=("manual", "robot"), default=None, help="older spelling of --scene hand / --scene robot")
    p.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    p.set_defaults(handler=cmd_simulate_figure)

    p = sim.add_parser("serial", help="a virtual board streaming frames on a pty")
    p.add_argument("--link", help="keep this symlink pointing at the pty (removed on exit)")
    p.add_argument("--scene", type=_scene, default=None, help=SCENE_HELP)
    p.add_argument("--surfaces", default=None, help=SURFACES_HELP)
    p.add_argument("--mode", choices=("manual", "robot"), default=None, help="older spelling of --scene hand / --scene robot")
    p.add_argument("--speed", type=_positive_float, default=1.0, help="times real time")
    p.add_argument("--corrupt", type=_probability, default=0.0, help="probability a frame is corrupted")
    p.add_argument("--drop", type=_probability, default=0.0, help="probability a frame is dropped")
    p.add_argument("--garbage", type=_probability, default=0.0, help="probability of garbage before a frame")
    p.add_argument("--unplug-at", default="", help="comma-separated sensor times (s) at which to unplug for --unplug-s")
    p.add_argument("--unplug-s", type=_positive_float, default=0.3, help="how long each unplug lasts, s of sensor time")
    p.add_argument("--seconds", type=_positive_float, default=None, help="stop after this much sensor time, s (default: run until stopped)")
    p.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    p.add_argument("--fs", type=_positive_float, default=None, help="sample rate, Hz (default: the scene's)")
    p.add_argument("--channels", type=_channels, default=None, help="channels (default: the scene's)")
    p.add_argument("--log", help="write one JSON line per event sent (slides, faults) to this file")
    p.set_defaults(handler=cmd_simulate_serial)
    p = sub.add_parser("run", help="the daemon: serial port -> roughness labels over ZeroMQ")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--port", help="serial device (overrides sensor.port)")
    p.add_argument("--model", help="model file (overrides model.path; default: the shipped model)")
    p.add_argument("--no-model", action="store_true", help="publish slides and status only")
    p.add_argument("--shadow", metavar="MODEL", help="a candidate model to run in the shadow of the live one (overrides model.shadow): its "
                                                     "labels on shadow/<id>, never as the live ones; status.shadow says how often they agree")
    p.add_argument("--publish", help="ZeroMQ endpoint to bind (overrides publish.endpoint)")
    p.add_argument("--sensor-id", help="sensor id in topics (overrides sensor.id)")
    p.add_argument("--record", help="also write every sample received to this .npz, streamed to disk as OUT.npz.journal (tactiled recover) "
                   "and converted on exit (an existing file needs --force)")
    p.add_argument("--samples", action="store_true", help="also publish the raw samples on samples/<id> (sets publish.samples)")
    p.add_argument("--raw", metavar="OUT.bin", help="also write every byte read from the port, as read (replay it with tactiled replay OUT.bin)")
    p.add_argument("--no-wait", action="store_true", help="exit 2 at once if the serial device is missing (default: wait for it)")
    p.add_argument("--force", action="store_true", help="let --record and --raw replace existing files, and run a model whose analysis "
                                                        "cannot keep up with the sensor (below 5x real time on this machine)")
    p.set_defaults(handler=cmd_run)

    p = sub.add_parser("curve-keys", help="create a ZeroMQ CURVE certificate pair (NAME.key, NAME.key_secret) in DIR")
    p.add_argument("dir", help="folder for the certificates (created if missing)")
    p.add_argument("name", help="certificate name: NAME.key (public) and NAME.key_secret")
    p.add_argument("--force", action="store_true", help="replace an existing pair of that name")
    p.set_defaults(handler=cmd_curve_keys)

    p = sub.add_parser("monitor", help="terminal view of a running daemon")
    p.add_argument("--connect", help=CONNECT_HELP)
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--truth", help="a virtual board's log (simulate serial --log): show the true surface of each slide")
    p.set_defaults(handler=cmd_monitor)

    for name, help_, handler in (("lsl", "Lab Streaming Layer outlets of a daemon's raw samples and labels (tactiled[lsl])", cmd_lsl),
                                 ("ros2", "ROS 2 topics of a daemon's labels, status and raw samples (tactiled[ros2])", cmd_ros2)):
        p = sub.add_parser(name, help=help_)
        p.add_argument("--connect", help=CONNECT_HELP)
        p.add_argument("--config", help=CONFIG_HELP)
        p.add_argument("--sensor-id", help="sensor to bridge (default: sensor.id of --config)")
        if name == "lsl":
            p.add_argument("--nan-lost", action="store_true", help="push lost samples as NaN rows (a regular stream); each lost range "
                                                                   "is a marker either way")
        else:
            p.add_argument("--ros-args", nargs=argparse.REMAINDER, default=None, metavar="ARG",
                           help="the rest goes to ROS: -r __ns:=/robot1, -r __node:=NAME, -r FROM:=TO, -p endpoint:=…, -p sensor_id:=…, "
                                "-p frame_id:=…, --params-file F (docs/integrations.md)")
        p.set_defaults(handler=handler)

    p = sub.add_parser("demo", help="simulated sensor + daemon + monitor")
    p.add_argument("--scene", type=_scene, default="hand",
                   help="the simulated sensor's scene (docs/simulator.md; the shipped model knows hand and robot sliding)")
    p.add_argument("--seed", type=_seed, default=0, help="the simulated sensor's random seed")
    p.add_argument("--publish", help="endpoint for the demo daemon (default: an ipc socket in a temporary folder)")
    p.add_argument("--headless", action="store_true", help="print one line per label (with the true surface) instead of the monitor")
    p.add_argument("--seconds", type=_positive_float, default=None, help="with --headless: run this long, s (wall time; default 20); exit 0 if labels came")
    p.set_defaults(handler=cmd_demo)

    p = sub.add_parser("replay", help="run recordings through the daemon's pipeline")
    p.add_argument("files", nargs="+", help="recordings (.npz), or raw serial captures (.bin, as run --raw writes: decoded with the "
                                            "config's sensor), one after the other")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--json", action="store_true", help="one JSON object per slide")
    p.add_argument("--speed", type=_positive_float, default=None, help="pace at X times real time (default: as fast as possible)")
    p.add_argument("--model", help=MODEL_HELP)
    p.add_argument("--no-model", action="store_true", help="no classification (labels are null)")
    p.add_argument("--publish", help="also publish the daemon's messages on this ZeroMQ endpoint: slides, labels and status (and the "
                                     "raw samples with --samples), so bridges and the monitor work on a replay as on a live sensor")
    p.add_argument("--wait-subscriber", type=_wait_s, default=1.0, metavar="S",
                   help="with --publish: wait up to S s for a first subscriber before sending, so that one already started misses "
                        "nothing (0: send at once)")
    p.add_argument("--samples", action="store_true", help="with --publish: also publish the raw samples on samples/<id>, as run --samples "
                                                         "(.npz recordings)")
    p.add_argument("--block", type=_count, default=None, help="samples per block fed to the pipeline (default 65536)")
    p.add_argument("--force", action="store_true", help="run a model whose analysis cannot keep up with real time (below 5x on this machine)")
    p.set_defaults(handler=cmd_replay)

    p = sub.add_parser("features", help="feature vectors of every slide")
    p.add_argument("files", nargs="+", help="recordings (.npz) whose slides to analyse")
    p.add_argument("-o", "--output", required=True, help="features file to write (.npz: one row per window, docs/features.md)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--jobs", type=_int_in(0, 4096), default=0, metavar="N", help=JOBS_HELP)
    p.set_defaults(handler=cmd_features)

    p = sub.add_parser("train", help="train a model from labelled recordings (finds what works on them)")
    p.add_argument("files", nargs="+", help="labelled recordings (.npz): per-slide ground truth or a file-level label")
    p.add_argument("-o", "--output", required=True, help="model file to write (.npz)")
    p.add_argument("--force", action="store_true", help="replace an existing output file")
    p.add_argument("--config", help="config file (detector, spikes, feature settings; default: the built-in defaults)")
    p.add_argument("--method", choices=("auto", "quick", "paper"), default="auto",
                   help="auto: score features, classifiers and windows by grouped CV and keep the simplest within one standard error of "
                        "the best; quick: a small search for a first model in "
                        "seconds (band energies and texture, linear and kNN); paper: the papers' DWT + SFS + ELM")
    p.add_argument("--folds", type=_int_in(2, 1000), default=5, help="outer cross-validation folds, grouped by file")
    p.add_argument("--min-slides", type=_count, default=2, help="fewest slides a surface needs")
    p.add_argument("--drop-rare", action="store_true", help="train without surfaces that have too few slides instead of stopping")
    p.add_argument("--group-by", choices=("file", "slide"), default="file",
                   help="what cross-validation folds keep together: file (every surface needs two recordings) or slide "
                        "(allows one recording per surface; the estimates are then optimistic, and train says so)")
    p.add_argument("--scheduler", help="dask.distributed scheduler address (tcp://host:port) to run the cross-validation on a cluster")
    p.add_argument("--seed", type=_seed, default=0, help=SEED_HELP + " (the same files, options and seed give the same model file)")
    p.set_defaults(handler=cmd_train)

    p = sub.add_parser("evaluate", help="the papers' experiments by grouped cross-validation")
    p.add_argument("files", nargs="+", help="recordings (.npz) with per-slide ground truth, all of one rate and channel count")
    p.add_argument("--report", required=True, help="output folder: report.md, report.json, PNG figures")
    p.add_argument("--force", action="store_true", help="write into a report folder that is not empty")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--experiments", type=_experiments, default=EXPERIMENTS,
                   help="a: classifiers, b: window grid, c: sampling rate, d: feature count, e: clustering, f: error against run time, "
                        "g: the default method against decision time")
    p.add_argument("--folds", type=_int_in(2, 1000), default=5, help="cross-validation folds, grouped by file")
    p.add_argument("--quick", action="store_true", help="small grids and fewer features (for tests)")
    p.add_argument("--seed", type=_seed, default=0, help=SEED_HELP)
    p.set_defaults(handler=cmd_evaluate)

    p = sub.add_parser("score", help="accuracy of a model on ground-truth slides")
    p.add_argument("model", help="model file (.npz) to score")
    p.add_argument("files", nargs="+", help="recordings (.npz) with per-slide ground truth or a file label, unseen in training")
    p.add_argument("--config", help=CONFIG_HELP)
    p.add_argument("--json", action="store_true", help="the report as one JSON object")
    p.add_argument("--jobs", type=_int_in(0, 4096), default=0, metavar="N", help=JOBS_HELP)
    p.set_defaults(handler=cmd_score)
    _describe(parser)
    return parser


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every parser under ``parser`` (itself under ""), keyed by its words after the program name, in help order."""
    out = {"": parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                out.update({f"{name} {k}".strip(): p for k, p in subcommands(child).items()})
    return out


def _describe(parser: argparse.ArgumentParser) -> None:
    """Give every subcommand its one-line help as description and its example (:data:`EXAMPLES`) as epilog."""
    for words, p in subcommands(parser).items():
        for action in p._actions:
            if isinstance(action, argparse._SubParsersAction):
                for choice in action._choices_actions:
                    child = action.choices[choice.dest]
                    child.description = child.description or choice.help
        example = EXAMPLES.get(words)
        codes = "exit codes: 0 ok, 1 failure, 2 usage or bad input\n\n" if not words else ""
        if example:
            p.epilog = f"{codes}example:\n  {example}"


def main(argv: Sequence[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    level = logging.WARNING - 10 * min(args.verbose, 2)
    logging.basicConfig(level=level, format="tactiled: %(levelname)s: %(message)s", stream=sys.stderr)
    handler: Handler = args.handler
    # every matrix here is small: BLAS threads only add overhead (13x slower ELM fits measured)
    from threadpoolctl import threadpool_limits

    threadpool_limits(1)
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
