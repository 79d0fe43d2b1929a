"""The command line as a newcomer meets it: help on everything, examples that parse, one-line errors, docs/cli.md current."""

from __future__ import annotations

import argparse
import os
import re
import shlex
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from tactiled.cli.clidoc import REGENERATE, reference
from tactiled.cli.cmd_learn import ANOTHER_UNIT
from tactiled.cli.main import build_parser, main, subcommands
from tactiled.errors import TactiledError
from tactiled.learn.model import load_model
from tactiled.sim.physics import pick_surfaces
from tests.conftest import REPO, cli_here, tactiled_cmd, usage_error

COMMANDS = subcommands(build_parser())


def test_every_argument_of_every_command_has_help() -> None:
    missing = [f"tactiled {words}: {action.dest}" for words, p in COMMANDS.items() for action in p._actions
               if not (action.help or "").strip() or action.help == argparse.SUPPRESS]
    assert not missing, f"arguments without help: {missing}"
    assert len(COMMANDS) >= 19  # the top level, 15 commands, simulate and its three


@pytest.mark.parametrize("words", list(COMMANDS))
def test_help_runs_and_ends_with_an_example_that_parses(words: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_:
        main([*words.split(), "--help"])
    assert exit_.value.code == 0
    out = capsys.readouterr().out
    epilog = COMMANDS[words].epilog or ""
    assert "example:\n  " in epilog, f"tactiled {words} has no example"
    example = epilog.rsplit("example:\n  ", 1)[1]
    assert out.rstrip().endswith(f"example:\n  {example}")
    assert COMMANDS[words].description, f"tactiled {words} has no description"
    argv = shlex.split(example)
    assert argv[0] == "tactiled" and " ".join(argv[1:]).startswith(words)
    build_parser().parse_args(argv[1:])  # the example is a valid command line (SystemExit otherwise)


def test_defaults_are_shown() -> None:
    text = COMMANDS["simulate serial"].format_help()
    assert "times real time (default: 1.0)" in text and "(default: 0.0)" in text
    assert "(default: None)" not in "".join(p.format_help() for p in COMMANDS.values())
    assert "(default: False)" not in "".join(p.format_help() for p in COMMANDS.values())


def test_every_option_that_takes_a_value_says_its_default() -> None:
    """Each optional, non-required option with a value names its default in --help (a value, the config key, or what none means)."""
    import argparse

    from tactiled.cli.common import HelpFormatter

    silent = [f"tactiled {words} {'/'.join(a.option_strings)}" for words, parser in COMMANDS.items() for a in parser._actions
              if a.option_strings and a.nargs != 0 and not a.required and not isinstance(a, argparse._HelpAction)
              and "default" not in HelpFormatter("x")._get_help_string(a)]
    assert not silent, silent


def test_docs_cli_md_is_generated_from_the_parser() -> None:
    wanted = reference()
    have = (REPO / "docs" / "cli.md").read_text(encoding="utf-8")
    assert have == wanted, f"docs/cli.md is out of date: regenerate it with `{REGENERATE}`"


def test_surface_examples_in_help_are_accepted() -> None:
    for words in ("simulate dataset", "simulate serial"):
        text = next(a.help for a in COMMANDS[words]._actions if "--surfaces" in a.option_strings) or ""
        names = re.findall(r"\b(?:Ra\d\.\d\d|G\d\.\d\dmm)\b", text)
        assert names
        for name in names:
            assert [s.name for s in pick_surfaces(name, "grating" if name.startswith("G") else "self-affine")] == [name]


def test_argument_types_reject_bad_values_by_name_not_function(capsys: pytest.CaptureFixture[str]) -> None:
    """A bad value is one line naming the option and the value, never a Python function name."""
    for words, p in COMMANDS.items():
        for action in p._actions:
            if callable(action.type) and action.type not in (int, float, str):
                with pytest.raises(argparse.ArgumentTypeError):  # never ValueError: argparse would print the function's name
                    action.type("?x")
                assert not action.type.__name__.startswith("_"), f"tactiled {words} {action.dest}"
    for argv, what in ((["record", "--seconds", "abc", "-o", "x.npz"], "argument --seconds: not a number: 'abc'"),
                       (["record", "--seconds", "-1", "-o", "x.npz"], "argument --seconds: must be > 0, got -1"),
                       (["simulate", "serial", "--drop", "2"], "argument --drop: must be in [0, 1], got 2"),
                       (["evaluate", "a.npz", "--report", "r", "--experiments", "az"], "argument --experiments: letters from abcdefg"),
                       (["demo", "--scene", "nonsense"], "argument --scene: unknown scene 'nonsense'; known: hand, robot"),
                       (["simulate", "dataset", "--out", "d", "--scene", "robot,nonsense"], "argument --scene: unknown scene 'nonsense'"),
                       (["run", "--prot", "/dev/ttyACM0"], "tactiled run: error: unrecognized arguments: --prot /dev/ttyACM0; did you mean --port? "
                                                           "(see tactiled run --help)"),
                       (["simulate", "figure", "-o", "f.png", "--sed", "3"], "did you mean --seed? (see tactiled simulate figure --help)"),
                       (["rn"], "invalid choice: 'rn'")):
        assert what in usage_error(argv, capsys)


@pytest.mark.parametrize("option, value, what", [("--folds", "1", "must be an integer >= 2, got 1"), ("--folds", "two", "not an integer"),
                                                 ("--min-slides", "0", "must be an integer >= 1"), ("--seed", "-1", "must be an integer >= 0")])
def test_train_rejects_impossible_options_in_one_line(option: str, value: str, what: str, capsys: pytest.CaptureFixture[str]) -> None:
    assert f"argument {option}: {what}" in usage_error(["train", "x.npz", "-o", "m.npz", option, value], capsys)


def test_train_library_rejects_impossible_options(tmp_path: Path) -> None:
    from tactiled.config import load_config
    from tactiled.learn.train import train

    for kwargs, what in (({"folds": 1}, "--folds"), ({"min_slides": 0}, "--min-slides"), ({"seed": -1}, "--seed"), ({"method": "x"}, "--method")):
        with pytest.raises(TactiledError, match=what):
            train([tmp_path / "none.npz"], load_config(None), **kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_simulate_serial_removes_its_link_on_exit(tmp_path: Path, sig: signal.Signals) -> None:
    link = tmp_path / "tty"
    proc = subprocess.Popen(tactiled_cmd("simulate", "serial", "--link", str(link), "--surfaces", "2"), stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline().strip() == str(link)  # printed once the link exists
        assert link.is_symlink() and os.readlink(link).startswith("/dev/pts/")
        proc.send_signal(sig)
        assert proc.wait(60) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert not os.path.lexists(link)


def test_simulate_and_train_give_the_same_fingerprint_in_another_process(tmp_path: Path) -> None:
    """The documented commands are reproducible: two processes (with different hash seeds) simulate and train the same model."""
    def commands(i: int) -> str:
        data, env = tmp_path / f"d{i}", f"PYTHONHASHSEED={i}"
        simulate = shlex.join(tactiled_cmd("simulate", "dataset", "--out", str(data), "--surfaces", "2", "--files-per-surface", "2",
                                           "--slides-per-file", "2", "--scene", "robot", "--fs", "2200", "--channels", "1"))
        train = shlex.join(tactiled_cmd("train", "--method", "quick", "-o", str(tmp_path / f"m{i}.npz"), "--folds", "2"))
        return f"{env} {simulate} && {env} {train} {shlex.quote(str(data))}/*.npz"

    procs = [subprocess.Popen(["sh", "-c", commands(i)], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO) for i in (1, 2)]
    outs = [p.communicate(timeout=600) for p in procs]
    assert all(p.returncode == 0 for p in procs), [err for _, err in outs]
    fingerprints = [re.findall(r"fingerprint ([0-9a-f]{16})", out) for out, _ in outs]
    assert len(fingerprints[0]) == 1 and fingerprints[0] == fingerprints[1]
    assert load_model(tmp_path / "m1.npz").fingerprint == fingerprints[0][0]  # the file written loads back as the model printed
    last = outs[0][0].strip().splitlines()[-1]  # its estimates are said to hold for the unit that recorded, and what a gain costs
    assert last.startswith(ANOTHER_UNIT.split("{")[0]) and "with the films' gains 20 % off, the choice's cross-validated accuracy is" in last
    assert "at another gain" in outs[0][0] and load_model(tmp_path / "m1.npz").summary["gain_tolerance"] == 0.2


def test_a_model_says_once_that_the_configs_analysis_sections_are_not_used(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    from tactiled.files.recording import Recording, save_recording
    from tactiled.sim.physics import SimParams, simulate_file

    params = SimParams()
    sim = simulate_file(params, pick_surfaces("Ra1.00")[0], 1, 0)
    files = [str(tmp_path / f"r{i}.npz") for i in range(2)]
    for f in files:
        save_recording(f, Recording(sim.samples, params.fs, params.volts_per_count))
    config = tmp_path / "c.toml"
    config.write_text("[window]\nduration_s = 0.25\n\n[spikes]\nmethod = \"none\"\n")
    res = cli_here(capfd, "replay", "--config", str(config), *files)  # by main() in this process: the same handler and lines
    assert res.returncode == 0, res.stderr
    said = [line for line in res.stderr.splitlines() if "its own settings" in line]
    assert len(said) == 1 and said[0].endswith("the config's [window], [spikes]"), res.stderr
    plain = cli_here(capfd, "replay", *files)
    assert plain.returncode == 0 and "its own settings" not in plain.stderr


@pytest.mark.parametrize(("argv", "message"), [
    (("demo", "--headless", "--scene", "nonsense"), "unknown scene 'nonsense'"),
    (("curve-keys", "README.md", "daemon"), "README.md: exists and is not a folder"),
    (("features", "tests/hostile/rec-good.npz", "-o", "/no/such/folder/f.npz"), "folder /no/such/folder does not exist"),
    (("train", "tests/hostile/rec-good.npz", "-o", "/no/such/folder/m.npz"), "folder /no/such/folder does not exist"),
])
def test_first_day_mistakes_get_one_line_before_any_work(argv: tuple[str, ...], message: str, capfd: pytest.CaptureFixture[str],
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(REPO)  # the paths are the checkout's
    res = cli_here(capfd, *argv)  # by main() in this process: the same handler and line
    assert res.returncode == 2 and message in res.stderr and len(res.stderr.strip().splitlines()) == 1, res.stderr


@pytest.mark.parametrize("argv, message", [
    (["train", "x.npz", "-o", "{missing}/m.npz"], "folder {missing} does not exist"),
    (["train", "x.npz", "-o", "{tmp}/m.txt"], "m.txt: must end in .npz"),
    (["train", "x.npz", "-o", "{existing}"], "exists (--force overwrites it)"),
    (["features", "x.npz", "-o", "{existing}"], "exists (--force overwrites it)"),
    (["features", "x.npz", "-o", "{tmp}/f.csv"], "f.csv: must end in .npz"),
    (["evaluate", "a.npz", "b.npz", "--report", "{full}"], "folder exists and is not empty"),
    (["export", "x.npz", "-o", "{tmp}/x.json"], "x.json: must end in .mcap"),
    (["record", "--seconds", "1", "-o", "{tmp}/x.txt"], "x.txt: must end in .npz"),
    (["recover", "j.journal", "-o", "{existing}"], "exists (--force overwrites it)"),
    (["run", "--record", "{tmp}/r.mcap"], "r.mcap: must end in .npz"),
    (["run", "--raw", "{tmp}/r.npz"], "r.npz: must end in .bin"),
    (["simulate", "figure", "-o", "{tmp}/f.jpg"], "f.jpg: must end in .png"),
    (["simulate", "dataset", "--out", "{existing}"], "exists and is not a folder"),
    (["simulate", "serial", "--link", "{existing}", "--seconds", "1"], "old.npz: exists and is not a symlink"),
    (["simulate", "serial", "--link", "{missing}/tty", "--seconds", "1"], "folder {missing} does not exist"),
    (["simulate", "serial", "--log", "{existing}", "--seconds", "1"], "old.npz: exists (--force overwrites it)"),
    (["curve-keys", "{existing}", "daemon"], "exists and is not a folder"),
    (["curve-keys", "{full}", "robot"], "robot.key: exists (--force overwrites it)"),
])
def test_every_output_is_checked_before_any_work(argv: list[str], message: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """One policy (docs/cli.md): folder there and writable, the right extension, nothing replaced without --force; one line, exit 2."""
    existing, full = tmp_path / "old.npz", tmp_path / "full"
    existing.write_bytes(b"")
    full.mkdir()
    (full / "robot.key").write_text("")
    names = {"tmp": str(tmp_path), "missing": str(tmp_path / "missing"), "existing": str(existing), "full": str(full)}
    assert main([a.format(**names) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert message.format(**names) in err and len(err.splitlines()) == 1, err


def test_a_dataset_folder_takes_more_scenes_but_replaces_nothing_unasked(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = ["simulate", "dataset", "--out", str(tmp_path / "d"), "--surfaces", "2", "--files-per-surface", "1", "--slides-per-file", "1"]
    assert main(base) == 0 and main([*base, "--scene", "robot"]) == 0  # another scene beside the first
    capsys.readouterr()
    assert main(base) == 2 and "hand_Ra0.44_00.npz: exists (2 of the files to write do; --force replaces them)" in capsys.readouterr().err
    assert main([*base, "--force"]) == 0


def test_config_example_prints_the_shipped_example_that_loads(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from tactiled.config import load_config

    assert main(["config", "--example"]) == 0
    text = capsys.readouterr().out
    assert text == (REPO / "configs" / "tactiled.toml").read_text(encoding="utf-8") and "[sensor]" in text
    (tmp_path / "my.toml").write_text(text)
    load_config(tmp_path / "my.toml")  # raises on any bad key


def test_the_process_exits_with_mains_code_after_freezing_its_objects(monkeypatch: pytest.MonkeyPatch) -> None:
    """``run`` (the console script, ``python -m tactiled``): main's return value is the exit code, and the objects are frozen out
    of the cycle collector just before (the exit's collections skip them); main's own callers (these tests) are not frozen."""
    import gc
    import importlib

    cli_main = importlib.import_module("tactiled.cli.main")  # the module: tactiled.cli's own ``main`` is the function
    seen: list[str] = []
    monkeypatch.setattr(cli_main, "main", lambda: seen.append("main") or 3)
    monkeypatch.setattr(gc, "freeze", lambda: seen.append("freeze"))
    with pytest.raises(SystemExit) as stop:
        cli_main.run()
    assert stop.value.code == 3 and seen == ["main", "freeze"]


def test_python_m_tactiled_prints_everything_and_exits_with_the_code(tmp_path: Path) -> None:
    """The frozen exit loses no output: every slide line and the summary of a replay, exit 0; a usage error exits 2."""
    import sys

    from tactiled.files.recording import save_recording
    from tests.conftest import lossy_recording

    save_recording(tmp_path / "r.npz", lossy_recording(0))
    out = subprocess.run([sys.executable, "-m", "tactiled", "replay", str(tmp_path / "r.npz")], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.count(": slide ") == 3 and "3 slides, " in out.stdout.splitlines()[-1], out
    bad = subprocess.run([sys.executable, "-m", "tactiled", "replay", str(tmp_path / "missing.npz")], capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "missing.npz" in bad.stderr


def test_a_command_runs_numpys_blas_on_one_thread(tmp_path: Path) -> None:
    """The handler imports numpy after main set the thread variables (unless the environment sets them): OpenBLAS loads with
    one thread (threadpoolctl before numpy was loaded limited nothing), and the variables reach the command's workers."""
    import sys

    from tactiled.files.recording import save_recording
    from tests.conftest import lossy_recording

    save_recording(tmp_path / "r.npz", lossy_recording(0))
    code = ("import contextlib, io, os, sys\nfrom tactiled.cli.main import main\nassert 'numpy' not in sys.modules\n"
            "with contextlib.redirect_stdout(io.StringIO()):\n    assert main(['replay', sys.argv[1]]) == 0\n"
            "from threadpoolctl import threadpool_info\n"
            "print([i['num_threads'] for i in threadpool_info() if i['internal_api'] == 'openblas'], os.environ['OMP_NUM_THREADS'])")
    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", code, str(tmp_path / "r.npz")], capture_output=True, text=True, timeout=120, env=env)
    assert out.returncode == 0 and out.stdout.split()[-2:] in (["[1]", "1"], ["[]", "1"]), out


def test_replay_sets_glibcs_heap_thresholds_and_prints_the_same(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """Each file a replay plays (in this process or a worker) asks glibc to keep the pipeline's temporaries in its heap
    (:func:`tactiled.run.heap.keep_freed_memory`: mallopt succeeds on glibc, elsewhere it is a no-op), and the same lines
    are printed with it as without."""
    import platform
    import sys

    from tactiled.files.recording import save_recording
    from tactiled.service import replay_files
    from tests.conftest import lossy_recording

    path = str(tmp_path / "r.npz")
    save_recording(path, lossy_recording(0))
    out = subprocess.run([sys.executable, "-c", "from tactiled.run.heap import keep_freed_memory; print(keep_freed_memory())"],
                         capture_output=True, text=True, timeout=60, check=True)
    assert out.stdout.strip() == str(platform.libc_ver()[0] == "glibc")
    calls: list[int] = []
    monkeypatch.setattr(replay_files, "keep_freed_memory", lambda: calls.append(1) or False)
    assert main(["replay", path, path]) == 0 and calls == [1, 1]
    without = capsys.readouterr().out
    monkeypatch.undo()
    assert main(["replay", path, path]) == 0 and capsys.readouterr().out == without and ": slide " in without


def test_train_offers_the_choices_the_trainer_takes() -> None:
    """train's options are written out in the parser (it imports no learning code, for a quick --help); they are the trainer's."""
    from tactiled.learn.search import ENSEMBLE_DEFAULT, ENSEMBLE_MODES, NOVELTY_DEFAULT, NOVELTY_TESTS

    options = {a.dest: a for a in COMMANDS["train"]._actions}
    assert sorted(options["novelty"].choices) == sorted(NOVELTY_TESTS) and options["novelty"].default == NOVELTY_DEFAULT
    assert sorted(options["ensemble"].choices) == sorted(ENSEMBLE_MODES) and options["ensemble"].default == ENSEMBLE_DEFAULT


def test_train_writes_its_model_when_its_output_is_closed_early(tmp_path: Path) -> None:
    """``tactiled train ... | head -3``: the model is written before the leaderboard is printed (it was lost with the pipe)."""
    from tactiled.sim.simulate import write_dataset

    out = tmp_path / "m.npz"
    data = write_dataset(tmp_path / "d", scene="robot", seed=0, files_per_surface=2, slides_per_file=2, surfaces="2")
    proc = subprocess.Popen(tactiled_cmd("train", "--method", "quick", "--folds", "2", "-o", str(out), *map(str, data)),
                            stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
    assert proc.stdout is not None
    proc.stdout.close()  # the reader went away before the first line
    proc.wait(300)
    assert load_model(out).fingerprint


@pytest.mark.parametrize("module", ["tactiled.config", "tactiled.cli.main"])
@pytest.mark.parametrize("entry", ["console script", "-m"])
def test_ctrl_c_while_the_command_line_imports_exits_1_without_a_traceback(module: str, entry: str) -> None:
    """A real SIGINT, sent by the process to itself as ``module`` starts to import (the hook stands in for a user's quick
    Ctrl-C, which lands there in a bare start-up's first ~40 ms): one exit 1, nothing on stderr, as a Ctrl-C during a command."""
    start = ("from tactiled.cli.entry import run; run()" if entry == "console script"
             else "import runpy; runpy.run_module('tactiled', run_name='__main__')")
    code = ("import builtins, os, signal\n"
            "real = builtins.__import__\n"
            "def hook(name, *a, **k):\n"
            f"    if name == {module!r}:\n"
            "        builtins.__import__ = real\n"
            "        os.kill(os.getpid(), signal.SIGINT)\n"
            "    return real(name, *a, **k)\n"
            "builtins.__import__ = hook\n"
            "import sys; sys.argv = ['tactiled', '--help']\n" + start)
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, cwd=REPO)
    assert (proc.returncode, proc.stderr) == (1, ""), proc.stderr
    assert "usage:" not in proc.stdout  # stopped before the help
