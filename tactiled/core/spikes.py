"""Spike (outlier) removal: pure functions over (n, C) float64 arrays in volts.

``hampel``: a sample is an outlier when it lies more than ``nsigma`` scaled MADs
(1.4826·MAD) from the median of its ``2·half_width + 1`` neighbourhood; it is replaced
by that median (MATLAB ``hampel``; windows truncated at the edges by nearest padding).
``mad``: the same test against the whole window's median and MAD (MATLAB ``isoutlier``).
"""

from __future__ import annotations

import numpy as np
import numpy.typing as npt

MAD_SCALE = 1.4826


def remove_spikes(x: npt.NDArray[np.float64], method: str = "mad", half_width: int = 5,
                  nsigma: float = 4.0) -> tuple[npt.NDArray[np.float64], int]:
    """(cleaned copy of x (n, C), number of samples replaced). ``method``: hampel, mad or none."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2:
        raise ValueError(f"x must have shape (n, C), got {x.shape}")
    if method == "none" or x.shape[0] == 0:
        return x.copy(), 0
    if method == "hampel":
        from scipy.ndimage import median_filter  # SciPy only for the method that needs it (it costs ~70 MB resident)

        size = (2 * half_width + 1, 1)
        med = median_filter(x, size=size, mode="nearest")
        mad = median_filter(np.abs(x - med), size=size, mode="nearest")
    elif method == "mad":
        # medians per channel on contiguous rows: the same values as np.median(x, axis=0), without its overhead
        xt = np.ascontiguousarray(x.T)
        med_c = median_last(xt)[:, None]
        dev = np.abs(xt - med_c)
        outlier = _outliers(dev, med_c, median_last(dev)[:, None], nsigma)
        count = int(np.count_nonzero(outlier))
        if not count:
            return x.copy(), 0
        return np.where(outlier, med_c, xt).T.copy(), count
    else:
        raise ValueError(f"method must be hampel, mad or none, got {method!r}")
    outlier = _outliers(np.abs(x - med), med, mad, nsigma)
    return np.where(outlier, med, x), int(np.count_nonzero(outlier))


def _outliers(dev: npt.NDArray[np.float64], med: npt.NDArray[np.float64], mad: npt.NDArray[np.float64], nsigma: float) -> npt.NDArray[np.bool_]:
    """Where the deviation ``dev`` from the median ``med`` exceeds ``nsigma`` scaled MADs (arrays broadcast together).

    A flat neighbourhood (MAD = 0) flags any deviation; only a large one counts as a spike.
    """
    out: npt.NDArray[np.bool_] = (dev > (nsigma * MAD_SCALE) * mad) & (dev > 1e-12 * (1.0 + np.abs(med)))
    return out


def median_last(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The median along the last axis, by ``np.partition`` (the same values as ``np.median``, less overhead)."""
    n = a.shape[-1]
    k = n // 2
    if n % 2:
        odd: npt.NDArray[np.float64] = np.partition(a, k, axis=-1)[..., k]
        return odd
    p = np.partition(a, k, axis=-1)  # one selection; the (k-1)-th is the largest below it (faster than kth=(k-1, k))
    out: npt.NDArray[np.float64] = p[..., :k].max(axis=-1) / 2 + p[..., k] / 2  # halves first: no overflow, the same rounding
    return out
