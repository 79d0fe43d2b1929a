"""Spike (outlier) removal: pure functions over (n, C) float64 arrays in volts.

``hampel``: a sample is an outlier when it lies more than ``nsigma`` scaled MADs
(1.4826·MAD) from the median of its ``2·half_width + 1`` neighbourhood; it is replaced
by that median (MATLAB ``hampel``; windows truncated at the edges by nearest padding).
``mad``: the same test against the whole window's median and MAD (MATLAB ``isoutlier``).
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt

MAD_SCALE = 1.4826


def remove_spikes(x: npt.NDArray[np.float64], method: str = "mad", half_width: int = 5,
                  nsigma: float = 4.0) -> tuple[npt.NDArray[np.float64], int]:
    """(cleaned copy of x (n, C), number of samples replaced). ``method``: hampel, mad or none."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must have shape (n, C), got {x.shape}")
    clean, counts = remove_spikes_many(x[None], method, half_width, nsigma)
    return clean[0], int(counts[0])


def remove_spikes_many(x: npt.NDArray[np.float64], method: str = "mad", half_width: int = 5,
                       nsigma: float = 4.0, *, overwrite: bool = False,
                       medians: npt.NDArray[np.float64] | None = None) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.int64]]:
    """(cleaned copies of W windows x (W, n, C) V, samples replaced in each (W,)): each window as :func:`remove_spikes` alone.

    The cleaned windows (W, n, C) are a view of (W, C, n) contiguous rows for ``mad`` and ``none``: each channel's samples
    contiguous, as the features' transforms read them. ``overwrite`` (``mad``): ``x`` is the caller's scratch, a view of
    such rows, and may be cleaned in place rather than copied. ``medians`` (``mad``): each window's channels' medians (W, C),
    the values :func:`median_last` gives, when the caller has them (from the int16 counts: :func:`median_last` ``scale``).
    """
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 3:
        raise ValueError(f"x must have shape (W, n, C), got {x.shape}")
    if method == "none" or x.shape[1] == 0:
        return np.ascontiguousarray(x.transpose(0, 2, 1)).transpose(0, 2, 1), np.zeros(x.shape[0], dtype=np.int64)
    if method == "hampel":
        from scipy.ndimage import median_filter  # SciPy only for the method that needs it (it costs ~70 MB resident)

        size = (1, 2 * half_width + 1, 1)
        med = median_filter(x, size=size, mode="nearest")
        mad = median_filter(np.abs(x - med), size=size, mode="nearest")
        outlier = _outliers(np.abs(x - med), med, mad, nsigma)
        return np.where(outlier, med, x), np.count_nonzero(outlier, axis=(1, 2)).astype(np.int64)
    if method != "mad":
        raise ValueError(f"method must be hampel, mad or none, got {method!r}")
    # medians per window and channel on contiguous rows: the same values as np.median(x, axis=1), without its overhead
    xt = np.ascontiguousarray(x.transpose(0, 2, 1))
    med_c = (median_last(xt) if medians is None else medians)[..., None]
    dev = np.subtract(xt, med_c)
    np.abs(dev, out=dev)
    k = dev.shape[-1] // 2
    mad = median_last(dev, in_place=True)[..., None]  # dev is reordered: only its largest values are needed below
    # a row has an outlier when its largest deviation (after the partition, among the upper half; NaN left out) is one
    suspect = np.nonzero(np.fmax.reduce(dev[..., k:], axis=-1) > _threshold(med_c, mad, nsigma)[..., 0])
    counts = np.zeros(x.shape[0], dtype=np.int64)
    if not suspect[0].size:
        return xt.transpose(0, 2, 1), counts
    rows = xt[suspect]  # (m, n): the rows with an outlier (a copy), their deviations recomputed in order
    med_s = med_c[suspect]
    dev_s = np.subtract(rows, med_s)
    outlier = _outliers(np.abs(dev_s, out=dev_s), med_s, mad[suspect], nsigma)
    np.add.at(counts, suspect[0], row_counts(outlier))
    np.copyto(rows, np.broadcast_to(med_s, rows.shape), where=outlier)
    clean = xt.copy() if np.may_share_memory(xt, x) and not overwrite else xt  # never the caller's samples, unless its scratch
    clean[suspect] = rows
    return clean.transpose(0, 2, 1), counts


def _threshold(med: npt.NDArray[np.float64], mad: npt.NDArray[np.float64], nsigma: float) -> npt.NDArray[np.float64]:
    """The deviation from the median ``med`` above which a sample is an outlier: ``nsigma`` scaled MADs, and (a flat
    neighbourhood, MAD = 0, would flag any deviation) more than 1e-12 (1 + |med|): only a large one counts as a spike."""
    out: npt.NDArray[np.float64] = np.maximum((nsigma * MAD_SCALE) * mad, 1e-12 * (1.0 + np.abs(med)))
    return out


def _outliers(dev: npt.NDArray[np.float64], med: npt.NDArray[np.float64], mad: npt.NDArray[np.float64], nsigma: float) -> npt.NDArray[np.bool_]:
    """Where the deviation ``dev`` from the median ``med`` exceeds :func:`_threshold` (arrays broadcast together)."""
    out: npt.NDArray[np.bool_] = dev > _threshold(med, mad, nsigma)
    return out


SHORT_ROWS = 256  # rows up to this long are sorted whole: cheaper than a selection (the detector's 20 sub-blocks per hop)


def median_last(a: npt.NDArray[Any], in_place: bool = False, scale: float | None = None) -> npt.NDArray[np.float64]:
    """The median along the last axis, by partitioning (sorting rows of at most :data:`SHORT_ROWS`): the same values as
    ``np.median``, less overhead; ``in_place``: reorder ``a`` itself (its order is lost) rather than a copy. Either way the
    upper half of each row of the reordered array holds its largest values.

    ``scale`` (> 0, finite): the median of ``a * scale`` (e.g. int16 counts and volts per count), the same values as
    ``median_last(a * scale)``: the middle values are chosen in ``a`` (a positive scale keeps their order) and only they
    are scaled. Integers narrower than 32 bits are selected as int32 (the same values): numpy's vectorised selection
    covers 32- and 64-bit types, and int16 rows took ten times as long as int32 (and four times as long as float64) on
    an AVX2 host, numpy 2.4.
    """
    n = a.shape[-1]
    k = n // 2
    if not in_place and a.dtype.kind in "iu" and a.dtype.itemsize < 4:
        a = a.astype(np.int32)
    if in_place:
        if n <= SHORT_ROWS:
            a.sort(axis=-1)
        else:
            a.partition(k, axis=-1)
        p = a
    elif n <= SHORT_ROWS:
        p = np.sort(a, axis=-1)
    else:
        p = np.partition(a, k, axis=-1)  # one selection; the (k-1)-th is the largest below it (faster than kth=(k-1, k))
    upper = p[..., k] if scale is None else p[..., k] * scale
    if n % 2:
        odd: npt.NDArray[np.float64] = upper.copy() if in_place and scale is None else upper
        return odd
    below = p[..., k - 1] if n <= SHORT_ROWS else p[..., :k].max(axis=-1)
    if scale is not None:
        below = below * scale
    out: npt.NDArray[np.float64] = below / 2 + upper / 2  # halves first: no overflow, the same rounding
    return out


def row_counts(b: npt.NDArray[np.bool_]) -> npt.NDArray[np.int64]:
    """(...,) how many of each row of ``b`` (..., n) bool are True: ``np.count_nonzero(b, axis=-1)``, 8 bytes at a time
    (``np.bitwise_count`` of the rows seen as uint64; numpy casts every bool to int for a count along an axis) when the rows
    allow it."""
    if hasattr(np, "bitwise_count") and b.dtype == np.bool_ and b.ndim and b.shape[-1] % 8 == 0 and b.flags.c_contiguous:
        return np.bitwise_count(b.view(np.uint64)).sum(axis=-1, dtype=np.int64)  # type: ignore[no-any-return]
    return np.count_nonzero(b, axis=-1)  # type: ignore[no-any-return]
