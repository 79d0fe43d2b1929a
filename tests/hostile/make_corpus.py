"""Regenerate the hostile-input corpus in this folder (run only on purpose; the files are committed).

    python tests/hostile/make_corpus.py [NAME ...]

Every file is built byte for byte the same on every run (fixed zip timestamps, seeded noise).
tests/test_hostile.py runs each through the CLI and checks the one-line error it expects. The
model variants are derived from one small valid linear model and carry a correct fingerprint,
so each is refused by the check it targets, not by the fingerprint.
"""

from __future__ import annotations

import io
import json
import sys
import zipfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parents[1]))

from tactiled.learn.model import _fingerprint, default_model_path  # noqa: E402

STAMP = (1980, 1, 1, 0, 0, 0)
BOMB_SHAPE = (2**29, 2)  # int16: 2 GiB of zeros, bzip2-compressed to about 1.5 kB


def npy(arr: Any) -> bytes:
    buf = io.BytesIO()
    a = np.asanyarray(arr)
    # writes only: the one object-array member (rec-samples-object.npz) is pickled so that the loaders' refusal is tested
    np.lib.format.write_array(buf, a, allow_pickle=a.dtype.hasobject)
    return buf.getvalue()


def zip_bytes(members: dict[str, bytes], compression: int = zipfile.ZIP_DEFLATED) -> bytes:
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name, data in members.items():
            info = zipfile.ZipInfo(name if "." in name else f"{name}.npy", STAMP)
            info.compress_type = compression
            zf.writestr(info, data)
    return buf.getvalue()


def npz(arrays: dict[str, Any]) -> bytes:
    return zip_bytes({k: npy(v) for k, v in arrays.items()})


def good_recording() -> dict[str, Any]:
    noise = np.random.default_rng(0).normal(0, 40, (4000, 2)).astype(np.int16)
    return {"samples": noise, "fs": np.float64(20000), "volts_per_count": np.float64(5 / 32768), "meta": np.str_("{}")}


def npy_header(shape: tuple[int, ...], descr: str = "<i2") -> bytes:
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


def bz2_bomb() -> bytes:
    """samples: a (2**29, 2) int16 array of zeros in a bzip2 member: 2 GiB from about 1.5 kB (takes ~40 s to build)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        zf.writestr(zipfile.ZipInfo("fs.npy", STAMP), npy(np.float64(20000)))
        info = zipfile.ZipInfo("samples.npy", STAMP)
        info.compress_type = zipfile.ZIP_BZIP2
        with zf.open(info, "w", force_zip64=True) as out:
            out.write(npy_header(BOMB_SHAPE))
            chunk = bytes(1 << 24)
            for _ in range(2 * BOMB_SHAPE[0] * BOMB_SHAPE[1] // len(chunk)):
                out.write(chunk)
    return buf.getvalue()


def small_model() -> tuple[dict[str, Any], dict[str, Any]]:
    """Header and arrays of a small valid linear model on the shipped model's features (no fingerprint yet)."""
    with np.load(default_model_path(), allow_pickle=False) as shipped:
        header = json.loads(shipped["header"].item())
        mean, scale = shipped["scaler_mean"], shipped["scaler_scale"]
    header.pop("fingerprint")
    f = len(header["settings"]["names"])
    header.update(classifier="linear", method="corpus", params={"C": 1.0}, classes=["rough", "smooth"], summary={}, temperature=1.0)
    rng = np.random.default_rng(1)
    arrays = {"classes": np.array(["rough", "smooth"]), "scaler_mean": mean, "scaler_scale": scale, "coef": rng.normal(0, 1, (1, f)),
              "intercept": np.zeros(1)}
    return header, arrays


def model_bytes(header: dict[str, Any], arrays: dict[str, Any], extra: dict[str, bytes] | None = None) -> bytes:
    header = {**header, "fingerprint": _fingerprint(header, arrays)}
    return zip_bytes({"header": npy(np.str_(json.dumps(header, sort_keys=True))), **{k: npy(v) for k, v in arrays.items()}, **(extra or {})})


def model_variant(change: Callable[[dict[str, Any], dict[str, Any]], None]) -> bytes:
    header, arrays = small_model()
    change(header, arrays)
    return model_bytes(header, arrays)


def _settings(**kw: Any) -> Callable[[dict[str, Any], dict[str, Any]], None]:
    return lambda h, a: h["settings"].update(kw)


def _svm_huge(h: dict[str, Any], a: dict[str, Any]) -> None:
    h.update(classifier="svm", params={"C": 10.0, "gamma": "scale", "kernel": "rbf"})
    del a["coef"], a["intercept"]
    rows = 20_000
    a["train_x"] = np.zeros((rows, len(h["settings"]["names"])))
    a["train_y"] = np.array(["rough", "smooth"] * (rows // 2))


def _svm_fitted_bad(h: dict[str, Any], a: dict[str, Any]) -> None:
    """A small svm whose stored fitted SVM names a support vector beyond its training rows."""
    _svm_huge(h, a)
    a.update(train_x=a["train_x"][:10], train_y=a["train_y"][:10], svm_support=np.array([0, 5, 99]), svm_dual_coef=np.ones((1, 3)),
             svm_intercept=np.zeros(1), svm_n_support=np.array([2, 1]), svm_gamma=np.float64(0.1))


def files() -> dict[str, Callable[[], bytes]]:
    nested = "[" * 100_000 + "]" * 100_000
    rec = good_recording()
    return {
        # recordings
        "rec-good.npz": lambda: npz(rec),
        "rec-bomb-bzip2.npz": bz2_bomb,
        "rec-meta-nested.npz": lambda: npz({**rec, "meta": np.str_('{"a": ' + nested + "}")}),
        "rec-meta-huge-int.npz": lambda: npz({**rec, "meta": np.str_('{"a": ' + "9" * 5000 + "}")}),
        "rec-samples-nan.npz": lambda: npz({**rec, "samples": np.full((100, 2), np.nan, dtype=np.float32)}),
        "rec-samples-complex.npz": lambda: npz({**rec, "samples": np.zeros((100, 2), dtype=np.complex128)}),
        "rec-samples-uint8.npz": lambda: npz({**rec, "samples": np.zeros((100, 2), dtype=np.uint8)}),
        "rec-samples-object.npz": lambda: npz({**rec, "samples": np.array([[{"x": 1}]], dtype=object)}),
        "rec-samples-struct.npz": lambda: npz({**rec, "samples": np.zeros((10, 2), dtype=[("a", "<i2")])}),
        "rec-fs-tiny.npz": lambda: npz({**rec, "fs": np.float64(1e-9)}),
        "rec-fs-nan.npz": lambda: npz({**rec, "fs": np.float64(np.nan)}),
        "rec-channels-1000.npz": lambda: npz({**rec, "samples": np.zeros((2, 1000), dtype=np.int16)}),
        "rec-truncated.npz": lambda: npz(rec)[: len(npz(rec)) // 2],
        "rec-declares-more.npz": lambda: zip_bytes({"samples": npy_header((10**6, 2)) + bytes(100), "fs": npy(np.float64(20000))}),
        "rec-members-100.npz": lambda: zip_bytes({**{k: npy(v) for k, v in rec.items()}, **{f"x{i}": npy(np.int8(i)) for i in range(100)}}),
        "rec-not-zip.npz": lambda: b"PK\x03\x04" + bytes(200),
        # models
        "model-good.npz": lambda: model_bytes(*small_model()),
        "model-temperature-zero.npz": lambda: model_variant(lambda h, a: h.update(temperature=0.0)),
        "model-temperature-nan.npz": lambda: model_variant(lambda h, a: h.update(temperature=float("nan"))),
        "model-temperature-inf.npz": lambda: model_variant(lambda h, a: h.update(temperature=float("inf"))),
        "model-temperature-string.npz": lambda: model_variant(lambda h, a: h.update(temperature="1")),
        "model-window-huge.npz": lambda: model_variant(_settings(duration_s=59.0)),
        "model-level-99.npz": lambda: model_variant(_settings(level=99)),
        "model-half-width-0.npz": lambda: model_variant(_settings(half_width=0)),
        "model-half-width-float.npz": lambda: model_variant(_settings(half_width=5.5)),
        "model-wavelet-bogus.npz": lambda: model_variant(_settings(wavelet="bogus")),
        "model-band-beyond-nyquist.npz": lambda: model_variant(lambda h, a: h["settings"]["names"].__setitem__(0, "film1.psd.100-15000Hz.power")),
        "model-third-channel.npz": lambda: model_variant(lambda h, a: h["settings"]["names"].__setitem__(0, "film3.time.A1.sd")),
        "model-coef-nan.npz": lambda: model_variant(lambda h, a: a.__setitem__("coef", np.full_like(a["coef"], np.nan))),
        "model-coef-shape.npz": lambda: model_variant(lambda h, a: a.__setitem__("coef", np.zeros((3, 3)))),
        "model-scale-zero.npz": lambda: model_variant(lambda h, a: a.__setitem__("scaler_scale", np.zeros_like(a["scaler_scale"]))),
        "model-svm-huge.npz": lambda: model_variant(_svm_huge),
        "model-svm-gamma-negative.npz": lambda: model_variant(lambda h, a: (_svm_huge(h, a), h["params"].update(gamma=-1.0),
                                                                          a.update(train_x=a["train_x"][:10], train_y=a["train_y"][:10]))),
        "model-svm-c-huge.npz": lambda: model_variant(lambda h, a: (_svm_huge(h, a), h["params"].update(C=1e9),
                                                                    a.update(train_x=a["train_x"][:10], train_y=a["train_y"][:10]))),
        "model-svm-fitted-bad.npz": lambda: model_variant(_svm_fitted_bad),
        "model-header-nested.npz": lambda: zip_bytes({"header": npy(np.str_('{"format": ' + nested + "}"))}),
        "model-extra-member.npz": lambda: model_bytes(*small_model(), extra={"junk.npy": npy(np.zeros(10))}),
        # configs
        "config-fs-inf.toml": lambda: b"[sensor]\nfs = inf\n",
        "config-ring-1e9.toml": lambda: b"[ring]\nseconds = 1e9\n",
        "config-fs-1e12.toml": lambda: b"[sensor]\nfs = 1e12\n",
        "config-fs-tiny.toml": lambda: b"[sensor]\nfs = 0.01\n",
        "config-half-width-huge.toml": lambda: b"[spikes]\nhalf_width = 1000000000\n",
        "config-baudrate-2p63.toml": lambda: b"[sensor]\nbaudrate = 9223372036854775808\n",
        "config-nested-arrays.toml": lambda: b"x = " + b"[" * 500 + b"]" * 500 + b"\n",
        "config-port-socket.toml": lambda: b"[sensor]\nport = \"socket://192.0.2.1:4000\"\n",
        "config-retry-nan.toml": lambda: b"[serial]\nretry_max_s = nan\n",
    }


def main(only: list[str]) -> None:
    for name, make in files().items():
        if only and name not in only:
            continue
        (HERE / name).write_bytes(make())
        print(f"{name}: {(HERE / name).stat().st_size} bytes")


if __name__ == "__main__":
    main(sys.argv[1:])  # names: only those files
