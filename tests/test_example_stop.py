"""clients/example_controller.py stops on Ctrl-C as the README says it is stopped: one line, no traceback."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

from tests.conftest import REPO


def test_ctrl_c_stops_the_controller_without_a_traceback(tmp_path: Path) -> None:
    ctl = subprocess.Popen([sys.executable, str(REPO / "clients" / "example_controller.py"), f"ipc://{tmp_path}/no-daemon"],
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert ctl.stdout is not None
        first = ctl.stdout.readline()  # it listens (no daemon: it waits)
        assert first.startswith("controller: labels from ipc://"), first
        ctl.send_signal(signal.SIGINT)
        out, err = ctl.communicate(timeout=20)
    finally:
        ctl.kill()
    assert ctl.returncode == 0 and out.strip().endswith("stopped") and "Traceback" not in err, (out, err)
