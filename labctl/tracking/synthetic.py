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
