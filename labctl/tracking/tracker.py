"""Marker tracking on the table plane: Kalman filter (CV, CA or IMM of both) with prediction.

Paper §4.2 (after its ref. [13], Croft, Fenton & Benhabib): the fixed camera's marker centroid,
mapped through the calibration onto the table plane, updates a recursive Kalman filter; the
one-step-ahead prediction keeps the search window on the marker and multiple-step-ahead
predictions (the filter's extrapolation equations run forward) give the object's future path.

Built on filterpy 2.0.0 with its pitfalls avoided (DESIGN §4): measurements always go in as
(2, 1) column vectors, ``update`` is never given an ``H`` override, H is built by hand rather
than by ``kinematic_kf``, and ``batch_filter`` is not used. Frames: table-plane / world X-Y,
millimetres; times in seconds (any monotonic clock; frames may be dropped).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from filterpy.kalman import IMMEstimator, KalmanFilter

from .models import plane_matrices, position_matrix

ModelName = Literal["cv", "ca", "imm"]


class TrackingError(ValueError):
    """Bad input to the tracker (non-finite measurement, prediction into the past, no track yet).

    A ``ValueError`` (the tracking layer imports nothing else from labctl); callers at the edges
    turn it into a ``UserInputError`` or ``LabctlError`` as fits.
    """


@dataclass(frozen=True)
class PredictedPath:
    """The mean predicted marker path, a snapshot that no longer depends on the tracker.

    ``p(t) = position + velocity·Δ + acceleration·Δ²/2`` with ``Δ = t - t_ref`` (table-plane mm,
    s). This is exactly the Kalman mean extrapolation of the CV/CA models (and of an IMM with its
    mode probabilities frozen at ``t_ref``), so it also gives the path's velocity and acceleration
    analytically, as the interception planner needs (paper §4.3, G(t)).
    """

    t_ref: float
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(2))

    def __call__(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and accelerations, each (N, 2), at ``times`` (s)."""
        d = np.atleast_1d(np.asarray(times, dtype=float))[:, None] - self.t_ref
        p = self.position + self.velocity * d + 0.5 * self.acceleration * d * d
        v = self.velocity + self.acceleration * d
        a = np.broadcast_to(self.acceleration, p.shape).copy()
        return p, v, a


class _KalmanFilter2D(KalmanFilter):
    """filterpy's filter with a closed-form Gaussian log-likelihood of the 2-D innovation.

    filterpy evaluates it through scipy.stats (about 0.15 ms a call); the IMM needs it on every
    update of every model. Same value: ``-½ (yᵀ S⁻¹ y + log det(2π S))``.
    """

    @property
    def log_likelihood(self):
        if self._log_likelihood is None:
            y = self.y.reshape(-1)
            S = self.S
            det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
            m2 = (S[1, 1] * y[0] ** 2 - (S[0, 1] + S[1, 0]) * y[0] * y[1] + S[0, 0] * y[1] ** 2) / det
            self._log_likelihood = float(-0.5 * (m2 + np.log((2 * np.pi) ** 2 * det)))
        return self._log_likelihood


class MarkerTracker:
    """Track one marker centroid on the table plane and predict it at any future time.

    ``model``: ``"cv"`` (constant velocity, white-acceleration noise of spectral density
    ``process_noise²`` mm²/s³), ``"ca"`` (constant acceleration, white-jerk noise of density
    ``jerk_noise²`` mm²/s⁵) or ``"imm"`` (interacting multiple models: that CV and that CA,
    switching probability ``imm_switch_prob`` per update). ``measurement_noise_mm`` is the
    centroid's standard deviation per axis on the table plane. A measurement whose Mahalanobis
    distance from the prediction exceeds ``gate_sigma`` is rejected; after ``max_misses``
    consecutive rejections the track is restarted on the newest measurement (the marker really
    moved differently). Paper §4.2.
    """

    def __init__(
        self,
        model: ModelName = "cv",
        process_noise: float = 5.0,
        measurement_noise_mm: float = 0.7,
        gate_sigma: float = 4.0,
        *,
        jerk_noise: float = 2.0,
        imm_switch_prob: float = 0.02,
        init_speed_sigma: float = 150.0,
        init_accel_sigma: float = 50.0,
        max_misses: int = 10,
    ) -> None:
        if model not in ("cv", "ca", "imm"):
            raise TrackingError(f"unknown tracking model {model!r} (expected cv, ca or imm)")
        for name, value in (
            ("process_noise", process_noise),
            ("measurement_noise_mm", measurement_noise_mm),
            ("gate_sigma", gate_sigma),
            ("jerk_noise", jerk_noise),
            ("init_speed_sigma", init_speed_sigma),
            ("init_accel_sigma", init_accel_sigma),
        ):
            if not np.isfinite(value) or value <= 0:
                raise TrackingError(f"{name} must be a positive number, got {value!r}")
        if not 0.0 < imm_switch_prob < 1.0:
            raise TrackingError(f"imm_switch_prob must be in (0, 1), got {imm_switch_prob!r}")
        self.model = model
        self.gate_sigma = float(gate_sigma)
        self.max_misses = int(max_misses)
        self._q_cv = float(process_noise) ** 2
        self._q_ca = float(jerk_noise) ** 2
        self._R = np.eye(2) * float(measurement_noise_mm) ** 2
        self._init_sigmas = (float(init_speed_sigma), float(init_accel_sigma))
        self._switch = float(imm_switch_prob)
        self.reset()

    @classmethod
    def from_config(cls, cfg, **overrides) -> MarkerTracker:
        """Build from a :class:`labctl.config.lab.TrackingConfig` (model, noises, gate)."""
        kw = dict(
            model=cfg.model,
            process_noise=cfg.process_noise,
            measurement_noise_mm=cfg.measurement_noise_mm,
            gate_sigma=cfg.gate_sigma,
        )
        kw.update(overrides)
        return cls(**kw)

    # -- state -------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the track; the next measurement starts a new one."""
        self._t: float | None = None
        self._updates = 0
        self._misses = 0
        self.last_mahalanobis: float | None = None
        if self.model == "cv":
            self._specs = [(1, self._q_cv, False)]
        elif self.model == "ca":
            self._specs = [(2, self._q_ca, False)]
        else:
            self._specs = [(1, self._q_cv, True), (2, self._q_ca, False)]
        self._dim_axis = 2 if self.model == "cv" else 3
        self._H = position_matrix(self._dim_axis)
        self._kfs = []
        for _ in self._specs:
            kf = _KalmanFilter2D(dim_x=2 * self._dim_axis, dim_z=2)
            kf.H = self._H.copy()
            kf.R = self._R.copy()
            self._kfs.append(kf)
        self._imm = None

    @property
    def initialized(self) -> bool:
        """True once a measurement has started the track."""
        return self._t is not None

    @property
    def time(self) -> float | None:
        """Time (s) of the last accepted measurement."""
        return self._t

    @property
    def mode_probabilities(self) -> np.ndarray:
        """IMM mode probabilities ``[P(CV), P(CA)]``; ``[1.]`` for a single model."""
        return np.array([1.0]) if self._imm is None else self._imm.mu.copy()

    def _start(self, t: float, z: np.ndarray) -> None:
        speed_sigma, accel_sigma = self._init_sigmas
        d = self._dim_axis
        x = np.zeros((2 * d, 1))
        x[0, 0], x[d, 0] = z
        P = np.zeros((2 * d, 2 * d))
        for base in (0, d):
            P[base, base] = self._R[0, 0]
            P[base + 1, base + 1] = speed_sigma**2
            if d == 3:
                P[base + 2, base + 2] = accel_sigma**2
        for kf, (_, _, embed) in zip(self._kfs, self._specs):
            kf.x = x.copy()
            kf.P = P.copy()
            if embed:  # the CV model inside the IMM carries no acceleration
                for base in (0, d):
                    kf.P[base + 2, base + 2] = 1e-9
        if self.model == "imm":
            M = np.array([[1 - self._switch, self._switch], [self._switch, 1 - self._switch]])
            self._imm = IMMEstimator(self._kfs, np.array([0.5, 0.5]), M)
        self._t = t
        self._updates = 1
        self._misses = 0

    def _set_dt(self, dt: float) -> None:
        for kf, (order, q, embed) in zip(self._kfs, self._specs):
            kf.F, kf.Q = plane_matrices(order, dt, q, embed_in_ca=embed)

    def _snapshot(self):
        snap = [(kf.x.copy(), kf.P.copy()) for kf in self._kfs]
        if self._imm is not None:
            imm = self._imm
            snap.append((imm.mu.copy(), imm.cbar.copy(), imm.omega.copy(), imm.x.copy(), imm.P.copy()))
        return snap

    def _restore(self, snap) -> None:
        for kf, (x, P) in zip(self._kfs, snap):
            kf.x, kf.P = x, P
        if self._imm is not None:
            imm = self._imm
            imm.mu, imm.cbar, imm.omega, imm.x, imm.P = snap[-1]

    # -- filtering -----------------------------------------------------------------------------

    def update(self, t: float, z_xy) -> bool:
        """Fuse the centroid ``z_xy`` (table-plane mm) measured at time ``t`` (s).

        Returns False when the measurement is gated out (its Mahalanobis distance from the
        one-step-ahead prediction exceeds ``gate_sigma``) or is not newer than the last one;
        the filter state is then unchanged. Raises :class:`TrackingError` on non-finite input.
        """
        t = float(t)
        z = np.asarray(z_xy, dtype=float).reshape(-1)
        if z.shape != (2,) or not np.all(np.isfinite(z)) or not np.isfinite(t):
            raise TrackingError(f"expected a finite time and a finite (x, y) measurement, got {t!r}, {z_xy!r}")
        if self._t is None:
            self._start(t, z)
            return True
        dt = t - self._t
        if dt <= 0.0:
            return False
        snap = self._snapshot()
        self._set_dt(dt)
        if self._imm is not None:
            self._imm.predict()
            x_prior, P_prior = self._imm.x, self._imm.P
        else:
            self._kfs[0].predict()
            x_prior, P_prior = self._kfs[0].x, self._kfs[0].P
        zc = z.reshape(2, 1)  # filterpy wants column vectors
        y = zc - self._H @ x_prior
        S = self._H @ P_prior @ self._H.T + self._R
        d2 = float((y.T @ np.linalg.solve(S, y))[0, 0])
        self.last_mahalanobis = float(np.sqrt(max(d2, 0.0)))
        if self._updates >= 3 and d2 > self.gate_sigma**2:
            self._restore(snap)
            self._misses += 1
            if self._misses >= self.max_misses:
                self.reset()
                self._start(t, z)
                return True
            return False
        if self._imm is not None:
            self._imm.update(zc)
        else:
            self._kfs[0].update(zc)
        self._t = t
        self._updates += 1
        self._misses = 0
        return True

    # -- estimates and predictions -------------------------------------------------------------

    def _require_track(self) -> None:
        if self._t is None:
            raise TrackingError("no track yet: call update() with a measurement first")

    def _model_predictions(self, dt: float):
        """Each model's (x, P) extrapolated ``dt`` s past the last update, without touching the filter."""
        out = []
        for kf, (order, q, embed) in zip(self._kfs, self._specs):
            if dt == 0.0:
                out.append((kf.x.copy(), kf.P.copy()))
                continue
            F, Q = plane_matrices(order, dt, q, embed_in_ca=embed)
            out.append((F @ kf.x, F @ kf.P @ F.T + Q))
        return out

    def _combined(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        preds = self._model_predictions(dt)
        if self._imm is None:
            return preds[0]
        mu = self._imm.mu
        x = sum(m * xp for m, (xp, _) in zip(mu, preds))
        P = sum(m * (Pp + (xp - x) @ (xp - x).T) for m, (xp, Pp) in zip(mu, preds))
        return x, P

    def _check_future(self, t: float) -> float:
        self._require_track()
        t = float(t)
        if not np.isfinite(t):
            raise TrackingError(f"prediction time must be finite, got {t!r}")
        dt = t - self._t
        if dt < -1e-9:
            raise TrackingError(f"cannot predict into the past: t={t:.6f} s is before the last update {self._t:.6f} s")
        return max(dt, 0.0)

    def predict(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted marker position (2,) mm and its covariance (2, 2) mm² at time ``t`` ≥ last update.

        Runs the Kalman extrapolation equations over ``t - t_last`` in one exact step (paper §4.2:
        one-step-ahead for the search window, multiple-step-ahead for the path). The filter's
        state is not changed. For the IMM the models' predictions are moment-matched with the
        current mode probabilities.
        """
        x, P = self._combined(self._check_future(t))
        idx = [0, self._dim_axis]
        return x[idx, 0].copy(), P[np.ix_(idx, idx)].copy()

    def predict_path(self, times) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`predict` at each of ``times``: means (N, 2) mm and covariances (N, 2, 2) mm²."""
        times = np.atleast_1d(np.asarray(times, dtype=float))
        means = np.empty((len(times), 2))
        covs = np.empty((len(times), 2, 2))
        for i, t in enumerate(times):
            means[i], covs[i] = self.predict(t)
        return means, covs

    def estimate(self) -> tuple[np.ndarray, np.ndarray]:
        """Posterior ``[x, y, vx, vy]`` (mm, mm/s) and its 4×4 covariance at the last update."""
        self._require_track()
        x, P = self._combined(0.0)
        d = self._dim_axis
        idx = [0, d, 1, d + 1]
        return x[idx, 0].copy(), P[np.ix_(idx, idx)].copy()

    def velocity(self) -> np.ndarray:
        """Posterior marker velocity (2,) in mm/s at the last update."""
        return self.estimate()[0][2:]

    def predicted_path(self) -> PredictedPath:
        """The mean predicted path as a :class:`PredictedPath` snapshot (for G(t), paper §4.3)."""
        self._require_track()
        preds = self._model_predictions(0.0)
        mu = np.array([1.0]) if self._imm is None else self._imm.mu
        d = self._dim_axis
        p = sum(m * xp[[0, d], 0] for m, (xp, _) in zip(mu, preds))
        v = sum(m * xp[[1, d + 1], 0] for m, (xp, _) in zip(mu, preds))
        a = np.zeros(2)
        if d == 3:
            for m, (xp, _), (order, _, _) in zip(mu, preds, self._specs):
                if order == 2:
                    a = a + m * xp[[2, d + 2], 0]
        return PredictedPath(self._t, np.asarray(p, float), np.asarray(v, float), a)
