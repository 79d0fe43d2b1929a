"""What every command module of the CLI shares: exit codes, the parser class (help with defaults, one-line errors
with "did you mean"), argument types that say their range, help texts, and small output helpers."""

from __future__ import annotations

import argparse
import difflib
import math
import os
import re
import sys
from collections.abc import Callable, Sequence
from typing import Any, NoReturn

from tactiled.config import Config, load_config
from tactiled.errors import TactiledError

EXIT_OK, EXIT_FAIL, EXIT_USAGE = 0, 1, 2

Handler = Callable[[argparse.Namespace], int]
Sub = Any  # the _SubParsersAction that add_parser is called on (argparse does not export its type)


def config_of(args: argparse.Namespace, overrides: dict[str, object] | None = None) -> Config:
    """The config of ``--config`` (the built-in defaults without it), with the command line's ``overrides`` (None: not given)."""
    return load_config(getattr(args, "config", None)).override(overrides or {})


def say(msg: str) -> None:
    """One line on stderr, as ``tactiled: msg``."""
    print(f"tactiled: {msg}", file=sys.stderr, flush=True)


def files_done(what: str) -> Callable[[int, int], None]:
    """Progress over files on one line of stderr (rewritten in place on a terminal; only the last count otherwise)."""
    tty = sys.stderr.isatty()

    def done(i: int, n: int) -> None:
        if tty or i == n:
            print(f"\r{what}: {i}/{n} files", end="\n" if i == n else "", file=sys.stderr, flush=True)
    return done


class HelpFormatter(argparse.ArgumentDefaultsHelpFormatter, argparse.RawDescriptionHelpFormatter):
    """Help that shows each option's default (when it has a value worth showing) and keeps examples as written."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if "(default" in text or "default:" in text or action.default is None or action.default is False or action.default in ("", argparse.SUPPRESS) \
                or not action.option_strings:
            return text
        return f"{text} (default: %(default)s)"


class Parser(argparse.ArgumentParser):
    """An argument parser whose help shows defaults and whose errors are one line (subcommands inherit both)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        kwargs.setdefault("formatter_class", HelpFormatter)
        super().__init__(*args, **kwargs)

    def error(self, message: str) -> NoReturn:
        """Exit 2 with one line: the problem, the closest option or subcommand there is, and where the help is."""
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}{did_you_mean(message, self)} (see {self.prog} --help)\n")

    def parse_args(self, args: Sequence[str] | None = None, namespace: Any = None) -> Any:  # type: ignore[override]
        """As argparse, but an unknown option is reported by the subcommand it was given to, with the closest one it has."""
        ns, extras = self.parse_known_args(args, namespace)
        if extras:
            words = [a for a in (sys.argv[1:] if args is None else list(args)) if not a.startswith("-")]
            known = subcommands(self)
            chosen = max((k for k in known if k and words[:len(k.split())] == k.split()), key=len, default="")
            known[chosen].error(f"unrecognized argument{'s' if len(extras) > 1 else ''}: {' '.join(extras)}")
        return ns


def did_you_mean(message: str, parser: argparse.ArgumentParser) -> str:
    """"; did you mean X?" for an unknown option or subcommand close to one that exists, else ""."""
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


def subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    """Every parser under ``parser`` (itself under ""), keyed by its words after the program name, in help order."""
    out = {"": parser}
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for name, child in action.choices.items():
                out.update({f"{name} {k}".strip(): p for k, p in subcommands(child).items()})
    return out


def overrides(key: str) -> str:
    """Help for an option that overrides config ``key`` (``section.name``): the key, and its built-in default."""
    from tactiled.config import Config

    section, name = key.split(".")
    value = getattr(getattr(Config(), section), name)
    built_in = f"built in {value!r}" if value not in ("", None) else "none built in"
    return f"(overrides {key}; default: the config's, {built_in})"


def command(sub: Sub, name: str, help: str, handler: Handler, example: str = "") -> argparse.ArgumentParser:
    """A subcommand ``name`` of ``sub``: its one-line ``help`` (also its description), the ``handler`` that runs it, and
    an ``example`` shown at the end of its --help."""
    p: argparse.ArgumentParser = sub.add_parser(name, help=help, description=help, epilog=f"example:\n  {example}" if example else None)
    p.set_defaults(handler=handler)
    return p


# ---- argument types: each names its range in errors and in help ---------------------------------

def number(text: str) -> float:
    """A finite number."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not a number: {text!r}") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"must be a finite number, got {text}")
    return value


def positive(text: str) -> float:
    """A finite number > 0."""
    value = number(text)
    if not value > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return value


def number_in(low: float, high: float, name: str) -> Callable[[str], float]:
    """An argparse type: a number in ``[low, high]``, called ``name`` in help."""

    def parse(text: str) -> float:
        value = number(text)
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"must be in [{low:g}, {high:g}], got {text}")
        return value

    parse.__name__ = name
    return parse


def int_in(low: int, high: int = 2**31) -> Callable[[str], int]:
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


def scene(text: str) -> str:
    """A scene, or scenes joined by commas, that the simulator knows (checked when given: the simulator loads lazily)."""
    from tactiled.sim.physics import parse_scene

    try:
        parse_scene(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--scene: ")) from None
    return text


number.__name__ = "number"
positive.__name__ = "number > 0"
scene.__name__ = "scene"
count, seed, channels = int_in(1), int_in(0, 2**32 - 1), int_in(1, 8)
probability, wait_s = number_in(0.0, 1.0, "probability"), number_in(0.0, 3600.0, "seconds")
jobs = int_in(0, 4096)

CONFIG_HELP = "TOML config file (every key is explained in the example: tactiled config --example; default: the built-in defaults)"
JOBS_HELP = "worker processes over the files (default 0: one per core; 1: in this process)"
SCENE_HELP = ("scene, or scenes joined by commas: hand (default), robot, continuous, fluctuating, hot-gain, one-channel, grating "
              "(docs/simulator.md), e.g. continuous,one-channel")
SURFACES_HELP = ("N surfaces spread over the range, or names such as Ra0.44,Ra4.43 (the grating scene: G0.10mm,G1.00mm) "
                 "(default: all 15)")
CONNECT_HELP = ("daemon endpoint to subscribe to (default: publish.endpoint of --config; for 'auto', the built-in default, "
                "the local daemon's socket: /run/tactiled/<sensor.id>.sock or $XDG_RUNTIME_DIR/tactiled/<sensor.id>.sock)")
CURVE_HELP = ("a daemon that requires ZeroMQ CURVE (publish.curve_secret_key_file): its public certificate and this subscriber's "
              "secret one, whose public half is in the daemon's publish.curve_authorized_dir (tactiled curve-keys makes a pair; "
              "default: none)")
SEED_HELP = "random seed"
MODEL_HELP = ("model file (default: --config's model.path, as tactiled run takes it; else the shipped model, when it fits the "
              "recording's rate and channels)")
FORCE_HELP = "replace an existing output file"


def set_in_config(args: argparse.Namespace, key: str, given: object) -> str | None:
    """Where a value came from, for an error about it: ``--config``'s ``key`` (``my.toml: model.path``), or None when the
    command line gave it (``given``), whose error names it itself."""
    return None if given else f"{getattr(args, 'config', None)}: {key}"


def subscriber_curve(args: argparse.Namespace, config: Config) -> tuple[str, str] | None:
    """The CURVE certificates a subscribing command (monitor, a bridge) connects with: ``--curve``; refused in one line when
    the config's daemon requires CURVE (``publish.curve_secret_key_file``), the endpoint is the config's and none was given:
    it would wait for ever, hearing nothing."""
    if args.curve:
        for path in args.curve:  # before anything connects (a file that is no certificate: the client library says so)
            if not os.path.isfile(path):
                raise TactiledError(f"--curve {path}: no such certificate file (tactiled curve-keys makes them)")
        return (args.curve[0], args.curve[1])
    if config.publish.curve_secret_key_file and not args.connect:
        raise TactiledError(f"{args.config or 'the config'}: publish.curve_secret_key_file is set: that daemon serves only subscribers "
                            "with an authorised key; pass --curve DAEMON.key MY.key_secret (tactiled curve-keys makes a pair, whose .key "
                            "goes into publish.curve_authorized_dir)")
    return None
