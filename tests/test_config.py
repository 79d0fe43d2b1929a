from __future__ import annotations

from pathlib import Path

import pytest

from tactiled.config import Config, is_local_endpoint, load_config, parse_config
from tactiled.errors import ConfigError
from tests.conftest import REPO, cli_here, run_cli


def test_shipped_config_is_valid_and_matches_defaults() -> None:
    assert load_config(REPO / "configs" / "tactiled.toml") == Config()


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("[detector]\non_factor = 2.0\n", "detector.on_factor: must be > detector.off_factor"),
        ("[sensor]\nfs = -1\n", "sensor.fs: must be in [100, 1e6] Hz"),
        ("[sensor]\nfs = 1e12\n", "sensor.fs: must be in [100, 1e6] Hz"),
        ("[sensor]\nfs = 0.01\n", "sensor.fs: must be in [100, 1e6] Hz"),
        ("[sensor]\nfs = inf\n", "sensor.fs: must be a finite number"),
        ("[sensor]\nfs = nan\n", "sensor.fs: must be a finite number"),
        ("[serial]\nretry_max_s = inf\n", "serial.retry_max_s: must be a finite number"),
        ("[serial]\nrest_batch_s = 2\n", "serial.rest_batch_s: must be in [0, 1] s"),
        ("[detector]\nhop_ms = -inf\n", "detector.hop_ms: must be a finite number"),
        ("[publish]\nstatus_interval_s = nan\n", "publish.status_interval_s: must be a finite number"),
        ("[ring]\nseconds = 1e9\n", "ring.seconds: must be in [1, 3600] s"),
        ("[ring]\nseconds = 3600\n[sensor]\nfs = 1e6\nchannels = 8\n", "ring.seconds: 3600 s of 8 channels at 1e\\+06 Hz would take"),
        ("[spikes]\nhalf_width = 100000000\n", "spikes.half_width: must be in 1..1000"),
        ("[sensor]\nbaudrate = 9223372036854775808\n", "sensor.baudrate: must be an integer"),
        ("[sensor]\nbaudrate = 9223372036854775807\n", "sensor.baudrate: must be an integer"),
        ("[sensor]\nbaudrate = 0\n", "sensor.baudrate: must be in 50..12000000"),
        ("[sensor]\nbaudrate = 115200.0\n", "sensor.baudrate: must be an integer"),
        ("[sensor]\nport = 'socket://10.0.0.1:4000'\n", "sensor.port: is a URL \\(socket://\\), not a device path; set sensor.allow_url = true"),
        ("[sensor]\nport = 'rfc2217://h:1'\n", "sensor.port: is a URL"),
        ("[sensor]\nport = 'loop://'\n", "sensor.port: is a URL"),
        ("x = " + "[" * 500 + "]" * 500 + "\n", "not valid TOML: arrays or tables nested too deeply"),
        ("x = " + "{a = " * 500 + "1" + "}" * 500 + "\n", "not valid TOML: arrays or tables nested too deeply"),
        ("[features]\ndomains = " + repr(["time"] * 100) + "\n", "features.domains: must be a list of at most 64 strings"),
        ("[sensor]\nfs = 'fast'\n", "sensor.fs: must be a number"),
        ("[sensr]\nfs = 1\n", "sensr: unknown key"),
        ("[window]\nstrt_s = 1\n", "window.strt_s: unknown key"),
        ("[features]\nstats = ['mean', 'median']\n", "features.stats: must be a non-empty subset"),
        ("[publish]\nendpoint = 'tcp://0.0.0.0:7350'\n", "publish.endpoint: binds a non-loopback address"),
        ("[control]\nendpoint = 'tcp://0.0.0.0:7351'\n", "control.endpoint: must be empty, an ipc:// path or a tcp:// loopback address"),
        ("[control]\nendpoint = 'tcp://10.1.2.3:7351'\n", "control.endpoint: must be empty, an ipc:// path or a tcp:// loopback"),
        ("[spikes\n", "not valid TOML"),
    ],
)
def test_bad_values_name_the_key(text: str, message: str) -> None:
    with pytest.raises(ConfigError, match=message.replace("[", r"\[")) as err:
        parse_config(text, "x.toml")
    assert str(err.value).startswith("x.toml: ") and "\n" not in str(err.value)


def test_a_url_port_is_allowed_when_asked() -> None:
    assert parse_config("[sensor]\nport = 'loop://'\nallow_url = true\n").sensor.port == "loop://"


def test_config_size_is_bounded(tmp_path: Path) -> None:
    big = tmp_path / "big.toml"
    big.write_text("# " + "x" * (2 << 20) + "\n")
    with pytest.raises(ConfigError, match="larger than"):
        load_config(big)
    with pytest.raises(ConfigError, match="not UTF-8"):
        (tmp_path / "bin.toml").write_bytes(b"\xff\xfe[sensor]")
        load_config(tmp_path / "bin.toml")


def test_override_revalidates() -> None:
    config = Config().override({"sensor.port": "/dev/ttyUSB3", "sensor.fs": None})
    assert config.sensor.port == "/dev/ttyUSB3"
    with pytest.raises(ConfigError, match=r"sensor\.channels"):
        Config().override({"sensor.channels": 9})


def test_local_endpoints() -> None:
    assert is_local_endpoint("tcp://127.0.0.1:1") and is_local_endpoint("ipc:///tmp/x") and is_local_endpoint("tcp://[::1]:5")
    assert not is_local_endpoint("tcp://0.0.0.0:1") and not is_local_endpoint("tcp://*:1")


def test_check_config_cli(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    ok = cli_here(capfd, "check-config", str(REPO / "configs" / "tactiled.toml"))
    assert ok.returncode == 0, ok.stderr
    bad = tmp_path / "bad.toml"
    bad.write_text("[detector]\nmin_slide_s = 0\n")
    res = cli_here(capfd, "check-config", str(bad))
    assert res.returncode == 2
    assert res.stderr.strip().splitlines() == [f"tactiled: error: {bad}: detector.min_slide_s: must be in (0, 60] s"]


def test_a_missing_model_file_stops_only_the_commands_that_would_load_it(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A config whose model.path names a file that is gone: check-config, run and replay that would load it say so in one
    line naming the key, exit 2; check-config --no-model, run --model OTHER, replay --model OTHER and replay --no-model go on
    (every command that read the config refused it, even those that need no model: an outside audit)."""
    import numpy as np

    from tactiled.files.recording import Recording, save_recording

    gone = tmp_path / "gone.npz"
    cfg = tmp_path / "c.toml"
    cfg.write_text(f'[model]\npath = "{gone}"\n')
    rec = tmp_path / "r.npz"
    save_recording(rec, Recording(np.zeros((20_000, 2), dtype=np.int16), 20_000.0, 1e-4))
    shipped = str(REPO / "tactiled" / "data" / "default_model.npz")
    said = f"tactiled: error: {cfg}: model.path: {gone}: no such model file"
    for argv in (["check-config", str(cfg)], ["run", "--config", str(cfg), "--port", str(tmp_path / "none"), "--no-wait"],
                 ["replay", "--config", str(cfg), str(rec)]):
        res = cli_here(capfd, *argv)
        assert res.returncode == 2 and res.stderr.strip().splitlines() == [said], (argv, res.stderr)
    for argv in (["check-config", str(cfg), "--no-model"], ["replay", "--config", str(cfg), "--model", shipped, str(rec)],
                 ["replay", "--config", str(cfg), "--no-model", str(rec)]):
        res = cli_here(capfd, *argv)
        assert res.returncode == 0 and "model.path" not in res.stderr, (argv, res.stderr)
    res = run_cli("run", "--config", str(cfg), "--model", shipped, "--port", str(tmp_path / "none"), "--no-wait")
    assert "model.path" not in res.stderr and "none" in res.stderr, res.stderr  # on to the port, which is missing


def test_check_config_says_whether_run_would_find_a_model(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """A sensor at 2.2 kHz on one channel: the config is valid, but the shipped model does not fit it and no model.path is
    set, so run would refuse it: an error naming the key (it said "ok" and exit 0, an outside audit found); with --no-model
    (a config for record or run --no-model) it is ok. A model.path that does not fit is an error naming the key, as run
    refuses it."""
    sensor = "[sensor]\nfs = 2200\nchannels = 1\n"
    one = tmp_path / "one.toml"
    one.write_text(sensor)
    res = cli_here(capfd, "check-config", str(one))
    assert res.returncode == 2 and res.stdout == "", res.stdout
    assert res.stderr.strip().splitlines() == [
        f"tactiled: error: {one}: model.path: not set, and the shipped model does not fit this sensor (model trained at fs 20000 Hz, "
        "sensor fingertip0 is 2200 Hz): tactiled run would refuse it; train one (tactiled train) and set model.path, or check a "
        "config for record or run --no-model with --no-model"], res.stderr
    run = cli_here(capfd, "run", "--config", str(one), "--port", str(tmp_path / "none"), "--no-wait")
    assert run.returncode == 2 and "no model fits this sensor" in run.stderr, run.stderr  # what the check foretold
    res = cli_here(capfd, "check-config", str(one), "--no-model")
    assert res.returncode == 0 and res.stdout.strip() == f"{one}: ok (without a model)" and res.stderr == "", res.stderr
    named = tmp_path / "named.toml"
    named.write_text(sensor + f'[model]\npath = "{REPO / "tactiled" / "data" / "default_model.npz"}"\n')
    res = cli_here(capfd, "check-config", str(named))
    assert res.returncode == 2 and res.stderr.strip().splitlines() == [
        f"tactiled: error: {named}: model.path: {REPO / 'tactiled' / 'data' / 'default_model.npz'}: model trained at fs 20000 Hz, sensor fingertip0 is "
        "2200 Hz"], res.stderr
    assert cli_here(capfd, "check-config", str(REPO / "configs" / "tactiled.toml")).stderr == ""  # the shipped model fits: nothing to say
    lazy = tmp_path / "lazy.toml"  # 0.05 s between reads: 4.5 KiB of the standard board's frames wait, more than a tty holds
    lazy.write_text("[serial]\nread_interval_s = 0.05\n")
    res = cli_here(capfd, "check-config", str(lazy))
    assert res.returncode == 0 and "serial.read_interval_s = 0.05 s lets ~4.5 KiB of frames wait between reads" in res.stderr, res.stderr
    slow = tmp_path / "slow.toml"  # record works at 100 Hz; run --no-model cannot analyse: said, naming the keys (run said it alone)
    slow.write_text("[sensor]\nfs = 100\nchannels = 1\n")
    res = cli_here(capfd, "check-config", str(slow), "--no-model")
    assert res.returncode == 0 and "run --no-model cannot analyse with this config (record can record with it): " \
        "window.duration_s = 0.5 s at 100 Hz is too short for " \
        "features.families = dwt, psd, tex" in res.stderr, res.stderr
