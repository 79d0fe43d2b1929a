"""What a checkout's wheels hold: tactiled depends on tactiled-client, which alone owns tactiled_client, and the file the
systemd unit names in Documentation= is one the tactiled wheel installs.

The wheels are built as pip builds them (``pip wheel --no-deps``, offline: ``--no-build-isolation --no-index`` with the
venv's setuptools from the dev extra) from a copy of the sources, so the checkout's build/ folders are left alone.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.conftest import REPO

UNIT = REPO / "systemd" / "tactiled@.service"


def _copy_sources(dest: Path, *, clients: bool) -> Path:
    dest.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy2(REPO / name, dest / name)
    for name in ("tactiled", "clients") if clients else ("tactiled",):
        shutil.copytree(REPO / name, dest / name, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    return dest


@dataclass
class Built:
    src: Path  # the copy of the checkout
    wheels: dict[str, zipfile.ZipFile]  # tactiled, tactiled-client, and alone: tactiled built without clients/ beside it (as from its sdist)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Built:
    root = tmp_path_factory.mktemp("packaging")
    src = _copy_sources(root / "src", clients=True)
    alone = _copy_sources(root / "alone", clients=False)
    # what a build of this checkout from before tactiled-client was split off left: setuptools puts build/lib in the wheel
    (src / "build" / "lib" / "tactiled_client").mkdir(parents=True)
    (src / "build" / "lib" / "tactiled_client" / "__init__.py").write_text("")
    builds = {name: (folder, root / f"out-{name}") for name, folder in (("tactiled", src), ("tactiled-client", src / "clients"), ("alone", alone))}
    procs = {name: subprocess.Popen([sys.executable, "-m", "pip", "wheel", "-q", "--no-deps", "--no-build-isolation", "--no-index", "-w", str(out),
                                     str(folder)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for name, (folder, out) in builds.items()}
    found: dict[str, zipfile.ZipFile] = {}
    for name, proc in procs.items():
        log, _ = proc.communicate(timeout=300)
        assert proc.returncode == 0, f"pip wheel {builds[name][0]} failed (setuptools>=70.1 from pip install -e '.[dev]'?):\n{log}"
        (whl,) = builds[name][1].glob("*.whl")
        found[name] = zipfile.ZipFile(whl)
    return Built(src, found)


def _dist_info(whl: zipfile.ZipFile) -> str:
    (name,) = {n.split("/")[0] for n in whl.namelist() if n.split("/")[0].endswith(".dist-info")}
    return name


def _record(whl: zipfile.ZipFile) -> list[str]:
    return [line.split(",")[0] for line in whl.read(f"{_dist_info(whl)}/RECORD").decode().splitlines() if line]


def _metadata(whl: zipfile.ZipFile, field: str) -> list[str]:
    head = whl.read(f"{_dist_info(whl)}/METADATA").decode().split("\n\n")[0]
    return [line.split(": ", 1)[1] for line in head.splitlines() if line.startswith(f"{field}: ")]


def test_tactiled_owns_no_client_file_and_requires_the_client_from_the_checkout(built: Built) -> None:
    record = _record(built.wheels["tactiled"])
    assert "tactiled/__init__.py" in record and "tactiled/data/default_model.npz" in record
    assert [p for p in record if not p.startswith(("tactiled/", "tactiled-"))] == []  # no tactiled_client/ (not even the stale build/)
    client = [r for r in _metadata(built.wheels["tactiled"], "Requires-Dist") if r.startswith("tactiled-client")]
    assert client == [f"tactiled-client @ {(built.src / 'clients').as_uri()}"]


def test_tactiled_built_without_clients_beside_it_requires_the_same_version_from_an_index(built: Built) -> None:
    wheels = built.wheels
    (version,) = _metadata(wheels["alone"], "Version")
    assert [r for r in _metadata(wheels["alone"], "Requires-Dist") if r.startswith("tactiled-client")] == [f"tactiled-client=={version}"]
    assert _metadata(wheels["tactiled-client"], "Version") == [version]  # the pin names a version the client has


def test_the_client_wheel_owns_the_client_library(built: Built) -> None:
    record = _record(built.wheels["tactiled-client"])
    sources = sorted([*(f"tactiled_client/{p.name}" for p in (REPO / "clients" / "tactiled_client").glob("*.py")), "tactiled_client/py.typed"])
    assert sorted(p for p in record if p.startswith("tactiled_client/")) == sources
    assert [p for p in record if not p.startswith(("tactiled_client/", "tactiled_client-"))] == []


def test_the_unit_documentation_is_a_file_the_wheel_installs(built: Built) -> None:
    """Documentation=file://PREFIX/share/... where PREFIX is that of ExecStart's PREFIX/bin/tactiled: the wheel's
    ``<name>.data/data/share/...`` is installed under the prefix (sys.prefix: the README's venv /opt/tactiled)."""
    keys = [line.split("=", 1) for line in UNIT.read_text().splitlines() if "=" in line and not line.startswith("#")]
    (exec_start,) = [v for k, v in keys if k == "ExecStart"]
    prefix = exec_start.split()[0].removesuffix("/bin/tactiled")
    (doc,) = [v for k, v in keys if k == "Documentation"]
    assert doc.startswith(f"file://{prefix}/"), (doc, prefix)
    whl = built.wheels["tactiled"]
    data = f"{_dist_info(whl).removesuffix('.dist-info')}.data/data/{doc.removeprefix(f'file://{prefix}/')}"
    assert data in _record(whl)
    assert whl.read(data) == (REPO / "README.md").read_bytes()
