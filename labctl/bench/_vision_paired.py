"""Paired comparison of the two methods of the vision degradation suite.

Both methods see the same images (:func:`labctl.bench._vision_suite.run_case` with
``per_image=True``), so the difference of their p95 normal errors is measured with a paired
bootstrap: whole image pairs (the two views of one pose pair share a camera and a disc) are
resampled with replacement, and each method's p95 is taken over the images it detected in that
resample, exactly as the suite's table takes it.
"""

from __future__ import annotations

import numpy as np


def paired_p95(ours, base, n_boot: int = 2000, seed: int = 0, q: float = 95.0, block: int = 2) -> dict:
    """p95 of ``ours`` and ``base`` (per-image errors in render order, NaN = not detected), their
    difference ours − base, and a percentile bootstrap 95 % interval of that difference resampling
    blocks of ``block`` consecutive images (one pose pair). Units are those of the inputs; a
    statistic that cannot be taken (a method detected nothing) is None."""
    a, b = np.asarray(ours, float), np.asarray(base, float)
    if a.shape != b.shape or a.size % block:
        raise ValueError("ours and base must be per-image arrays of the same whole number of blocks")
    a, b = a.reshape(-1, block), b.reshape(-1, block)
    n = a.shape[0]

    def stat(ia):
        x, y = a[ia].ravel(), b[ia].ravel()
        x, y = x[~np.isnan(x)], y[~np.isnan(y)]
        return (float(np.percentile(x, q)) if len(x) else np.nan), (float(np.percentile(y, q)) if len(y) else np.nan)

    p_o, p_b = stat(np.arange(n))
    rng = np.random.default_rng(seed)
    diffs = np.empty(n_boot)
    for k in range(n_boot):
        so, sb = stat(rng.integers(0, n, n))
        diffs[k] = so - sb
    diffs = diffs[~np.isnan(diffs)]
    lo, hi = (np.percentile(diffs, [2.5, 97.5]) if len(diffs) else (np.nan, np.nan))

    def num(v):  # JSON has no NaN
        return None if np.isnan(v) else float(v)

    return {"ours": num(p_o), "base": num(p_b), "diff": num(p_o - p_b), "lo": num(lo), "hi": num(hi),
            "n_images": int(a.size)}
