"""simulate: a surface named twice is refused (its files would overwrite the first's), and a scene's figure draws that
scene's surfaces under its name (an audit found the grating scene's figure drawing the self-affine grades, titled
"None sliding")."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

import tactiled.sim.simulate as simulate
from tactiled.sim.physics import pick_surfaces
from tests.conftest import cli_here


def test_a_surface_named_twice_is_refused_before_any_file(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(ValueError, match=r"'Ra0\.44' is named twice"):
        pick_surfaces("Ra0.44,Ra1.00,Ra0.44")
    res = cli_here(capfd, "simulate", "dataset", "--out", str(tmp_path / "d"), "--surfaces", "Ra0.44,Ra0.44", "--files-per-surface", "1",
                   "--slides-per-file", "1")
    assert res.returncode == 2 and "'Ra0.44' is named twice" in res.stderr and not (tmp_path / "d").exists(), res.stderr


def test_a_scenes_figure_draws_its_own_surfaces_under_its_name(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    drawn: list[str] = []
    titles: list[str] = []

    def two(spec: Any, family: str = "self-affine", specimen: int = 0) -> list[Any]:
        surfaces = pick_surfaces(spec, family, specimen)[:2]  # two rows: the same code, a quicker figure
        drawn.extend(s.name for s in surfaces)
        return surfaces

    import matplotlib.axes

    set_title = matplotlib.axes.Axes.set_title
    monkeypatch.setattr(matplotlib.axes.Axes, "set_title", lambda self, text, *a, **k: (titles.append(text), set_title(self, text, *a, **k))[1])
    monkeypatch.setattr(simulate, "pick_surfaces", two)
    simulate.write_figure(tmp_path / "g.png", scene="grating")
    assert drawn and all(name.startswith("G") for name in drawn), drawn
    assert any("scene grating" in t for t in titles) and not any("None" in t for t in titles), titles
    assert (tmp_path / "g.png").stat().st_size > 0
