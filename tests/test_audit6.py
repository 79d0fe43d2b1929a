"""An outside audit of the eighteenth session (2026-11-27): score names the recordings it skips for want of ground truth and
lists no recall for a surface the model was never taught; a slide's novelty is held to the threshold of its own number of
windows, final or provisional."""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from tactiled.sim.simulate import write_dataset
from tests.conftest import REPO, cli_here

REPO_MODEL = REPO / "tactiled" / "data" / "default_model.npz"


@pytest.fixture(scope="module")
def two_of_three(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[Path], list[Path]]:
    """A quick model of two surfaces of three (robot scene, 2 files of 3 slides each), the recordings of those two and of the
    third, which the model was never taught."""
    root = tmp_path_factory.mktemp("two_of_three")
    files = sorted(write_dataset(root / "sim", scene="robot", surfaces="3", files_per_surface=2, slides_per_file=3))
    surfaces = sorted({str(np.load(f)["surface"][0]) for f in files})
    taught = [f for f in files if str(np.load(f)["surface"][0]) != surfaces[1]]
    untaught = [f for f in files if f not in taught]
    model = root / "m.npz"
    res = cli_here(None, "train", *map(str, taught), "-o", str(model), "--method", "quick", "--folds", "2")
    assert res.returncode == 0, res.stderr
    return model, taught, untaught


def test_score_names_a_recording_without_ground_truth_and_exits_2(two_of_three: tuple[Path, list[Path], list[Path]], tmp_path: Path,
                                                                   capfd: pytest.CaptureFixture[str]) -> None:
    """A held-out file recorded without --label vanished from score's figures: "16/16 files" of 24 given, exit 0."""
    model, taught, _ = two_of_three
    bare = tmp_path / "bare.npz"
    with np.load(taught[0]) as z:
        arrays = {k: z[k] for k in z.files if k not in ("surface", "slide_start", "slide_stop", "ra_um", "label")}
    np.savez(bare, **arrays)
    for json_flag in ((), ("--json",)):
        res = cli_here(capfd, "score", str(model), *map(str, taught[1:]), str(bare), *json_flag)
        assert res.returncode == 2, res.stderr
        assert f"skipped: {bare}: no ground truth (neither per-slide surfaces nor a file label)" in res.stderr
    res = cli_here(capfd, "score", str(model), *map(str, taught[1:]))
    assert res.returncode == 0 and "skipped" not in res.stderr, res.stderr


def test_score_lists_no_recall_for_a_surface_the_model_was_never_taught(two_of_three: tuple[Path, list[Path], list[Path]],
                                                                         capfd: pytest.CaptureFixture[str]) -> None:
    """Its line says how its slides came out; a "recall 0.000" under it read as a total failure."""
    model, taught, untaught = two_of_three
    res = cli_here(capfd, "score", str(model), *map(str, taught + untaught))
    assert res.returncode == 0, res.stderr
    name = str(np.load(untaught[0])["surface"][0])
    recalls = [line.split(":")[0].strip() for line in res.stdout.splitlines() if ": recall " in line]
    assert f"not a surface of the model: {name}," in res.stdout
    assert sorted(recalls) == sorted({str(np.load(f)["surface"][0]) for f in taught}), res.stdout


def test_a_slide_is_held_to_the_novelty_threshold_of_its_own_number_of_windows(two_of_three: tuple[Path, list[Path], list[Path]]) -> None:
    """A slide of w windows, whole (final) or the first windows of one that goes on, is measured against the distance
    threshold of w windows: whole short slides of a taught surface were called unknown 4 to 8 times as often as long ones."""
    from tactiled.learn.model import load_model

    model, _, _ = two_of_three
    base = replace(load_model(model), novelty_threshold=math.inf)  # the distance part alone: the novelty is distance / threshold
    assert base.novelty_names is not None and np.isfinite(base.novelty_distance_threshold)
    x = np.random.default_rng(0).normal(size=(9, len(base.names)))
    rows = [(0, 1), (1, 3), (3, 9)]  # 1, 2 and 6 windows
    plain = base.novelty_many(x, rows)
    loose = replace(base, novelty_prefix=(4.0, 2.0, 1.5))  # beyond its last entry: a provisional label's last, a whole slide's 1
    final, provisional = loose.novelty_many(x, rows, final=True), loose.novelty_many(x, rows, final=False)
    assert final[:2] == provisional[:2]
    assert final == pytest.approx([p / f for p, f in zip(plain, (4.0, 2.0, 1.0), strict=True)], rel=1e-12)  # type: ignore[operator]
    assert provisional[2] == pytest.approx(plain[2] / 1.5, rel=1e-12)  # type: ignore[operator]


@pytest.mark.parametrize("kind", ["ipc", "tcp"])
def test_a_demo_on_an_endpoint_another_process_publishes_on_says_so_and_exits_2(kind: str, tmp_path: Path) -> None:
    """A second demo on the first one's endpoint printed the first one's labels (the true surface "?") and exited 0: its own
    daemon could not bind there and had gone."""
    import socket

    from tests.conftest import run_cli

    family = socket.AF_UNIX if kind == "ipc" else socket.AF_INET
    with socket.socket(family, socket.SOCK_STREAM) as other:  # a process that listens there
        other.bind(str(tmp_path / "pub") if kind == "ipc" else ("127.0.0.1", 0))
        other.listen()
        endpoint = f"ipc://{tmp_path}/pub" if kind == "ipc" else f"tcp://127.0.0.1:{other.getsockname()[1]}"
        res = run_cli("demo", "--publish", endpoint, "--headless", "--seconds", "20", timeout=60)
    assert res.returncode == 2 and res.stdout == "", res.stdout
    assert res.stderr.strip().splitlines() == [f"tactiled: error: demo --publish: another process already publishes on {endpoint} "
                                               "(another demo or daemon?); stop it or give this demo another endpoint"]


def test_enrol_refuses_recordings_of_rest_and_says_so_for_one_too_short_for_a_slide(two_of_three: tuple[Path, list[Path], list[Path]],
                                                                                   tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """Recordings of a finger at rest became 5 slides of a new surface (the detector without the model's start level takes a
    stream it cannot decide for one slide), where the daemon running that model finds none in them; a 0.07 s file was told
    to pass --label, which it had."""
    from tactiled.learn.model import load_model

    model, taught, _ = two_of_three
    assert load_model(model).start_level is not None  # learnt from the training recordings' rests
    with np.load(taught[0]) as z:
        arrays = {k: z[k] for k in z.files if k not in ("surface", "slide_start", "slide_stop", "ra_um", "label")}
    rests = []
    for i in range(3):
        noise = np.random.default_rng(i).integers(-3, 4, size=arrays["samples"].shape)  # a few counts of the board's noise, no touch
        rests.append(tmp_path / f"rest{i}.npz")
        np.savez(rests[-1], **{**arrays, "samples": noise.astype(np.int16)})
    res = cli_here(capfd, "enrol", str(model), *map(str, rests), "--label", "P80", "-o", str(tmp_path / "m2.npz"))
    assert res.returncode == 2 and not (tmp_path / "m2.npz").exists()
    assert res.stderr.strip() == (f"tactiled: error: no slide to enrol in {rests[0]}, {rests[1]}, {rests[2]}: the daemon running {model} "
                                  "finds none there (at rest, by the level it learnt between slides; recordings of the surface being "
                                  "slid over, please); nothing enrolled"), res.stderr
    short = tmp_path / "short.npz"
    np.savez(short, **{**arrays, "samples": arrays["samples"][: int(0.07 * float(arrays["fs"]))]})
    res = cli_here(capfd, "enrol", str(model), str(short), "--label", "P80", "-o", str(tmp_path / "m3.npz"))
    assert res.returncode == 2 and "no slide to enrol: the detector found none in" in res.stderr and "--label" not in res.stderr, res.stderr


def test_trains_time_left_is_measured_from_the_first_finished_task(monkeypatch: pytest.MonkeyPatch) -> None:
    """The workers' start-up was counted as work: "16/208 fits, 0:05 elapsed, about 0:57 left", then done at 0:06. Here the
    first task ends 10 s in (the start-up), each next one 1 s later: 2 s left after the second, where 11 s was said."""
    import tactiled.learn.search as search

    clock = iter([0.0, 10.0, 11.0, 12.0, 13.0])  # the start, then each task's end

    class Clock:
        @staticmethod
        def perf_counter() -> float:
            return next(clock)

    monkeypatch.setattr(search, "time", Clock)
    lines: list[str] = []
    out = search._run_with_progress([(abs, (-k,)) for k in range(4)], lines.append, None)
    assert out == [0, 1, 2, 3]
    assert lines == ["[#####               ] 1/4 fits, 0:10 elapsed", "[##########          ] 2/4 fits, 0:11 elapsed, about 0:02 left",
                     "[###############     ] 3/4 fits, 0:12 elapsed, about 0:01 left", "[####################] 4/4 fits, 0:13 elapsed"]


def test_surface_names_that_differ_only_in_case_are_said_in_train_and_refused_by_enrol(
        two_of_three: tuple[Path, list[Path], list[Path]], tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """"Ra1.00" typed "ra1.00" on two of four recordings became two surfaces without a word (train: each recall 0.00; enrol
    --label ra0.44 on a model knowing Ra0.44: "a new surface")."""
    from tactiled.files.recording import case_twins

    assert case_twins(["Ra1.00", "ra1.00", "P80", "RA1.00", "p60"]) == [["RA1.00", "Ra1.00", "ra1.00"]]
    model, taught, untaught = two_of_three
    name = str(np.load(taught[0])["surface"][0])
    renamed = []
    for f in taught:
        with np.load(f) as z:
            arrays = {k: z[k] for k in z.files}
        if f == taught[0]:
            arrays["surface"] = np.array([name.lower()] * len(arrays["surface"]))
        renamed.append(tmp_path / f.name)
        np.savez(renamed[-1], **arrays)
    # said with the slides per surface, before anything else (here train then stops: the lower-case name has one recording)
    res = cli_here(capfd, "train", *map(str, renamed), "-o", str(tmp_path / "m.npz"), "--method", "quick", "--folds", "2")
    assert f"warning: surfaces {name} and {name.lower()} differ only in case: taught as 2 surfaces" in res.stderr, res.stderr
    res = cli_here(capfd, "enrol", str(model), *map(str, untaught), "--label", name.lower(), "-o", str(tmp_path / "m2.npz"))
    assert res.returncode == 2 and not (tmp_path / "m2.npz").exists()
    assert res.stderr.strip() == (f"tactiled: error: {name.lower()}: {model} knows {name}, which differs only in case: enrolled, it would be "
                                  "a new surface; give the name the model knows (--label) to teach it more of that one"), res.stderr


def test_surfaces_recorded_unevenly_weigh_alike_in_the_choice_and_its_estimates() -> None:
    """2 recordings of one surface and 12 of another: the choice by slides picked a kNN that called 51 of 60 slides of a
    balanced test the larger surface, and promised 66.7 % where that test gave 46.7 %. Slide counts 3 or more times apart
    weigh each surface alike; a set recorded about evenly is judged by slides, bit for bit as before."""
    from tactiled.learn.score import recording_interval
    from tactiled.learn.search import IMBALANCE, Candidate, accuracy_of, surface_weights

    y = np.array([0] * 10 + [1] * 60 + [-1] * 5)  # -1: an unlabelled slide, no surface
    w = surface_weights(y, 2)
    assert w is not None and w == pytest.approx([3.5, 70 / 120])
    scores = np.zeros((75, 2))
    scores[:, 1] = 1.0  # always the larger surface
    assert accuracy_of(scores[:70], y[:70]) == pytest.approx(60 / 70)
    assert accuracy_of(scores[:70], y[:70], w) == pytest.approx(0.5)  # the balanced accuracy
    assert surface_weights(np.array([0] * 10 + [1] * (IMBALANCE * 10 - 1)), 2) is None
    assert surface_weights(np.array([0] * 44 + [1] * 45), 2) is None
    hits, groups = np.arange(30) % 3 == 0, np.arange(30) // 5
    assert recording_interval(hits, groups) == recording_interval(hits, groups, weights=np.ones(30))
    svm = Candidate(("psd",), "svm", 0.25)
    assert "class_weight" not in svm.params and replace(svm, balanced=True).params["class_weight"] == "balanced"
    assert replace(svm, balanced=True) == svm and replace(svm, balanced=True).name == svm.name
    assert "class_weight" not in replace(Candidate(("psd",), "knn", 0.25), balanced=True).params


def test_train_on_surfaces_recorded_unevenly_says_it_weighed_them_alike(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    from tactiled.learn.model import load_model

    small = sorted(write_dataset(tmp_path / "a", scene="robot", surfaces="Ra0.44", files_per_surface=2, slides_per_file=2, seed=3))
    large = sorted(write_dataset(tmp_path / "b", scene="robot", surfaces="Ra4.43", files_per_surface=4, slides_per_file=4, seed=4))
    res = cli_here(capfd, "train", *map(str, small + large), "-o", str(tmp_path / "m.npz"), "--method", "quick", "--folds", "2")
    assert res.returncode == 0, res.stderr
    assert "the choice, its cross-validated accuracies and the nested estimate weigh each surface alike" in res.stdout, res.stdout
    model = load_model(tmp_path / "m.npz")
    assert model.summary["cv_accuracy"]["weighted"] is True
    assert model.kind not in ("svm", "linear") or model.params["class_weight"] == "balanced"


def test_score_skips_a_recording_of_another_rate_with_its_line_and_scores_the_others(
        two_of_three: tuple[Path, list[Path], list[Path]], tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """One file at another rate made score refuse every file, where replay says its line and goes on."""
    model, taught, _ = two_of_three
    other = tmp_path / "10k.npz"
    with np.load(taught[0]) as z:
        np.savez(other, **{**{k: z[k] for k in z.files}, "fs": np.float64(10_000.0)})
    res = cli_here(capfd, "score", str(model), *map(str, taught[1:]), str(other))
    assert res.returncode == 2 and f"skipped: {other}: model trained at fs 20000 Hz, it is 10000 Hz" in res.stderr, res.stderr
    assert "accuracy " in res.stdout
    res = cli_here(capfd, "score", str(model), str(other))
    assert res.returncode == 2 and res.stderr.strip().splitlines()[-1] == (
        f"tactiled: error: no recording to score: none is readable and of {model}'s rate and channels (listed above)"), res.stderr


def test_features_says_why_a_recording_given_twice_is_refused(two_of_three: tuple[Path, list[Path], list[Path]], tmp_path: Path,
                                                              capfd: pytest.CaptureFixture[str]) -> None:
    """features refused it for what cross-validation would do with it, which features does not do."""
    _, taught, _ = two_of_three
    res = cli_here(capfd, "features", str(taught[0]), str(taught[0]), "-o", str(tmp_path / "f.npz"))
    assert res.returncode == 2 and res.stderr.strip() == (
        f"tactiled: error: {taught[0]} and {taught[0]} hold the same samples: one recording would count as two (its windows would be "
        "in the table twice); give each recording once"), res.stderr


def test_a_recordings_error_never_narrows_the_interval_below_that_of_none() -> None:
    """score: 50 of 50 right in 10 recordings gave [0.70, 1]; with an 11th recording holding one error (54 of 55) the
    percentile bootstrap gave [0.95, 1]: more certain for a miss. Resampled with a pseudo-recording of each outcome, the
    bound stays near the error-free one and an interval still holds its point."""
    from tactiled.learn.score import recording_interval

    def interval(wrong_per_recording: list[int], size: int = 5) -> list[float]:
        hits = np.concatenate([np.arange(size) >= w for w in wrong_per_recording])
        band = recording_interval(hits, np.repeat(np.arange(len(wrong_per_recording)), size))
        assert band is not None and band[0] <= hits.mean() <= band[1]
        return band

    none, one, two = interval([0] * 10), interval([0] * 10 + [1]), interval([0] * 10 + [1, 1])
    assert none == [0.7, 1.0]
    assert one[0] < 0.8 and two[0] < 0.8 and two[0] <= one[0] + 0.05


def test_train_names_a_surface_whose_slides_are_no_louder_than_rest(two_of_three: tuple[Path, list[Path], list[Path]], tmp_path: Path,
                                                                    capfd: pytest.CaptureFixture[str]) -> None:
    """Recordings of rest labelled P80 became a surface of 5 slides (each file one slide, the detector undecided) and cost
    the model its start level, "the quietest slides lie only 0.0 times above the loudest rest", without saying whose."""
    _, taught, _ = two_of_three
    with np.load(taught[0]) as z:
        arrays = {k: z[k] for k in z.files if k not in ("surface", "slide_start", "slide_stop", "ra_um")}
    rests = []
    for i in range(3):
        rests.append(tmp_path / f"rest{i}.npz")
        np.savez(rests[-1], **{**arrays, "label": np.str_("P80"),
                               "samples": np.random.default_rng(i).integers(-3, 4, size=arrays["samples"].shape).astype(np.int16)})
    res = cli_here(capfd, "train", *map(str, taught + rests), "-o", str(tmp_path / "m.npz"), "--method", "quick", "--folds", "2")
    assert res.returncode == 0, res.stderr
    note = next(line for line in (res.stdout + res.stderr).splitlines() if "start level" in line)
    assert note.startswith("train: no start level") and "the slides of P80 are no louder than the rests (recordings of rest labelled" in note, note


def test_an_ensemble_on_surfaces_recorded_unevenly_calibrates_the_partner_it_ships(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A reviewer: the provisional labels' calibration refitted the spectral partner unweighted (the module's SPECTRUM,
    which is not balanced) while the file held the weighted one."""
    import tactiled.learn.search as search
    from tactiled.config import Config
    from tactiled.learn.train import train

    small = sorted(write_dataset(tmp_path / "a", scene="robot", surfaces="Ra0.44", files_per_surface=2, slides_per_file=2, seed=3))
    large = sorted(write_dataset(tmp_path / "b", scene="robot", surfaces="Ra4.43", files_per_surface=4, slides_per_file=4, seed=4))
    scored: list[tuple[str, bool]] = []
    real = search._prefix_scorer

    def spy(ws: object, c: search.Candidate, *args: object) -> object:
        scored.append((c.name, c.balanced))
        return real(ws, c, *args)  # type: ignore[arg-type]

    monkeypatch.setattr(search, "_prefix_scorer", spy)
    result = train([*small, *large], Config(), folds=2, ensemble="always",
                   candidates=[search.Candidate(("psd",), "linear", 0.25), search.SPECTRUM])
    assert result.model.summary["cv_accuracy"]["weighted"] is True
    assert scored and all(balanced for _, balanced in scored), scored
    if result.model.partner is not None:
        assert result.model.partner.params.get("class_weight") == "balanced"


def test_a_low_rate_recording_with_a_disconnection_mark_replays_every_slide(tmp_path: Path, capfd: pytest.CaptureFixture[str]) -> None:
    """One channel at 2.2 kHz, a disconnection mark late in the file: replay fed it in blocks of 65 536 rows, 30 s, longer
    than the 20 s ring, so the first slides of each block were overwritten before their analysis (6 of 25 labels lost)."""
    from tactiled.files.recording import load_recording, save_recording

    files = sorted(write_dataset(tmp_path / "d", scene="one-channel", surfaces="Ra0.44,Ra4.43", files_per_surface=2, slides_per_file=20, seed=5))
    model = tmp_path / "m.npz"
    assert cli_here(capfd, "train", *map(str, files), "-o", str(model), "--method", "quick", "--folds", "2").returncode == 0
    rec = load_recording(files[0])
    assert rec.fs == 2200.0 and rec.samples.shape[0] > 70_000  # more than a default block
    marked = tmp_path / "marked.npz"
    mark = rec.samples.shape[0] - 100  # in the rest after the last slide
    save_recording(marked, replace(rec, disconnected=np.array([mark], dtype=np.int64)))

    def reasons(path: Path) -> list[str | None]:
        res = cli_here(capfd, "replay", "--json", "--model", str(model), str(path))
        assert res.returncode == 0, res.stderr
        return [__import__("json").loads(line)["reason"] for line in res.stdout.splitlines()]

    plain, cut = reasons(files[0]), reasons(marked)
    assert "overwritten" not in cut and cut == plain, (plain, cut)


def test_a_model_refuses_a_stream_of_more_channels_too(tmp_path: Path) -> None:
    """The shipped two-film model labelled a three-film sensor's slides at 20 kHz without a word, and check-config said ok."""
    from tactiled.errors import ModelError
    from tactiled.learn.model import load_model
    from tests.conftest import run_cli

    shipped = load_model()
    with pytest.raises(ModelError, match=r"^model of 2 channels, sensor s3 has 3$"):
        shipped.check_stream(20_000.0, 3, "sensor s3")
    shipped.check_stream(20_000.0, 2, "sensor s2")
    config = tmp_path / "three.toml"
    config.write_text('[sensor]\nid = "s3"\nchannels = 3\n')
    res = run_cli("check-config", str(config))
    assert res.returncode == 2 and "the shipped model does not fit this sensor (model of 2 channels, sensor s3 has 3)" in res.stderr, res.stderr


def test_replay_with_a_config_labels_with_its_model_path(two_of_three: tuple[Path, list[Path], list[Path]], tmp_path: Path,
                                                         capfd: pytest.CaptureFixture[str]) -> None:
    """run --config my.toml labels with model.path; replay --config my.toml used the shipped model, so it did not reproduce
    the daemon (an outside audit: 0 of 29 slides labelled, the shipped model not fitting the lab's sensor)."""
    import json

    from tactiled.learn.model import load_model

    model, taught, _ = two_of_three
    config = tmp_path / "my.toml"
    config.write_text(f'[model]\npath = "{model}"\n')
    res = cli_here(capfd, "replay", "--json", "--config", str(config), str(taught[0]))
    assert res.returncode == 0, res.stderr
    assert {json.loads(line)["model"] for line in res.stdout.splitlines()} == {load_model(model).fingerprint}
    other = cli_here(capfd, "replay", "--json", "--config", str(config), "--model", str(REPO_MODEL), str(taught[0]))
    assert {json.loads(line)["model"] for line in other.stdout.splitlines()} == {load_model(REPO_MODEL).fingerprint}  # --model first


def test_a_films_status_level_is_its_rms_about_the_mean() -> None:
    """A DC-coupled film at 0.6 V of offset: its plain RMS moved 0.640 -> 0.613..0.677 V between rest and slides, and the
    monitor's bars hardly moved (an outside audit). About the mean, the offset is gone; silence and one sample are 0."""
    from tactiled.core.features import film_levels

    t = np.arange(20_000) / 20_000.0
    x = np.stack([0.6 + 0.05 * np.sin(2 * np.pi * 200 * t), np.full_like(t, -1.5)], axis=1)
    counts = np.rint(x / 1e-4)
    level = film_levels(counts.sum(axis=0), np.einsum("ij,ij->j", counts, counts), len(t), 1e-4)
    assert level[0] == pytest.approx(0.05 / np.sqrt(2), rel=1e-3) and level[1] == 0.0
    assert film_levels(np.zeros(2), np.zeros(2), 0) == []
    assert film_levels(np.array([3.0]), np.array([9.0]), 1) == [0.0]
