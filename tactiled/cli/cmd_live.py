"""``tactiled run``, ``monitor``, ``lsl``, ``ros2`` and ``demo``: the live daemon and what watches it."""

from __future__ import annotations

import argparse
import logging
import sys

from tactiled.cli import common as c
from tactiled.cli.common import EXIT_FAIL, EXIT_OK, Sub, command, config_of, say
from tactiled.config import Config, endpoint_problem, subscribe_endpoint
from tactiled.errors import ConfigError, TactiledError


def cmd_run(args: argparse.Namespace) -> int:
    """The daemon, until SIGTERM or SIGINT (SIGHUP reloads the model)."""
    import asyncio

    from tactiled.files.outputs import check_output
    from tactiled.learn.choose import ModelChoice
    from tactiled.service.daemon import Daemon

    config = config_of(args, {"sensor.port": args.port, "sensor.id": args.sensor_id, "publish.endpoint": args.publish,
                              "model.path": args.model, "publish.samples": True if args.samples else None, "model.shadow": args.shadow})
    s = config.sensor
    where = f"sensor {s.id}"
    choice = ModelChoice(config, None if args.no_model else config.model.path or None, explicit=args.no_model, force=args.force, check_cost=False,
                         warn=say, set_by=c.set_in_config(args, "model.path", args.model))
    model = choice.for_stream(s.fs, s.channels, where)
    if model is None and not args.no_model:
        raise TactiledError("no model fits this sensor (train one with tactiled train, or pass --no-model)")
    if args.no_model and args.shadow:
        raise TactiledError("--shadow runs a candidate beside the live model: not with --no-model")
    # --no-model publishes slides and status only: no shadow either, as check-config --no-model checks the config
    shadow = ModelChoice(config, config.model.shadow, explicit=True, check_cost=False, set_by=c.set_in_config(args, "model.shadow", args.shadow)) \
        .for_stream(s.fs, s.channels, where) if config.model.shadow and not args.no_model else None
    for out, suffix in ((args.record, ".npz"), (args.raw, ".bin")):
        if out:
            check_output(out, args.force, (suffix,))  # before the port opens: never replace a file (or write a device) unasked
    if args.no_wait:
        from tactiled.board.serialsource import check_port

        check_port(s.port)

    async def main() -> int:
        try:
            daemon = Daemon(config, model, args.record, raw_to=args.raw, force=args.force, shadow=shadow,
                            model_path=str(choice.file) if model is not None and choice.file else None)  # what SIGHUP loads again
        except ConfigError as exc:  # a socket its config names cannot be bound: the file too, as check-config says it
            from_file = str(exc).startswith("control.") or (str(exc).startswith("publish.") and args.publish is None)
            raise ConfigError(f"{args.config}: {exc}") if args.config and from_file else exc from None
        print(f"tactiled: sensor {s.id} on {s.port}, publishing on {daemon.endpoint}", file=sys.stderr, flush=True)
        try:
            await daemon.run()
        finally:
            last = daemon.last_status
            if last is not None:  # Ctrl-C, SIGTERM, or the end of the source: what the run did, in one line
                stale = f", {last.discarded_at_start} stale bytes discarded at start" if last.discarded_at_start else ""
                print(f"tactiled: stopped after {last.uptime_s:.1f} s: {last.samples} samples, {last.samples_lost} lost, {last.slides} slides, "
                      f"{last.labels} labels, {last.unknown} unknown surface{stale}", file=sys.stderr, flush=True)
        return EXIT_OK if daemon.recording_error is None else EXIT_FAIL  # the recording failed (a full disk): logged, exit 1

    return asyncio.run(main())


def subscriber_endpoint(args: argparse.Namespace, config: Config, sensor: str | None = None) -> str:
    """Where a subscribing command (monitor, a bridge) connects: ``--connect``, else the config's publish endpoint
    (:func:`subscribe_endpoint`); refused in one line when no subscriber can connect there (ZeroMQ would raise ``Invalid
    argument``, or take a port past 65535 modulo 65536): not tcp://HOST:PORT (port 1..65535) or ipc://PATH."""
    endpoint: str = args.connect or subscribe_endpoint(config, sensor)
    problem = endpoint_problem(endpoint, connect=True)
    if problem is not None:
        where = f"--connect {endpoint}" if args.connect else f"publish.endpoint {endpoint} (a subscriber connects there)"
        raise TactiledError(f"{where}: must be tcp://HOST:PORT or ipc://PATH: {problem}")
    return endpoint


def cmd_monitor(args: argparse.Namespace) -> int:
    """The terminal view of a running daemon."""
    from tactiled.apps.monitor import run_monitor

    config = config_of(args)
    endpoint, curve = subscriber_endpoint(args, config), c.subscriber_curve(args, config)
    if not sys.stdout.isatty():  # it redraws a screen: into a file or a pipe it would write nothing readable
        raise TactiledError("monitor: its output is not a terminal (it redraws a screen); for lines to log or pipe, record the "
                            f"session (python -m tactiled_client record {endpoint} session.tlog, then replay it with --json)")
    return run_monitor(endpoint, args.truth, curve=curve)


def cmd_lsl(args: argparse.Namespace) -> int:
    """The LSL bridge, until stopped."""
    from tactiled.apps.bridges.cli import serve

    config = config_of(args)
    return serve("lsl", config, subscriber_endpoint(args, config, args.sensor_id), args.sensor_id, nan_lost=args.nan_lost,
                 curve=c.subscriber_curve(args, config))


def cmd_ros2(args: argparse.Namespace) -> int:
    """The ROS 2 bridge, until stopped."""
    from tactiled.apps.bridges.cli import serve

    config = config_of(args)
    return serve("ros2", config, subscriber_endpoint(args, config, args.sensor_id), args.sensor_id, ros_args=args.ros_args,
                 curve=c.subscriber_curve(args, config))


def check_demo_scene(spec: str) -> None:
    """Refuse (one line) a scene whose board the demo's daemon cannot read: the demo runs ``tactiled run`` with the default
    sensor settings and the shipped model, so the board must stream at their rate and channel count."""
    from tactiled.config import Config
    from tactiled.sim.physics import scene_params

    params, sensor = scene_params(spec), Config().sensor
    if (params.fs, params.channels) != (sensor.fs, sensor.channels):
        raise TactiledError(f"--scene {spec}: its board streams {params.channels} channel(s) at {params.fs:g} Hz, and the demo's daemon "
                            f"and the shipped model expect {sensor.channels} at {sensor.fs:g} Hz; run `tactiled simulate serial --scene "
                            f"{spec}` and `tactiled run` with a config and a model for that rate (README: train on your own surfaces)")


def cmd_demo(args: argparse.Namespace) -> int:
    """Virtual board + daemon with the shipped model + monitor (or, headless, label lines for ``--seconds``)."""
    from tactiled.apps.demo import run_demo

    if args.seconds is not None and not args.headless:
        raise TactiledError("--seconds needs --headless")
    check_demo_scene(args.scene)
    return run_demo(args.scene, args.seed, args.publish, args.headless, args.seconds if args.seconds is not None else 20.0)


def add_commands(sub: Sub) -> None:
    """run, monitor, lsl, ros2, demo."""
    p = command(sub, "run", "the daemon: serial port -> roughness labels over ZeroMQ", cmd_run, "tactiled run --config my.toml --model my_model.npz")
    p.set_defaults(log_level=logging.INFO)  # a service says what it runs and each model it swaps in (systemctl reload says nothing)
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--port", help="serial device " + c.overrides("sensor.port"))
    p.add_argument("--model", help="model file (overrides model.path; default: the shipped model)")
    p.add_argument("--no-model", action="store_true", help="publish slides and status only")
    p.add_argument("--shadow", metavar="MODEL", help="a candidate model to run in the shadow of the live one (overrides model.shadow): its "
                                                     "labels on shadow/<id>, never as the live ones; status.shadow says how often they agree; default: none)")
    p.add_argument("--publish", help="ZeroMQ endpoint to bind " + c.overrides("publish.endpoint"))
    p.add_argument("--sensor-id", help="sensor id in topics " + c.overrides("sensor.id"))
    p.add_argument("--record", help="also write every sample received to this .npz, streamed to disk as OUT.npz.journal (tactiled recover) "
                   "and converted on exit (an existing file needs --force; a device or FIFO is never written; if the recording fails, "
                   "a full disk, the daemon goes on publishing and exits 1; default: no recording)")
    p.add_argument("--samples", action="store_true", help="also publish the raw samples on samples/<id> (sets publish.samples)")
    p.add_argument("--raw", metavar="OUT.bin", help="also write every byte read from the port, as read (replay it with tactiled replay OUT.bin; default: none)")
    p.add_argument("--no-wait", action="store_true", help="exit 2 at once if the serial device is missing (default: wait for it)")
    p.add_argument("--force", action="store_true", help="let --record and --raw replace existing files, and run a model whose analysis "
                                                        "cannot keep up with the sensor (below 5x real time on this machine)")

    p = command(sub, "monitor", "terminal view of a running daemon", cmd_monitor, "tactiled monitor --connect ipc:///run/tactiled/fingertip0.sock")
    p.add_argument("--connect", help=c.CONNECT_HELP)
    p.add_argument("--config", help=c.CONFIG_HELP)
    p.add_argument("--truth", help="a virtual board's log (simulate serial --log): show the true surface of each slide (default: none)")
    p.add_argument("--curve", nargs=2, metavar=("DAEMON.key", "MY.key_secret"), help=c.CURVE_HELP)

    for name, help_, handler, example in (
            ("lsl", "Lab Streaming Layer outlets of a daemon's raw samples and labels (tactiled[lsl])", cmd_lsl,
             "tactiled lsl --sensor-id fingertip0"),
            ("ros2", "ROS 2 topics of a daemon's labels, status and raw samples (tactiled[ros2])", cmd_ros2,
             "tactiled ros2 --sensor-id fingertip0 --ros-args -r __ns:=/robot1")):
        p = command(sub, name, help_, handler, example)
        p.add_argument("--connect", help=c.CONNECT_HELP)
        p.add_argument("--config", help=c.CONFIG_HELP)
        p.add_argument("--sensor-id", help="sensor to bridge (default: sensor.id of --config)")
        p.add_argument("--curve", nargs=2, metavar=("DAEMON.key", "MY.key_secret"), help=c.CURVE_HELP)
        if name == "lsl":
            p.add_argument("--nan-lost", action="store_true", help="push lost samples as NaN rows (a regular stream; a gap longer "
                                                                   "than 30 s gets its marker only); each lost range is a marker either way")
        else:
            p.add_argument("--ros-args", nargs=argparse.REMAINDER, default=None, metavar="ARG",
                           help="the rest goes to ROS: -r __ns:=/robot1, -r __node:=NAME, -r FROM:=TO, -p endpoint:=…, -p sensor_id:=…, "
                                "-p frame_id:=…, --params-file F (docs/integrations.md; default: none)")

    p = command(sub, "demo", "simulated sensor + daemon + monitor", cmd_demo, "tactiled demo --scene robot")
    p.add_argument("--scene", type=c.scene, default="hand",
                   help="the simulated sensor's scene (docs/simulator.md; the shipped model knows hand and robot sliding at 20 kHz on "
                   "2 channels; a scene at another rate or channel count, such as one-channel, is refused)")
    p.add_argument("--seed", type=c.seed, default=0, help="the simulated sensor's random seed")
    p.add_argument("--publish", help="endpoint for the demo daemon (default: an ipc socket in a temporary folder)")
    p.add_argument("--headless", action="store_true", help="print one line per label (with the true surface) instead of the monitor")
    p.add_argument("--seconds", type=c.positive, default=None,
                   help="with --headless: run this long, s (wall time; default 20); exit 0 if labels came")
