"""The examples of docs/integrations.md are the files in docs/examples/, and they run as written.

The ROS 2 and LSL demos run inside a private network namespace (``unshare -rn``, loopback only),
with the simulated fingertip, each in a fresh temporary folder it is given.
"""

from __future__ import annotations

import ast
import importlib
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

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


def run_demo(script: str, folder: Path) -> str:
    probe = subprocess.run(["unshare", "-rn", "true"], capture_output=True, text=True)
    if probe.returncode != 0:
        pytest.skip(f"unshare -rn (a private network namespace) is not permitted here: {probe.stderr.strip()}")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}", "ROS_DOMAIN_ID": "43"}
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
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"}
    res = subprocess.run(["sh", str(EXAMPLES / "mcap_demo.sh"), str(tmp_path / "demo")], capture_output=True, text=True, timeout=300,
                         cwd=tmp_path, env=env)
    assert res.returncode == 0, res.stderr[-3000:]
    assert re.search(r"slides.mcap: \d+ samples messages, 3 slides, \d+ roughness messages", res.stdout), res.stdout
    assert re.search(r"slides_ros2.mcap: \d+ samples messages, 3 slides", res.stdout), res.stdout
    assert len(re.findall(r"^/tactiled/fingertip0/roughness \d \d+ Ra[\d.]+ [\d.]+$", res.stdout, flags=re.M)) == 3, res.stdout


def test_ros2_demo_runs_as_written(tmp_path: Path) -> None:
    importlib.import_module("rclpy")  # in the dev extras: a missing one fails
    out = run_demo("ros2_demo.sh", tmp_path)
    assert re.search(r"labels: \['Ra[\d.]+', 'Ra[\d.]+'\]; a batch of \d+ samples from index \d+ at \d+\.\d{9}", out), out


def doc_commands(text: str) -> list[str]:
    """The ``tactiled ...`` command lines of a markdown text's shell code (indented blocks, and fences that are not
    Python), each cut at the first shell operator (``|``, ``>``, ``&&``, ``&``, ``;``, ``#``)."""
    out, fence = [], None
    for line in text.splitlines():
        stripped = line.strip()
        if stripped.startswith("```"):
            fence = None if fence is not None else stripped[3:] or "text"
            continue
        command = stripped.removeprefix("$ ")
        if command.startswith("tactiled ") and (fence not in (None, "python") or (fence is None and line.startswith("    "))):
            out.append(re.split(r"\s(?:\||>|&&|&|;|#)(?:\s|$)", command)[0])
    return out


def test_every_command_in_the_readme_and_docs_parses() -> None:
    """Each tactiled command line shown in README.md and docs/*.md is accepted by the parser as written (docs/cli.md is
    the parser's own help): no option the CLI has renamed or dropped, no value it refuses."""
    import contextlib
    import io
    import shlex

    parser, bad, checked = build_parser(), [], 0
    for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]:
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
