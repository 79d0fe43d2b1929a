from __future__ import annotations

from pathlib import Path

import pytest

from tactiled.config import Config, is_local_endpoint, load_config, parse_config
from tactiled.errors import ConfigError
from tests.conftest import REPO, run_cli


def test_shipped_config_is_valid_and_matches_defaults() -> None:
    assert load_config(REPO / "configs" / "tactiled.toml") == Config()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[detector]\non_factor = 2.0\n", "detector.on_factor: must be > detector.off_factor"),
        ("[sensor]\nfs = -1\n", "sensor.fs: must be > 0 Hz"),
        ("[sensor]\nfs = 'fast'\n", "sensor.fs: must be a number"),
        ("[sensr]\nfs = 1\n", "sensr: unknown key"),
        ("[window]\nstrt_s = 1\n", "window.strt_s: unknown key"),
        ("[features]\nstats = ['mean', 'median']\n", "features.stats: must be a non-empty subset"),
        ("[publish]\nendpoint = 'tcp://0.0.0.0:7350'\n", "publish.endpoint: binds a non-loopback address"),
        ("[spikes\n", "not valid TOML"),
    ],
)
def test_bad_values_name_the_key(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")):
        parse_config(text, "x.toml")


def test_override_revalidates() -> None:
    config = Config().override({"sensor.port": "/dev/ttyUSB3", "sensor.fs": None})
    assert config.sensor.port == "/dev/ttyUSB3"
    with pytest.raises(ConfigError, match=r"sensor\.channels"):
        Config().override({"sensor.channels": 9})


def test_local_endpoints() -> None:
    assert is_local_endpoint("tcp://127.0.0.1:1") and is_local_endpoint("ipc:///tmp/x") and is_local_endpoint("tcp://[::1]:5")
    assert not is_local_endpoint("tcp://0.0.0.0:1") and not is_local_endpoint("tcp://*:1")


def test_check_config_cli(tmp_path: Path) -> None:
    ok = run_cli("check-config", str(REPO / "configs" / "tactiled.toml"))
    assert ok.returncode == 0, ok.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[detector]\nmin_slide_s = 0\n")
    res = run_cli("check-config", str(bad))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"tactiled: error: {bad}: detector.min_slide_s: must be in (0, 60] s"]
