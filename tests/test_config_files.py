"""The config files shipped in configs/: the unit's file is every default but its port, so it cannot drift from them."""

from __future__ import annotations

import dataclasses
from pathlib import Path

from tactiled.config import Config, load_config

REPO = Path(__file__).resolve().parents[1]


def test_the_units_config_is_the_defaults_but_its_port() -> None:
    unit = load_config(REPO / "configs" / "fingertip0.toml")
    assert unit.sensor.port == "/dev/tactile0"
    assert dataclasses.replace(unit, sensor=dataclasses.replace(unit.sensor, port=Config().sensor.port)) == Config()
    keys = {line.split("=")[0].strip() for line in (REPO / "configs" / "tactiled.toml").read_text().splitlines() if "=" in line and not line.startswith("#")}
    mine = {line.split("=")[0].strip() for line in (REPO / "configs" / "fingertip0.toml").read_text().splitlines() if "=" in line and not line.startswith("#")}
    assert mine == keys  # every key written out, as in the file of defaults
