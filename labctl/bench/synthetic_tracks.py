"""Generated table trajectories with known truth, for prediction tests and the planning benchmark.

The paper's object-motion simulator (an NC X-Y table, §5.2) moved objects at 4–12 mm/s; these
are the shapes the acceptance tests of the tracker use: a straight line, a 100 mm-radius arc,
an S-curve (two opposite 90° arcs) and stop-and-go along a line (trapezoidal speed changes at
the table's acceleration). All in table-plane mm and seconds, starting at the origin.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

SHAPES = ("line", "arc", "s_curve", "stop_and_go")


@dataclass(frozen=True)
class TableTrajectory:
    """A true marker path on the table plane: ``state(times) -> (pos, vel, acc)``, each (N, 2)."""

    shape: str
    speed_mm_s: float
    duration_s: float
    _state: Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray]]

    def state(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Position (mm), velocity (mm/s) and acceleration (mm/s²), each (N, 2), at ``times`` (s)."""
        return self._state(np.atleast_1d(np.asarray(times, dtype=float)))


def _line(speed: float, heading: float):
    u = np.array([np.cos(heading), np.sin(heading)])

    def state(t):
        return np.outer(speed * t, u), np.tile(speed * u, (len(t), 1)), np.zeros((len(t), 2))

    return state


def _arc(speed: float, radius: float, turn: float = 1.0):
    w = turn * speed / radius  # signed angular rate

    def state(t):
        ph = w * t
        p = np.column_stack([radius * np.sin(ph), turn * radius * (1 - np.cos(ph))])
        v = speed * np.column_stack([np.cos(ph), np.sin(ph)])
        a = speed * w * np.column_stack([-np.sin(ph), np.cos(ph)])
        return p, v, a

    return state


def _s_curve(speed: float, radius: float):
    theta = np.pi / 2
    t1 = radius * theta / speed
    first = _arc(speed, radius, 1.0)
    p1 = radius * np.array([np.sin(theta), 1 - np.cos(theta)])

    def state(t):
        p, v, a = first(np.minimum(t, t1))
        late = t > t1
        if np.any(late):
            u = speed * (t[late] - t1)
            ph = theta - u / radius
            p[late] = p1 + radius * np.column_stack([np.sin(theta) - np.sin(ph), np.cos(ph) - np.cos(theta)])
            v[late] = speed * np.column_stack([np.cos(ph), np.sin(ph)])
            a[late] = (speed**2 / radius) * np.column_stack([np.sin(ph), -np.cos(ph)])
        return p, v, a

    return state


def _stop_and_go(speed: float, go_s: float, stop_s: float, accel: float, duration: float):
    # piecewise-linear speed profile, integrated exactly on a grid containing every breakpoint
    ramp = speed / accel
    knots_t, knots_v = [0.0], [0.0]
    t = 0.0
    while t < duration + go_s + stop_s:
        knots_t += [t + ramp, t + go_s - ramp, t + go_s, t + go_s + stop_s]
        knots_v += [speed, speed, 0.0, 0.0]
        t += go_s + stop_s
    kt, kv = np.array(knots_t), np.array(knots_v)
    ks = np.concatenate([[0.0], np.cumsum(0.5 * (kv[1:] + kv[:-1]) * np.diff(kt))])
    ka = np.concatenate([np.diff(kv) / np.diff(kt), [0.0]])

    def state(tq):
        i = np.clip(np.searchsorted(kt, tq, side="right") - 1, 0, len(kt) - 2)
        dt = tq - kt[i]
        s = ks[i] + kv[i] * dt + 0.5 * ka[i] * dt * dt
        v = kv[i] + ka[i] * dt
        z = np.zeros_like(tq)
        return np.column_stack([s, z]), np.column_stack([v, z]), np.column_stack([ka[i], z])

    return state


def make_trajectory(shape: str, speed_mm_s: float, duration_s: float = 30.0, *, radius_mm: float = 100.0,
                    heading_rad: float = 0.3, table_accel_mm_s2: float = 200.0) -> TableTrajectory:
    """A :class:`TableTrajectory` of ``shape`` (one of :data:`SHAPES`) at constant path speed."""
    if shape == "line":
        fn = _line(speed_mm_s, heading_rad)
    elif shape == "arc":
        fn = _arc(speed_mm_s, radius_mm)
    elif shape == "s_curve":
        fn = _s_curve(speed_mm_s, radius_mm)
    elif shape == "stop_and_go":
        fn = _stop_and_go(speed_mm_s, go_s=4.0, stop_s=1.5, accel=table_accel_mm_s2, duration=duration_s)
    else:
        raise ValueError(f"unknown trajectory shape {shape!r} (have {', '.join(SHAPES)})")
    return TableTrajectory(shape, float(speed_mm_s), float(duration_s), fn)


def sample_measurements(traj: TableTrajectory, rate_hz: float = 30.0, noise_mm: float = 0.5,
                        drop_prob: float = 0.05, rng: np.random.Generator | None = None
                        ) -> tuple[np.ndarray, np.ndarray]:
    """Noisy centroid measurements of ``traj`` at ``rate_hz`` with frames dropped at random.

    Returns ``(times (M,), z (M, 2))``; Gaussian noise of ``noise_mm`` per axis.
    """
    rng = rng or np.random.default_rng(0)
    times = np.arange(0.0, traj.duration_s, 1.0 / rate_hz)
    keep = rng.random(len(times)) >= drop_prob
    keep[:2] = True
    times = times[keep]
    pos, _, _ = traj.state(times)
    return times, pos + rng.normal(0.0, noise_mm, pos.shape)


def prediction_errors(tracker, traj: TableTrajectory, horizons, warmup_s: float = 10.0, rate_hz: float = 30.0,
                      noise_mm: float = 0.5, drop_prob: float = 0.05,
                      rng: np.random.Generator | None = None) -> dict[float, np.ndarray]:
    """Errors (mm) of ``tracker``'s predictions ``h`` s ahead, for each horizon ``h``, along ``traj``.

    Feeds the noisy measurements of :func:`sample_measurements` one by one; after ``warmup_s``
    predicts every horizon whose target time is still inside the trajectory and compares with
    the true position. ``tracker`` is reset first.
    """
    tracker.reset()
    times, z = sample_measurements(traj, rate_hz, noise_mm, drop_prob, rng)
    horizons = [float(h) for h in horizons]
    errs: dict[float, list[float]] = {h: [] for h in horizons}
    for t, zi in zip(times, z):
        tracker.update(t, zi)
        if t < warmup_s:
            continue
        hs = [h for h in horizons if t + h <= traj.duration_s]
        if not hs:
            continue
        truth, _, _ = traj.state(np.array([t + h for h in hs]))
        for h, true_p in zip(hs, truth):
            mean, _ = tracker.predict(t + h)
            errs[h].append(float(np.hypot(*(mean - true_p))))
    return {h: np.array(e) for h, e in errs.items()}


def compare_with_bound(make_tracker, family: str, speed_mm_s: float, *, runs: int = 30, track_s=(2.0, 4.0),
                       horizon_s: float = 5.0, rate_hz: float = 30.0, sigma_mm: float = 0.7, with_ml: bool = True,
                       seed: int = 0, after_corner_s=(), corner_s: float = 2.0,
                       table_accel_mm_s2: float | None = None, drop_frames: float = 0.0,
                       curvature_sigma: float | None = None, prior=None) -> dict:
    """Monte-Carlo of a tracker's ``horizon_s`` prediction against the bound (:mod:`.track_bound`) on one family.

    ``make_tracker()`` builds a fresh tracker; each run feeds it the frames of a
    :func:`~.track_bound.make_scenario` path (random heading) and, after each of ``track_s`` seconds
    of tracking, predicts ``horizon_s`` ahead. For the zigzag, ``after_corner_s`` adds the
    instants that long after the corner (at ``corner_s``); ``table_accel_mm_s2``: the table's
    acceleration, for ``zigzag_stop`` (:func:`~.track_bound.make_scenario`); ``drop_frames``: the share of
    frames the tracker never gets, each independently (never an instant's own frame), as a busy live
    predictor skips some; the bound and the ML fit then use the same frames. ``curvature_sigma`` (mm⁻¹; arcs and
    circles): each run's curvature is drawn from N(0, curvature_sigma²) instead of the family's radius, i.e. the
    truth follows a tracker's curvature prior of that width; a filter whose mean and covariance are the posterior's
    then has a mean NEES of 2 over the runs (E[eᵀP⁻¹e] = tr(P⁻¹P)), where on one fixed radius near the prior's mean
    it scores less. ``prior`` (a :class:`~labctl.bench.nees.TrackPrior`; lines, arcs and circles): each run's truth
    drawn from a tracker's whole prior: a curve with its ``curve_probability`` (then of curvature
    N(0, ``curvature_sigma``²)), else a line; the family given then only names the cell (a line's cell holds the
    curves its prior allows, an arc's the lines), and the bound and the ML fit are the drawn truth's model.
    Returns, per instant (keyed by its
    time in s): the tracker's RMS error (mm), the Cramér-Rao bound on it, the RMS of the ML fit on
    the same measurements (if ``with_ml``), and the tracker's mean NEES of that prediction (2 dof)
    with its two-sided 95 % bounds for ``runs`` runs; and a tail-robust check of the same: the fraction of
    runs whose NEES is under chi-square(2)'s 95 % point (5.99), with its two-sided 95 % binomial bounds
    around 0.95 (the mean NEES of 64 heavy-tailed runs moved by ±0.5-1.2 between seed sets, see
    docs/notes/planning.md, "Fifth round"). ``nees_crb``: the mean NEES of the same errors against the
    Cramér-Rao covariance of that run's prediction, i.e. what a filter whose covariance were exactly the
    bound would score; ``cov_to_crb``: the median over runs of trace(P) / trace(CRB). A NEES below 2 with
    ``nees_crb`` as low says the errors themselves fell below the bound, not that the filter's covariance is wide.
    ``nees_ml_crb`` (with ``with_ml``): the mean NEES of the ML fit's own errors against the Cramér-Rao
    covariance, on the same runs: the reference estimator. On a line (linear, Gaussian) the ML fit is the
    optimal filter and the bound is exactly its covariance, so this is what a perfectly consistent, efficient
    estimator scores on these runs; when it is outside ``nees_bounds`` too, the runs, not the filter, put the
    cell outside. On curves and corners the ML fit is efficient only asymptotically.
    """
    from scipy.stats import binom, chi2

    from .track_bound import crb_prediction_cov, make_scenario, ml_prediction

    instants = sorted({float(t) for t in track_s} | {corner_s + float(t) for t in after_corner_s})
    duration = max(instants)
    rng = np.random.default_rng(seed)
    errs: dict[float, list[np.ndarray]] = {t: [] for t in instants}
    ml_errs: dict[float, list[np.ndarray]] = {t: [] for t in instants}
    nees: dict[float, list[float]] = {t: [] for t in instants}
    nees_crb: dict[float, list[float]] = {t: [] for t in instants}
    cov_to_crb: dict[float, list[float]] = {t: [] for t in instants}
    crb: dict[float, list[float]] = {t: [] for t in instants}
    nees_ml: dict[float, list[float]] = {t: [] for t in instants}
    drops = np.random.default_rng([seed, 1])  # its own stream: the runs' paths and noise do not change
    # the truths' curvatures (and modes) from their own streams too: headings and noise as on the family's radius
    curved, kappas = _drawn_truths(family, runs, seed, curvature_sigma, prior)
    for i in range(runs):
        kappa = None if kappas is None or not curved[i] else float(kappas[i])
        truth_family = family if curved is None else "arc" if curved[i] else "line"
        scn = make_scenario(truth_family, speed_mm_s, duration, rate_hz=rate_hz, sigma_mm=sigma_mm,
                            heading_rad=rng.uniform(-np.pi, np.pi), corner_s=corner_s,
                            table_accel_mm_s2=table_accel_mm_s2, curvature_mm_inv=kappa)
        z = scn.measure(rng)
        trk = make_tracker()
        marks = {int(round(t * rate_hz)): t for t in instants}
        keep = drops.random(len(z)) >= drop_frames
        keep[0] = True
        keep[list(marks)] = True
        for k, (t, zk) in enumerate(zip(scn.times, z)):
            if keep[k]:
                trk.update(t, zk)
            if k not in marks:
                continue
            ti = marks[k]
            truth = scn.current_motion(t, [t + horizon_s])[0]
            mean, cov = trk.predict(t + horizon_s)
            e = mean - truth
            errs[ti].append(e)
            nees[ti].append(float(e @ np.linalg.solve(cov, e)))
            bound = crb_prediction_cov(scn, k + 1, horizon_s, keep=keep)
            crb[ti].append(float(np.trace(bound)))
            nees_crb[ti].append(float(e @ np.linalg.solve(bound, e)))
            cov_to_crb[ti].append(float(np.trace(cov) / np.trace(bound)))
            if with_ml:
                e_ml = ml_prediction(scn, z, k + 1, horizon_s, keep=keep) - truth
                ml_errs[ti].append(e_ml)
                nees_ml[ti].append(float(e_ml @ np.linalg.solve(bound, e_ml)))
    lo, hi = chi2.ppf(0.025, 2 * runs) / runs, chi2.ppf(0.975, 2 * runs) / runs
    gate = chi2.ppf(0.95, 2)
    frac_bounds = (float(binom.ppf(0.025, runs, 0.95) / runs), float(binom.ppf(0.975, runs, 0.95) / runs))
    out = {}
    for t in instants:
        e = np.array(errs[t])
        row = {"rms_mm": float(np.sqrt(np.mean(np.sum(e**2, axis=1)))), "crb_mm": float(np.sqrt(np.mean(crb[t]))),
               "nees": float(np.mean(nees[t])), "nees_bounds": (float(lo), float(hi)),
               "nees_frac_95": float(np.mean(np.array(nees[t]) <= gate)), "nees_frac_bounds": frac_bounds,
               "nees_crb": float(np.mean(nees_crb[t])), "cov_to_crb": float(np.median(cov_to_crb[t])),
               "curved_runs": None if curved is None else int(np.sum(curved))}
        if with_ml:
            m = np.array(ml_errs[t])
            row["ml_rms_mm"] = float(np.sqrt(np.mean(np.sum(m**2, axis=1))))
            row["nees_ml_crb"] = float(np.mean(nees_ml[t]))
        out[t] = row
    return out


def _drawn_truths(family: str, runs: int, seed: int, curvature_sigma: float | None, prior):
    """Each run's (curved, curvature mm⁻¹) for :func:`compare_with_bound`: ``(None, None)`` for the family's own path.

    ``curvature_sigma`` alone: every run curved, the curvature N(0, σ²); ``prior``: the mode and the curvature from
    :meth:`~labctl.bench.nees.TrackPrior.draw` (both on the same ``[seed, 2]`` curvature stream)."""
    if curvature_sigma is None and prior is None:
        return None, None
    if curvature_sigma is not None and prior is not None:
        raise ValueError("give curvature_sigma or prior, not both")
    if family not in ("line", "arc", "circle"):
        raise ValueError(f"a truth drawn from a prior is a line or a curve, not a {family!r} (its legs, its corner)")
    if curvature_sigma is not None:
        return np.ones(runs, dtype=bool), np.random.default_rng([seed, 2]).normal(0.0, curvature_sigma, runs)
    return prior.draw(runs, seed)
