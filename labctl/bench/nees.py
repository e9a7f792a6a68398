"""Pooled NEES: a filter's consistency judged per trajectory family, not cell by cell.

The normalised estimation error squared of one prediction, ``ε = eᵀ P⁻¹ e`` (e the 2-D position error in
mm, P the filter's covariance in mm²), is χ²(2) when the filter is consistent and the error Gaussian; the
mean of N independent ones, times N, is χ²(2N) (Bar-Shalom, Li & Kirubarajan 2001, §5.4.2). With the
truth drawn from the filter's own prior (families, radii, speeds), E[ε] = tr(P⁻¹ P) = 2 holds for a
Bayes-consistent filter whether or not its posterior is Gaussian; only the band's width assumes χ².

Read cell by cell (a family × speed × instant), 44 cells of 64 runs each fail about 2 by chance at 95 %,
and the ideal reference estimator failed 7 of the planning bench's 44 (docs/notes/planning.md). Pooled
per family, the N runs of all its cells give one mean and one two-sided χ² band, the statistic the
planning bench's acceptance reads; the per-cell bands stay in its report as information.

Cells at several instants of the *same* runs (after 2 s and 4 s of one track) are positively
correlated, so their pooled mean spreads more than the band says: pooling them makes the check stricter
than its nominal 95 %. :func:`pooled_by_family` therefore also pools per (family, instant), whose cells
(the speeds, each on its own seeds) are independent and whose band is exact.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TrackPrior:
    """The prior a tracker declares over the motion it tracks: its mode, curvature and velocity priors (§4.2).

    ``curve_probability``: the IMM's prior probability of its coordinated-turn mode against the straight one
    (``tracking.family_prior`` for the family it is told, ``tracking.curve_prior`` blind); ``curvature_sigma``
    (mm⁻¹): the CT mode's curvature prior N(0, σ²); ``speed_sigma`` (mm/s per axis): the velocity prior
    N(0, σ² I), isotropic, so a truth drawn from it has a uniform heading. Read from a built tracker with
    :meth:`of`, never restated: a truth drawn from it is what that tracker's covariance claims to cover.
    """

    curve_probability: float
    curvature_sigma: float
    speed_sigma: float

    def __post_init__(self) -> None:
        """Reject a prior no truth can be drawn from (a probability outside [0, 1], a width not positive)."""
        if not 0.0 <= self.curve_probability <= 1.0:
            raise ValueError(f"curve_probability must be in [0, 1], got {self.curve_probability!r}")
        for name in ("curvature_sigma", "speed_sigma"):
            value = getattr(self, name)
            if not (np.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")

    @classmethod
    def of(cls, tracker) -> TrackPrior:
        """The prior ``tracker`` (a :class:`labctl.tracking.MarkerTracker`) was built with."""
        return cls(float(tracker.curve_prior), float(tracker.curvature_prior_sigma), float(tracker.speed_prior_sigma))

    def draw(self, runs: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
        """``runs`` truths' mode and curvature: ``(curved (runs,) bool, curvature (runs,) mm⁻¹)``.

        ``curved[i]`` is a Bernoulli(``curve_probability``) draw, the curvature N(0, ``curvature_sigma``²) where
        curved and 0 where straight. Each from its own stream of ``seed`` (the curvature's ``[seed, 2]``, the
        mode's ``[seed, 3]``), so the headings and the measurement noise a caller draws from ``seed`` itself
        are the same whatever the prior."""
        if runs < 0:
            raise ValueError(f"runs must be ≥ 0, got {runs}")
        kappa = np.random.default_rng([seed, 2]).normal(0.0, self.curvature_sigma, runs)
        curved = np.random.default_rng([seed, 3]).random(runs) < self.curve_probability
        return curved, np.where(curved, kappa, 0.0)


def nees_band(samples: int, dim: int = 2, level: float = 0.95) -> tuple[float, float]:
    """Two-sided ``level`` band of the mean of ``samples`` independent χ²(``dim``) NEES values.

    ``N·mean ~ χ²(dim·N)``, so the band is ``χ²⁻¹((1 ∓ level)/2; dim·N) / N``."""
    from scipy.stats import chi2

    if samples < 1 or dim < 1 or not 0.0 < level < 1.0:
        raise ValueError(f"need samples ≥ 1, dim ≥ 1 and 0 < level < 1, got {samples}, {dim}, {level}")
    a = (1.0 - level) / 2.0
    return float(chi2.ppf(a, dim * samples) / samples), float(chi2.ppf(1.0 - a, dim * samples) / samples)


def pooled_nees(cells: Iterable[dict], dim: int = 2, level: float = 0.95) -> dict:
    """The NEES of several cells pooled: their runs' mean, its χ² band and whether it lies inside.

    Each cell is a dict with ``nees`` (its runs' mean NEES) and ``runs`` (how many); the pooled mean is
    the runs-weighted mean of the cells' means, i.e. the mean over every run of every cell. Returns
    ``{"nees", "nees_95": [lo, hi], "holds", "runs", "cells"}``."""
    cells = list(cells)
    runs = sum(int(c["runs"]) for c in cells)
    if runs < 1:
        raise ValueError("no runs to pool")
    mean = sum(float(c["nees"]) * int(c["runs"]) for c in cells) / runs
    lo, hi = nees_band(runs, dim, level)
    return {"nees": mean, "nees_95": [lo, hi], "holds": bool(lo <= mean <= hi), "runs": runs, "cells": len(cells)}


def _key(row: dict) -> str:
    return f"{row['family']} {'corner +' if row.get('after_corner') else ''}{row['at_s']:g} s"


def pooled_by_family(rows: Iterable[dict], *, family_of=None, dim: int = 2, level: float = 0.95) -> dict:
    """Pool bench rows (``family``, ``at_s``, ``after_corner``, ``nees``, ``runs``) per family, and per family
    and instant.

    ``family_of(row)`` names the family a row is pooled in (default: its ``family``; e.g. arc and circle are one
    family once the curvature is drawn from the prior). Returns ``{"by_family": {family: pooled},
    "by_family_instant": {"<family> <instant>": pooled}, "holds": "k / n"}`` with :func:`pooled_nees`'s dicts;
    ``holds`` counts the families whose pooled mean is inside its band."""
    rows = list(rows)
    name = family_of or (lambda r: r["family"])
    fams: dict[str, list[dict]] = {}
    inst: dict[str, list[dict]] = {}
    for r in rows:
        fams.setdefault(name(r), []).append(r)
        inst.setdefault(_key({**r, "family": name(r)}), []).append(r)
    by_family = {f: pooled_nees(cs, dim, level) for f, cs in fams.items()}
    return {"by_family": by_family,
            "by_family_instant": {k: pooled_nees(cs, dim, level) for k, cs in inst.items()},
            "holds": f"{sum(p['holds'] for p in by_family.values())} / {len(by_family)}"}
