"""``tactiled simulate``: labelled datasets and the virtual board, from :mod:`tactiled.sim.physics`."""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from tactiled.errors import OutputError, TactiledError
from tactiled.files.recording import Recording, save_recording
from tactiled.sim.physics import (
    SensorSimulator,
    SimParams,
    Surface,
    hot_gain,
    other_unit,
    output,
    pick_surfaces,
    scene_params,
    simulate_file,
    with_mode,
)
from tactiled.sim.virtualboard import VirtualBoard


def _surfaces(spec: str | None, family: str = "self-affine", specimen: int = 0) -> list[Surface]:
    try:
        return pick_surfaces(spec, family, specimen)
    except ValueError as exc:
        raise TactiledError(str(exc)) from None


def scene_for(scene: str | None, mode: str | None = None, fs: float | None = None, channels: int | None = None) -> tuple[str, SimParams]:
    """(scene spec, parameters) from ``--scene`` (or the older ``--mode manual|robot``) and optional rate/channel overrides."""
    spec = scene or {"manual": "hand", "robot": "robot", None: "hand"}[mode]
    try:
        params = scene_params(spec)
    except ValueError as exc:
        raise TactiledError(str(exc)) from None
    if channels is not None and not 1 <= channels <= 8:
        raise TactiledError(f"--channels: must be in 1..8, got {channels}")
    if fs is not None and not 100 <= fs <= 200_000:
        raise TactiledError(f"--fs: must be in 100..200000 Hz, got {fs:g}")
    return spec, with_mode(params, None, fs, channels)


Mapper = Callable[[Callable[["FileTask"], Path], list["FileTask"], float], Iterable[Path]]


def write_dataset(out: Path, *, scene: str | None = None, seed: int = 0, surfaces: str | None = None, files_per_surface: int = 4,
                  slides_per_file: int = 5, mode: str | None = None, fs: float | None = None, channels: int | None = None,
                  progress: Callable[[str], None] | None = None, unit: int = 0, specimen: int = 0, force: bool = True,
                  mapper: Mapper | None = None) -> list[Path]:
    """Write ``files_per_surface`` recordings per surface of ``scene`` (docs/simulator.md) with ground truth; returns their paths.

    File names start with the scene (commas as ``+``): ``continuous+one-channel_Ra0.44_00.npz``. ``unit``: another unit of
    the same fingertip (:func:`other_unit`; 0 is the nominal one); ``specimen``: other specimens of the same grades
    (:func:`new_specimens`; 0 are the nominal ones). Both are recorded in each file's ``meta``; the ``ra_um`` labels are
    the grades' nominal Ra (µm), the specimen's own values are in ``meta["surface"]``. Without ``force``, a file of
    the same name already in ``out`` is an :class:`~tactiled.errors.OutputError` before anything is simulated.
    ``mapper(write_file, tasks, signal_s)`` writes the files and yields their paths in order (default: one after the
    other here; the CLI passes worker processes, :func:`tactiled.run.pool.map_files`); ``signal_s`` is about the seconds
    of signal in all, weighted as replaying that much would cost. Each file has its own seed: the files are the same
    whatever the mapper.
    """
    if files_per_surface < 1 or slides_per_file < 1:
        raise TactiledError("--files-per-surface and --slides-per-file must be >= 1")
    if unit < 0 or specimen < 0:
        raise TactiledError("--unit and --specimen must be >= 0")
    spec, params = scene_for(scene, mode, fs, channels)
    params = other_unit(params, unit)
    chosen = _surfaces(surfaces, params.family, specimen)
    hot = "hot-gain" in spec.split(",")
    prefix = spec.replace(",", "+")
    existing = [out / f"{prefix}_{s.name}_{f:02d}.npz" for s in chosen for f in range(files_per_surface)]
    existing = [p for p in existing if p.exists()]
    if existing and not force:
        raise OutputError(f"{existing[0]}: exists ({len(existing)} of the files to write do; --force replaces them)")
    out.mkdir(parents=True, exist_ok=True)
    tasks = []
    for i, surface in enumerate(chosen):
        file_params = replace(params, extra_gain=hot_gain(chosen, surface, params, seed + i)) if hot else params
        for f in range(files_per_surface):
            file_seed = int(np.random.SeedSequence([seed, i, f]).generate_state(1)[0])
            tasks.append(FileTask(out / f"{prefix}_{surface.name}_{f:02d}.npz", file_params, surface, slides_per_file, file_seed, spec, unit,
                                  specimen))
    per_file_s = slides_per_file * (sum(params.slide_s) + sum(params.rest_s)) / 2
    paths = []
    mapper = mapper or (lambda fn, items, _: map(fn, items))
    for k, path in enumerate(mapper(write_file, tasks, SIMULATION_COST * per_file_s * len(tasks)), 1):
        paths.append(path)
        if progress and k % files_per_surface == 0:
            i = k // files_per_surface - 1
            progress(f"simulate: {chosen[i].name} ({i + 1}/{len(chosen)})")
    return paths


# simulating a second of signal costs about as much CPU as replaying six (tactiled.run.pool.workers weighs signal by replay)
SIMULATION_COST = 6.0


@dataclass(frozen=True)
class FileTask:
    """One recording of :func:`write_dataset`: where, the simulator's parameters, the surface, slides and seed, and the
    scene, unit and specimen its ``meta`` names."""

    path: Path
    params: SimParams
    surface: Surface
    slides: int
    seed: int
    scene: str
    unit: int
    specimen: int


def write_file(task: FileTask) -> Path:
    """Simulate and save one recording of :func:`write_dataset` (in a worker process or this one); returns its path."""
    sim = simulate_file(task.params, task.surface, task.slides, task.seed)
    p = task.params
    rec = Recording(
        samples=sim.samples, fs=p.fs, volts_per_count=1.0 if p.float_output else p.volts_per_count,
        slide_start=np.array([t.start for t in sim.truth]), slide_stop=np.array([t.stop for t in sim.truth]),
        surface=np.array([t.surface.name for t in sim.truth]), ra_um=np.array([t.surface.grade_ra_um for t in sim.truth]),
        meta={"scene": task.scene, "simulator": p.to_meta(), "seed": task.seed, "surface": vars(task.surface), "unit": task.unit,
              "specimen": task.specimen,
              "v_max_mps": [t.v_max_mps for t in sim.truth], "force": [t.force for t in sim.truth]},
    )
    save_recording(task.path, rec)
    return task.path


def _seconds_list(option: str, text: str) -> list[float]:
    """``text``, comma-separated seconds, as floats (:class:`TactiledError` naming ``option`` if it is not)."""
    try:
        return [float(t) for t in text.split(",") if t.strip()]
    except ValueError:
        raise TactiledError(f"{option}: not a list of seconds: {text!r}") from None


def board_params(scene: str | None, mode: str | None = None, fs: float | None = None, channels: int | None = None) -> SimParams:
    """The parameters of a virtual board of ``scene`` (:func:`scene_for`): a board sends int16 counts, so a scene of float
    volts (``one-channel``) is quantised at the default ADC's scale (its own ``volts_per_count`` of 1 would round its
    signal to a count or two); a continuous scene slides back to back."""
    _, params = scene_for(scene, mode, fs, channels)
    if params.float_output:
        params = replace(params, float_output=False, volts_per_count=SimParams.volts_per_count)
    if params.continuous:
        params = replace(params, rest_s=(0.0, 0.0))  # back-to-back slides: the stream never rests
    return params


def run_virtual_board(args: argparse.Namespace) -> int:
    """Run a virtual board until SIGINT/SIGTERM or ``--seconds``; prints the device path first."""
    params = board_params(getattr(args, "scene", None), args.mode, args.fs, args.channels)
    unplug_at, reset_at = _seconds_list("--unplug-at", args.unplug_at), _seconds_list("--reset-at", getattr(args, "reset_at", ""))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):  # before the link exists, so that no stop leaves it behind
        signal.signal(sig, lambda *_: stop.set())
    log = open(args.log, "w", encoding="utf-8") if args.log else None  # noqa: SIM115 - closed below
    board = None
    try:
        model = SensorSimulator(params, args.seed)
        if args.rest_first > 0:
            model.add_rest(args.rest_first)
        try:
            board = VirtualBoard(model, _surfaces(args.surfaces, params.family), link=args.link, speed=args.speed,
                                 corrupt=args.corrupt, drop=args.drop, garbage=args.garbage, unplug_at=unplug_at,
                                 unplug_s=args.unplug_s, seed=args.seed, log=log, reset_at=reset_at)
        except ValueError as exc:
            raise TactiledError(str(exc)) from None
        path = board.open()
        print(args.link or path, flush=True)
        board.run(stop, args.seconds)
    finally:
        if board is not None:
            board.remove_link()
            board.close()
        if log:
            log.close()
    sys.stdout.flush()
    return 0


def write_figure(out: Path, scene: str | None = None, seed: int = 0, mode: str | None = None) -> None:
    """One slide per surface class of ``scene`` (or the older ``mode``): film 1's raw signal and its spectrum (PNG; needs matplotlib)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise TactiledError("the figure needs matplotlib: pip install 'tactiled[report]'") from None
    scene_name, params = scene_for(scene, mode)
    surfaces = pick_surfaces(None, params.family)
    fig, axes = plt.subplots(len(surfaces), 2, figsize=(11, 1.1 * len(surfaces)), sharex="col")
    for row, surface in enumerate(surfaces):
        model = SensorSimulator(params, seed + row)
        model.add_rest(0.3)
        truth = model.add_slide(surface, 1.3)
        model.add_rest(0.3)
        volts = output(model.read_volts(model.scheduled_end), params).astype(np.float64) * params.volts_per_count
        t = np.arange(volts.shape[0]) / params.fs
        axes[row, 0].plot(t, volts[:, 0], lw=0.4)
        axes[row, 0].axvspan(truth.start / params.fs, truth.stop / params.fs, color="orange", alpha=0.15)
        axes[row, 0].set_ylabel(surface.name, rotation=0, ha="right", fontsize=8)
        seg = volts[truth.start + round(0.3 * params.fs):truth.start + round(0.8 * params.fs), 0]
        spec = np.abs(np.fft.rfft(seg * np.hanning(seg.size))) / seg.size
        f = np.fft.rfftfreq(seg.size, 1 / params.fs)
        axes[row, 1].semilogy(f, spec + 1e-9, lw=0.4)
        axes[row, 1].set_xlim(0, 3000)
        axes[row, 1].set_ylim(1e-6, 1e-1)
    axes[-1, 0].set_xlabel("time, s (shaded: ground-truth slide)")
    axes[-1, 1].set_xlabel("frequency, Hz (window 0.3-0.8 s after the start of motion)")
    axes[0, 0].set_title(f"film 1, volts (scene {scene_name})")
    axes[0, 1].set_title("amplitude spectrum, V")
    fig.tight_layout()
    fig.savefig(out, dpi=90)
    plt.close(fig)
