"""Host 1: the object-trajectory predictor and robot-motion planner (paper §4, Fig. 1 Module 2).

The run's state machine lives here (paper §2, §5.2):

1. ``wait``      — find the marker in the fixed camera (full frame);
2. ``track``     — follow it with the one-step-ahead window, Kalman filter on the table plane;
3. ``intercept`` — time-optimal move to the initial viewing point on G(t), re-planned as the
   predictions improve;
4. ``initial``   — two images of one marker from two viewpoints, the recognizer resolves its pose;
5. ``standard``  — time-optimal move to the standard view along the marker normal, snapshot;
6. ``match``     — the recognizer matches; if ambiguous, back to 3 for another marker;
7. ``done`` / ``failed``.

The class is driven from outside — ``on_frame`` (fixed camera), ``on_message`` (recognizer),
``tick`` (clock) — by a live or a virtual runtime; it owns no clock, thread or process. It
commands the robot through the :class:`labctl.drivers.interfaces.Robot` interface.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, cast

import numpy as np

from ..drivers.interfaces import Frame, Robot, RobotStatus
from ..errors import DeviceError, MotionRefused
from ..geometry import make_T, matrix_to_rotvec, rotvec_to_matrix
from ..planning import Interception, camera_placement_trajectory, plan_interception, rest_to_rest_times
from ..planning.arm import ArmModel
from ..planning.arm_plan import ArmCheckSettings, ArmPlanner, JointPath, fit_plan
from ..planning.interception import plan_quintic_arriving
from ..planning.quintic import Trajectory
from ..planning.ruckig_interception import (
    RuckigTrajectory,
    plan_interception_ruckig,
    plan_ruckig_arriving,
    ruckig_limits,
)
from ..planning.ruckig_profile import JerkLimits, controller_limits
from ..planning.targets import prediction_margin_mm, standard_view_path, view_holds_marker, viewing_distance_with_margin
from ..planning.tti_bound import Leg, identity_bound
from ..timebase import wire_time_s
from ..tracking.bridge import OcclusionBridge
from ..tracking.tracker import MarkerTracker, position_from_frames
from ..vision import detect_markers, detect_markers_windowed, red_blob_centroid
from . import messages as m
from .context import RunContext, marker_thresholds

#: a robot at rest farther than this (mm) from the end of its segment did not run it to the end
ARRIVAL_TOL_MM = 1.0
#: after a controller's arrival time on the run's own clock (s): its replies give times to 1 µs, rounded either way
SHARED_CLOCK_MARGIN_S = 1e-4
GO_LINE_BYTES = 12  # "#<seq> GO <id>*HH\n" (dialect 1.4): what starts a held segment
#: a robot heartbeat's round trip on the line: "#<seq> HB*HH\n" and its "$<seq> ok*HH\n" (~11 bytes each)
HB_ROUND_TRIP_BYTES = 24
#: fixed-camera positions kept for :func:`position_from_frames` (a minute at 30 frames/s)
TRACK_HISTORY = 1800
#: the initial view's azimuths tried, in order, about the side facing the robot's home (deg): the nearest side
#: is the shortest reach, so the first reachable view is the one least far round the marker; the far side last
INITIAL_AZIMUTH_STEPS_DEG = (0.0, 20.0, -20.0, 45.0, -45.0, 90.0, -90.0, 180.0)
#: the second image steps up (``run.second_image_move: elevation``) only while the view stays at most this high
#: (deg): straight above (90°) the azimuth no longer places the camera and image-up (world +z) lies along the
#: optical axis; beyond it the step goes sideways round the marker instead
MAX_STEP_UP_ELEVATION_DEG = 85.0
#: the initial view's azimuths an arm chooses among (deg, round the marker), by its joint-space time
ARM_AZIMUTH_STEP_DEG = 15.0
#: a standard view the arm cannot fly as planned is tried with the camera rolled about its optical axis (deg)
#: and then a little nearer or farther (a share of the stand-off, within the library's 3 % stand-off tolerance)
ARM_STANDARD_ALTERNATIVES = ((0.0, 1.0), (90.0, 1.0), (-90.0, 1.0), (180.0, 1.0), (0.0, 0.97), (0.0, 1.03))

STAGES = ("wait", "track", "intercept", "initial", "standard", "match", "done", "failed")


@dataclass
class StageTimes:
    """Start time of each stage, for the per-stage durations of the result."""

    started: dict[str, float] = field(default_factory=dict)
    durations: dict[str, float] = field(default_factory=dict)
    current: str | None = None

    def enter(self, stage: str, now: float) -> None:
        """Enter ``stage`` at time ``now`` (s), adding the time spent in the previous stage to its duration.

        A stage entered on a frame exposed before the previous stage began (a live run's first frame: the
        camera's latest, up to a frame period older than the predictor's start) begins when that one did,
        so no duration is negative."""
        if self.current is not None:
            now = max(now, self.started[self.current])
            self.durations[self.current] = self.durations.get(self.current, 0.0) + now - self.started[self.current]
        self.current = stage
        self.started[stage] = now


def _wire_pose(R: np.ndarray, p) -> np.ndarray:
    """The 4×4 pose (W ← flange) as a segment command carries it: position rounded to 0.01 mm, rotation
    vector to 1e-4 rad (0.006°, 0.02 mm at a 200-mm stand-off). The controller prints six decimals;
    these ~20 bytes fewer a segment line are ~20 ms less before each leg starts at 9600 bps."""
    rv = np.round(matrix_to_rotvec(np.asarray(R, dtype=float)), 4)
    return make_T(rotvec_to_matrix(rv), np.round(np.asarray(p, dtype=float), 2))


def _vec3(v) -> tuple[float, float, float]:
    """A 3-vector as a tuple of floats (a leg's end points and start state, for the bound)."""
    x, y, z = map(float, v)
    return x, y, z


def _t_hit(plan: Interception | None) -> float:
    """The arrival time (s) of a reachable plan: the only kind the run keeps."""
    assert plan is not None and plan.t_hit is not None
    return plan.t_hit


def _reached(plan: Interception | None) -> tuple[Trajectory | RuckigTrajectory, float]:
    """The trajectory and arrival time (s) of a reachable plan: the only kind the run keeps and sends."""
    assert plan is not None and plan.trajectory is not None and plan.t_hit is not None
    return plan.trajectory, plan.t_hit


class _RestAt:
    """G(t) for arriving at rest: the positions of ``G`` with zero velocity and acceleration."""

    def __init__(self, G):
        self.G = G
        self.rotation = G.rotation

    def __call__(self, times):
        p, v, a = self.G(times)
        return p, np.zeros_like(v), np.zeros_like(a)


class _Scaled:
    """A table-plane path rescaled about the origin (the displacement scale of a point at another height)."""

    def __init__(self, path, s: float):
        self.path, self.s = path, s

    def __call__(self, times):
        p, v, a = self.path(times)
        return self.s * p, self.s * v, self.s * a


def _segment_line(plan: Interception):
    """What a plan's first segment sends: (the segment, its end pose 4×4 as the line rounds it, its duration s
    in whole ms never shorter than planned, the profile/limits keywords — ruckig: the controller re-runs it)."""
    end = _reached(plan)[0].segments[0]
    R_end = end.orientation(end.t1) if end.rot_coeffs is not None else cast(_RestAt, plan.target).rotation
    T_end = _wire_pose(cast(np.ndarray, R_end), end.state(end.t1)[0])
    kw: dict[str, Any] = {"profile": "ruckig", "limits": cast(JerkLimits, cast(RuckigTrajectory, end).limits).wire(
        cast(RuckigTrajectory, end).base)} if isinstance(end, RuckigTrajectory) else {}
    duration = math.ceil((end.t1 - end.t0) * 1000.0 - 1e-6) / 1000.0
    return end, T_end, duration, kw


class PredictorPlanner:
    """Host 1's logic. ``send(msg)`` goes to the recognizer; ``log(event, **fields)`` to the record.

    ``rest``: the robot's status read when it was opened (``Robot.ensure_ready``), if any; a robot
    standing still there is where the first leg starts, so that leg needs no STATUS round trip
    (~0.1 s at 9600 bps) on the way from first sight to the first command. ``family``: the
    trajectory family of the table program this run drives (``line``/``arc``/``circle``/``zigzag``), which
    sets the tracker's curve prior (``tracking.family_prior``); None when labctl does not drive
    the motion (``external``, no table) or the program is a G-code file."""

    def __init__(self, ctx: RunContext, robot: Robot, send: Callable[[m.Message], object],
                 log: Callable[..., None], *, t_start: float = 0.0, clock: Callable[[], float] | None = None,
                 profile: str | None = None, rest: RobotStatus | None = None, shared_clock: bool = False,
                 family: str | None = None):
        self.ctx, self.robot, self.send, self.log = ctx, robot, send, log
        # the runtime's clock: device round trips take time, so a command leaves later than the frame's time
        self.clock_fn = clock
        # the controller's replies give times on its own clock; they are the run's only in the simulated lab
        self.shared_clock = shared_clock
        cfg = ctx.lab.config
        self.cfg = cfg
        # the family of the program labctl drives the table along, if it does (paper §5.1): the tracker's
        # curve prior (tracking.family_prior); None (parts moved by something else): family-blind
        # ... and that table's corners are GRBL's: it slows to rest at a sharp one and speeds up again
        table = ctx.lab.table
        stops = {"stop_accel_mm_s2": table.accel_mm_s2} if family is not None and table is not None \
            and cfg.tracking.stop_corners else {}
        self.tracker = MarkerTracker.from_config(cfg.tracking, family=family, **stops)
        log("tracking_prior", t=t_start, family=family, curve_prior=self.tracker.curve_prior)
        self.bridge = OcclusionBridge(cfg.tracking.max_bridge_s)  # a gap in the sightings, bridged on the prediction
        self.stage = "wait"
        self.stage_times = StageTimes()
        self.stage_times.enter("wait", t_start)
        self.t_start = t_start
        self.deadline = t_start + cfg.run.timeout_s
        self.n_updates = 0
        self.t_first_seen: float | None = None
        self.t_last_seen: float | None = None
        self.last_px: np.ndarray | None = None
        self.plan: Interception | None = None
        self.plan_kind: m.CaptureKind | None = None
        self.t_last_plan = -math.inf
        self.segment_id = 0
        self.view_id = 0
        self.pending: int | None = None  # view id awaiting the recognizer
        self.views_used = 0
        self.markers_tried = 0
        self.azimuth_deg: float | None = None
        self.elevation_step_deg = 0.0  # the second image's step up from the initial viewing angle
        self.marker_pose: m.MarkerPose | None = None
        self.R_w_c_ref = np.eye(3)
        self.t_requested: dict[int, float] = {}
        self.track_xy: deque[tuple[float, float, float]] = deque(maxlen=TRACK_HISTORY)  # (t, x, y) of each update
        self.pose_view_id: int | None = None
        self.spare_poses: list[m.MarkerPose] = []
        self.used_normals: list[np.ndarray] = []
        self.coasting = False
        self.t_marker_pose: float | None = None
        self.marker_is_spare = False  # the marker being viewed was resolved from earlier images (_try_spare)
        self.identity: m.Identity | None = None
        self.failure: str | None = None
        self.robot_path: list[tuple[float, list[float]]] = []
        # a segment command is ~100 bytes: at 9600 bps it reaches the controller ~0.1 s after it is sent; the first
        # segment's measured latency replaces this guess (``_latency_measured``), later ones are averaged in
        self.latency_s = wire_time_s(100, ctx.lab.robot.baud)
        self._latency_measured = False
        self.plan_shift = 0.0  # controller time − plan time of the segment being executed
        self.t_robot_log = -math.inf
        self.min_quintic_s = 0.0  # sum over legs of the paper's quintic rest-to-rest time (the old bound)
        # the legs flown, for the honest bound (tti_bound): the one under way (start state, kind) and those done
        self.legs: list[Leg] = []
        self.leg_start: tuple | None = None
        self.leg_jerk_limited = False
        self.n_images = 0
        # where the robot stands still (4×4 W ← flange), known without asking once it has been read or reached
        self.rest_T: np.ndarray | None = None
        self.T_end: np.ndarray | None = None  # the commanded end pose of the segment under way
        self._asked_rest = False
        if rest is not None and not rest.moving:  # the status read when the robot was opened: no STATUS later
            self.rest_T = np.asarray(rest.T_base_flange, dtype=float).copy()
        self.t1c: float | None = None  # the controller's arrival time of the segment under way (its clock)
        # ... on the run's clock, never early (:meth:`_accepted`): when its view's image may be taken
        self.t_arrive: float | None = None
        # the image requested at that promised arrival before the segment's @DONE came: (segment id, view id,
        # t_capture), and the recognizer's replies to it, held until the @DONE confirms it (run.image_at_arrival)
        self.provisional: tuple[int, int, float] | None = None
        self._held_replies: list[m.Message] = []
        # the segment profile (run.profile): ruckig only if the controller lists it (dialect 1.2)
        self.profile = robot.choose_profile(profile or cfg.run.profile)
        self.jerk = ruckig_limits(ctx.lab.robot, cfg.run.robot_stop_budget_s)  # what ruckig segments carry
        self.jerk_ctrl = controller_limits(ctx.lab.robot)  # the controller's own: not sent
        # an arm (drivers/robot.yaml arm:): every path is checked in its joint space before it is sent, from the
        # configuration it will have (planning.arm_plan); None: a flange in the task-space box, as before
        self.arm: ArmPlanner | None = None
        if ctx.lab.arm is not None:
            self.arm = ArmPlanner(ArmModel.from_config(ctx.lab.arm),
                                  ArmCheckSettings.from_run(cfg.run, ctx.lab.robot))
        self.arm_q: np.ndarray | None = None  # the arm's configuration at rest (rest_T), once known
        self.arm_path: JointPath | None = None  # the segment under way as the arm flies it (the plan's time line)
        self._arm_checked: tuple[Interception, JointPath, float] | None = None  # the last plan checked, its stretch
        self.leg_q0: np.ndarray | None = None  # the arm's configuration where the leg under way started
        self.std_roll_deg, self.std_standoff_scale = 0.0, 1.0  # the standard view's roll and stand-off chosen
        # the second image's leg, sent (SEG hold=1, dialect 1.4) while the first leg flies and run by a ~12-byte
        # GO once the first image's exposure has ended: (plan, id, arm check, azimuth and elevation step); None: none
        self.held: tuple[Interception, int, tuple | None, tuple[float, float]] | None = None
        self._held_tried = False  # tried for the leg under way (once: the first leg is no longer re-planned)

    # -- helpers ------------------------------------------------------------------------------
    @property
    def finished(self) -> bool:
        """The run reached ``done`` or ``failed``."""
        return self.stage in ("done", "failed")

    def _enter(self, stage: str, now: float) -> None:
        self.stage_times.enter(stage, now)
        self.stage = stage
        self.log("stage", t=now, stage=stage)

    def fail(self, now: float, reason: str) -> None:
        """End the run as failed with ``reason`` (logged, robot stopped); no-op once finished."""
        if self.finished:
            return
        self.failure = reason
        self.log("failure", t=now, reason=reason, stage=self.stage)
        self._enter("failed", now)
        self._stop_robot(now)

    def _stop_robot(self, now: float) -> None:
        try:
            self.robot.stop()
        except Exception as exc:  # noqa: BLE001 — a stop must never raise out of a failure path
            self.log("robot_stop_failed", t=now, error=str(exc))

    def _flange_state(self, now: float):
        """Current commanded flange state (p, v, a) and rotation, from the plan being executed."""
        if self.plan is not None and self.plan.trajectory is not None:
            traj = self.plan.trajectory
            now = now - self.plan_shift
            t = min(max(now, traj.t_start), traj.t_end)
            p, v, a = traj.state(t)
            R = traj.orientation(t)
            if now >= traj.t_end:
                v, a = np.zeros(3), np.zeros(3)
            if R is not None:
                return (p, v, a), R
        T = self._rest_pose()
        return (T[:3, 3].copy(), np.zeros(3), np.zeros(3)), T[:3, :3].copy()

    def _rest_pose(self) -> np.ndarray:
        """The flange pose (4×4, W) of the robot at rest: the pose it reached (@DONE of the last commanded
        segment), else one STATUS (a ~0.1 s round trip at 9600 bps, so it is asked once, while waiting)."""
        if self.rest_T is None:
            self.rest_T = np.asarray(self.robot.status().T_base_flange, dtype=float).copy()
        return self.rest_T

    def _marker_path(self):
        return self.tracker.predicted_path()

    def _send_segment(self, now: float, plan: Interception) -> None:
        """Command the plan's first segment; the controller splices it in from its own state on receipt,
        which is the plan's start time (now + the command's transmission time)."""
        end, T_end, duration, kw = _segment_line(plan)
        self.segment_id += 1
        now = self._now(now)
        t0c, t1c = self.robot.segment(T_end, duration, self.segment_id, replace=True, **kw)
        self._accepted(now, plan, end, T_end, t0c, t1c, t_reply=self._now(now))

    def _accepted(self, now: float, plan: Interception, end, T_end: np.ndarray, t0c: float, t1c: float,
                  line: bool = True, t_reply: float | None = None) -> None:
        """The controller took the plan's first segment (``self.segment_id``), which starts at its ``t0c`` and
        ends at ``t1c``: the motion under way from now on. ``line``: started by the segment's own line (its
        start measures a segment line's latency), not by a held segment's ``GO``. ``t_reply``: when its reply
        had been read (s, run clock; default ``now``)."""
        ruckig = isinstance(end, RuckigTrajectory)
        self.held = None  # a SEGNOW drops a held segment at the controller; a GO has run it
        # accepted (a refused splice raises, and the motion under way, its end and its leg stay as they were)
        self.T_end = T_end
        if self.arm is not None and self._arm_checked is not None and self._arm_checked[0] is plan:
            _, self.arm_path, stretch = self._arm_checked
            self.log("arm_plan", t=now, id=self.segment_id, kind=self.plan_kind, ratio=self.arm_path.ratio,
                     stretch=stretch, q_end_deg=np.degrees(self.arm_path.q_end))
        self.rest_T = None  # moving: at rest again only when the segment is done
        if not ruckig:
            self.leg_jerk_limited = False  # a quintic segment: no jerk limit binds this leg
        # The controller reports when it started the segment. On the run's own clock (the simulated lab)
        # that measures the command latency, and the plan is re-timed to what the robot really does. A
        # controller on its own clock (real hardware, a served lab) can be off by any amount: a guessed
        # offset taken for latency would start every re-plan that much later, and the run never arrives.
        shared = self.shared_clock and math.isfinite(t0c)
        self.t1c = t1c if shared and math.isfinite(t1c) else None
        self.t_arrive = self._arrival_on_run_clock(t0c, t1c, now if t_reply is None else t_reply)
        if shared and 0.0 <= t0c - now < 1.0:
            if line:  # the guess above is ~30 % long under the session's segment defaults: not averaged in
                measured = t0c - now
                self.latency_s = 0.5 * self.latency_s + 0.5 * measured if self._latency_measured else measured
                self._latency_measured = True
            self.plan_shift = t0c - end.t0
        else:
            self.plan_shift = 0.0
        self.log("segment", t=now, id=self.segment_id, kind=self.plan_kind, t_end=end.t1, t0c=t0c, t1c=t1c,
                 p=T_end[:3, 3], rotvec=matrix_to_rotvec(T_end[:3, :3]))

    def _arrival_on_run_clock(self, t0c: float, t1c: float, t_reply: float) -> float | None:
        """When (s, run clock) the segment the controller started at ``t0c`` and promised to end at ``t1c`` (its
        clock) stands at its end, never early; None without ``run.image_at_arrival`` or the two times.

        On the run's own clock (the simulated lab) that is ``t1c`` and a margin for the reply's µs rounding
        (:data:`SHARED_CLOCK_MARGIN_S`). A controller on its own clock is mapped through its reply: it starts a
        segment (SEGNOW, or GO at rest) before it answers, so the reply read at ``t_reply`` plus the segment's own
        duration is at or after the arrival; ``run.arrival_clock_margin_s`` covers the clocks' rates."""
        if not self.cfg.run.image_at_arrival or not (math.isfinite(t0c) and math.isfinite(t1c)):
            return None
        if self.shared_clock:
            return t1c + SHARED_CLOCK_MARGIN_S
        return t_reply + (t1c - t0c) + self.cfg.run.arrival_clock_margin_s

    # -- planning ----------------------------------------------------------------------------
    def _initial_view_target(self, azimuth_deg: float, margin: bool = True):
        """The initial view of the marker from ``azimuth_deg``; with ``margin``, far enough back that the
        prediction's uncertainty stays well inside the view, else at the nominal distance."""
        cam = self.ctx.mobile_camera
        distance = viewing_distance_with_margin(self.cfg.viewing.initial_distance_mm,
                                                self._commit_margin_mm() if margin else 0.0,
                                                float(np.arctan2(0.5 * cam.height, cam.K[1, 1])))
        G = camera_placement_trajectory(self._marker_path(), distance,
                                        (self.ctx.initial_angle_deg or self.cfg.viewing.initial_angle_deg)
                                        + self.elevation_step_deg, azimuth_deg,
                                        marker_z_mm=self.ctx.plane_height_mm, T_f_c=self.ctx.T_f_c2)
        return _RestAt(G)

    def _now(self, now: float) -> float:
        return max(now, self.clock_fn()) if self.clock_fn is not None else now

    def _plan(self, now: float, kind: str, target) -> Interception:
        """Plan from where the robot will be when the command reaches the controller; for an arm, checked in
        its joint space and slowed or refused (:meth:`_arm_fit`)."""
        t0 = self._now(now) + self.latency_s
        state, R = self._flange_state(t0)
        plan = self._plan_from(t0, state, R, target)
        if self.arm is None or not plan.reachable:
            return plan
        return self._arm_fit(plan, t0, state, R, target)

    def _plan_from(self, t0: float, state, R, target, duration: float | None = None,
                   slow: float = 1.0) -> Interception:
        """The earliest arrival on ``target`` from ``state`` (p, v, a) and rotation ``R`` at ``t0``; with
        ``duration`` (s), the arrival at ``t0 + duration`` (a stretched segment), its ruckig acceleration and
        jerk limits time-scaled by ``slow`` (the arm's joint accelerations bind). Ruckig if the controller
        runs it, else (or if ruckig finds none) the paper's quintic (whose accelerations fall with T²)."""
        horizon = self.cfg.run.plan_horizon_s
        if self.profile == "ruckig":
            traj = self.plan.trajectory if self.plan is not None else None
            w = traj.angular_velocity(t0 - self.plan_shift) if isinstance(traj, RuckigTrajectory) else None
            if duration is None:
                plan = plan_interception_ruckig(state, t0, target, self.ctx.limits, horizon, R0=R, w0=w,
                                                jerk=self.jerk, base=self.jerk_ctrl)
            else:
                jerk = self.jerk if slow == 1.0 else self.jerk.slowed(slow)
                plan = plan_ruckig_arriving(state, t0, target, duration, self.ctx.limits, R0=R, w0=w, jerk=jerk,
                                            base=self.jerk_ctrl)
            if plan.reachable:
                return plan
        if duration is not None:
            return plan_quintic_arriving(state, t0, target, duration, self.ctx.limits, R0=R)
        return plan_interception(state, t0, target, self.ctx.limits, horizon_s=horizon, R0=R)

    # -- the arm -----------------------------------------------------------------------------------
    def _arm_rest_q(self) -> np.ndarray | None:
        """The arm's configuration at rest: where its last segment ended, else the rest pose's in the arm's
        home branch (IK from its home configuration)."""
        assert self.arm is not None
        if self.arm_q is None:
            self.arm_q = self.arm.configuration_at(self._rest_pose())
        return self.arm_q

    def _arm_q_at(self, t: float, p, R) -> np.ndarray | None:
        """The configuration the arm will have at ``t`` (s, host time) where the flange is at (``p``, ``R``):
        IK from the committed segment's own joint path there (the arm's Cartesian servo follows it), or from
        the rest configuration."""
        assert self.arm is not None
        if self.plan is not None and self.arm_path is not None:
            seed: np.ndarray | None = self.arm_path.q_at(t - self.plan_shift)
        else:
            seed = self._arm_rest_q()
        if seed is None:
            return None
        res = self.arm.model.ik(make_T(R, p), seed)
        return res.q if res.ok else seed

    def _arm_fit(self, plan: Interception, t0: float, state, R, target) -> Interception:
        """``plan`` as the arm can fly it (:func:`~labctl.planning.arm_plan.fit_plan`): checked in joint space from
        the configuration it will have at ``t0``; over a joint's speed, stretched by exactly the peak ratio and
        checked again; not followable: unreachable with the reason, so the caller tries another view."""
        assert self.arm is not None
        arm = self.arm
        q0 = self._arm_q_at(t0, state[0], R)
        if q0 is None:
            return Interception(None, None, "the arm has no configuration at the start pose", "arm_unreachable",
                                target)
        fit = fit_plan(plan, t0, lambda p: arm.check(_reached(p)[0], t0, _t_hit(p), q0),
                       lambda T, slow: self._plan_from(t0, state, R, target, duration=T, slow=slow))
        if fit.plan.reachable and fit.path is not None:
            self._arm_checked = (fit.plan, fit.path, fit.stretch)
        return fit.plan

    def _arm_view_time(self, target, now: float) -> float:
        """A view's rough cost for an arm (s): the larger of the rest-to-rest time at the planner's limits and
        the joints' least time (:meth:`ArmPlanner.joint_time_s`, IK from the rest configuration), to the
        ``target``'s pose now; inf where the arm cannot reach it in its branch."""
        assert self.arm is not None
        q0 = self._arm_rest_q()
        if q0 is None:
            return math.inf
        T = cast(_RestAt, target).G.pose(now)
        (p0, _, _), _ = self._flange_state(now)
        cart = rest_to_rest_times(p0, T[:3, 3], self.ctx.limits.v_max, self.ctx.limits.a_max)[0]
        return max(cart, self.arm.joint_time_s(q0, T))

    def _start_move(self, now: float, kind: m.CaptureKind, plan: Interception,
                    started: tuple[int, float, float, float] | None = None) -> None:
        """Fly ``plan`` as the leg to the ``kind`` view: send it, or with ``started`` (segment id, t0c, t1c, when the
        reply was read) a held segment the controller has just started (:meth:`_go_held`; ``now`` then is when its
        ``GO`` was sent)."""
        if kind == "initial1":
            self._held_tried = False  # a new first leg: its second may be held again
        traj, t_hit = _reached(plan)
        seg0 = traj.segments[0]
        p0, v0, a0 = traj.state(seg0.t0)  # the state the plan starts from: where the leg begins
        R0 = traj.orientation(seg0.t0)
        self.leg_start = (kind, p0, v0, a0, R0)
        if self.arm is not None:
            checked = self._arm_checked
            self.leg_q0 = checked[1].qs[0].copy() if checked is not None and checked[0] is plan else None
        self.leg_jerk_limited = True  # until a segment of the leg is sent without the controller's jerk limit
        self.plan, self.plan_kind, self.t_last_plan = plan, kind, now
        _, quintic = rest_to_rest_times(p0, traj.state(t_hit)[0],
                                        self.ctx.lab.robot.v_max_mm_s, self.ctx.lab.robot.a_max_mm_s2)
        self.min_quintic_s += quintic
        if started is not None:
            self.segment_id = started[0]
            end, T_end, _, _ = _segment_line(plan)
            self._accepted(now, plan, end, T_end, started[1], started[2], line=False, t_reply=started[3])
        else:
            try:
                self._send_segment(now, plan)
            except MotionRefused as exc:  # the arm cannot fly the leg: the run ends with the reason, nothing moved
                self.fail(now, f"the robot refused the {kind} leg: {exc}")
                return
        self.log("plan", t=now, kind=kind, t_hit=plan.t_hit)
        horizon = np.linspace(now, max(t_hit, now + 1.0), 12)
        self.log("predict", t=now, path=self._marker_path()(horizon)[0])

    def _commit_margin_mm(self) -> float:
        """3-σ radius (mm) of the predicted marker position ``commit_horizon_s`` ahead."""
        _, cov = self.tracker.predict(cast(float, self.tracker.time) + self.cfg.tracking.commit_horizon_s)
        return prediction_margin_mm(cov)

    def _ready_to_commit(self, now: float) -> bool:
        """Plan once the prediction is good enough for the interception, or after ``min_track_s``."""
        assert self.t_first_seen is not None  # tracking
        gate = self.cfg.tracking.commit_margin_mm
        if gate is None or now - self.t_first_seen >= self.cfg.tracking.min_track_s:
            return True
        return self._commit_margin_mm() <= gate

    def _choose_azimuth(self) -> float:
        """Initial viewing side: from the marker towards the robot's home (shortest reach); for an arm, of the
        azimuths every :data:`ARM_AZIMUTH_STEP_DEG` round the marker, the view quickest for the arm from the
        configuration it has (:meth:`_arm_view_time`), the nearest to the home side on a tie."""
        mp = self._marker_path()(np.array([self.tracker.time]))[0][0]
        home = np.asarray(self.ctx.lab.robot.home_mm)
        az0 = math.degrees(math.atan2(home[1] - mp[1], home[0] - mp[0]))
        if self.arm is None:
            return az0
        now = cast(float, self.tracker.time)
        steps = np.arange(0.0, 360.0, ARM_AZIMUTH_STEP_DEG)
        deltas = sorted(((d + 180.0) % 360.0) - 180.0 for d in steps)
        deltas.sort(key=abs)
        best, best_t = az0, math.inf
        for d in deltas:
            t = self._arm_view_time(self._initial_view_target(az0 + d), now)
            if t < best_t - 1e-9:
                best, best_t = az0 + d, t
        return best

    def _plan_initial(self, now: float, kind: m.CaptureKind) -> bool:
        # the margin-widened views first, then the nominal ones: while the table speeds up (0.5 s to 100 mm/s)
        # the manoeuvre mode's 3-σ margin puts every widened view out of reach (docs/notes/planning.md,
        # "Frames caught up"), and the newest mean prediction is the best aim there is
        last: str | None = ""
        assert self.azimuth_deg is not None  # chosen on entering intercept
        for margin in (True, False):
            for delta in INITIAL_AZIMUTH_STEPS_DEG:
                az = self.azimuth_deg + delta
                plan = self._plan(now, kind, self._initial_view_target(az, margin))
                if plan.reachable:
                    self.azimuth_deg = az
                    self._start_move(now, kind, plan)
                    return True
                last = plan.reason
        self.fail(now, f"initial viewing point unreachable: {last}")
        return False

    def _hold_second_leg(self, now: float) -> None:
        """Once the first leg is no longer re-planned (``replan_until_s`` before its arrival), plan the second
        image's leg from the first's commanded end and send it held (``SEG … hold=1``, dialect 1.4): its ~70
        bytes cross the line while the first leg flies, and after the first image only a ~12-byte ``GO`` does
        (:meth:`_go_held`). The robot still moves only once that image's exposure has ended: GO is sent on
        its ``FrameTaken``. Planned for the start the GO will give it (arrival, ``@DONE``, the exposure, GO)."""
        if self.held is not None or self._held_tried or self.plan_kind != "initial1" or self.T_end is None \
                or not self.robot.holds or _t_hit(self.plan) - now >= self.cfg.run.replan_until_s:
            return
        self._held_tried = True
        baud, fps = self.ctx.lab.robot.baud, float(self.ctx.lab.mobile_camera.fps or self.cfg.run.fps)
        # the GO leaves once the exposure has ended and the @DONE has come: the image waits for the @DONE, or
        # (run.image_at_arrival) is exposed from the arrival while the @DONE crosses the line
        after = max(1.0 / fps, wire_time_s(16, baud)) if self.cfg.run.image_at_arrival \
            else wire_time_s(16, baud) + 1.0 / fps
        t0 = _t_hit(self.plan) + self.plan_shift + after + wire_time_s(GO_LINE_BYTES, baud)
        T = self.T_end
        state, R = (T[:3, 3].copy(), np.zeros(3), np.zeros(3)), T[:3, :3].copy()
        before = (self.azimuth_deg, self.elevation_step_deg)
        self._step_for_second_image()
        assert self.azimuth_deg is not None  # chosen on entering intercept
        stepped, plan, az = (self.azimuth_deg, self.elevation_step_deg), None, self.azimuth_deg
        for margin in (True, False):  # as _plan_initial tries them
            for delta in INITIAL_AZIMUTH_STEPS_DEG:
                plan = self._plan_from(t0, state, R, self._initial_view_target(stepped[0] + delta, margin))
                if plan.reachable and self.arm is not None:
                    plan = self._arm_fit(plan, t0, state, R, self._initial_view_target(stepped[0] + delta, margin))
                if plan.reachable:
                    az = stepped[0] + delta
                    break
            if plan is not None and plan.reachable:
                break
        self.azimuth_deg, self.elevation_step_deg = before  # nothing changes until the GO
        if plan is None or not plan.reachable:
            return
        end, T_end, duration, kw = _segment_line(plan)
        try:
            self.robot.segment(T_end, duration, self.segment_id + 1, hold=True, **kw)
        except DeviceError as exc:  # refused (E02, E1x): the second leg is sent after the image, as before
            self.log("hold_refused", t=now, error=str(exc))
            return
        self.held = (plan, self.segment_id + 1, self._arm_checked, (az, stepped[1]))
        self.log("segment_held", t=now, id=self.segment_id + 1, p=T_end[:3, 3], t_start=t0)

    def _go_held(self, now: float) -> bool:
        """Start the held second leg (``GO``) after the first image's exposure; False if none is held or the
        controller refused it (the caller plans the leg afresh, as without a held one)."""
        held, self.held = self.held, None
        if held is None:
            return False
        plan, sid, arm_checked, (az, elevation) = held
        sent = self._now(now)  # as for a segment line: the plan is re-timed from when GO left, not its reply
        try:
            t0c, t1c = self.robot.go(sid)
        except DeviceError as exc:  # E21 (dropped), a latched fault, the arm: plan it afresh from where it is
            self.log("hold_refused", t=now, error=str(exc))
            return False
        self.azimuth_deg, self.elevation_step_deg = az, elevation
        self._arm_checked = arm_checked
        self._start_move(sent, "initial2", plan, started=(sid, t0c, t1c, self._now(sent)))
        return True

    def _replan(self, now: float) -> None:
        """Re-plan the unexecuted motion with the newest prediction (paper §4.3)."""
        run = self.cfg.run
        if self.plan is None or now - self.t_last_plan < run.replan_every_s \
                or _t_hit(self.plan) - now < run.replan_until_s:
            return
        assert self.plan_kind is not None  # set with the plan
        if self.plan_kind == "standard":
            plan = self._plan(now, self.plan_kind, self._standard_target())
        else:  # the nominal view of the newest prediction, if the widened one is out of reach, beats the old aim
            assert self.azimuth_deg is not None  # chosen on entering intercept
            plan = self._plan(now, self.plan_kind, self._initial_view_target(self.azimuth_deg))
            if not plan.reachable:
                plan = self._plan(now, self.plan_kind, self._initial_view_target(self.azimuth_deg, margin=False))
        self.t_last_plan = now
        if not plan.reachable:
            return  # keep executing the current plan
        (old_traj, old_hit), (new_traj, new_hit) = _reached(self.plan), _reached(plan)
        if self.plan_kind != "standard" and run.initial_view_hold and new_hit > old_hit \
                and self._initial_view_holds():
            return  # a later arrival only to centre a marker the view under way already holds
        old_end = old_traj.state(old_hit)[0]
        new_end = new_traj.state(new_hit)[0]
        if np.linalg.norm(new_end - old_end) > 0.5 or abs(new_hit - old_hit) > 0.02:
            old, old_shift = self.plan, self.plan_shift
            self.plan = plan
            try:
                self._send_segment(now, plan)
            except DeviceError as exc:  # the controller refused the splice: keep the motion it runs
                self.plan, self.plan_shift = old, old_shift
                self.log("replan_refused", t=now, error=str(exc))

    def _standard_target(self, mp: m.MarkerPose | None = None, t_ref: float | None = None,
                         measured: bool | None = None, choice: tuple[float, float] | None = None):
        """G(t) of the standard view (paper §4.3): the marker, carried by the table's predicted
        motion from where it was measured, seen along its normal from the stand-off; at rest.
        Default: the marker being viewed (``marker_pose`` measured at ``t_marker_pose``). ``measured``: carry it
        by the table's measured motion up to the newest frame (:meth:`_table_since`), as for a spare marker
        (default: whether the marker being viewed is one); else by the newest path extended back to its images.
        ``choice``: the camera's roll about its optical axis (deg) from the least-rotation one and the share of
        the stand-off (default: the ones chosen for the view under way, :meth:`_plan_standard`)."""
        roll_deg, scale_standoff = (self.std_roll_deg, self.std_standoff_scale) if choice is None else choice
        R_ref = self.R_w_c_ref
        if roll_deg:
            c, s = math.cos(math.radians(roll_deg)), math.sin(math.radians(roll_deg))
            R_ref = R_ref @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])  # about the camera's z
        mp = self.marker_pose if mp is None else mp
        t_ref = cast(float, self.t_marker_pose if t_ref is None else t_ref)
        assert mp is not None  # the marker being viewed, or the one given
        scale = self.ctx.displacement_scale(mp.center_w[2])
        if measured is None:
            measured = self.marker_is_spare
        ref = self._table_since(t_ref) if measured else None
        ref_xy = None if ref is None else scale * ref
        return _RestAt(standard_view_path(_Scaled(self._marker_path(), scale), t_ref,
                                          mp.center_w, mp.normal_w, self.cfg.viewing.standoff_mm * scale_standoff,
                                          R_ref, T_f_c=self.ctx.T_f_c2, table_xy_at_ref=ref_xy))

    def _table_since(self, t_ref: float) -> np.ndarray | None:
        """The point of the newest predicted path (table plane, mm) the table's motion since ``t_ref`` is counted
        from: the path at the newest frame less the motion the frames measured from ``t_ref`` to it
        (:func:`position_from_frames` at both ends); None without frames there.

        A spare marker's standard view is planned a view's flight (1-3 s) after its images: on the zigzag the
        table has turned corners since, and the newest leg extended back to the images cuts them (tens of mm at
        100 mm/s: 18 of 19 spare views missed, docs/notes/planning.md "Tenth round"). For the marker just resolved
        the extended leg is kept: its view is planned at once, and right after a corner the instant-corner path's
        lead on GRBL's ramp and the extended leg's offset partly cancel (measured: with this for every view, 14
        of 30 zigzag trials at 100 mm/s were slower)."""
        frames = np.array(self.track_xy) if self.track_xy else np.zeros((0, 3))
        times, xy, t_last = frames[:, 0], frames[:, 1:], cast(float, self.tracker.time)
        at_ref, at_last = position_from_frames(times, xy, t_ref), position_from_frames(times, xy, t_last)
        if at_ref is None or at_last is None:
            return None
        return self._marker_path()(np.array([t_last]))[0][0] - (at_last - at_ref)

    def _travel_s(self, pose: m.MarkerPose, now: float) -> float:
        """Rough time (s) from where the robot stands to ``pose``'s standard view (rest-to-rest at the
        planner's limits, the view where the marker is now): to rank spare markers."""
        _, R = self._flange_state(now)
        self.R_w_c_ref = R @ self.ctx.T_f_c2[:3, :3]
        G = self._standard_target(pose, self.t_requested.get(pose.view_id, now), measured=True, choice=(0.0, 1.0))
        if self.arm is not None:  # an arm: its joints' least time counts too, and a view it cannot reach goes last
            return self._arm_view_time(G, now)
        p1 = G(np.array([now]))[0][0]
        p0 = self._flange_state(now)[0][0]
        return rest_to_rest_times(p0, p1, self.ctx.limits.v_max, self.ctx.limits.a_max)[0]

    def _initial_view_holds(self) -> bool:
        """Does the initial view under way still show the marker inside the central half of the image at its
        arrival, by the newest prediction with its 3-σ margin? An initial image needs the marker in view, not
        centred; re-aiming at the centre each time the prediction moves lengthens the flight (the table's start
        ramp: docs/notes/planning.md, "Ninth round")."""
        traj, t_hit = _reached(self.plan)
        R = traj.orientation(t_hit)
        if R is None:
            return False
        T_w_c = make_T(R, traj.state(t_hit)[0]) @ self.ctx.T_f_c2
        mean, cov = self.tracker.predict(t_hit)
        marker = np.array([mean[0], mean[1], self.ctx.plane_height_mm])
        return view_holds_marker(self.ctx.mobile_camera, T_w_c, marker, prediction_margin_mm(cov))

    def _plan_standard(self, now: float) -> bool:
        """Plan the standard view of the marker being viewed; an arm that cannot fly it tries the camera rolled
        about its optical axis, then a little nearer or farther (:data:`ARM_STANDARD_ALTERNATIVES`), in order."""
        _, R = self._flange_state(now)
        self.R_w_c_ref = R @ self.ctx.T_f_c2[:3, :3]
        choices = ARM_STANDARD_ALTERNATIVES if self.arm is not None else ((0.0, 1.0),)
        first: Interception | None = None
        for self.std_roll_deg, self.std_standoff_scale in choices:
            plan = self._plan(now, "standard", self._standard_target())
            first = plan if first is None else first
            if plan.reachable:
                break
        else:
            plan = cast(Interception, first)
            self.std_roll_deg, self.std_standoff_scale = 0.0, 1.0
        if not plan.reachable:
            self.log("standard_view_unreachable", t=now, reason=plan.reason, code=plan.code)
            return False
        self._start_move(now, "standard", plan)
        return True

    def _arrived(self, now: float) -> np.ndarray | None:
        """The flange pose (4×4, W) once the robot stands at the end of its segment, else None.

        The controller's ``@DONE <id>`` of the segment under way says it stands at the commanded end
        pose: read without waiting, no round trip. A controller that sends no ``@DONE`` (or one lost on
        the line) is asked with STATUS, from the planned arrival on (still moving: wait, up to 1 s)."""
        if self.T_end is not None:
            self.robot.poll()
            if self.segment_id in self.robot.done_ids:
                self.rest_T = np.asarray(self.T_end, dtype=float).copy()
                return self.rest_T
            # @DONE leaves the controller at the arrival and is ~10 bytes on the line: wait for it a few
            # frames rather than ask STATUS (a ~0.1 s round trip at 9600 bps that holds up the image)
            if now < _t_hit(self.plan) + self.plan_shift + self._done_grace_s:
                if self.provisional is None and self.t_arrive is not None and now >= self.t_arrive \
                        and self.cfg.run.image_at_arrival:
                    # the controller promised to stand at the end pose from t_arrive: the image is taken from then,
                    # and used once the @DONE says the segment ran to its end (docs/protocols/robot.md §5, §10)
                    kind = self.plan_kind
                    assert kind is not None  # set with the plan
                    view = self._request_capture(self.t_arrive, kind, self.T_end, provisional=True)
                    self.provisional = (self.segment_id, view, self.t_arrive)
                return None
        self._discard_provisional(now, "no @DONE within the grace")
        st = self.robot.status()
        latched = self.robot.latched
        if latched:  # its watchdog or a STOP cut the move: an image from where it stood would be a wrong view
            self.fail(now, f"the robot controller stopped the robot ({latched}) before it reached the view")
            return None
        if st.moving and now < _t_hit(self.plan) + self.plan_shift + 1.0:
            return None
        T = np.asarray(st.T_base_flange, dtype=float)
        if self.T_end is not None and np.linalg.norm(T[:3, 3] - self.T_end[:3, 3]) > ARRIVAL_TOL_MM:
            self.fail(now, f"the robot stands {np.linalg.norm(T[:3, 3] - self.T_end[:3, 3]):.1f} mm from its "
                           "commanded view")
            return None
        self.rest_T = T.copy()
        return self.rest_T

    def wake_at(self) -> float | None:
        """When (s, the runtime's clock, if it is the controller's as in the simulated lab) the planner acts on the
        segment under way's arrival: at the arrival itself, where its image is requested then
        (``run.image_at_arrival``, :attr:`t_arrive`), else (or once requested) when its ``@DONE`` reaches the host:
        the controller's arrival time plus the line's bytes (~12; 16 allowed). A runtime that ticks the planner
        then, not only at the next fixed-camera frame, takes the image as soon as the robot stands still. None
        when no arrival is awaited."""
        if self.finished or self.plan is None or self.pending is not None or self.t1c is None:
            return None
        if self.provisional is None and self.t_arrive is not None:
            return self.t_arrive
        return self.t1c + wire_time_s(16, self.ctx.lab.robot.baud)

    def heartbeat_can_wait(self, now: float, late_s: float) -> bool:
        """Should a robot heartbeat due ``late_s`` (s) ago wait at ``now`` (s)? True when the image the planner
        requests at the promised arrival (:attr:`t_arrive`; without ``run.image_at_arrival``, the ``@DONE``'s
        :meth:`wake_at`) falls within the heartbeat's round trip (~25 ms at 9600 bps), which would block the loop
        past it and hold up that view's image; never once the beat is a quarter of the watchdog's slack late
        (``watchdog_s − heartbeat_s``: 75 ms in the sample lab), so the controller hears from the host well inside
        its watchdog."""
        robot = self.ctx.lab.robot
        rt = wire_time_s(HB_ROUND_TRIP_BYTES, robot.baud)
        if late_s >= 0.25 * (robot.watchdog_s - robot.heartbeat_s) or self.finished:
            return False
        if self.cfg.run.image_at_arrival:
            t = self.t_arrive if self.provisional is None and self.pending is None and self.plan is not None else None
        else:
            t = self.wake_at()
        return t is not None and now < t <= now + rt

    @property
    def _done_grace_s(self) -> float:
        """How long (s) after the planned arrival an ``@DONE`` may still be on its way: its ~16 bytes on
        the robot's line plus three fixed-camera frame periods (the ticks that read it)."""
        return wire_time_s(16, self.ctx.lab.robot.baud) + 3.0 / self.cfg.run.fps

    def _end_leg(self, T_flange: np.ndarray) -> None:
        """Close the leg under way at the rest pose ``T_flange`` where its image is taken (for the bound)."""
        if self.leg_start is None:
            return
        kind, p0, v0, a0, R0 = self.leg_start
        q0 = q1 = None
        if self.arm is not None and self.leg_q0 is not None and self.arm_q is not None:
            q0, q1 = tuple(map(float, self.leg_q0)), tuple(map(float, self.arm_q))
        self.legs.append(Leg(kind, _vec3(p0), _vec3(T_flange[:3, 3]), _vec3(v0), _vec3(a0), R0=R0,
                             R1=T_flange[:3, :3].copy(),
                             j_max=self.jerk_ctrl.j_max if self.leg_jerk_limited else None, q0=q0, q1=q1))
        self.leg_start = None

    # -- capture ---------------------------------------------------------------------------------
    def _request_capture(self, now: float, kind: m.CaptureKind, T_w_f: np.ndarray, provisional: bool = False) -> int:
        """Ask the recognizer for an image exposed from ``now`` on (s); the camera pose comes from the robot's
        reported flange (``provisional``: the commanded end pose, at the promised arrival, not yet confirmed by
        ``@DONE``: nothing waits on its replies until it is, :meth:`_at_view`). Returns its view id."""
        T_w_c2 = T_w_f @ self.ctx.T_f_c2
        self.view_id += 1
        self.n_images += 1
        if not provisional:
            self.pending = self.view_id
        self.t_requested[self.view_id] = now
        self.send(m.CaptureRequest(view_id=self.view_id, kind=kind, t_capture=now,
                                   position=tuple(T_w_c2[:3, 3]), rotvec=tuple(matrix_to_rotvec(T_w_c2[:3, :3]))))
        self.log("capture_request", t=now, view_id=self.view_id, kind=kind, T_w_c2=T_w_c2, provisional=provisional)
        return self.view_id

    def _use_pose(self, msg: m.MarkerPose, now: float, spare: bool = False) -> bool:
        """Go for the standard view of this resolved marker (``spare``: one resolved from earlier images, not
        the one just resolved); False if the robot cannot reach it."""
        self.marker_pose, self.t_marker_pose = msg, self.t_requested.get(msg.view_id, now)
        self.marker_is_spare = spare
        self.pose_view_id = msg.view_id
        self.used_normals.append(np.asarray(msg.normal_w, dtype=float))
        self._enter("standard", now)
        return self._plan_standard(now)

    def _try_spare(self, now: float) -> bool:
        """Another marker already resolved from the last two images, if one faces a new way."""
        def novelty(pose):  # the face turned furthest from every face already viewed shows most that is new
            n = np.asarray(pose.normal_w, dtype=float)
            return min((float(np.arccos(np.clip(n @ u, -1.0, 1.0))) for u in self.used_normals), default=np.pi)

        floor = np.radians(self.cfg.run.spare_novelty_deg)
        # only faces turned from every viewed one tell something new; of those, the nearest view is
        # the quickest (run.spare_order "nearest"), or the most novel face ("novel", the old order)
        self.spare_poses = [p for p in self.spare_poses if novelty(p) >= floor]
        if self.cfg.run.spare_order == "nearest":
            self.spare_poses.sort(key=lambda p: self._travel_s(p, now))
        else:
            self.spare_poses.sort(key=novelty, reverse=True)
        while self.spare_poses:
            pose = self.spare_poses.pop(0)
            if self._use_pose(pose, now, spare=True):
                return True
        return False

    def _step_for_second_image(self) -> None:
        """Move the viewpoint for the next marker image: ``run.second_image_elevation_deg`` up towards the top
        (``run.second_image_move: elevation``, while the view stays ≤ :data:`MAX_STEP_UP_ELEVATION_DEG` high), else
        ``run.second_image_azimuth_deg`` sideways round the marker (``azimuth``, the paper's). A marker facing
        up — the recogniser prefers one — has its two pose candidates in the vertical plane through the line
        of sight, so a step in that plane separates them most (duality margin 0.35 rad for 10° up against
        0.14 for 10° round, one trial), and it is the way to its standard view straight above."""
        run = self.cfg.run
        base = self.ctx.initial_angle_deg or self.cfg.viewing.initial_angle_deg
        up = run.second_image_elevation_deg
        if run.second_image_move == "elevation" and base + self.elevation_step_deg + up <= MAX_STEP_UP_ELEVATION_DEG:
            self.elevation_step_deg += up
        else:
            assert self.azimuth_deg is not None  # chosen on entering intercept
            self.azimuth_deg += run.second_image_azimuth_deg

    def _next_marker(self, now: float) -> None:
        """Look at the object from another side to pick up another marker (ambiguity or no pose)."""
        self.markers_tried += 1
        if self.markers_tried >= self.cfg.run.max_viewpoints:
            self.fail(now, f"no marker gave a usable pose from {self.markers_tried} viewpoints")
            return
        assert self.azimuth_deg is not None  # chosen on entering intercept
        self.azimuth_deg += self.cfg.run.next_viewpoint_deg
        self.elevation_step_deg = 0.0
        self.marker_pose = None
        self._enter("intercept", now)
        self._plan_initial(now, "initial1")

    # -- inputs ----------------------------------------------------------------------------------
    def on_frame(self, frame: Frame) -> None:
        """A fixed-camera frame: detect, track, and (re)plan (paper §5.2: ~65 ms per cycle in 1996)."""
        self.on_frames([frame])

    def on_frames(self, frames: Sequence[Frame]) -> None:
        """Fixed-camera frames, oldest first (the ones a busy loop would have missed, then the newest): track each,
        then (re)plan once, at the newest."""
        for frame in frames:
            if self.finished:
                return
            self._track(frame)
        if not self.finished:
            self.tick(frames[-1].t)

    def _track(self, frame: Frame) -> None:
        """Detect the marker in one fixed-camera frame and update the tracker; notice a lost marker."""
        now = frame.t
        cam_cfg = self.ctx.lab.fixed_camera
        thresholds = marker_thresholds(cam_cfg)
        pred_px = self._predicted_px(now) if self.tracker.initialized else None
        if pred_px is not None and not self.ctx.fixed_camera.contains(pred_px, margin=-5):
            self.fail(now, "the object left the fixed camera's field of view")
            return
        if pred_px is not None and self.bridge.bridging(now):  # tracking: seen, or bridged on the prediction
            # the one-step-ahead window (§5.2); centroids only: the fixed camera needs no ellipse
            markers = detect_markers_windowed(frame.image, pred_px, self.cfg.tracking.window_px, refine=False,
                                              thresholds=thresholds)
            if markers:
                markers.sort(key=lambda mk: float(np.hypot(*(np.asarray(mk.centroid) - pred_px))))
        else:
            markers = detect_markers(frame.image, refine=False, thresholds=thresholds)
            if markers and self.last_px is not None:
                markers.sort(key=lambda mk: float(np.hypot(*(np.asarray(mk.centroid) - self.last_px))))
            elif markers:
                markers.sort(key=lambda mk: -mk.area)
        if markers:
            px = np.asarray(markers[0].centroid, dtype=float)
        else:  # a marker seen edge-on is no ellipse, but its red pixels still locate the object (§5.2)
            px = red_blob_centroid(frame.image, pred_px if pred_px is not None else self.last_px,
                                   thresholds=thresholds)
        xy = None if px is None else self.ctx.fixed_pixel_to_plane(px)
        if xy is None or not self.tracker.update(now, xy):
            self.bridge.missed(now)
        else:
            if (b := self.bridge.seen(now)) is not None:
                self.log("track_bridged", t=now, t_start=b.t_start, t_end=b.t_end, duration_s=b.duration_s,
                         frames=b.frames, stage=self.stage)
            self.track_xy.append((now, float(xy[0]), float(xy[1])))
            self.n_updates += 1
            self.t_last_seen, self.last_px = now, px
            if self.t_first_seen is None:
                self.t_first_seen = now
                self._enter("track", now)
            self.log("track", t=now, x=float(xy[0]), y=float(xy[1]), px=px)
        if self.t_last_seen is not None and self.bridge.expired(now):
            gap = {"gap_s": self.bridge.gap_s(now), "frames": self.bridge.frames}
            if self.stage == "track":  # lost before any plan: start again
                self.log("marker_lost", t=now, **gap)
                self.tracker.reset()
                self.bridge.reset()
                self.t_first_seen = self.t_last_seen = None
                self._enter("wait", now)
            elif not self.coasting:  # later stages coast on the prediction (the object moves predictably)
                self.coasting = True
                self.log("marker_lost", t=now, coasting=True, **gap)
        elif self.t_last_seen == now:
            self.coasting = False

    def _predicted_px(self, now: float):
        if not self.tracker.initialized:
            return self.last_px
        return self.ctx.plane_to_fixed_pixel(self.tracker.predict(now)[0])

    def on_message(self, msg: m.Message, now: float) -> None:
        """A message from the recognizer at ``now`` (s): frame taken, marker pose, identity or ambiguous match; each
        moves the state machine on."""
        if self.finished:
            return
        if self.provisional is not None:
            # replies to an image whose arrival the @DONE has not confirmed yet: held until it does (the robot
            # stays put, no pose or identity is used); the @DONE may have come meanwhile
            self._held_replies.append(msg)
            if self.stage in ("intercept", "initial", "standard") and self.pending is None and self.plan is not None:
                self._at_view(now)
            return
        if isinstance(msg, m.FrameTaken):
            self.t_requested[msg.view_id] = msg.t  # the image's own time
        if isinstance(msg, m.FrameTaken) and msg.view_id == self.pending and self.plan_kind == "initial1":
            self.pending = None  # the exposure has ended: the robot may move
            if not self._go_held(now):
                self._step_for_second_image()
                self._plan_initial(now, "initial2")
        elif isinstance(msg, m.MarkerPose) and msg.view_id == self.pending:
            self.pending = None
            self.log("pose_received", t=now, center_w=msg.center_w, normal_w=msg.normal_w, ambiguous=msg.ambiguous,
                     margin=msg.margin)
            if msg.ambiguous:
                # the two views did not separate the candidates: one more image, further round
                self._step_for_second_image()
                self._plan_initial(now, "initial2")
                return
            self.spare_poses = []
            if not self._use_pose(msg, now) and not self._try_spare(now):
                self._next_marker(now)
        elif isinstance(msg, m.MarkerPose) and msg.view_id == self.pose_view_id and not msg.ambiguous:
            self.spare_poses.append(msg)  # another marker resolved from the same two images
        elif isinstance(msg, m.Identity):
            self.pending = None
            self.identity = msg
            self.log("identity", t=now, object=self.ctx.names[msg.object_id], score=msg.score,
                     candidates=[self.ctx.names[i] for i in msg.candidates])
            self._enter("done", now)
            self._stop_robot(now)
        elif isinstance(msg, m.Ambiguous):
            self.pending = None
            self.log("ambiguous", t=now, candidates=[self.ctx.names[i] for i in msg.candidates])
            if self.views_used >= self.cfg.run.max_views:
                self.fail(now, f"still ambiguous after {self.views_used} standard views")
                return
            if not self._try_spare(now):
                self._next_marker(now)
        elif isinstance(msg, m.Failure):
            self.pending = None
            self.log("recognizer_failure", t=now, code=msg.code, text=msg.text)
            if msg.code in (m.FailureCode.NO_MARKER_FOUND, m.FailureCode.MARKER_LOST, m.FailureCode.NO_MATCH,
                            m.FailureCode.VIEW_MISALIGNED):
                if msg.code == m.FailureCode.VIEW_MISALIGNED:
                    # the aim missed (the table turned during the flight): nothing was matched, so the view does
                    # not count towards run.max_views, which bounds the views an ambiguity may take
                    self.views_used -= 1
                if not self._try_spare(now):
                    self._next_marker(now)
            else:
                self.fail(now, f"recognizer: {msg.text}")

    def tick(self, now: float) -> None:
        """Advance the state machine on the clock: planning, arrivals, time-outs."""
        if self.finished:
            return
        if now > self.deadline:
            self.fail(now, f"no identity within the run's {self.cfg.run.timeout_s:g} s")
            return
        if self.stage == "wait" and self.rest_T is None and not self._asked_rest:
            # learn where the robot stands while nothing else is to be done: the first leg needs no STATUS
            self._asked_rest = True
            st = self.robot.status()
            if not st.moving:
                self.rest_T = np.asarray(st.T_base_flange, dtype=float).copy()
        if self.stage == "track":
            if self.n_updates >= self.cfg.tracking.commit_min_updates and self._ready_to_commit(now):
                self.azimuth_deg = self._choose_azimuth()
                self._enter("intercept", now)
                self._plan_initial(now, "initial1")
            return
        if self.plan is not None and now - self.t_robot_log >= 0.2:  # the commanded path, for the report
            self.t_robot_log = now
            self.log("robot", t=now, p=self._flange_state(now)[0][0], planned=True)
        if self.stage in ("intercept", "initial", "standard") and self.pending is None and self.plan is not None:
            if now < _t_hit(self.plan) + self.plan_shift and self.provisional is None:
                self._replan(now)
                self._hold_second_leg(now)
                return
            self._at_view(now)
            if self.pending is None:
                return
        wait_s = self.cfg.run.recognizer_timeout_s
        if self.pending is not None and now - self.stage_times.started[self.stage] > wait_s:
            self.fail(now, f"the recognizer did not answer within {wait_s:g} s (stage {self.stage})")

    def _at_view(self, now: float) -> None:
        """Once the robot stands at the end of its leg: close the leg and take (or adopt) the view's image."""
        T_flange = self._arrived(now)
        if T_flange is None:
            return
        prov, self.provisional = self.provisional, None
        t = prov[2] if prov is not None else now  # the image's request: at the promised arrival, or now
        p = T_flange[:3, 3]
        self.robot_path.append((t, p.tolist()))
        self.log("robot", t=t, p=p)
        kind = self.plan_kind
        assert kind is not None  # set with the plan
        if self.arm is not None:  # at rest where its segment ended: the configuration it followed there
            seed = self.arm_path.q_end if self.arm_path is not None else self._arm_rest_q()
            res = self.arm.model.ik(T_flange, seed) if seed is not None else None
            self.arm_q = res.q if res is not None and res.ok else seed
            self.arm_path = None
        self._end_leg(T_flange)
        self.plan = None
        if kind == "standard":
            self.views_used += 1
            self._enter("match", t)
        else:
            self._enter("initial", t)
        if prov is None:
            self._request_capture(now, kind, T_flange)  # robot base = world
            return
        # the @DONE confirms the image taken at the promised arrival: its replies are used from now on
        self.pending = prov[1]
        self.log("capture_confirmed", t=now, view_id=prov[1])
        replies, self._held_replies = self._held_replies, []
        for msg in replies:
            self.on_message(msg, now)

    def _discard_provisional(self, now: float, why: str) -> None:
        """Forget the image requested at the promised arrival (no @DONE came): the recognizer goes back to its
        state before it (``Discard``), its replies are dropped, and it does not count as an image."""
        prov, self.provisional = self.provisional, None
        if prov is None:
            return
        self.n_images -= 1
        self.t_requested.pop(prov[1], None)
        self.send(m.Discard(view_id=prov[1]))
        self.log("capture_discarded", t=now, view_id=prov[1], reason=why)
        # an Identity, Ambiguous or Failure names no view: it answers the one pending, the discarded image
        kept = [msg for msg in self._held_replies
                if isinstance(msg, m.FrameTaken | m.MarkerPose) and msg.view_id != prov[1]]
        self._held_replies = []
        for msg in kept:
            self.on_message(msg, now)

    # -- result ------------------------------------------------------------------------------------
    def result(self, now: float) -> dict:
        """The run's result: identity, time to identity and its lower bounds (s), views, stage durations, failure."""
        if self.stage_times.current is not None and self.stage_times.current not in ("done", "failed"):
            self.stage_times.enter(self.stage_times.current, now)
        ident = self.identity
        t_id = (self.stage_times.started["done"] - self.t_start) if ident is not None else None
        lower = lower_q = parts = None
        if t_id is not None and self.t_first_seen is not None:
            parts = self.bound()
            lower = parts["bound_s"]
            # the paper's quintic over the same legs, from first sight, with the same frames: the profile's own cost
            lower_q = parts["first_sight_s"] + self.min_quintic_s + parts["frames_s"]
        return {
            "identity": self.ctx.names[ident.object_id] if ident is not None else None,
            "score": ident.score if ident is not None else None,
            "candidates": [self.ctx.names[i] for i in ident.candidates] if ident is not None else [],
            "time_to_identity_s": t_id,
            "lower_bound_s": lower,
            "lower_bound_quintic_s": lower_q,
            "ratio_to_bound": (t_id / lower) if lower else None,
            "bound": parts,
            "time_from_first_sight_s": (t_id - (cast(float, self.t_first_seen) - self.t_start))
            if parts and t_id is not None else None,
            "views": self.views_used,
            "stages": {k: round(v, 4) for k, v in self.stage_times.durations.items()},
            "failure": self.failure,
        }


    def bound(self) -> dict:
        """The honest lower bound of this run's time to identity (:mod:`.tti_bound`): first sight, the legs
        flown at the controller's own limits (not the planner's margins or stop-budget cap), the mobile
        camera's frame time per image."""
        rc = self.ctx.lab.robot
        first = (self.t_first_seen - self.t_start) if self.t_first_seen is not None else 0.0
        fps = float(self.ctx.lab.mobile_camera.fps or 0.0)
        qd = {"qd_max": tuple(map(float, self.arm.model.qd_max))} if self.arm is not None else {}
        out = identity_bound(first, self.legs, self.n_images, 1.0 / fps if fps > 0 else 0.0,
                             v_max=float(rc.v_max_mm_s), a_max=float(rc.a_max_mm_s2),
                             w_max=math.radians(float(rc.w_max_deg_s)), **qd)  # each leg carries its own jerk limit
        out["legs"] = [leg.kind for leg in self.legs]
        return out


class ProgramProgress:
    """Pumps the table's G-code program from the run loop and logs its progress to the record.

    One :meth:`pump` per loop iteration sends what fits in GRBL's buffer and reads the replies
    without waiting, so frames, planning and heartbeats go on while a long arc executes (issue
    13). ``table_progress`` events (lines acknowledged / total) are logged at most every
    ``every_s`` seconds and when the program is accepted; a fault raises the driver's error.
    Once GRBL has accepted the whole program the table is still watched (``watch``: status at
    its rate, read without waiting), so a link that drops while it runs the tail is noticed —
    reconnected within ``reconnect_s`` or a typed error."""

    def __init__(self, program, log, every_s: float = 0.5):
        self.program, self.log, self.every_s = program, log, every_s
        self._t_logged = -1e18
        self._logged_acked = -1

    def pump(self, now: float) -> None:
        """Keep the table's program streaming, and log its progress at most every ``every_s`` (s)."""
        prog = self.program
        if prog.active:
            prog.pump(0.0)
        else:
            prog.table.watch()
        if prog.acked != self._logged_acked and (now - self._t_logged >= self.every_s or prog.done):
            self.log("table_progress", t=now, **prog.progress())
            self._t_logged, self._logged_acked = now, prog.acked

