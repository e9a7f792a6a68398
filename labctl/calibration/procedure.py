"""The lab's calibration procedure, one for the simulator and for hardware: fixed camera, mobile
camera + hand-eye, table registration — through the device interfaces only
(:mod:`labctl.drivers.interfaces`: ``Camera.grab``, ``Table.stream``/``status``,
``Robot.segment``/``status``), with a :class:`Prompt` for what a person must do (insert a
spacer). The simulator implements the same prompt with a hook that places the spacer.

World frame W = the robot's base frame B (the robot's reported flange poses are in it). The
table's machine frame ("table") is where the target's dots are known: the target sits on
locating pins on the carriage (:class:`~.target.Layout`), GRBL moves it.

1. **Fixed camera C1** (Tsai 1987 §IV.B, non-coplanar, as the paper, He et al. 1996 §5): the
   target is moved by GRBL to known table positions at one or more spacer heights (two or more
   for a flat target) — Tsai's own procedure of moving a plate to known positions. One Tsai
   calibration over all the dots in the table frame → intrinsics and ``T_c1_table``.
2. **Mobile camera C2 + hand-eye**: with the target held still, the robot visits N stations that
   view it; Tsai at the first station gives the intrinsics, pose-only fits give ``T_c2_t`` at all
   stations, Tsai–Lenz (1989) gives X = ``T_f_c2``, a reprojection refinement over all stations
   fixes the f/Tz coupling and gives the target's pose ``T_b_t``.
3. **Table registration** (He et al. 1996 §5, the object-motion simulator registered to the
   world): the robot follows the target to registration positions (its station shifted by the
   commanded table motion); each view gives the target's pose in B (``T_b_f·X·T_c2_t``), and the
   target origins against the commanded positions fit the table frame ``T_w_table``
   (:func:`.table.fit_table_frame`). Then ``T_w_c1 = T_w_table · T_c1_table⁻¹``.

Dot centroids are corrected for the perspective bias of a circle's centroid, iterating with the
current estimate (:func:`.dots.circle_centroid_bias`). The computation (``calibrate_*``) is
pure: images and poses in, models out; :func:`capture` is the only part that touches devices.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Protocol, cast

import numpy as np

from ..errors import DeviceError
from ..geometry import CameraModel, apply, invert, look_at, make_T, rotation_angle
from ..timebase import Clock
from .dots import DotError, circle_centroid_bias, detect_dots, identify
from .handeye import MIN_AXIS_SPREAD_DEG, axis_spread_deg, pose_error, refine_hand_eye, target_in_base, tsai_lenz
from .table import TableRegistration, fit_table_frame, pixel_to_plane
from .target import PlaneTarget, Target
from .tsai import Sensor, TsaiResult, calibrate, refine_pose

BIAS_ITERATIONS = 2


class Prompt(Protocol):
    """What a person (or, in the simulator, a hook) does during calibration."""

    def place_target(self, spacer_mm: float, index: int, count: int) -> None:
        """Put the target on its locating pins on a ``spacer_mm`` spacer (0: none); return when done."""


@dataclass
class Devices:
    """The opened devices the procedure uses (any may be None when its step is not run) and the
    clock they run on (a :class:`labctl.timebase.Clock`: wall time or the simulator's virtual clock)."""

    # drivers.interfaces' Table, Robot and Camera, or None (Any: calibration does not import drivers)
    table: Any
    robot: Any
    fixed: Any
    mobile: Any
    clock: Clock


@dataclass(frozen=True)
class Motion:
    """Motion policy (from the driver files): robot limits and the settle time before a grab."""

    v_max_mm_s: float = 500.0
    a_max_mm_s2: float = 1500.0
    w_max_deg_s: float = 120.0
    settle_s: float = 0.3
    table_timeout_s: float = 120.0
    robot_timeout_s: float = 60.0
    poll_s: float = 0.2  # status polls while moving; every robot request also feeds its watchdog
    position_tol_mm: float = 0.02
    fresh_frame_s: float = 5.0  # how long to wait for a frame exposed after the motion ended
    robot_tol_mm: float = 0.5  # a move ended this close to its pose (the dialect reports 4 decimals)
    robot_tol_deg: float = 0.05
    robot_retries: int = 5  # re-commands of a move the controller's watchdog cut short (each resumes where it stopped)


# --- plan ---------------------------------------------------------------------------------------
@dataclass
class Plan:
    """Everything the procedure will do, in order, and what is wrong with it (``problems``)."""

    fixed: list[tuple[float, tuple[float, float]]] = field(default_factory=list)  # (spacer mm, table xy)
    robot_spacer_mm: float = 0.0
    robot_table_xy: tuple[float, float] = (0.0, 0.0)
    stations: list[np.ndarray] = field(default_factory=list)  # T_b_f
    registration: list[tuple[tuple[float, float], np.ndarray]] = field(default_factory=list)  # (xy, T_b_f)
    problems: list[str] = field(default_factory=list)

    def to_dict(self) -> dict:
        """JSON-ready summary of the plan; robot poses as flange position (mm) and tilt from straight down (deg)."""
        def pose(T):
            return {"xyz_mm": [round(float(v), 3) for v in T[:3, 3]],
                    "tilt_deg": round(float(np.degrees(np.arccos(np.clip(-T[2, 2], -1, 1)))), 2)}
        return {"fixed": [{"spacer_mm": h, "table_xy_mm": list(xy)} for h, xy in self.fixed],
                "robot": {"spacer_mm": self.robot_spacer_mm, "table_xy_mm": list(self.robot_table_xy),
                          "stations": [pose(T) for T in self.stations]},
                "registration": [{"table_xy_mm": list(xy), "flange": pose(T)} for xy, T in self.registration],
                "problems": list(self.problems)}


def _aim(target: Target) -> np.ndarray:
    return np.array([0.0, 0.0, 0.5 * target.height_mm])


class StationReach(Protocol):
    """Can the robot's arm fly straight moves through ``poses`` (flange ``T_b_f``, 4×4 mm) in order, from the
    configuration it starts in? (:class:`labctl.planning.arm_plan.StationReach` for a lab whose robot is an arm.)"""

    def __call__(self, poses: Sequence[np.ndarray]) -> bool:
        """True if every pose and every move between them is within the arm's reach, limits and margins."""
        ...


def plan_stations(target: Target, T_w_t: np.ndarray, nominal: CameraModel, X_nominal: np.ndarray, *,
                  distance_mm: float = 1000.0, workspace=None, n: int = 10,
                  margin_px: float = 12.0, reach: StationReach | None = None) -> list[np.ndarray]:
    """Flange poses ``T_b_f`` looking at the target (at ``T_w_t``) from ``distance_mm``: tilts up
    to ~30° at golden-angle azimuths with varied roll (Tsai–Lenz need rotations about different
    axes), each keeping every dot in view of the nominal camera and the flange inside
    ``workspace`` ((min, max) corners, mm). Distances vary by ±10 % so that the robot's known
    motions along the line of sight separate f from the distance (Tsai 1987 §V's f/Tz coupling). With
    ``reach`` (an arm), a station is kept only if the arm flies to it from the stations before it."""
    aim = apply(T_w_t, _aim(target))
    solid = target.solid().transformed(T_w_t)
    out: list[np.ndarray] = []
    for i in range(96):
        tilt = (0.0, 24.0, 16.0, 30.0, 20.0, 28.0, 12.0, 26.0)[i % 8]
        az = np.radians(37.0 + 137.508 * i)
        el = np.radians(tilt)
        d = distance_mm * (1.0, 1.1, 0.92, 1.05, 0.96, 1.12, 0.9, 1.0, 1.08)[i % 9]
        eye = aim + d * np.array([np.sin(el) * np.cos(az), np.sin(el) * np.sin(az), np.cos(el)])
        roll = np.radians(((i * 29) % 40) - 20.0)
        up = np.array([np.sin(roll), np.cos(roll), 0.0])
        T_w_c = look_at(eye, aim, up=up)
        if not _sees(nominal, T_w_c, solid.dots, margin_px):
            continue
        T_b_f = T_w_c @ invert(X_nominal)
        if workspace is not None and not _inside(T_b_f, workspace):
            continue
        if reach is not None and not reach([*out, T_b_f]):
            continue
        out.append(T_b_f)
        if len(out) == n:
            break
    return out


def _sees(cam: CameraModel, T_w_c: np.ndarray, points_w: np.ndarray, margin_px: float) -> bool:
    pc = apply(invert(T_w_c), points_w)
    return bool(np.all(pc[:, 2] > 0) and np.all(cam.contains(cam.project(pc), margin=margin_px)))


def _inside(T_b_f: np.ndarray, workspace) -> bool:
    lo, hi = (np.asarray(w, float) for w in workspace)
    return bool(np.all(T_b_f[:3, 3] >= lo) and np.all(T_b_f[:3, 3] <= hi))


def plan_calibration(target: Target, *, cameras: str, travel_mm, workspace, T_w_table: np.ndarray,
                     nominal_mobile: CameraModel, X_nominal: np.ndarray,
                     nominal_fixed: CameraModel | None = None, T_w_c1: np.ndarray | None = None,
                     reach: StationReach | None = None) -> Plan:
    """The poses of a calibration run and their checks against the table's travel, the robot's
    workspace and the nominal cameras' views. ``T_w_table``, ``X_nominal`` and ``T_w_c1`` are
    nominal (a previous calibration or the driver files); without ``T_w_c1`` the fixed camera's
    view is not checked. ``reach``: the robot's arm, which must fly the stations and then the
    registration poses in order (None: the workspace box only). Pure: nothing moves."""
    plan = Plan()
    travel = np.asarray(travel_mm, float)
    solid = target.solid()

    def on_table(xy, what):
        if not (np.all(np.asarray(xy) >= 0) and np.all(np.asarray(xy) <= travel[:2])):
            plan.problems.append(f"{what}: table position {tuple(xy)} is outside the travel 0..{travel[0]:g} × "
                                 f"0..{travel[1]:g} mm")
            return False
        return True

    if cameras in ("fixed", "all"):
        for h in target.spacers_mm:
            for xy in target.fixed_positions_mm:
                plan.fixed.append((float(h), (float(xy[0]), float(xy[1]))))
                on_table(xy, "fixed camera")
                if nominal_fixed is not None and T_w_c1 is not None:
                    pts = apply(T_w_table @ target.T_table_t(xy, h), solid.dots)
                    if not _sees(nominal_fixed, T_w_c1, pts, 4.0):
                        plan.problems.append(f"fixed camera: the target at table {tuple(xy)} on {h:g} mm is not "
                                             "wholly in view")
    if cameras in ("mobile", "all"):
        h = float(target.spacers_mm[0])
        xy0 = cast("tuple[float, float]", tuple(float(v) for v in target.robot_position_mm))  # (x, y)
        plan.robot_spacer_mm, plan.robot_table_xy = h, xy0
        on_table(xy0, "robot stations")
        T_w_t = T_w_table @ target.T_table_t(xy0, h)
        plan.stations = plan_stations(target, T_w_t, nominal_mobile, X_nominal, distance_mm=target.robot_distance_mm,
                                      workspace=workspace, n=target.robot_stations, reach=reach)
        if len(plan.stations) < 3:
            plan.problems.append(f"only {len(plan.stations)} robot stations see the whole target inside the robot's "
                                 "workspace; need at least 3 (move the target or change robot_distance_mm)")
        else:
            rel = [invert(b)[:3, :3] @ a[:3, :3] for i, a in enumerate(plan.stations) for b in plan.stations[i + 1:]]
            spread = axis_spread_deg(rel)
            if spread < MIN_AXIS_SPREAD_DEG:
                plan.problems.append(f"degenerate robot stations: all rotations are about one axis (axes spread "
                                     f"{spread:.1f}°, need ≥ {MIN_AXIS_SPREAD_DEG:.0f}°), X is not observable")
        if plan.stations:
            T0 = plan.stations[0]
            for xy in target.registration_positions_mm:
                xy = (float(xy[0]), float(xy[1]))
                shift = T_w_table[:3, :3] @ np.array([xy[0] - xy0[0], xy[1] - xy0[1], 0.0])
                T = make_T(T0[:3, :3], T0[:3, 3] + shift)
                plan.registration.append((xy, T))
                on_table(xy, "table registration")
                if not _inside(T, workspace):
                    plan.problems.append(f"table registration: flange {np.round(T[:3, 3], 1).tolist()} for table "
                                         f"{xy} is outside the robot's workspace")
            if reach is not None and not reach([*plan.stations, *(T for _, T in plan.registration)]):
                plan.problems.append("table registration: the robot's arm cannot fly the registration poses after "
                                     "its stations (move the target or change robot_distance_mm)")
    return plan


# --- capture (the only part that touches devices) -----------------------------------------------
@dataclass
class Captures:
    """Images taken by the procedure, in plan order.

    ``fixed``: (spacer mm, table xy mm, C1 image); ``stations``: (C2 image, reported ``T_b_f``);
    ``registration``: (table xy mm, C1 image, C2 image); ``robot_recovered``: moves re-commanded after a
    watchdog stop.
    """

    fixed: list[tuple[float, tuple[float, float], np.ndarray]] = field(default_factory=list)
    stations: list[tuple[np.ndarray, np.ndarray]] = field(default_factory=list)  # (image, reported T_b_f)
    registration: list[tuple[tuple[float, float], np.ndarray, np.ndarray]] = field(default_factory=list)
    robot_recovered: list[str] = field(default_factory=list)  # moves re-commanded after a watchdog stop


def move_table(devs: Devices, xy, motion: Motion) -> None:
    """Rapid to machine coordinates ``xy`` (``G53``) and wait until GRBL reports Idle there."""
    x, y = float(xy[0]), float(xy[1])
    devs.table.stream(["G21G90", f"G53G0X{x:.3f}Y{y:.3f}"])
    deadline = devs.clock.now() + motion.table_timeout_s
    while True:
        st = devs.table.status()
        if st.state.startswith("Alarm") or st.state.startswith("Door"):
            raise DeviceError(f"table: {st.state} while moving to {x:g}, {y:g}")
        if st.state == "Idle" and abs(st.position[0] - x) <= motion.position_tol_mm \
                and abs(st.position[1] - y) <= motion.position_tol_mm:
            return
        if devs.clock.now() > deadline:
            raise DeviceError(f"table: not at {x:g}, {y:g} after {motion.table_timeout_s:g} s "
                              f"(state {st.state}, at {st.position[0]:.3f}, {st.position[1]:.3f})")
        if devs.robot is not None:
            devs.robot.heartbeat()
        devs.clock.sleep(motion.poll_s)


def segment_duration(T_from: np.ndarray, T_to: np.ndarray, motion: Motion) -> float:
    """A quintic segment's duration that keeps its peak speed (1.875·d/T), acceleration
    (5.77·d/T²) and angular speed within half the robot's limits (s)."""
    d = float(np.linalg.norm(T_to[:3, 3] - T_from[:3, 3]))
    a = float(np.degrees(rotation_angle(T_from[:3, :3].T @ T_to[:3, :3])))
    return max(0.5, 2 * 1.875 * d / motion.v_max_mm_s, np.sqrt(2 * 5.774 * d / motion.a_max_mm_s2),
               2 * 1.875 * a / motion.w_max_deg_s)


class _Robot:
    """Moves the robot one segment at a time through the Robot interface (heartbeats by polling).

    A move ends only when the controller reports the segment done *at the commanded pose*. If it
    stopped short — its watchdog brought it to rest because a request came late, as happens on
    an overloaded host — the latched fault is cleared (``Robot.clear``) and the move is commanded
    again from where it stopped, up to ``motion.robot_retries`` times per move (counted in
    ``recovered``); otherwise it is a DeviceError. The target does not move meanwhile, so an
    image is only ever taken at a planned pose."""

    def __init__(self, devs: Devices, motion: Motion):
        self.devs, self.motion, self.seg = devs, motion, 0
        self.recovered: list[str] = []

    def move(self, T_b_f: np.ndarray) -> np.ndarray:
        """Move to ``T_b_f`` and wait until the controller reports it done there; returns the reported pose."""
        robot = self.devs.robot
        for attempt in range(self.motion.robot_retries + 1):
            try:
                T_rep = self._move_once(T_b_f)
                why = _pose_miss(T_rep, T_b_f, self.motion)
            except DeviceError as exc:
                if getattr(exc, "code", None) != 40:  # the dialect's E40: stopped by the watchdog, needs CLEAR
                    raise
                why = str(exc)
            if why is None:
                return T_rep
            if attempt == self.motion.robot_retries:
                raise DeviceError(f"robot: segment {self.seg} did not reach its pose ({why})")
            robot.clear()
            self.recovered.append(f"segment {self.seg}: {why}")
        raise AssertionError("unreachable")

    def _move_once(self, T_b_f: np.ndarray) -> np.ndarray:
        robot, devs = self.devs.robot, self.devs
        here = robot.status().T_base_flange
        self.seg += 1
        robot.segment(T_b_f, segment_duration(here, T_b_f, self.motion), self.seg)
        deadline = devs.clock.now() + self.motion.robot_timeout_s
        asked = devs.clock.now()
        while True:
            # requests start poll_s apart (not poll_s after the last reply): a status exchange takes
            # ~0.1 s at 9600 bps, and the controller's watchdog counts from one request to the next
            devs.clock.sleep(max(0.0, self.motion.poll_s - (devs.clock.now() - asked)))
            asked = devs.clock.now()
            st = robot.status()  # every request feeds the controller's watchdog
            if not st.moving and st.segment_id == self.seg:
                return st.T_base_flange
            if devs.clock.now() > deadline:
                raise DeviceError(f"robot: segment {self.seg} not done after {self.motion.robot_timeout_s:g} s")


def _pose_miss(T_rep: np.ndarray, T_cmd: np.ndarray, motion: Motion) -> str | None:
    """Why the reported pose is not the commanded one (None: it is, within ``motion``'s tolerances)."""
    d = float(np.linalg.norm(T_rep[:3, 3] - T_cmd[:3, 3]))
    a = float(np.degrees(rotation_angle(T_cmd[:3, :3].T @ T_rep[:3, :3])))
    if d <= motion.robot_tol_mm and a <= motion.robot_tol_deg:
        return None
    return f"stopped {d:.2f} mm / {a:.3f}° from it"


def _grab(devs: Devices, camera, motion: Motion) -> np.ndarray:
    """An image exposed after the devices came to rest: wait ``settle_s``, then grab until a frame's
    timestamp (the camera's exposure time on the devices' clock) is no older than the moment the
    motion ended — a network camera's pipeline may still hold frames exposed during the motion."""
    at_rest = devs.clock.now()
    devs.clock.sleep(motion.settle_s)
    deadline = devs.clock.now() + motion.fresh_frame_s
    while True:
        if devs.robot is not None:
            devs.robot.heartbeat()
        frame = camera.grab()
        if frame.t >= at_rest:
            return np.asarray(frame.image)
        if devs.clock.now() > deadline:
            raise DeviceError(f"camera: no frame exposed after the motion ended within {motion.fresh_frame_s:g} s "
                              f"(newest exposed {at_rest - frame.t:.3f} s before); check its clock/latency_s")


def capture(devs: Devices, prompt: Prompt, plan: Plan, motion: Motion = Motion(), *,
            keep: Callable[[str, np.ndarray], None] | None = None,
            progress: Callable[[str], None] | None = None) -> Captures:
    """Run ``plan`` on the devices: for each spacer (prompted), the fixed camera's images at its
    table positions; with the first spacer also the robot's stations and registration views.
    ``keep(name, image)`` stores each image as it is taken. The robot returns to where it
    started before the fixed camera looks again. Raises DeviceError on a device fault."""
    tick = progress or (lambda _m: None)
    store = keep or (lambda _n, _i: None)
    cap = Captures()
    st = devs.table.status()
    if st.state.startswith("Alarm"):  # never unlock here: after an alarm the position is unknown
        raise DeviceError("table: in Alarm (position unknown): home it (`labctl table home`) before calibrating")
    spacers = sorted({h for h, _ in plan.fixed} | ({plan.robot_spacer_mm} if plan.stations else set()),
                     key=lambda h: (h != plan.robot_spacer_mm, h))
    robot = _Robot(devs, motion) if plan.stations else None
    for k, h in enumerate(spacers):
        prompt.place_target(h, k, len(spacers))
        for hh, xy in plan.fixed:
            if hh != h:
                continue
            move_table(devs, xy, motion)
            img = _grab(devs, devs.fixed, motion)
            cap.fixed.append((h, xy, img))
            store(f"fixed_h{h:g}_x{xy[0]:g}_y{xy[1]:g}", img)
            tick(f"fixed camera: spacer {h:g} mm, table {xy[0]:g}, {xy[1]:g}")
        if robot is not None and h == plan.robot_spacer_mm:
            start = devs.robot.status().T_base_flange
            move_table(devs, plan.robot_table_xy, motion)
            for i, T in enumerate(plan.stations):
                T_rep = robot.move(T)
                img = _grab(devs, devs.mobile, motion)
                cap.stations.append((img, T_rep))
                store(f"mobile_station{i + 1:02d}", img)
                tick(f"mobile camera: station {i + 1}/{len(plan.stations)}")
            for xy, T in plan.registration:
                move_table(devs, xy, motion)
                T_rep = robot.move(T)
                img = _grab(devs, devs.mobile, motion)
                cap.registration.append((xy, img, T_rep))
                store(f"table_x{xy[0]:g}_y{xy[1]:g}", img)
                tick(f"table registration: {xy[0]:g}, {xy[1]:g}")
            robot.move(start)
    if robot is not None:
        cap.robot_recovered = list(robot.recovered)
    return cap


# --- computation ----------------------------------------------------------------------------------
@dataclass
class TargetView:
    """One calibrated view of the target: Tsai result (world = the frame of the placements)."""

    result: TsaiResult
    model_idx: np.ndarray
    pixels: np.ndarray  # bias-corrected centroids (N, 2)
    raw_pixels: np.ndarray


def observe_target(image: np.ndarray, target: Target, nominal: CameraModel):
    """Detect and identify the target's dots: (model indices, centroids (N, 2), initial T_c_t)."""
    solid = target.solid()
    blobs = detect_dots(image)
    mi, bi, T0 = identify(blobs, solid.dots, target.fiducial_indices, nominal)
    return mi, blobs.centers[bi], T0


def calibrate_on_target(images: list[np.ndarray], placements: list[np.ndarray], target: Target,
                        nominal: CameraModel, *, full: bool = False, coplanar: bool = False,
                        intrinsics: CameraModel | None = None) -> TargetView:
    """One Tsai calibration (Tsai 1987 §IV) from the target's dots in one or more images taken by
    the same, unmoved camera, the target at ``placements[k]`` (``T_w_t``, W any frame) in image
    k; with ``intrinsics`` only the pose is fitted. The dots' centroid bias is removed
    iteratively with the current estimate. Returns the view; its result's ``T_c_w`` maps W into
    the camera."""
    solid = target.solid()
    obs = [observe_target(img, target, nominal) for img in images]
    P_w = np.vstack([apply(T, solid.dots[mi]) for (mi, _, _), T in zip(obs, placements)])
    n_w = np.vstack([solid.normals[mi] @ T[:3, :3].T for (mi, _, _), T in zip(obs, placements)])
    radii = np.concatenate([solid.radii[mi] for mi, _, _ in obs])
    raw = np.vstack([px for _, px, _ in obs])
    px = raw.copy()
    res = None
    for _ in range(BIAS_ITERATIONS + 1):
        if intrinsics is None:
            res = calibrate(P_w, px, Sensor.of(nominal), full=full, coplanar=coplanar)
        else:
            start = res.T_c_w if res is not None else obs[0][2] @ invert(placements[0])
            res = refine_pose(intrinsics, start, P_w, px)
        px = raw - circle_centroid_bias(res.camera, res.T_c_w, P_w, n_w, radii)
    res = cast(TsaiResult, res)  # the loop ran at least once
    res = TsaiResult(camera=res.camera, T_c_w=res.T_c_w, method=res.method,
                     residuals_px=res.camera.project_world(res.T_c_w, P_w) - px)
    return TargetView(result=res, model_idx=np.concatenate([mi for mi, _, _ in obs]), pixels=px, raw_pixels=raw)


def _tsai_frame_shift(target: Target) -> np.ndarray:
    """Tsai's RAC needs the world origin away from the camera's y axis (Tsai 1987 §IV.B, Ty ≠ 0):
    a single view is calibrated in a frame s whose origin lies beyond a corner of the target.
    Returns ``T_s_t``."""
    w, length = target.footprint_mm
    return make_T(None, [w, length, 0.0])


def calibrate_single_view(image: np.ndarray, target: Target, nominal: CameraModel, *, full: bool = False,
                          intrinsics: CameraModel | None = None) -> tuple[TargetView, np.ndarray]:
    """:func:`calibrate_on_target` on one image in the target's own frame; returns (view, T_c_t).
    A flat target is calibrated with Tsai's coplanar method (§IV.A, sx held)."""
    T_s_t = _tsai_frame_shift(target)
    view = calibrate_on_target([image], [T_s_t], target, nominal, full=full, intrinsics=intrinsics,
                               coplanar=isinstance(target, PlaneTarget))
    return view, view.result.T_c_w @ T_s_t


@dataclass
class FixedCalibration:
    """Fixed camera C1: Tsai model, ``T_table_c1`` (C1 → table machine frame, mm) and the target fit."""

    camera: CameraModel
    T_table_c1: np.ndarray  # C1 in the table's machine frame
    view: TargetView


def calibrate_fixed(cap: Captures, target: Target, nominal: CameraModel, *, full: bool = False) -> FixedCalibration:
    """C1 from the target at every (spacer, table position): one Tsai calibration over all the dots
    in the table frame (Tsai 1987 §IV.B; the spacers make a flat target non-coplanar)."""
    images = [img for _, _, img in cap.fixed]
    placements = [target.T_table_t(xy, h) for h, xy, _ in cap.fixed]
    view = calibrate_on_target(images, placements, target, nominal, full=full)
    return FixedCalibration(camera=view.result.camera, T_table_c1=invert(view.result.T_c_w), view=view)


@dataclass
class MobileCalibration:
    """Mobile camera C2: Tsai model and hand-eye ``T_f_c2`` (C2 → flange F, mm).

    ``T_b_f``/``T_c_t`` are the used stations' flange poses in the robot base B and target poses in C2;
    ``T_b_t`` the target in B; the Tsai–Lenz and OpenCV hand-eye solutions are kept for comparison;
    ``skipped`` lists the stations left out.
    """

    camera: CameraModel
    T_f_c2: np.ndarray
    intrinsics_view: TargetView
    station_views: list[TargetView]
    T_b_f: list[np.ndarray]
    T_c_t: list[np.ndarray]
    T_b_t: np.ndarray  # the target's pose in B, from the robot's stations
    T_f_c2_tsai_lenz: np.ndarray | None = None  # before the reprojection refinement
    T_f_c2_opencv: np.ndarray | None = None
    refined_residuals_px: np.ndarray | None = None
    skipped: list[int] = field(default_factory=list)


def calibrate_mobile(cap: Captures, target: Target, nominal: CameraModel, *, full: bool = False) -> MobileCalibration:
    """Intrinsics by Tsai at the first station, target poses at all, X by Tsai–Lenz, then the
    reprojection refinement over all stations (X, T_b_t, f, κ1, sx)."""
    images = [img for img, _ in cap.stations]
    flanges = [np.asarray(T, float) for _, T in cap.stations]
    intr, _ = calibrate_single_view(images[_intrinsics_station(images, target, nominal)], target, nominal, full=full)
    cam = intr.result.camera
    views, T_c_t, used, skipped = [], [], [], []
    for k, img in enumerate(images):
        try:
            view, T = calibrate_single_view(img, target, nominal, intrinsics=cam)
        except DotError:
            skipped.append(k)
            continue
        views.append(view)
        T_c_t.append(T)
        used.append(flanges[k])
    X_tl = tsai_lenz(used, T_c_t)
    X_cv = _opencv_hand_eye(used, T_c_t)
    solid = target.solid()
    T_b_t0 = target_in_base(used, T_c_t, X_tl)
    cam, X, T_b_t, res = refine_hand_eye(cam, X_tl, T_b_t0, used, [solid.dots[v.model_idx] for v in views],
                                         [v.pixels for v in views])
    return MobileCalibration(camera=cam, T_f_c2=X, intrinsics_view=intr, station_views=views, T_b_f=used,
                             T_c_t=T_c_t, T_b_t=T_b_t, T_f_c2_tsai_lenz=X_tl, T_f_c2_opencv=X_cv,
                             refined_residuals_px=res, skipped=skipped)


def _intrinsics_station(images: list[np.ndarray], target: Target, nominal: CameraModel) -> int:
    """The station whose single view calibrates the intrinsics: the first for a 3D target; for a
    flat one the view most oblique to it — Tsai's coplanar method cannot separate f from the
    distance when the target plane is parallel to the image plane (Tsai 1987 §IV.A)."""
    if not isinstance(target, PlaneTarget):
        return 0
    best, best_tilt = 0, -1.0
    for k, img in enumerate(images):
        try:
            _, _, T_c_t = observe_target(img, target, nominal)
        except DotError:
            continue
        tilt = float(np.arccos(np.clip(abs(T_c_t[2, 2]), 0.0, 1.0)))
        if tilt > best_tilt:
            best, best_tilt = k, tilt
    return best


def _opencv_hand_eye(T_b_f, T_c_t) -> np.ndarray | None:
    """cv2.calibrateHandEye (Tsai method) on the same data, as a cross-check (OpenCV 4.x only)."""
    try:
        import cv2

        R, t = cv2.calibrateHandEye([T[:3, :3] for T in T_b_f], [T[:3, 3] for T in T_b_f],
                                    [T[:3, :3] for T in T_c_t], [T[:3, 3] for T in T_c_t],
                                    method=cv2.CALIB_HAND_EYE_TSAI)
    except (AttributeError, ImportError):
        return None
    return make_T(R, np.ravel(t))


def register_table(cap: Captures, target: Target, mc: MobileCalibration, spacer_mm: float,
                   robot_table_xy) -> TableRegistration:
    """The table frame in W (= B) from the target's poses in B at commanded table positions: the
    pose from the hand-eye refinement at the stations' position, and at every registration view
    ``T_b_f·X·T_c2_t`` (pose fitted with C2's calibrated intrinsics). The target origins
    against the commanded positions fit ``m = o + A·p`` (:func:`.table.fit_table_frame`)."""
    xy = [tuple(robot_table_xy)]
    origins = [mc.T_b_t[:3, 3]]
    for p, img, T_b_f in cap.registration:
        if tuple(p) == tuple(robot_table_xy):
            continue  # the hand-eye refinement's estimate of this position is the better one
        _, T_c_t = calibrate_single_view(img, target, mc.camera, intrinsics=mc.camera)
        xy.append(tuple(p))
        origins.append((np.asarray(T_b_f, float) @ mc.T_f_c2 @ T_c_t)[:3, 3])
    mount = target.mount_on_table
    return fit_table_frame(np.array(xy), np.array(origins), (mount[0], mount[1]), marker_height_mm=spacer_mm)


# --- errors against ground truth (simulated lab) ---------------------------------------------------
def table_plane_error(cam: CameraModel, T_w_c: np.ndarray, cam_true: CameraModel, T_w_c_true: np.ndarray,
                      step_px: int = 16, z_w: float = 0.0) -> dict:
    """World-point error on the table plane z = ``z_w``: each pixel of a grid over the image is
    back-projected with the truth and with the estimate; returns max/rms error (mm), the field
    of view (mm, the true footprint's larger extent) and the max error as % of it."""
    u, v = np.meshgrid(np.arange(0, cam_true.width, step_px, dtype=float),
                       np.arange(0, cam_true.height, step_px, dtype=float))
    px = np.stack([u.ravel(), v.ravel()], axis=-1)
    pt = pixel_to_plane(cam_true, T_w_c_true, px, z_w)
    pe = pixel_to_plane(cam, T_w_c, px, z_w)
    e = np.linalg.norm(pe - pt, axis=1)
    fov = max(float(np.ptp(pt[:, 0])), float(np.ptp(pt[:, 1])))
    return {"max_mm": float(e.max()), "rms_mm": float(np.sqrt(np.mean(e**2))), "fov_mm": fov,
            "max_percent_of_fov": float(100.0 * e.max() / fov)}


def hand_eye_error(X: np.ndarray, X_true: np.ndarray) -> dict:
    """``{rotation_deg, translation_mm}`` between an estimated hand-eye pose ``X`` and ``X_true``."""
    rot, trans = pose_error(X, X_true)
    return {"rotation_deg": rot, "translation_mm": trans}
