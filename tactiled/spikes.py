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
        med_c = _median_rows(xt)
        dev = np.abs(xt - med_c[:, None])
        mad_c = _median_rows(dev)
        outlier = (dev > (nsigma * MAD_SCALE) * mad_c[:, None]) & (dev > (1e-12 * (1.0 + np.abs(med_c)))[:, None])
        count = int(np.count_nonzero(outlier))
        if not count:
            return x.copy(), 0
        out = np.where(outlier, med_c[:, None], xt).T.copy()
        return out, count
    else:
        raise ValueError(f"method must be hampel, mad or none, got {method!r}")
    outlier = np.abs(x - med) > nsigma * MAD_SCALE * mad
    # a flat neighbourhood (MAD = 0) flags any deviation; only call it a spike if it is large
    outlier &= np.abs(x - med) > 1e-12 * (1.0 + np.abs(med))
    out = np.where(outlier, med, x)
    return out, int(np.count_nonzero(outlier))


def _median_rows(a: npt.NDArray[np.float64]) -> npt.NDArray[np.float64]:
    """The median of each row of ``a`` (C, n), as ``np.median(a, axis=1)``."""
    n = a.shape[1]
    k = n // 2
    if n % 2:
        return np.partition(a, k, axis=1)[:, k]
    p = np.partition(a, k, axis=1)  # one selection; the (k-1)-th is the largest below it (faster than kth=(k-1, k))
    out: npt.NDArray[np.float64] = (p[:, :k].max(axis=1) + p[:, k]) / 2
    return out
