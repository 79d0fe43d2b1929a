"""The examples of README.md and docs/*.md run as written.

Every code block of README.md and docs/*.md (but the files in ``UNMARKED``) has an HTML comment on the line before it,
which renders invisibly: ``<!-- runnable -->`` (``test_runnable_blocks_run_in_a_fresh_folder`` runs it, with the
simulator; ``<!-- runnable: exits 2 -->`` for an example of a refusal) or ``<!-- not runnable: REASON -->`` saying why
not (needs hardware, root, a running daemon; runs until stopped; a measurement that takes minutes; a diagram). The
runnable blocks of a file run in order in one fresh temporary folder (a shell block by ``bash -euo pipefail``, a
Python one by this venv's python; the venv's bin first on PATH), so that a block may use what an earlier one made; the
checkout's files the docs name as inputs (``INPUTS``) are copies there. A runnable block names no ``tcp://``
endpoint (nor an ``ipc:///`` one outside its folder), and one that needs the network or multicast (LSL, ROS 2) is not runnable.

The examples of docs/integrations.md are the files in docs/examples/, and they run as written. The ROS 2 and LSL
demos run inside a private network namespace (``unshare -rn``, loopback only), with the simulated fingertip, each in
a fresh temporary folder it is given.
"""

from __future__ import annotations

import ast
import importlib
import os
import re
import shutil
import subprocess
import sys
from dataclasses import dataclass
from pathlib import Path

import pytest
from markdown_it import MarkdownIt

from tactiled.cli.main import build_parser
from tests.conftest import REPO

EXAMPLES = REPO / "docs" / "examples"


def test_integrations_md_shows_every_example_file_as_it_is() -> None:
    doc = (REPO / "docs" / "integrations.md").read_text()
    blocks = re.findall(r"```(?:bash|python)\n(.*?)```", doc, flags=re.S)
    for path in sorted(EXAMPLES.iterdir()):
        if path.suffix in (".sh", ".py"):
            assert path.read_text() in blocks, f"{path.name} is not shown as it is in docs/integrations.md"


def test_the_launch_files_command_is_one_tactiled_accepts() -> None:
    tree = ast.parse((EXAMPLES / "tactiled_bridge.launch.py").read_text())
    cmd = next(ast.literal_eval(n.value) for n in tree.body if isinstance(n, ast.Assign) and getattr(n.targets[0], "id", "") == "CMD")
    args = build_parser().parse_args(cmd[1:])
    assert cmd[0] == "tactiled" and args.command == "ros2" and args.ros_args[:2] == ["-r", "__ns:=/robot1"]


def venv_env(**extra: str) -> dict[str, str]:
    """This process's environment with the venv's bin first on PATH (``tactiled`` and ``python`` are the venv's), and ``extra``."""
    return {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}", **extra}


def run_demo(script: str, folder: Path) -> str:
    probe = subprocess.run(["unshare", "-rn", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"unshare -rn (a private network namespace) is not permitted here: {probe.stderr.strip()}")
    env = venv_env(ROS_DOMAIN_ID="43")
    res = subprocess.run(["unshare", "-rn", "sh", str(EXAMPLES / script), str(folder / "demo")], capture_output=True, text=True,
                         timeout=150, cwd=folder, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    return res.stdout


def test_lsl_demo_runs_as_written(tmp_path: Path) -> None:
    importlib.import_module("pylsl")  # in the dev extras: a missing one fails
    out = run_demo("lsl_demo.sh", tmp_path)
    m = re.search(r"sensor fingertip0 at 20000.0 Hz: (\d+) samples, 0 stamps not increasing, (\d+) loss markers; first label: Ra", out)
    assert m and int(m.group(1)) > 0, out


def test_mcap_demo_runs_as_written(tmp_path: Path) -> None:
    importlib.import_module("mcap")  # in the dev extras: a missing one fails
    importlib.import_module("rosbags")  # in the dev extras: a missing one fails
    res = subprocess.run(["sh", str(EXAMPLES / "mcap_demo.sh"), str(tmp_path / "demo")], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path, env=venv_env())
    assert res.returncode == 0, res.stderr[-3000:]
    assert re.search(r"slides.mcap: \d+ samples messages, 3 slides, \d+ roughness messages", res.stdout), res.stdout
    assert re.search(r"slides_ros2.mcap: \d+ samples messages, 3 slides", res.stdout), res.stdout
    assert len(re.findall(r"^/tactiled/fingertip0/roughness \d \d+ Ra[\d.]+ [\d.]+$", res.stdout, flags=re.M)) == 3, res.stdout


def test_ros2_demo_runs_as_written(tmp_path: Path) -> None:
    importlib.import_module("rclpy")  # in the dev extras: a missing one fails
    out = run_demo("ros2_demo.sh", tmp_path)
    assert re.search(r"labels: \['Ra[\d.]+', 'Ra[\d.]+'\]; a batch of \d+ samples from index \d+ at \d+\.\d{9}", out), out


@dataclass(frozen=True)
class Block:
    """A code block of a markdown text, as CommonMark reads it (indented or fenced)."""

    line: int  # its first line, from 1 (a fence's opening line)
    lang: str  # a fence's info string ("python", "bash"); "" for an indented block or a bare fence
    code: str
    marker: str  # the HTML comment on the line before it ("" if none)

    @property
    def exit_code(self) -> int | None:
        """The exit status a runnable block must end with; None if it is not runnable."""
        m = MARKER.fullmatch(self.marker)
        return None if m is None or m["why"] is not None else int(m["exit"] or 0)


MARKER = re.compile(r"<!-- (?:runnable(?:: exits (?P<exit>\d+))?|not runnable: (?P<why>\S.*?)) -->")


def code_blocks(text: str) -> list[Block]:
    """The code blocks of a markdown text, in order, each with the comment on the line before it."""
    tokens = MarkdownIt("commonmark").parse(text)
    comments = {t.map[1]: t.content.strip() for t in tokens if t.type == "html_block" and t.map}
    return [Block(t.map[0] + 1, t.info.strip(), t.content, comments.get(t.map[0], ""))
            for t in tokens if t.type in ("fence", "code_block") and t.map]


def doc_commands(text: str) -> list[str]:
    """The ``tactiled ...`` command lines of a markdown text's shell code (indented blocks, and fences that are not
    Python), each cut at the first shell operator (``|``, ``>``, ``&&``, ``&``, ``;``, ``#``)."""
    lines = [line.strip().removeprefix("$ ") for block in code_blocks(text) if block.lang != "python" for line in block.code.splitlines()]
    return [re.split(r"\s(?:\||>|&&|&|;|#)(?:\s|$)", command)[0] for command in lines if command.startswith("tactiled ")]


DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
UNMARKED = {
    "cli.md": "the --help of every command, generated from the parser (tactiled/cli/clidoc.py); "
              "test_cli.py parses the example each ends with",
}
INPUTS = ("tests/hostile",)  # the checkout's files that runnable blocks read, copied into their folder


def runnable_blocks(doc: Path) -> list[Block]:
    return [b for b in code_blocks(doc.read_text(encoding="utf-8")) if b.exit_code is not None]


@pytest.mark.parametrize("name", [str(d.relative_to(REPO)) for d in DOCS if d.name not in UNMARKED and runnable_blocks(d)])
def test_runnable_blocks_run_in_a_fresh_folder(name: str, tmp_path: Path) -> None:
    for folder in INPUTS:
        shutil.copytree(REPO / folder, tmp_path / folder, ignore=shutil.ignore_patterns("__pycache__"))
    (tmp_path / "run").mkdir()  # the default endpoints (tactiled_client.endpoints): a daemon started without --publish binds there
    env = venv_env(TACTILED_RUNTIME_DIR=str(tmp_path / "run"), PYTHONUNBUFFERED="1")
    for block in runnable_blocks(REPO / name):
        argv = [sys.executable, "-c", block.code] if block.lang == "python" else ["bash", "-euo", "pipefail", "-c", block.code]
        res = subprocess.run(argv, capture_output=True, text=True, timeout=120, cwd=tmp_path, env=env)
        assert res.returncode == block.exit_code, (f"{name}:{block.line} exited {res.returncode}, not {block.exit_code}:\n"
                                                   f"{res.stdout[-2000:]}\n{res.stderr[-3000:]}")


def test_every_code_block_is_marked_runnable_or_says_why_not() -> None:
    """A new example cannot slip in untried: each block says whether the test above runs it, or why not."""
    bad, runnable = [], 0
    for doc in DOCS:
        if doc.name in UNMARKED:
            continue
        for block in code_blocks(doc.read_text(encoding="utf-8")):
            where = f"{doc.relative_to(REPO)}:{block.line}: {block.code.strip().splitlines()[0][:60]}"
            if not MARKER.fullmatch(block.marker):
                bad.append(f"{where}: no <!-- runnable --> or <!-- not runnable: REASON --> on the line before it")
            elif block.exit_code is not None:
                runnable += 1
                if re.search(r"tcp://|ipc:///", block.code):
                    bad.append(f"{where}: a runnable block names a tcp:// endpoint, or an ipc:/// one outside its folder "
                               "(use ipc://NAME, relative to the folder, or the default)")
    assert not bad, "\n".join(bad)
    assert runnable >= 5 and set(UNMARKED) <= {d.name for d in DOCS}


def test_every_command_in_the_readme_and_docs_parses() -> None:
    """Each tactiled command line shown in README.md and docs/*.md is accepted by the parser as written (docs/cli.md is
    the parser's own help): no option the CLI has renamed or dropped, no value it refuses."""
    import contextlib
    import io
    import shlex

    parser, bad, checked = build_parser(), [], 0
    for doc in DOCS:
        if doc.name == "cli.md":
            continue
        for command in doc_commands(doc.read_text(encoding="utf-8")):
            checked += 1
            err = io.StringIO()
            try:
                with contextlib.redirect_stderr(err):
                    parser.parse_args(shlex.split(command)[1:])
            except SystemExit as exc:
                if exc.code:
                    bad.append(f"{doc.name}: {command}: {err.getvalue().strip()}")
    assert not bad, "\n".join(bad)
    assert checked >= 20  # the README and docs show that many command lines
