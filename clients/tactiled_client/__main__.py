"""``python -m tactiled_client record|replay|control``: capture a session's messages, play them back, and ask a
running daemon to load a model or run one in its shadow (pyzmq + msgpack only).

    python -m tactiled_client record tcp://robot:7350 session.tlog --seconds 600 --topics roughness slide status
    python -m tactiled_client replay session.tlog --json
    python -m tactiled_client replay session.tlog --publish tcp://127.0.0.1:7350 --speed 2
    python -m tactiled_client control ipc:///run/tactiled/fingertip0.control load new_model.npz

Exit status: 0 done, 1 the daemon refused the request (its reason on stderr), the machine refused a write of the recording
(a full disk, a file-size limit: one line, every message before it kept) or the reader of the output went away
(``replay --json | head``: nothing is printed), 2 bad arguments or a file that cannot be read or no reply (one line on
stderr), 130 interrupted.

``replay --json`` prints each message's fields exactly as recorded: bytes as base64, a msgpack extension value (which
tactiled never sends, but a subscriber delivers) as ``{"ext": code, "data": base64}`` (a timestamp is code -1). The
recorder's summary line says how many messages it did not record and why the last was not (a message no reader could
read back: over 64 MiB, a body that is no msgpack map; or a publisher whose connection the size limit dropped).
"""

from __future__ import annotations

import argparse
import base64
import json
import signal
import sys
from collections.abc import Sequence
from typing import Any, NoReturn

import msgpack

from tactiled_client import schema
from tactiled_client.errors import ClientError, LogError
from tactiled_client.log import Entry, WriteFailed, check_body


class _Parser(argparse.ArgumentParser):
    """An argument parser whose errors are one line, as ``tactiled``'s are (its subcommands' parsers are of this class too)."""

    def error(self, message: str) -> NoReturn:
        """Exit 2 with one line: the problem and where the help is (argparse prints the whole usage first)."""
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The parser of ``python -m tactiled_client`` (record, replay, control); docs/cli.md shows its help."""
    ap = _Parser(prog="python -m tactiled_client", description="record and replay tactiled sessions (docs/messages.md)")
    sub = ap.add_subparsers(dest="command", required=True, metavar="COMMAND")
    p = sub.add_parser("record", help="record what a daemon publishes to a session log")
    p.add_argument("endpoint", nargs="+", help="daemon endpoint(s), e.g. tcp://127.0.0.1:7350, then the output file")
    p.add_argument("--seconds", type=float, default=None, help="stop after this long (default: until Ctrl-C or SIGTERM)")
    p.add_argument("--topics", nargs="+", choices=schema.TOPICS, default=None, help="only these topics (default: every one)")
    p.add_argument("--sensor", default=None, help="only this sensor id")
    p.add_argument("--curve", nargs=2, metavar=("DAEMON_PUBLIC", "MY_SECRET"), default=None, help="CURVE certificate files")
    p.add_argument("--force", action="store_true", help="overwrite the output file")
    p = sub.add_parser("replay", help="play a session log, tactiled MCAP file or tactiled replay --json output")
    p.add_argument("file", help="the recorded file")
    out = p.add_mutually_exclusive_group(required=True)
    out.add_argument("--json", action="store_true", help="print the messages as JSON lines (bytes as base64)")
    out.add_argument("--publish", metavar="ENDPOINT", help="publish on ENDPOINT as the daemon would (fresh per-topic seq)")
    p.add_argument("--speed", type=float, default=None, help="1 = recorded pace, 2 = twice as fast (default: --json as fast as possible, "
                                                           "--publish at the recorded pace)")
    p.add_argument("--topics", nargs="+", choices=schema.TOPICS, default=None, help="only these topics")
    p.add_argument("--sensor", default=None, help="only this sensor id")
    p.add_argument("--wait-subscriber", type=float, default=0.0, metavar="S", help="--publish: wait up to S s for a first subscriber "
                                                                                   "(default: 0, do not wait)")
    p = sub.add_parser("control", help="ask a running daemon (its control.endpoint) to load a model, run one in its shadow, or for status")
    p.add_argument("endpoint", help="the daemon's control endpoint (control.endpoint in its config)")
    p.add_argument("cmd", choices=("load", "shadow", "status"), help="load: swap in a model file at the next slide; shadow: run a "
                                                                      "candidate model in the shadow of the live one (no path: stop it)")
    p.add_argument("path", nargs="?", default=None, help="the model file (load, shadow)")
    p.add_argument("--curve", nargs=2, metavar=("DAEMON_PUBLIC", "MY_SECRET"), default=None, help="CURVE certificate files")
    p.add_argument("--timeout", type=float, default=30.0, help="seconds to wait for the reply (default: 30)")
    return ap


def _jsonable(v: Any) -> Any:
    """``v`` (a decoded msgpack value) as JSON can hold it: bytes as base64, extension values as ``{"ext", "data"}``."""
    if isinstance(v, bytes):
        return base64.b64encode(v).decode()
    if isinstance(v, msgpack.ExtType):
        return {"ext": v.code, "data": base64.b64encode(v.data).decode()}
    if isinstance(v, msgpack.Timestamp):
        return {"ext": -1, "data": base64.b64encode(v.to_bytes()).decode()}
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, list):
        return [_jsonable(x) for x in v]
    return v


def _json_line(entry: Entry, file: str) -> str:
    """One ``replay --json`` line: the entry's topic and its body's fields; :class:`LogError` naming the record if the body
    nests deeper than JSON can be written."""
    where = f"{file}: {entry.where}" if entry.where else file
    try:
        return json.dumps({"topic": entry.topic, **_jsonable(check_body(entry.body, where))})
    except RecursionError:
        raise LogError(f"{where}: message body nests too deep to print as JSON") from None


class _Refusals:
    """The messages the recorder did not record: how many, and why the last was not (for its summary line)."""

    def __init__(self) -> None:
        self.count = 0
        self.last = ""

    def __call__(self, why: str) -> None:
        self.count += 1
        self.last = why

    def summary(self) -> str:
        """``; N not recorded (the last: why)``, or nothing."""
        return f"; {self.count} not recorded (the last: {self.last})" if self.count else ""


def main(argv: Sequence[str] | None = None) -> int:
    """The command; returns the exit status."""
    args = build_parser().parse_args(argv)
    stopping = False

    def stop(signum: int, frame: object) -> None:
        nonlocal stopping
        if stopping:  # a second Ctrl-C or SIGTERM: do not wait for the drain (what was recorded stays: each message is whole)
            raise KeyboardInterrupt
        stopping = True

    try:
        if args.command == "record":
            from tactiled_client.record import record

            if len(args.endpoint) < 2:
                raise ClientError("record needs an endpoint and an output file")
            before = signal.signal(signal.SIGTERM, stop), signal.signal(signal.SIGINT, stop)
            *endpoints, out = args.endpoint
            refused = _Refusals()
            try:
                n = record(endpoints, out, seconds=args.seconds, topics=args.topics, sensor=args.sensor,
                           curve=tuple(args.curve) if args.curve else None, stop=lambda: stopping, overwrite=args.force,
                           on_refused=refused)
            finally:  # main may run inside another program (a test): give its handlers back
                signal.signal(signal.SIGTERM, before[0])
                signal.signal(signal.SIGINT, before[1])
            quiet = "" if n or refused.count else f" (nothing came from {', '.join(endpoints)}: is a daemon publishing there?)"
            print(f"{out}: {n} messages{refused.summary()}{quiet}", file=sys.stderr)
            return 0
        if args.command == "control":
            import os

            from tactiled_client.control import control

            path = os.path.abspath(args.path) if args.path else None  # the daemon may run in another folder
            answer = control(args.endpoint, args.cmd, path, curve=tuple(args.curve) if args.curve else None, timeout=args.timeout)
            if not answer.get("ok"):
                print(f"tactiled_client: {args.endpoint}: refused: {answer.get('error')}", file=sys.stderr)
                return 1
            print(json.dumps(_jsonable(answer)))
            return 0
        from tactiled_client.replay import BlockingReplay, publish

        if args.publish:
            n = publish(args.file, args.publish, speed=args.speed if args.speed is not None else 1.0, topics=args.topics, sensor=args.sensor,
                        wait_subscriber_s=args.wait_subscriber, warn=lambda note: print(f"warning: {note}", file=sys.stderr))
            print(f"{args.file}: published {n} messages on {args.publish}", file=sys.stderr)
            return 0
        with BlockingReplay(args.file, args.topics, args.sensor, speed=args.speed) as rep:
            for entry in rep.entries():  # every field exactly as recorded
                print(_json_line(entry, args.file), flush=True)
            if rep.reader.truncated:
                print(f"warning: {rep.reader.truncated}", file=sys.stderr)
        return 0
    except WriteFailed as exc:  # the machine refused (a full disk): one line, what was already recorded stays
        print(f"tactiled_client: {exc}", file=sys.stderr)
        return 1
    except ClientError as exc:
        print(f"tactiled_client: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    except BrokenPipeError:  # the reader of stdout went away (replay --json | head -1): quiet, as tactiled is
        _stdout_to_devnull()
        return 1


def _stdout_to_devnull() -> None:
    """Point stdout at /dev/null, so that flushing what is still buffered at exit does not raise again (Python's advice for
    SIGPIPE)."""
    import os

    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)
    except (OSError, ValueError):  # no file descriptor behind stdout (run inside another program): nothing to flush there
        pass


if __name__ == "__main__":
    sys.exit(main())
