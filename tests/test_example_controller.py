"""clients/example_controller.py runs as its docstring says, against the demo daemon, and takes any label name."""

from __future__ import annotations

import importlib.util
import queue
import subprocess
import sys
import threading
from pathlib import Path
from types import ModuleType

from tests.conftest import REPO, tactiled_cmd, wait_for

EXAMPLE = REPO / "clients" / "example_controller.py"


def _example() -> ModuleType:
    spec = importlib.util.spec_from_file_location("example_controller", EXAMPLE)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_rough_or_not_for_any_label_name() -> None:
    ex = _example()
    assert ex.is_rough("Ra4.43", 2.0, set()) and not ex.is_rough("Ra0.44", 2.0, set())
    assert ex.is_rough("P60", 2.0, {"P60"}) and not ex.is_rough("P120", 2.0, {"P60"}) and not ex.is_rough("Rayon", 2.0, set())


def test_controller_steers_on_the_demo_daemons_labels(tmp_path: Path) -> None:
    endpoint = f"ipc://{tmp_path}/demo"
    demo = subprocess.Popen(tactiled_cmd("demo", "--publish", endpoint, "--headless", "--seconds", "120", "--scene", "robot"),
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    ctl = subprocess.Popen([sys.executable, str(EXAMPLE), endpoint], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines: queue.Queue[str] = queue.Queue()
    assert ctl.stdout is not None
    reader = threading.Thread(target=lambda: [lines.put(line) for line in ctl.stdout], daemon=True)  # type: ignore[union-attr]
    reader.start()
    seen: list[str] = []

    def steered() -> bool:
        try:
            seen.append(lines.get(timeout=1.0))
        except queue.Empty:
            return False
        return any(" final Ra" in line for line in seen) and any("-> sliding speed" in line for line in seen)

    try:
        wait_for(steered, timeout=120, what="a final label and a speed from the controller")
    finally:
        ctl.terminate()
        demo.terminate()
        ctl.wait(10)
        demo.wait(30)
    assert all("Traceback" not in line for line in seen)
    assert not processes_naming(str(tmp_path)), "SIGTERM to the demo left its board or daemon running"


def processes_naming(text: str) -> list[int]:
    """PIDs of the processes whose command line contains ``text``."""
    pids = []
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            if text.encode() in cmdline.read_bytes():
                pids.append(int(cmdline.parent.name))
        except OSError:
            continue
    return pids
