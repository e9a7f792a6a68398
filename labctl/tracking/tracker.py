"""Marker tracking on the table plane: Kalman filters (CV, CT, CA, or an IMM) with prediction.

Paper §4.2 (after its ref. [13], Croft, Fenton & Benhabib): the fixed camera's marker centroid,
mapped through the calibration onto the table plane, updates a recursive Kalman filter; the
one-step-ahead prediction keeps the search window on the marker and multiple-step-ahead
predictions (the filter's extrapolation equations run forward) give the object's future path.

Models (Bar-Shalom, Li & Kirubarajan 2001, ch. 6 and §11.7):

* ``cv`` — constant velocity with near-zero white-acceleration noise: on a straight path it is
  the least-squares line fit, the best the data allow;
* ``ct`` — coordinated turn (constant speed and curvature κ, turn rate ω = κ·|v|; an EKF:
  nonlinear mean, Jacobian covariance), for arcs and circles. The curvature's prior is the
  table's tightest radius (80 mm in the lab's programs), the same at every speed;
* ``imm`` — interacting multiple models of that CV, that CT and a *manoeuvre* mode (CV with a
  large white-acceleration noise, proportional to the speed) that absorbs corners such as a
  zigzag's; on detecting one, the quiet modes restart at the corner's ML time (a GLR over the
  recent frames) and take over again;
* ``ca`` — constant acceleration, kept as a standalone comparison only (measured in
  docs/notes/planning.md: it costs 4–10× on lines and has the wrong shape for arcs).

The CV, CT and manoeuvre modes share the state ``[x, vx, y, vy, κ]`` so the IMM can mix them.
Long-horizon predictions propagate the CT mode's mean through the turn and its covariance by
the cubature rule (2n points, Arasaratnam & Haykin 2009), which keeps the banana-shaped
uncertainty of a poorly known turn rate honest (where the curvature is within ``PROFILE_SIGMAS`` σ of
zero, by the exact curvature profile, ``MarkerTracker._curvature_profile``); the manoeuvre mode
extrapolates with the quiet CV noise (a corner is a transient, not a motion that continues). The CT
mode's estimate behind those predictions is re-linearised by a Gauss-Newton fit of the turn to its recent frames (see
``MarkerTracker._turn_refit``): the EKF alone kept its first frames' linearisation errors. Mode
weights below :data:`MIX_FLOOR` are left out of the IMM's mixing and predictions.

Built on filterpy 2.0.0 with its pitfalls avoided (docs/architecture.md, "Hand-written versus
library code"): measurements always go in as (2, 1) column vectors, ``update`` is never given
an ``H`` override, H is built by hand rather than by ``kinematic_kf``, and ``batch_filter`` is
not used. Frames: table-plane / world X-Y, millimetres; times in seconds (any monotonic clock;
frames may be dropped).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Protocol, cast

import numpy as np
from filterpy.kalman import IMMEstimator, KalmanFilter

from .models import (
    TURN_DIM,
    plane_matrices,
    position_matrix,
    straight_transition_5d,
    turn_jacobian,
    turn_positions,
    turn_positions_jacobian,
    turn_process_noise,
    turn_transition,
)

ModelName = Literal["cv", "ct", "ca", "imm"]
MIX_FLOOR = 1e-3  # mode weights below this are dropped from the IMM's mixing and from its predictions
MODELS = ("cv", "ct", "ca", "imm")
# the CT prediction integrates the curvature exactly (MarkerTracker._curvature_profile) where |κ| < this many σ of it
PROFILE_SIGMAS = 4.0
# the GLR corner test: −2 log of the prior odds against a corner in the recent window (MarkerTracker._glr_detects);
# the same odds weigh a suspected, not yet detected corner into the predictions (MarkerTracker._corner_suspicion)
GLR_THRESHOLD = 25.0
# after a restart at a corner, the manoeuvre mode's share: at 0.02 its mixing leaked into the new leg's
# quiet modes for ~1 s (5-s covariance up to 1.2x the CRB at 100 mm/s, docs/notes/planning.md, sixth round)
RESTART_MANEUVER_PROB = 1e-3
#: a stopping corner's slow-down starts are tried on this many points of each frame interval
SUBFRAME_STEPS = 4
_GH_X, _GH_W = np.polynomial.hermite_e.hermegauss(9)  # probabilists' Gauss-Hermite nodes in σ, weights (sum √2π)


def position_from_frames(times, xy, t: float, half_window_s: float = 0.1) -> np.ndarray | None:
    """Where the tracked point was at ``t`` (s): the least-squares line through the measured positions ``xy``
    (N, 2, mm, table plane) at ``times`` (N, s) within ``half_window_s`` of ``t``, evaluated at ``t``; None with
    fewer than 3 there. A local fit, not the track's model: it does not cut the corners the path has turned
    between ``t`` and the newest frame (±0.1 s at 30 frames/s: 7 frames, 0.7 mm noise → ~0.3 mm)."""
    times = np.asarray(times, dtype=float)
    near = np.abs(times - t) <= half_window_s
    if np.count_nonzero(near) < 3:
        return None
    dt = times[near] - t
    A = np.column_stack([np.ones_like(dt), dt])
    coef, *_ = np.linalg.lstsq(A, np.asarray(xy, dtype=float)[near], rcond=None)
    return coef[0]


class TrackingError(ValueError):
    """Bad input to the tracker (non-finite measurement, prediction into the past, no track yet).

    A ``ValueError`` (the tracking layer imports nothing else from labctl); callers at the edges
    turn it into a ``UserInputError`` or ``LabctlError`` as fits.
    """


def _turn_offsets(v: np.ndarray, w: float, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Displacements (N, 2) and velocities (N, 2) after times ``d`` of a turn at rate ``w`` from velocity ``v``."""
    wt = w * d
    c, s = np.cos(wt), np.sin(wt)
    if abs(w) < 1e-9:
        so, co = d, 0.5 * w * d * d
    else:
        so, co = s / w, (1.0 - c) / w
    disp = np.column_stack([so * v[0] - co * v[1], co * v[0] + so * v[1]])
    vel = np.column_stack([c * v[0] - s * v[1], s * v[0] + c * v[1]])
    return disp, vel


def _stop_profiles(tau, r1, r2) -> tuple[np.ndarray, ...]:
    """The distance profiles of a corner the table stops at (GRBL's planner at a sharp junction).

    ``tau`` (s) since the old leg began to slow down; ``r1``, ``r2`` (s): the old leg's ramp down and the new
    leg's ramp up (speed / the table's acceleration). Returns ``(D1, D1', D2, D2')``: the old leg's distance
    over its speed ``τ − τ²/2r1`` (``r1/2`` once stopped) and the new leg's ``σ²/2r2`` then ``σ − r2/2`` with
    ``σ = τ − r1`` (0 before), and their rates. ``r1 = r2 = 0`` is the instant corner: ``D1 = 0``, ``D2 = τ``.
    """
    tau, r1, r2 = np.broadcast_arrays(*(np.asarray(a, float) for a in (tau, r1, r2)))
    tau = np.maximum(tau, 0.0)  # before the slow-down nothing has happened yet
    sig = tau - r1
    with np.errstate(divide="ignore", invalid="ignore"):
        down = np.where(tau < r1, tau - tau * tau / (2 * r1), 0.5 * r1)
        down_rate = np.where(tau < r1, 1.0 - tau / r1, 0.0)
        up = np.where(sig <= 0, 0.0, np.where(sig < r2, sig * sig / (2 * r2), sig - 0.5 * r2))
        up_rate = np.where(sig <= 0, 0.0, np.where(sig < r2, sig / r2, 1.0))
    return down, down_rate, up, up_rate


class TrackingSettings(Protocol):
    """What the tracker reads of its config (:class:`labctl.config.lab.TrackingConfig`, the one source of these
    settings' defaults; tracking imports nothing of labctl, so it names the fields it reads)."""

    @property
    def model(self) -> str:
        """``cv``, ``ct``, ``ca`` or ``imm``."""
        ...

    @property
    def process_noise(self) -> float:
        """Square root of the quiet modes' white-acceleration density (mm/s^1.5)."""
        ...

    @property
    def measurement_noise_mm(self) -> float:
        """The centroid's standard deviation per axis on the table plane (mm)."""
        ...

    @property
    def gate_sigma(self) -> float:
        """Mahalanobis distance beyond which a measurement is rejected."""
        ...

    def curve_prior_for(self, family: str | None) -> float:
        """The IMM's prior probability of a curve for motion of ``family`` (None: family-blind)."""
        ...


@dataclass(frozen=True)
class PredictedPath:
    """The mean predicted marker path, a snapshot that no longer depends on the tracker.

    With ``turn_rate`` ω = 0: ``p(t) = position + velocity·Δ + acceleration·Δ²/2`` (Δ = t − t_ref;
    table-plane mm, s) — the CV/CA mean extrapolation. With ω ≠ 0 (and no acceleration) the
    path is the coordinated turn: the velocity rotates at ω and the position follows the arc,
    so G(t) is the true curve, not its tangent (paper §4.3). Velocities and accelerations are
    analytic, as the interception planner needs.
    """

    t_ref: float
    position: np.ndarray
    velocity: np.ndarray
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(2))
    turn_rate: float = 0.0

    def __call__(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and accelerations, each (N, 2), at ``times`` (s)."""
        d = np.atleast_1d(np.asarray(times, dtype=float)) - self.t_ref
        if self.turn_rate == 0.0:
            dd = d[:, None]
            p = self.position + self.velocity * dd + 0.5 * self.acceleration * dd * dd
            v = self.velocity + self.acceleration * dd
            a = np.broadcast_to(self.acceleration, p.shape).copy()
            return p, v, a
        disp, v = _turn_offsets(np.asarray(self.velocity, float), float(self.turn_rate), d)
        a = self.turn_rate * np.column_stack([-v[:, 1], v[:, 0]])
        return self.position + disp, v, a


@dataclass(frozen=True)
class StopLegPath:
    """A new leg after a corner the table stops at (:func:`_stop_profiles`): from ``t0`` (s) the old leg's
    velocity ``v1`` slows to rest in ``r1`` s, then ``v2`` is reached in ``r2`` s; ``corner`` (mm) is where
    the slow-down starts."""

    t0: float
    r1: float
    r2: float
    corner: np.ndarray
    v1: np.ndarray
    v2: np.ndarray

    def __call__(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Positions, velocities and accelerations, each (N, 2), at ``times`` (s)."""
        tau = np.atleast_1d(np.asarray(times, float)) - self.t0
        down, down_rate, up, up_rate = _stop_profiles(tau, self.r1, self.r2)
        sig = tau - self.r1
        slowing = np.where((tau >= 0) & (tau < self.r1), -1.0 / max(self.r1, 1e-12), 0.0)
        speeding = np.where((sig > 0) & (sig < self.r2), 1.0 / max(self.r2, 1e-12), 0.0)
        pos = self.corner + np.outer(down, self.v1) + np.outer(up, self.v2)
        vel = np.outer(down_rate, self.v1) + np.outer(up_rate, self.v2)
        return pos, vel, np.outer(slowing, self.v1) + np.outer(speeding, self.v2)


@dataclass(frozen=True)
class MixturePath:
    """The IMM's mean path: ``Σ wᵢ pathᵢ(t)`` with the mode probabilities frozen at ``t_ref``.

    A detected corner's candidate new legs join the modes' paths (:meth:`MarkerTracker._corner_legs`;
    its ML leg with weight −1: the modes already follow it).
    """

    t_ref: float
    weights: tuple[float, ...]
    paths: tuple[PredictedPath, ...]

    def __call__(self, times) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Mixture-weighted positions, velocities and accelerations, each (N, 2), at ``times`` (s)."""
        out = [np.zeros((len(np.atleast_1d(times)), 2)) for _ in range(3)]
        for w, path in zip(self.weights, self.paths):
            for acc, part in zip(out, path(times)):
                acc += w * part
        return out[0], out[1], out[2]


class _KalmanFilter2D(KalmanFilter):
    """filterpy's filter with a closed-form Gaussian log-likelihood of the 2-D innovation.

    filterpy evaluates it through scipy.stats (about 0.15 ms a call); the IMM needs it on every
    update of every model. Same value: ``-½ (yᵀ S⁻¹ y + log det(2π S))``.
    """

    _log_likelihood: float | None  # set by filterpy's update() (None until computed)
    x: np.ndarray
    P: np.ndarray
    y: np.ndarray
    S: np.ndarray

    @property
    def log_likelihood(self) -> float:
        if self._log_likelihood is None:
            y = self.y.reshape(-1)
            S = self.S
            det = S[0, 0] * S[1, 1] - S[0, 1] * S[1, 0]
            m2 = (S[1, 1] * y[0] ** 2 - (S[0, 1] + S[1, 0]) * y[0] * y[1] + S[0, 0] * y[1] ** 2) / det
            self._log_likelihood = float(-0.5 * (m2 + np.log((2 * np.pi) ** 2 * det)))
        return self._log_likelihood


class _TurnFilter(_KalmanFilter2D):
    """EKF of the coordinated turn: nonlinear mean propagation, Jacobian covariance, linear (x, y) update.

    ``dt`` is set before each ``predict`` (filterpy's IMM calls ``predict()`` without arguments).
    """

    dt = 0.0

    def predict(self, u=None, B=None, F=None, Q=None):
        J = turn_jacobian(self.x, self.dt)
        self.x = turn_transition(self.x, self.dt).reshape(-1, 1)
        self.P = J @ self.P @ J.T + (self.Q if Q is None else Q)
        self.x_prior = self.x.copy()
        self.P_prior = self.P.copy()


class _LogIMM(IMMEstimator):
    """filterpy's IMM with the mode probabilities updated from log-likelihoods.

    filterpy multiplies raw likelihoods, which underflow to its floor for every mode at once
    when a fast corner makes all innovations large; then the probabilities go flat.
    """

    omega: np.ndarray  # filterpy's mixing weights ω[i, j] (set in its _compute_mixing_probabilities)

    def update(self, z):
        logl = np.empty(self.N)
        for i, f in enumerate(self.filters):
            f.update(z)
            logl[i] = f.log_likelihood
        w = np.log(np.maximum(self.cbar, 1e-300)) + logl
        w = np.exp(w - w.max())
        self.mu = w / w.sum()
        self.likelihood = np.exp(logl - logl.max())
        self._compute_mixing_probabilities()
        self._compute_state_estimate()
        self.x_post = self.x.copy()
        self.P_post = self.P.copy()

    def _compute_mixing_probabilities(self):
        """filterpy's mixing weights, with those below :data:`MIX_FLOOR` dropped (each column renormalised).

        A mode holding 1e-6 of the probability still mixed its covariance into the others: the
        manoeuvre mode's (white acceleration ∝ speed, ~3000 (mm/s)² of velocity variance per frame
        at 100 mm/s) doubled the CV mode's velocity variance on a fast line, whose 5-s NEES fell
        to 0.7 (bounds 1.54–2.52 for 64 runs).
        """
        super()._compute_mixing_probabilities()
        om = np.where(self.omega < MIX_FLOOR, 0.0, self.omega)
        self.omega = om / om.sum(axis=0, keepdims=True)


@dataclass(frozen=True)
class _Mode:
    kind: str  # "cv" | "ct" | "man" (manoeuvre) | "ca"
    q: float  # white-acceleration (or jerk, for ca) spectral density
    q_turn: float = 0.0  # curvature random-walk density (mm⁻²/s)


def _cubature(x: np.ndarray, P: np.ndarray, fn) -> tuple[np.ndarray, np.ndarray]:
    """Mean ``fn(x)`` and the cubature-rule covariance of ``fn`` over N(x, P) around it."""
    n = len(x)
    try:
        L = np.linalg.cholesky(0.5 * (P + P.T))
    except np.linalg.LinAlgError:
        w, V = np.linalg.eigh(0.5 * (P + P.T))
        L = V * np.sqrt(np.clip(w, 0.0, None))
    S = np.sqrt(n) * L
    m = fn(x)
    pts = np.array([fn(x + S[:, k]) for k in range(n)] + [fn(x - S[:, k]) for k in range(n)])
    d = pts - m
    return m, d.T @ d / (2 * n)


class MarkerTracker:
    """Track one marker centroid on the table plane and predict it at any future time.

    Built from the lab's tracking config ``cfg`` (``MarkerTracker(cfg, family=…)``; its model, noises, gate and
    curve prior have their defaults only there); a keyword overrides one of them, and the tracker's own
    settings below, which no lab tunes, have their defaults here.

    ``model``: ``"cv"``, ``"ct"``, ``"imm"`` or ``"ca"`` (see the module doc). ``process_noise``
    is the square root of the white-acceleration density (mm/s^1.5) of the quiet CV and CT
    modes; ``curvature_noise`` that of the CT curvature's random walk (mm⁻¹/s^0.5);
    ``maneuver_noise`` that of the IMM's manoeuvre mode *per mm/s of speed* (a corner turns the
    velocity, so its size scales with the speed); ``jerk_noise`` that of the standalone CA model
    (mm/s^2.5). ``imm_switch_prob`` is the per-update probability of leaving a quiet mode (half
    to each other mode); the manoeuvre mode is left with ``maneuver_exit_prob``, to CT with the
    prior probability ``curve_prior`` (also the initial probability of a curve; the lab's value is
    chosen by measurement, docs/notes/planning.md). ``init_curvature_sigma`` is the
    curvature prior (the table's tightest radius). ``corner_window_s``: the frames the corner
    detection tests (see :meth:`_after_imm_update`); ``corner_refine_s``: how long after a detection
    the corner's time is still re-estimated; ``refit_window_s``: frames the CT mode's
    re-linearised fit uses (see :meth:`_turn_refit`).
    ``measurement_noise_mm`` is the centroid's standard deviation per axis on the table plane.
    A measurement whose Mahalanobis distance from the prediction exceeds ``gate_sigma`` is
    rejected; after ``max_misses`` consecutive rejections the track is restarted on the newest
    measurement (the marker really moved differently). Paper §4.2.
    """

    def __init__(
        self,
        cfg: TrackingSettings,
        *,
        family: str | None = None,
        model: str | None = None,
        process_noise: float | None = None,
        measurement_noise_mm: float | None = None,
        gate_sigma: float | None = None,
        curve_prior: float | None = None,
        curvature_noise: float = 1e-5,
        maneuver_noise: float = 3.0,
        jerk_noise: float = 2.0,
        imm_switch_prob: float = 1e-6,
        maneuver_exit_prob: float = 0.3,
        init_speed_sigma: float = 150.0,
        init_curvature_sigma: float = 1 / 80,
        init_accel_sigma: float = 50.0,
        max_misses: int = 10,
        corner_window_s: float = 0.6,
        corner_refine_s: float = 2.0,
        refit_window_s: float = 10.0,
        stop_accel_mm_s2: float | None = None,
    ) -> None:
        # the lab's settings come from its config (lab.yaml ``tracking:``), the only place they have defaults;
        # a keyword given here overrides one (tests, benches)
        model = cfg.model if model is None else model
        process_noise = cfg.process_noise if process_noise is None else process_noise
        measurement_noise_mm = cfg.measurement_noise_mm if measurement_noise_mm is None else measurement_noise_mm
        gate_sigma = cfg.gate_sigma if gate_sigma is None else gate_sigma
        curve_prior = cfg.curve_prior_for(family) if curve_prior is None else curve_prior
        if model not in MODELS:
            raise TrackingError(f"unknown tracking model {model!r} (expected {', '.join(MODELS)})")
        for name, value in (
            ("process_noise", process_noise),
            ("measurement_noise_mm", measurement_noise_mm),
            ("gate_sigma", gate_sigma),
            ("curvature_noise", curvature_noise),
            ("maneuver_noise", maneuver_noise),
            ("jerk_noise", jerk_noise),
            ("init_speed_sigma", init_speed_sigma),
            ("init_curvature_sigma", init_curvature_sigma),
            ("init_accel_sigma", init_accel_sigma),
            ("refit_window_s", refit_window_s),
            ("corner_window_s", corner_window_s),
            ("corner_refine_s", corner_refine_s),
        ):
            if not np.isfinite(value) or value <= 0:
                raise TrackingError(f"{name} must be a positive number, got {value!r}")
        for name, value in (("imm_switch_prob", imm_switch_prob), ("maneuver_exit_prob", maneuver_exit_prob),
                            ("curve_prior", curve_prior)):
            if not 0.0 < value < 1.0:
                raise TrackingError(f"{name} must be in (0, 1), got {value!r}")
        self.model = cast(ModelName, model)  # checked against MODELS above
        self.gate_sigma = float(gate_sigma)
        self.max_misses = int(max_misses)
        self._corner_window = float(corner_window_s)
        self._corner_refine = float(corner_refine_s)
        self._refit_window = float(refit_window_s)
        self._q = float(process_noise) ** 2
        self._q_turn = float(curvature_noise) ** 2
        self._man_rel = float(maneuver_noise)
        self._man_min_speed = 2.0  # mm/s
        self._q_man_now = 0.0
        self._q_ca = float(jerk_noise) ** 2
        self._R = np.eye(2) * float(measurement_noise_mm) ** 2
        self._init_sigmas = (float(init_speed_sigma), float(init_curvature_sigma), float(init_accel_sigma))
        self._switch = float(imm_switch_prob)
        self._exit = float(maneuver_exit_prob)
        self._curve_prior = float(curve_prior)
        if stop_accel_mm_s2 is not None and not (np.isfinite(stop_accel_mm_s2) and stop_accel_mm_s2 > 0):
            raise TrackingError(f"stop_accel_mm_s2 must be a positive number or None, got {stop_accel_mm_s2!r}")
        self._stop_accel = None if stop_accel_mm_s2 is None else float(stop_accel_mm_s2)
        self.reset()

    @property
    def curve_prior(self) -> float:
        """The IMM's prior probability of a curve (its CT mode) against a line, as built."""
        return self._curve_prior

    @property
    def curvature_prior_sigma(self) -> float:
        """Standard deviation (mm⁻¹) of the CT mode's prior on the curvature, as built."""
        return self._init_sigmas[1]

    @property
    def speed_prior_sigma(self) -> float:
        """Standard deviation (mm/s) per axis of the track's prior on the velocity, N(0, σ² I), as built.

        Isotropic, so its heading is uniform; diffuse against the table's speeds, so the frames overrule it."""
        return self._init_sigmas[0]

    @classmethod
    def from_config(cls, cfg: TrackingSettings, family: str | None = None, **overrides) -> MarkerTracker:
        """Build from a :class:`labctl.config.lab.TrackingConfig` (model, noises, gate, curve prior): the same as
        ``MarkerTracker(cfg, family=family, **overrides)``.

        ``family``: the trajectory family of the program labctl drives the table along (``line``,
        ``arc``, ``circle``, ``zigzag``; paper §5.1), which sets the IMM's curve prior from
        ``tracking.family_prior``; None, ``external`` or an unknown name (motion labctl does not
        drive, a G-code file) keeps the family-blind ``tracking.curve_prior``.
        """
        return cls(cfg, family=family, **overrides)

    # -- state -------------------------------------------------------------------------------

    def reset(self) -> None:
        """Forget the track; the next measurement starts a new one."""
        self._t: float | None = None
        self._updates = 0
        self._misses = 0
        self.last_mahalanobis: float | None = None
        quiet_cv = _Mode("cv", self._q)
        quiet_ct = _Mode("ct", self._q, self._q_turn)
        self._modes = {
            "cv": [quiet_cv],
            "ct": [quiet_ct],
            "ca": [_Mode("ca", self._q_ca)],
            "imm": [quiet_cv, quiet_ct, _Mode("man", 0.0)],
        }[self.model]
        if self.model == "ca":
            self._pos, self._vel = [0, 3], [1, 4]
            self._H = position_matrix(3)
            dim = 6
        else:
            self._pos, self._vel = [0, 2], [1, 3]
            self._H = np.array([[1.0, 0, 0, 0, 0], [0, 0, 1.0, 0, 0]])
            dim = TURN_DIM
        self._kfs = []
        for mode in self._modes:
            kf = (_TurnFilter if mode.kind == "ct" else _KalmanFilter2D)(dim_x=dim, dim_z=2)
            kf.H = self._H.copy()
            kf.R = self._R.copy()
            self._kfs.append(kf)
        self._imm: _LogIMM | None = None
        self._history: list = []  # IMM only: (t, z, quiet x, P, cumulative NIS, μ) per frame
        self._nis = 0.0
        self._in_corner = False
        # the corner hypotheses the predictions weigh in: a detected corner's times, or corners not (yet) detected
        self._hypotheses: dict | None = None
        self._suspicion_pending = False  # the undetected corners are due: computed on the next prediction
        self._corner: dict | None = None  # a detected corner whose time is still being refined
        self._zbuf: list[tuple[float, np.ndarray]] = []  # IMM only: (t, z) of the recent frames
        # CT refit (see _turn_refit): frames (t, z) since the quiet modes' start, an optional anchor
        # (t, position, whitening 2x2) and the curvature prior (mean, variance); cache keyed by _rev
        self._frames: list[tuple[float, np.ndarray]] = []
        self._anchor: tuple[float, np.ndarray, np.ndarray] | None = None
        self._curv_prior = (0.0, self._init_sigmas[1] ** 2)
        self._rev = 0
        self._segment = 0  # counts (re)starts of the quiet modes: a warm start never crosses one
        self._refit_warm: tuple[int, float, np.ndarray] | None = None
        self._refit_cache: tuple[int, list[tuple[np.ndarray, np.ndarray]]] | None = None
        self._ct_nodes: tuple[int, list | None] | None = None
        self.corners: list[float] = []  # estimated corner times (s) the IMM restarted its quiet modes at

    @property
    def initialized(self) -> bool:
        """True once a measurement has started the track."""
        return self._t is not None

    @property
    def time(self) -> float | None:
        """Time (s) of the last accepted measurement."""
        return self._t

    @property
    def mode_names(self) -> tuple[str, ...]:
        """Names of the modes, in the order of :attr:`mode_probabilities` (``man``: manoeuvre)."""
        return tuple(m.kind for m in self._modes)

    @property
    def mode_probabilities(self) -> np.ndarray:
        """IMM mode probabilities in :attr:`mode_names` order (``[P(CV), P(CT), P(man)]``); ``[1.]`` for one model."""
        return np.array([1.0]) if self._imm is None else self._imm.mu.copy()

    def _start(self, t: float, z: np.ndarray) -> None:
        speed_sigma, curvature_sigma, accel_sigma = self._init_sigmas
        dim = self._kfs[0].dim_x
        x = np.zeros((dim, 1))
        x[self._pos, 0] = z
        P = np.zeros((dim, dim))
        P[self._pos, self._pos] = self._R[0, 0]
        P[self._vel, self._vel] = speed_sigma**2
        if self.model == "ca":
            P[[2, 5], [2, 5]] = accel_sigma**2
        else:
            P[4, 4] = curvature_sigma**2
        for kf in self._kfs:
            kf.x = x.copy()
            kf.P = P.copy()
        if self.model == "imm":
            s, e = self._switch, self._exit
            c = self._curve_prior  # the prior odds of a curve, also after a manoeuvre
            M = np.array([[1 - s, s / 2, s / 2], [s / 2, 1 - s, s / 2], [e * (1 - c), e * c, 1 - e]])
            self._imm = _LogIMM(self._kfs, np.array([(1 - c) * 0.99, c * 0.99, 0.01]), M)
        self._t = self._t_start = t
        self._updates = 1
        self._misses = 0
        self._frames = [(t, z.copy())]
        self._anchor = None
        self._curv_prior = (0.0, curvature_sigma**2)
        self._rev += 1
        self._segment += 1

    def _matrices(self, mode: _Mode, dt: float, *, extrapolate: bool = False):
        """``(F, Q)`` of ``mode`` over ``dt`` (F is None for the CT mode: its mean is nonlinear)."""
        if mode.kind == "ca":
            return plane_matrices(2, dt, mode.q)
        if mode.kind == "ct":
            return None, turn_process_noise(dt, mode.q, mode.q_turn)
        q = mode.q
        if mode.kind == "man":
            q = self._q if extrapolate else self._q_man_now
        return straight_transition_5d(dt), turn_process_noise(dt, q, self._q_turn)

    def _set_dt(self, dt: float) -> None:
        if self._imm is not None:  # the manoeuvre mode's noise scales with the speed: a corner turns the velocity
            speed = float(np.hypot(self._imm.x[1, 0], self._imm.x[3, 0]))
            self._q_man_now = (self._man_rel * max(speed, self._man_min_speed)) ** 2
        for kf, mode in zip(self._kfs, self._modes):
            F, kf.Q = self._matrices(mode, dt)
            if F is None:
                kf.dt = dt
            else:
                kf.F = F

    def _snapshot(self) -> list[tuple[np.ndarray, ...]]:
        """Each mode's (x, P), then for the IMM its (μ, c̄, ω, x, P): what :meth:`_restore` puts back."""
        snap: list[tuple[np.ndarray, ...]] = [(kf.x.copy(), kf.P.copy()) for kf in self._kfs]
        if self._imm is not None:
            imm = self._imm
            snap.append((imm.mu.copy(), imm.cbar.copy(), imm.omega.copy(), imm.x.copy(), imm.P.copy()))
        return snap

    def _restore(self, snap: list[tuple[np.ndarray, ...]]) -> None:
        for kf, (x, P) in zip(self._kfs, snap):
            kf.x, kf.P = x, P
        if self._imm is not None:
            imm = self._imm
            imm.mu, imm.cbar, imm.omega, imm.x, imm.P = snap[-1]

    # -- filtering -----------------------------------------------------------------------------

    def update(self, t: float, z_xy) -> bool:
        """Fuse the centroid ``z_xy`` (table-plane mm) measured at time ``t`` (s).

        Returns False when the measurement is gated out (its Mahalanobis distance from the
        one-step-ahead prediction of every mode exceeds ``gate_sigma``) or is not newer than the last one;
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
        else:
            self._kfs[0].predict()
        zc = z.reshape(2, 1)  # filterpy wants column vectors
        # gate on the mode that explains z best: a corner is the manoeuvre mode's to take, not an outlier
        d2 = np.inf
        for kf in self._kfs:
            y = zc - self._H @ kf.x
            S = self._H @ kf.P @ self._H.T + self._R
            d2 = min(d2, float((y.T @ np.linalg.solve(S, y))[0, 0]))
        self.last_mahalanobis = float(np.sqrt(max(d2, 0.0)))
        if self._updates >= 3 and d2 > self.gate_sigma**2:
            self._restore(snap)
            self._misses += 1
            if self._misses >= self.max_misses:
                self.reset()
                self._start(t, z)
                return True
            return False
        self._frames.append((t, z.copy()))
        while t - self._frames[0][0] > self._refit_window:
            self._frames.pop(0)
        self._rev += 1
        if self._imm is not None:
            self._imm.update(zc)
            self._after_imm_update(t, z)
        else:
            self._kfs[0].update(zc)
        self._t = t
        self._updates += 1
        self._misses = 0
        return True

    # -- corners: the IMM's manoeuvre detection, then a restart of the quiet modes at the corner -----------

    def _after_imm_update(self, t: float, z: np.ndarray) -> None:
        """Keep the recent history; on a corner, restart the quiet modes there and keep refining its time.

        The IMM's mixing lets the manoeuvre mode's short-memory velocity leak into the quiet modes
        for as long as it holds probability, so after a corner they would learn the new leg slowly.
        Instead, once ``P(man) > ½`` (a few frames after the corner) or a GLR test on the last
        ``corner_window_s`` of frames fires (Willsky & Jones 1976), the corner frame is estimated by
        maximum likelihood (:meth:`_best_corner`: the old track's innovations before it, a straight
        new leg from the old track's position after it) and the quiet modes are re-run from there
        with a diffuse velocity, so the new leg is the least-squares fit of every frame since the
        corner, anchored at the corner. For ``corner_refine_s`` after the detection the corner time
        is re-estimated on every frame from the *frozen* old-track history and every frame since
        (the new leg's frames sharpen it), and the quiet modes re-run whenever it moves. The
        detection history restarts with the new leg: the old track's large post-corner innovations
        must not look like a second corner. Every prediction weighs in the candidate corner times, and
        between detections the corners not yet detected (:meth:`_with_corner_hypotheses`).
        """
        imm = self._imm_filter()
        quiet = self._kfs[int(np.argmax(imm.mu[:2]))]  # the old track: the likelier of CV and CT
        Sinv = np.linalg.inv(quiet.S)
        self._nis += float(quiet.y[:, 0] @ Sinv @ quiet.y[:, 0]) + float(np.log(np.linalg.det(quiet.S)))
        self._history.append((t, z.copy(), quiet.x.copy(), quiet.P.copy(), self._nis, imm.mu.copy()))
        while self._history and t - self._history[0][0] > 2 * self._corner_window:
            self._history.pop(0)
        self._zbuf.append((t, z.copy()))
        while t - self._zbuf[0][0] > 2 * self._corner_window + self._corner_refine + 0.5:
            self._zbuf.pop(0)
        if t - self._t_start < 2 * self._corner_window:
            return  # the track's first frames: the quiet modes are still converging, not turning a corner
        if self._corner is not None:
            if t - self._corner["t_detect"] > self._corner_refine:
                self._corner = None  # the corner's time is settled
            else:
                self._refine_corner()
        if self._corner is not None and self._stop_accel is not None and t < self._up_to_speed():
            return  # the stop's ramps are the refined corner's frames, not a new corner
        recent = [h for h in self._history if t - h[0] <= self._corner_window]
        if self._corner is None:  # the corners not (yet) detected: only a prediction needs them (~0.5 ms)
            self._hypotheses, self._suspicion_pending = None, True
        if imm.mu[2] < 0.5 and not self._glr_detects(recent):
            self._in_corner = False
            return
        if self._in_corner or len(recent) < 4:
            return
        self._in_corner = True
        # the old track's history up to the detection, frozen: the corner lies in it
        self._corner = {"t_detect": t, "entries": list(self._history), "j": None}
        self._refine_corner()

    def _glr_detects(self, hist: list, threshold: float = GLR_THRESHOLD) -> bool:
        """A slow corner the manoeuvre mode misses: the GLR statistic (no corner vs the best corner) > threshold."""
        if len(hist) < 8 or hist[-1][4] - hist[-6][4] < 5 * (2.0 + np.log(self._R[0, 0] ** 2)):
            return False  # the old track still explains the last frames (expected NIS 2 per frame)
        cost, _ = self._best_corner(hist, [(h[0], h[1]) for h in hist])
        return hist[-1][4] - cost > threshold

    def _corner_hypotheses(self) -> dict | None:
        """The hypotheses the predictions weigh in: a detected corner's times, else the undetected corners."""
        if self._suspicion_pending:
            self._hypotheses, self._suspicion_pending = self._corner_suspicion(), False
        return self._hypotheses

    def _corner_suspicion(self) -> dict | None:
        """The corners the GLR has not (yet) detected, as hypotheses the predictions weigh in; None if none count.

        The detection is a hard decision at ``GLR_THRESHOLD`` = −2 log of the prior odds against a corner:
        a corner at candidate j has the posterior odds ``exp((G_j − GLR_THRESHOLD)/2)`` against none, with
        ``G_j`` the GLR statistic of :meth:`_corner_costs` over the detection history (up to 2 ×
        ``corner_window_s``). Each candidate whose new leg has at least ``corner_window_s``/2 of frames (a
        shorter one predicts nothing yet: its velocity is the noise of a few frames) is kept with its new
        leg's least-squares state and covariance; :meth:`_with_corner_hypotheses` adds their second moments
        about the track's mean. At 4 mm/s a 97° corner is ~2 mm off the old line 0.5 s after it and in 1-3 runs of
        64 not yet detected: those runs' 5-s NEES was 1500-1700 (docs/notes/planning.md, sixth round).
        """
        hist = self._history
        if len(hist) < 8:
            return None
        js, costs, v2s, dps, A, ramps = self._corner_costs(hist, [(h[0], h[1]) for h in hist])
        te = np.array([h[0] for h in hist])
        keep = te[-1] - te[js] >= 0.5 * self._corner_window
        log_odds = 0.5 * (hist[-1][4] - costs[keep] - GLR_THRESHOLD)
        if not len(log_odds) or log_odds.max() < -7.0:
            return None  # every hypothesis below e⁻⁷ ≈ 1e-3 of the track: not worth a prediction's time
        odds = np.exp(np.minimum(log_odds, 700.0))  # a corner the detection has not taken yet can be that certain
        js = js[keep]
        corner = np.array([hist[j - 1][2][self._pos, 0] for j in js]) + dps[keep]
        return {"w": odds / (1.0 + odds.sum()), "corner": corner, "v2": v2s[keep], "cov": np.linalg.inv(A[keep]),
                **self._ramp_fields(ramps, keep)}

    @staticmethod
    def _ramp_fields(ramps, keep=slice(None)) -> dict:
        t0, r1, r2, v1 = ramps
        return {"t0": t0[keep], "r1": r1[keep], "r2": r2[keep], "v1": v1[keep]}

    @staticmethod
    def _legs_at(hyp: dict, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Each hypothesis's new leg at ``t``: positions (n, 2), velocities (n, 2), and the rates of the position
        and the velocity in ``v2`` (the Jacobian's blocks; ``corner`` enters with the identity)."""
        down, down_rate, up, up_rate = _stop_profiles(t - hyp["t0"], hyp["r1"], hyp["r2"])
        pos = hyp["corner"] + hyp["v1"] * down[:, None] + hyp["v2"] * up[:, None]
        vel = hyp["v1"] * down_rate[:, None] + hyp["v2"] * up_rate[:, None]
        return pos, vel, np.stack([up, up_rate], axis=1)

    def _corner_legs(self) -> tuple[np.ndarray, list] | None:
        """A detected corner's candidate times as paths to add to the track's: (weights, straight new legs).

        The quiet modes follow its ML candidate time (:meth:`_refine_corner`), so the posterior mean over
        the candidates is the track + Σ wⱼ legⱼ − leg_ML: the legs ``corner + v2·(t − t0)`` with their
        weights and the ML leg with −1. None without a detected corner (a suspected one moves no mean:
        with the GLR's odds as weights the zigzag's straight legs at 4 mm/s were 6 % worse, 64 runs).
        """
        hyp = self._corner_hypotheses()
        if hyp is None or hyp["cov"] is not None:
            return None
        if "ref" not in hyp:
            legs = [PredictedPath(float(t0), c, v) for t0, c, v in zip(hyp["t0"], hyp["corner"], hyp["v2"])]
            return np.r_[hyp["w"], -1.0], legs + [legs[hyp["ml"]]]
        # after a stop the modes hold the most likely leg's state at the last frame, maybe still on its ramps:
        # that state's constant velocity is what they add, the legs with their ramps what is meant
        t_ref, p_ref, v_ref = hyp["ref"]
        stop_legs: list = [StopLegPath(float(t0), float(r1), float(r2), c, v1, v)
                           for t0, r1, r2, c, v1, v in zip(hyp["t0"], hyp["r1"], hyp["r2"], hyp["corner"], hyp["v1"],
                                                           hyp["v2"])]
        return np.r_[hyp["w"], -1.0], stop_legs + [PredictedPath(float(t_ref), p_ref, v_ref)]

    def _with_corner_hypotheses(self, x: np.ndarray, P: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
        """``(x, P)`` at ``t`` with the corner hypotheses' new legs mixed in.

        A detected corner: the mean moves to the posterior mean over its candidate times
        (:meth:`_corner_legs`) and the covariance adds their legs' spread about it (each one's own
        uncertainty is the quiet modes'). Corners not yet detected: the track (its ``P``, weight 1 − Σw)
        and each suspected leg with its own least-squares covariance, second moments about the track's
        mean, which is kept.
        """
        hyp = self._corner_hypotheses()
        if hyp is None:
            return x, P
        idx = self._pos + self._vel  # [x, y, vx, vy]
        w = hyp["w"]
        pos, vel, rates = self._legs_at(hyp, t)
        legs = np.concatenate([pos, vel], axis=1)
        x, P = x.copy(), P.copy()
        if hyp["cov"] is None:
            if "ref" in hyp:  # after a stop: about the modes' own constant-velocity extrapolation (_corner_legs)
                t_ref, p_ref, v_ref = hyp["ref"]
                d = legs - np.r_[p_ref + v_ref * (t - t_ref), v_ref]
            else:
                d = legs - legs[hyp["ml"]]
            shift = w @ d
            x[idx, 0] += shift
            P[np.ix_(idx, idx)] += (w[:, None] * d).T @ d - np.outer(shift, shift)
            return x, P
        J = np.zeros((len(w), 4, 4))  # (corner offset, v2) -> (position, velocity) at t
        J[:, :2, :2] = np.eye(2)
        J[:, :2, 2:] = rates[:, 0, None, None] * np.eye(2)
        J[:, 2:, 2:] = rates[:, 1, None, None] * np.eye(2)
        d = legs - x[idx, 0]
        legs_cov = np.einsum("n,nij->ij", w, J @ hyp["cov"] @ J.transpose(0, 2, 1)) + (w[:, None] * d).T @ d
        P[np.ix_(idx, idx)] = (1.0 - w.sum()) * P[np.ix_(idx, idx)] + legs_cov
        return x, P

    def _best_corner(self, entries: list, frames: list) -> tuple[float, int]:
        """ML corner: (cost, j), the corner between ``entries[j-1]`` and ``entries[j]`` (:meth:`_corner_costs`)."""
        js, costs, *_ = self._corner_costs(entries, frames)
        if not len(js):
            return np.inf, 1
        k = int(np.argmin(costs))
        return float(costs[k]), int(js[k])

    def _corner_costs(self, entries: list, frames: list, between_frames: bool = False) -> tuple:
        """Each candidate corner j's cost and new leg: (js, costs, v2s (n, 2), δps (n, 2), normal matrices (n, 4, 4),
        (t0, r1, r2, v1) the leg's start and ramps, :func:`_stop_profiles`; the ramps are 0 unless the table
        stops at its corners, :meth:`_stop_corner_costs`).

        The corner lies between ``entries[j-1]`` and ``entries[j]``.

        ``entries``: the old track's (t, z, x, P, cumulative NIS, μ) per frame; ``frames``: (t, z)
        of every frame from ``entries[1]`` on (later ones too). For each j the cost is −2 log of the
        likelihood of all frames: the old track's cumulative NIS up to j−1, then a straight new leg
        ``p0 + δp + v2·τ`` through the frames since j, with ``p0`` the old track's position at j−1
        (τ from there), ``δp`` under its covariance and ``v2`` free (both by least squares).
        Bar-Shalom et al. 2001 §11.3 (a manoeuvre's onset by ML); units of the old track's NIS.
        """
        ft = np.array([f[0] for f in frames])
        fz = np.array([f[1] for f in frames]).reshape(-1, 2)
        # candidates whose new leg has ≥ 2 frames; for each, suffix sums over the frames since entries[j]
        te = np.array([e[0] for e in entries])
        start = np.searchsorted(ft, te[1:] - 1e-9)
        js = np.flatnonzero(len(ft) - start >= 2) + 1
        if not len(js):
            e = np.zeros(0)
            return js, e, np.zeros((0, 2)), np.zeros((0, 2)), np.zeros((0, 4, 4)), (e, e, e, np.zeros((0, 2)))
        start = start[js - 1]

        def suffix(a):
            return np.concatenate([np.cumsum(a[::-1], axis=0)[::-1], np.zeros((1,) + a.shape[1:])])[start]

        n = (len(ft) - start).astype(float)
        S1, S2 = suffix(ft), suffix(ft * ft)
        Sz, Stz, Szz = suffix(fz), suffix(ft[:, None] * fz), suffix(np.sum(fz * fz, axis=1))
        t0 = te[js - 1]
        p0 = np.array([entries[j - 1][2][self._pos, 0] for j in js])
        P0 = np.array([self._anchor_cov(entries, int(j), between_frames) for j in js])
        nis0 = np.array([entries[j - 1][4] for j in js])
        if self._stop_accel is not None:
            return self._stop_corner_costs(entries, js, start, ft, fz, t0, p0, P0, nis0)
        # τ = t − t0 and z' = z − p0, from the suffix sums
        st = S1 - n * t0
        stt = S2 - 2 * t0 * S1 + n * t0 * t0
        sz = Sz - n[:, None] * p0
        stz = Stz - t0[:, None] * Sz - st[:, None] * p0
        szz = Szz - 2 * np.sum(p0 * Sz, axis=1) + n * np.sum(p0 * p0, axis=1)
        A, sol, costs = self._new_leg_fit(P0, nis0, n, st, stt, sz, stz, szz)
        zero = np.zeros(len(js))
        return js, costs, sol[:, 2:], sol[:, :2], A, (t0, zero, zero, np.zeros((len(js), 2)))

    def _new_leg_fit(self, P0, nis0, n, sg, sgg, sy, sgy, syy, prior_v: float = 0.0) -> tuple[np.ndarray, ...]:
        """Each candidate's new leg ``δp + v2·g`` by least squares: (normal matrices (n, 4, 4), (δp, v2) (n, 4), costs).

        From the sums over its frames of 1 (``n``), the regressor ``g`` and ``g²``, the residual ``y`` after the
        anchor, ``g·y`` and ``|y|²``; ``δp ~ N(0, P0)``, ``v2`` with the prior precision ``prior_v`` per axis.
        The cost is the old track's NIS ``nis0`` plus the minimum of the quadratic, ``c − bᵀA⁻¹b``.
        """
        R = self._R[0, 0]
        eye = np.eye(2)
        A = np.zeros((len(n), 4, 4))
        A[:, :2, :2] = np.linalg.inv(P0) + eye * (n / R)[:, None, None]
        A[:, :2, 2:] = A[:, 2:, :2] = eye * (sg / R)[:, None, None]
        A[:, 2:, 2:] = eye * (sgg / R + prior_v)[:, None, None]
        bvec = np.concatenate([sy, sgy], axis=1) / R
        sol = np.linalg.solve(A, bvec[:, :, None])[:, :, 0]
        return A, sol, nis0 + syy / R - np.sum(bvec * sol, axis=1) + n * np.log(R * R)

    def _stop_corner_costs(self, entries, js, start, ft, fz, t0, p0, P0, nis0) -> tuple:
        """:meth:`_corner_costs` for a table that stops at its corners (``stop_accel_mm_s2``, GRBL at a sharp junction).

        From candidate j the old leg slows from its speed ``v1`` (the old track's at ``entries[j-1]``) to rest
        in ``r1 = |v1|/a`` and the new leg speeds up to ``v2`` in ``r2 = |v2|/a``: the frames since j are
        ``p0 + v1·D1(τ) + δp + v2·D2(τ)`` (:func:`_stop_profiles`), still linear in ``(δp, v2)``; ``r2`` is
        taken from ``|v1|`` first (the program's legs share one feed), then from the fit's ``v2``. The
        straight new leg from the anchor (the instant corner) put the 5-s prediction 7.3× the bound 0.5 s after
        a 50 mm/s stop (docs/notes/planning.md, seventh round). Also returns, per candidate, ``(t0, r1, r2, v1)``.
        """
        a = self._stop_accel
        v1 = np.array([entries[j - 1][2][self._vel, 0] for j in js])
        # the old leg slows down from anywhere in the frame interval after entries[j-1]: a quarter-frame grid
        # (each j four times; a start a frame late put the 5-s prediction 2× the bound 1.5 s after 50 mm/s)
        te = np.array([e[0] for e in entries])
        frac = np.tile(np.arange(SUBFRAME_STEPS) / SUBFRAME_STEPS, len(js))
        rep = np.repeat(np.arange(len(js)), SUBFRAME_STEPS)
        delay = frac * (te[js] - te[js - 1])[rep]
        js, start, P0, nis0, v1 = js[rep], start[rep], P0[rep], nis0[rep], v1[rep]
        t0 = t0[rep] + delay
        shift = v1 * delay[:, None]  # the old track's own motion up to the slow-down's start
        p0 = p0[rep] + shift
        r1 = np.hypot(v1[:, 0], v1[:, 1]) / a
        tau = ft[None, :] - t0[:, None]
        mask = (np.arange(len(ft))[None, :] >= start[:, None]).astype(float)
        n = mask.sum(axis=1)
        down = _stop_profiles(tau, r1[:, None], 0.0)[0]
        y = (fz[None, :, :] - p0[:, None, :] - v1[:, None, :] * down[:, :, None]) * mask[:, :, None]
        syy = np.einsum("cfk,cfk->c", y, y)
        sy = y.sum(axis=1)
        prior_v = 1.0 / self._init_sigmas[0] ** 2  # the new leg's diffuse speed, as a restart starts it

        def fit(r2):
            g = _stop_profiles(tau, r1[:, None], r2[:, None])[2] * mask
            sg, sgg, sgy = g.sum(axis=1), (g * g).sum(axis=1), np.einsum("cf,cfk->ck", g, y)
            return self._new_leg_fit(P0, nis0, n, sg, sgg, sy, sgy, syy, prior_v)

        first = fit(r1)[1]  # the legs share the program's feed: the old leg's speed first
        r2 = np.hypot(first[:, 2], first[:, 3]) / a
        A, sol, costs = fit(r2)
        return js, costs, sol[:, 2:], sol[:, :2] + shift, A, (t0, r1, r2, v1)

    def _anchor_cov(self, entries: list, j: int, between_frames: bool = True) -> np.ndarray:
        """The covariance (2, 2) mm² of the new leg's anchor for a corner between ``entries[j-1]`` and ``entries[j]``.

        The anchor is the old track's position at ``entries[j-1]``, but a corner lies anywhere in the frame
        interval after it: the new leg extended back to ``t_{j-1}`` misses the anchor by ``(v1 − v2)·δ``, δ
        uniform in [0, Δt]; with ``|v1 − v2| ≈ √2·|v1|`` (a right-angle turn) ``between_frames`` adds
        ``|v1|² Δt² / 6`` per axis. The bench's corners, exactly on a frame, hid it: half a frame off, the 5-s
        prediction 1 s after a 100 mm/s corner was 9.7x the bound (docs/notes/planning.md, sixth round). The
        detection's GLR keeps the tight anchor: with the looser one it fired on straight legs (a 50 mm/s zigzag
        restarted at 1.43 s, 0.57 s before its corner).
        """
        t0, _, x0, P0, *_ = entries[j - 1]
        cov = P0[np.ix_(self._pos, self._pos)]
        if not between_frames:
            return cov
        v1 = x0[self._vel, 0]
        return cov + np.eye(2) * float(v1 @ v1) * (entries[j][0] - t0) ** 2 / 6.0

    def _refine_corner(self) -> None:
        """Re-estimate the detected corner on the frames so far; re-run the quiet modes from it if it moved."""
        c = self._corner
        if c is None:
            return
        entries = c["entries"]
        frames = [f for f in self._zbuf if f[0] >= entries[1][0] - 1e-9] if len(entries) > 1 else []
        if len(entries) < 2 or len(frames) < 2:
            return
        js, costs, v2s, dps, A, ramps = self._corner_costs(entries, frames, between_frames=True)
        if not len(js):
            return
        k = int(np.argmin(costs))
        j = int(js[k])
        # the corner time's posterior over the candidates (flat prior, exp(−cost/2)) and each candidate's new leg:
        # every prediction takes their posterior mean and spread at the instant predicted
        # (:meth:`_with_corner_hypotheses`). Added instead once to the re-run filters, the spread was shrunk by later
        # frames as if it were a Gaussian prior: 12 mm/s, 0.5 s after the corner, 5-s NEES 3.06, the runs whose ML
        # corner was a frame or two off 3.2-8.3 (docs/notes/planning.md, sixth round)
        w = np.exp(-0.5 * (costs - costs[k]))
        w /= w.sum()
        p0s = np.array([entries[i - 1][2][self._pos, 0] for i in js])
        hyp = {"w": w, "corner": p0s + dps, "v2": v2s, "cov": None, "ml": k, **self._ramp_fields(ramps)}
        self._hypotheses, self._suspicion_pending = hyp, False
        if j == c["j"]:
            if self._stop_accel is not None:  # the fit through both ramps, again with this frame (set only up
                # to speed, the IMM's mixing leaked the manoeuvre mode into the leg: 50 mm/s 2 s after 1.75× the bound)
                self._set_on_leg(hyp, k, A[k], entries[j - 1], frames)
            return  # the same corner: no re-run
        t0, _, x0, P0, _, mu0 = entries[j - 1]
        ct_anchor = P0[np.ix_(self._pos, self._pos)]
        P0 = P0.copy()
        P0[np.ix_(self._pos, self._pos)] = self._anchor_cov(entries, j)
        first = c["j"] is None
        c["j"] = j
        if first:
            self.corners.append(float(t0))
        else:
            self.corners[-1] = float(t0)
        if self._stop_accel is not None:
            self._set_on_leg(hyp, k, A[k], entries[j - 1], frames)
        else:
            new_leg = [f for f in frames if f[0] >= entries[j][0] - 1e-9]
            self._restart_at(t0, x0, P0, new_leg, ct_anchor)
        imm = self._imm_filter()
        if first:  # the quiet modes take over again, in the old track's proportions
            quiet = mu0[0] + mu0[1]
            keep = 1.0 - RESTART_MANEUVER_PROB
            share = mu0[:2] / quiet if quiet > 0 else np.array([1.0, 0.0])  # no quiet mode left: the line
            imm.mu = np.array([share[0] * keep, share[1] * keep, RESTART_MANEUVER_PROB])
        imm._compute_mixing_probabilities()
        imm._compute_state_estimate()
        # the detection history starts again with the new leg (its filters were just re-run)
        self._history = []
        self._in_corner = True

    def _up_to_speed(self) -> float:
        """When the refined stop corner's most likely new leg is up to speed (s; −∞ without one)."""
        hyp = self._hypotheses
        if hyp is None or "ml" not in hyp:
            return -np.inf
        k = hyp["ml"]
        return float(hyp["t0"][k] + hyp["r1"][k] + hyp["r2"][k])

    def _set_on_leg(self, hyp: dict, k: int, cov: np.ndarray, entry: tuple, frames: list) -> None:
        """Set every mode to hypothesis ``k``'s new leg after a stop, at the last frame (:meth:`_stop_corner_costs`).

        The least-squares fit of ``(δp, v2)`` (normal matrix ``cov``'s inverse) is the leg; a Kalman re-run
        would take the ramps' frames as constant velocity. Position and velocity at the last frame with their
        covariance through the ramps' profiles, the curvature the old track's (``entry``). The CT refit takes
        the frames once up to speed, anchored where the leg's line passes through the corner.
        """
        t_last = frames[-1][0]
        pos, vel, rates = self._legs_at({key: hyp[key][k:k + 1] for key in ("t0", "r1", "r2", "corner", "v1", "v2")},
                                        t_last)
        J = np.eye(4)  # (δp, v2) -> (position, velocity)
        J[:2, 2:] = rates[0, 0] * np.eye(2)
        J[2:, 2:] = rates[0, 1] * np.eye(2)
        C = J @ np.linalg.inv(cov) @ J.T
        hyp["ref"] = (float(t_last), pos[0].copy(), vel[0].copy())
        _, _, x0, P0, *_ = entry
        pv = self._pos + self._vel
        for kf in self._kfs:
            x, P = x0.copy(), P0.copy()
            x[self._pos, 0], x[self._vel, 0] = pos[0], vel[0]
            P[pv, :] = 0.0
            P[:, pv] = 0.0
            P[np.ix_(pv, pv)] = C
            kf.x, kf.P = x, P
        t0, r1, r2 = hyp["t0"][k], hyp["r1"][k], hyp["r2"][k]
        up_to_speed = t0 + r1 + r2
        self._frames = [(th, zh.copy()) for th, zh in frames if th >= up_to_speed - 1e-9]
        through = hyp["corner"][k] + 0.5 * r1 * hyp["v1"][k]
        anchor_cov = np.linalg.inv(cov)[:2, :2]
        self._anchor = (float(t0 + r1 + 0.5 * r2), through, np.linalg.cholesky(np.linalg.inv(anchor_cov)).T)
        self._curv_prior = (float(x0[4, 0]), float(P0[4, 4]))
        self._rev += 1
        self._segment += 1

    def _restart_at(self, t0: float, x0: np.ndarray, P0: np.ndarray, new_leg: list, ct_anchor: np.ndarray) -> None:
        """Re-run every mode as a quiet mode from the old track's (x0, P0) at ``t0`` over ``new_leg`` (t, z).

        ``ct_anchor``: the covariance (2, 2) of the CT refit's anchor, the old track's own (without the frame
        interval of :meth:`_anchor_cov`: with it a false restart on a 100 mm/s circle cost that cell 1.13 → 1.76x).
        """
        speed_sigma = self._init_sigmas[0]
        # the CT refit: the new leg's frames, anchored at the old track's corner position, with its curvature
        self._frames = [(th, zh.copy()) for th, zh in new_leg]
        self._anchor = (float(t0), x0[self._pos, 0].copy(), np.linalg.cholesky(np.linalg.inv(ct_anchor)).T)
        self._curv_prior = (float(x0[4, 0]), float(P0[4, 4]))
        self._rev += 1
        self._segment += 1
        for kf, mode in zip(self._kfs, self._modes):
            x = x0.copy()
            P = P0.copy()
            P[np.ix_(self._vel, self._vel)] = 0.0
            P[np.ix_(self._pos, self._vel)] = 0.0
            P[np.ix_(self._vel, self._pos)] = 0.0
            P[self._vel, self._vel] = speed_sigma**2
            kf.x, kf.P = x, P  # the curvature is kept: the new leg is likely shaped like the old
            tp = t0
            quiet = _Mode("cv", self._q, self._q_turn) if mode.kind == "man" else mode
            for th, zh in new_leg:
                F, Q = self._matrices(quiet, th - tp)
                if F is None:
                    kf.dt, kf.Q = th - tp, Q
                    kf.predict()
                else:
                    kf.predict(F=F, Q=Q)
                kf.update(zh.reshape(2, 1))
                tp = th

    # -- estimates and predictions -------------------------------------------------------------

    def _require_track(self) -> float:
        """The time of the last update (s); TrackingError before the first one."""
        if self._t is None:
            raise TrackingError("no track yet: call update() with a measurement first")
        return self._t

    def _imm_filter(self) -> _LogIMM:
        """The IMM estimator; TrackingError when this tracker runs a single model or has no track yet."""
        if self._imm is None:
            raise TrackingError(f"the {self.model!r} tracker has no IMM estimator (model 'imm' with a track)")
        return self._imm

    def _turn_refit(self, kf) -> tuple[np.ndarray, np.ndarray]:
        """The CT mode's posterior re-linearised over the recent frames: MAP (x, P) at the last update.

        The EKF linearises the turn at each frame's prior, so the errors of its first frames (speed
        and curvature still unknown) stay in its estimate: at 50 mm/s on the lab's 80 mm circle it
        was 1.35× the Cramér-Rao bound 4 s in where the ML fit is 1.09×. Here the constant turn
        ``[x, vx, y, vy, κ]`` at the last frame is fitted by Gauss-Newton to every frame since the
        track's (or the corner's) start within ``refit_window_s`` (the CT mode's near-zero process
        noise makes them one deterministic path), with the curvature prior (and, after a corner,
        the corner position as the restart left it), started at the EKF's estimate. ``P`` is the
        inverse of the Gauss-Newton information (the Laplace approximation). Bar-Shalom et al.
        2001 §10.5.1 (iterated filtering / re-linearisation); paper §4.2's multi-step prediction
        uses it. Falls back to the EKF when there are too few frames or the fit does not converge.
        """
        x_ekf, P_ekf = kf.x[:, 0].copy(), kf.P.copy()
        frames = self._frames
        if len(frames) < 10:
            return x_ekf.reshape(-1, 1), P_ekf
        t_last = frames[-1][0]
        d = np.fromiter((f[0] for f in frames), float, len(frames)) - t_last
        zs = np.array([f[1] for f in frames])
        w_meas = 1.0 / np.sqrt(self._R[0, 0])
        anchor = self._anchor
        if anchor is not None and t_last - anchor[0] > self._refit_window:
            anchor = None
        k_mean, k_var = self._curv_prior
        k_w = 1.0 / np.sqrt(k_var)
        speed_var = self._init_sigmas[0] ** 2

        def residuals(x):
            r = [((turn_positions(x, d) - zs) * w_meas).reshape(-1)]
            if anchor is not None:
                r.append(anchor[2] @ (turn_positions(x, [anchor[0] - t_last])[0] - anchor[1]))
            r.append([(x[4] - k_mean) * k_w])
            return np.concatenate(r)

        def jacobian(x):
            J = [turn_positions_jacobian(x, d).reshape(-1, 5) * w_meas]
            if anchor is not None:
                J.append(anchor[2] @ turn_positions_jacobian(x, [anchor[0] - t_last])[0])
            J.append(np.array([[0.0, 0.0, 0.0, 0.0, k_w]]))
            return np.vstack(J)

        # start at the last refit carried forward along its turn (one or two iterations then), else at the EKF
        warm = self._refit_warm
        x = x_ekf.copy()
        if warm is not None and warm[0] == self._segment:
            x = turn_transition(warm[2], t_last - warm[1])
        r = residuals(x)
        cost = float(r @ r)
        converged = False
        for _ in range(8):
            J = jacobian(x)
            speed = max(np.hypot(x[1], x[3]), 1.0)
            A = J.T @ J
            A[[1, 3], [1, 3]] += 1.0 / speed_var  # the track's diffuse velocity prior, as the EKF started
            try:
                step = np.linalg.solve(A, J.T @ r)
            except np.linalg.LinAlgError:
                break
            for _halving in range(4):  # accept only a step that lowers the cost
                x_new = x - step
                r_new = residuals(x_new)
                cost_new = float(r_new @ r_new)
                if np.isfinite(cost_new) and cost_new <= cost:
                    break
                step = 0.5 * step
            else:
                break
            small = np.all(np.abs(step) <= 1e-5 * np.maximum(np.abs(x), [1, speed, 1, speed, 1e-3]))
            x, r, cost = x_new, r_new, cost_new
            if small:
                converged = True
                break
        if not converged or not np.all(np.isfinite(x)):
            return x_ekf.reshape(-1, 1), P_ekf
        self._refit_warm = (self._segment, t_last, x.copy())
        P = np.linalg.inv(A)
        P = 0.5 * (P + P.T)
        self._ct_nodes = None
        if abs(x[4]) < PROFILE_SIGMAS * np.sqrt(P[4, 4]):
            self._ct_nodes = (self._rev, self._curvature_profile(x, P, cost, residuals, jacobian, speed_var))
        return x.reshape(-1, 1), P

    def _curvature_profile(self, x_map, P_map, cost_map, residuals, jacobian, speed_var):
        """The CT posterior integrated exactly over the curvature: nodes ``[(w, x, P)]`` at the last update.

        Where the curvature κ is within :data:`PROFILE_SIGMAS` σ of zero (a curve the frames barely
        show), the Laplace posterior's Gaussian in κ with the other states linear in it is too
        narrow for the 5-s prediction: on the 80-mm circle at 12 mm/s after 2 s (64 runs) its mean
        NEES was 3.04, a few runs whose frames look straight at 13-37. Here κ is put on
        Gauss-Hermite nodes of the Laplace marginal; at each node the other four states
        ``[x, vx, y, vy]`` (mm, mm/s) are re-fitted by Gauss-Newton to the same frames (the
        profile), with their conditional Laplace covariance, and each node is weighted by its
        exact posterior density over the proposal (importance weights, incl. the conditional
        covariance's determinant). Predictions propagate every node; their moments about the MAP
        path are the CT mode's prediction (:meth:`_model_predictions`). Bar-Shalom et al. 2001
        §10.5 (non-linear estimation); paper §4.2's multi-step prediction. Returns None if a node
        fit fails.
        """
        sk = float(np.sqrt(P_map[4, 4]))
        gain = P_map[:4, 4] / P_map[4, 4]  # the Laplace conditional mean of the other states given κ
        idx = [0, 1, 2, 3]
        nodes, logw = [], []
        for g, w_gh in zip(_GH_X, _GH_W):
            x = x_map.copy()
            x[4] = x_map[4] + g * sk
            x[:4] += gain * (g * sk)
            for _ in range(6):
                J = jacobian(x)[:, idx]
                A = J.T @ J
                A[[1, 3], [1, 3]] += 1.0 / speed_var
                step = np.linalg.solve(A, J.T @ residuals(x))
                x[:4] -= step
                if np.all(np.abs(step) <= 1e-6 * np.maximum(np.abs(x[:4]), 1.0)):
                    break
            r = residuals(x)
            J = jacobian(x)[:, idx]
            A = J.T @ J
            A[[1, 3], [1, 3]] += 1.0 / speed_var
            sign, logdet = np.linalg.slogdet(A)
            if not (np.all(np.isfinite(x)) and sign > 0 and np.isfinite(r @ r)):
                return None
            Pn = np.zeros((5, 5))
            Pn[:4, :4] = np.linalg.inv(A)
            nodes.append((x, 0.5 * (Pn + Pn.T)))
            logw.append(-0.5 * (float(r @ r) - cost_map) - 0.5 * logdet + 0.5 * g * g + np.log(w_gh))
        lw = np.array(logw)
        w = np.exp(lw - lw.max())
        w /= w.sum()
        return [(float(wi), xn, Pn) for wi, (xn, Pn) in zip(w, nodes)]

    def _mode_states(self) -> list[tuple[np.ndarray, np.ndarray]]:
        """Each mode's posterior (x (n, 1), P) at the last update; the CT mode's re-linearised (cached per update)."""
        if self._refit_cache is not None and self._refit_cache[0] == self._rev:
            return self._refit_cache[1]
        states = []
        for kf, mode, mu in zip(self._kfs, self._modes, self._weights()):
            refit = mode.kind == "ct" and mu > 0.0  # a mode the prediction drops needs no refit
            states.append(self._turn_refit(kf) if refit else (kf.x.copy(), kf.P.copy()))
        self._refit_cache = (self._rev, states)
        return states

    def _model_predictions(self, dt: float):
        """Each mode's (x, P) extrapolated ``dt`` s past the last update, without touching the filter."""
        out = []
        for (x, Px), mode in zip(self._mode_states(), self._modes):
            if dt == 0.0:
                out.append((x.copy(), Px.copy()))
                continue
            F, Q = self._matrices(mode, dt, extrapolate=True)
            nodes = self._ct_nodes[1] if self._ct_nodes is not None and self._ct_nodes[0] == self._rev else None
            if F is None and mode.kind == "ct" and nodes:
                # the curvature profile: every node's turn, second moments about the MAP's path
                m = turn_transition(x[:, 0], dt)
                P = np.zeros((len(m), len(m)))
                for w, xn, Pn in nodes:
                    mn = turn_transition(xn, dt)
                    Fn = turn_jacobian(xn, dt)
                    P += w * (Fn @ Pn @ Fn.T + np.outer(mn - m, mn - m))
                out.append((m.reshape(-1, 1), P + Q))
            elif F is None:
                m, P = _cubature(x[:, 0], Px, lambda s: turn_transition(s, dt))
                out.append((m.reshape(-1, 1), P + Q))
            else:
                out.append((F @ x, F @ Px @ F.T + Q))
        return out

    def _weights(self) -> np.ndarray:
        """The mode probabilities the predictions use: the IMM's, with those below :data:`MIX_FLOOR` dropped.

        A mode at 1e-6 whose 5-s prediction is 500 mm off (CV on a fast circle) adds 0.25 mm² of
        spread to a 0.3 mm² covariance: the NEES fell to 0.2–0.7 where the filter had long decided.
        """
        if self._imm is None:
            return np.array([1.0])
        mu = np.where(self._imm.mu < MIX_FLOOR, 0.0, self._imm.mu)
        return mu / mu.sum()

    def _combined(self, dt: float) -> tuple[np.ndarray, np.ndarray]:
        preds = self._model_predictions(dt)
        if self._imm is None:
            return preds[0]
        mu = self._weights()
        x = sum(m * xp for m, (xp, _) in zip(mu, preds))
        P = sum(m * (Pp + (xp - x) @ (xp - x).T) for m, (xp, Pp) in zip(mu, preds))
        return self._with_corner_hypotheses(x, P, self._require_track() + dt)

    def _check_future(self, t: float) -> float:
        t_last = self._require_track()
        t = float(t)
        if not np.isfinite(t):
            raise TrackingError(f"prediction time must be finite, got {t!r}")
        dt = t - t_last
        if dt < -1e-9:
            raise TrackingError(f"cannot predict into the past: t={t:.6f} s is before the last update {t_last:.6f} s")
        return max(dt, 0.0)

    def predict(self, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Predicted marker position (2,) mm and its covariance (2, 2) mm² at time ``t`` ≥ last update.

        Runs the extrapolation over ``t - t_last`` in one step (paper §4.2: one-step-ahead for
        the search window, multiple-step-ahead for the path). The filter's state is not
        changed. For the IMM the modes' predictions are moment-matched with the current mode
        probabilities.
        """
        x, P = self._combined(self._check_future(t))
        idx = self._pos
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
        idx = self._pos + self._vel
        return x[idx, 0].copy(), P[np.ix_(idx, idx)].copy()

    def velocity(self) -> np.ndarray:
        """Posterior marker velocity (2,) in mm/s at the last update."""
        return self.estimate()[0][2:]

    def turn_rate(self) -> float:
        """Posterior turn rate ω (rad/s, counter-clockwise positive), mode-weighted; 0 for CV/CA."""
        self._require_track()
        if self.model in ("cv", "ca"):
            return 0.0
        return float(sum(m * x[4, 0] * np.hypot(x[1, 0], x[3, 0])
                         for m, (x, _), mode in zip(self._weights(), self._mode_states(), self._modes)
                         if mode.kind == "ct"))

    def _mode_path(self, x: np.ndarray, mode: _Mode) -> PredictedPath:
        t_last = self._require_track()
        x = x[:, 0]
        p, v = x[self._pos], x[self._vel]
        if mode.kind == "ca":
            return PredictedPath(t_last, p.copy(), v.copy(), x[[2, 5]].copy())
        w = float(x[4] * np.hypot(*v)) if mode.kind == "ct" else 0.0  # ω = κ·|v|
        return PredictedPath(t_last, p.copy(), v.copy(), np.zeros(2), w)

    def predicted_path(self) -> PredictedPath | MixturePath:
        """The mean predicted path (for G(t), paper §4.3): a line, a parabola (CA) or the turn's arc.

        For the IMM, the modes' paths weighted by the mode probabilities at the last update,
        which is exactly the mean :meth:`predict` gives.
        """
        t_last = self._require_track()
        paths = [self._mode_path(x, mode) for (x, _), mode in zip(self._mode_states(), self._modes)]
        if self._imm is None:
            return paths[0]
        weights = [float(m) for m in self._weights()]
        corners = self._corner_legs()
        if corners is not None:
            weights += [float(v) for v in corners[0]]
            paths += corners[1]
        return MixturePath(t_last, tuple(weights), tuple(paths))
