"""``labctl calibrate`` end to end: plan, capture through the devices, compute, check against
ground truth when there is one, and write ``calibration/*.yaml`` (atomically, and only once
everything worked). The captured images are kept in ``calibration/captures/<time>/``.

Also the correspondence-file path (``labctl calibrate points``): parse ``xw yw zw Xf Yf`` lines
and calibrate them with Tsai's method beside OpenCV's ``calibrateCamera``.
"""

from __future__ import annotations

import datetime as _dt
import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import cast

import numpy as np

from ..errors import UserInputError
from ..geometry import CameraModel, look_at, make_T, rpy_willson
from . import store
from .dots import DotError
from .handeye import HandEyeInputError
from .procedure import (
    Captures,
    Devices,
    Motion,
    Plan,
    Prompt,
    StationReach,
    calibrate_fixed,
    calibrate_mobile,
    capture,
    hand_eye_error,
    plan_calibration,
    register_table,
    table_plane_error,
)
from .table import TableRegistrationError
from .target import TARGET_FILE, PlaneTarget, Target, TargetError, load_target, target_yaml
from .tsai import CalibrationInputError, Sensor, calibrate, calibrate_opencv

PLOT_FILE = "residuals.png"
CAPTURES_DIR = "captures"


@dataclass(frozen=True)
class Truth:
    """The simulated lab's ground truth (None on hardware)."""

    fixed_camera: CameraModel
    T_w_c1: np.ndarray
    mobile_camera: CameraModel
    T_f_c2: np.ndarray
    T_w_table: np.ndarray


def load_truth(path: Path | str) -> Truth:
    """Ground truth from a served simulated lab's ``served_truth.json`` (``labctl sim serve
    --lab-out``): ``fixed_camera: {T_w_c, model}``, ``mobile_camera: {T_f_c, model}``,
    ``table_origin_w_mm``, optional ``T_w_b`` (the robot base in W; the calibration's W is B).
    Raises UserInputError naming what is missing."""
    import json

    path = Path(path)
    try:
        d = json.loads(path.read_text(encoding="utf-8"))
        T_b_w = np.linalg.inv(np.asarray(d.get("T_w_b", np.eye(4)), float))
        fixed, mobile = d["fixed_camera"], d["mobile_camera"]
        return Truth(fixed_camera=CameraModel.from_dict(fixed["model"]),
                     T_w_c1=T_b_w @ np.asarray(fixed["T_w_c"], float),
                     mobile_camera=CameraModel.from_dict(mobile["model"]),
                     T_f_c2=np.asarray(mobile["T_f_c"], float),
                     T_w_table=T_b_w @ make_T(None, d["table_origin_w_mm"]))
    except (OSError, ValueError) as exc:
        raise UserInputError(f"cannot read the truth file {path}: {exc}") from None
    except (KeyError, TypeError) as exc:
        raise UserInputError(f"truth file {path}: missing or malformed {exc}") from None


@dataclass(frozen=True)
class Nominal:
    """What the plan starts from: the nominal cameras and poses (a previous calibration where
    there is one, else the driver files), the table's travel and the robot's workspace and limits."""

    fixed_camera: CameraModel
    T_w_c1: np.ndarray | None
    mobile_camera: CameraModel
    X: np.ndarray
    T_w_table: np.ndarray
    travel_mm: tuple[float, float]
    workspace: tuple
    motion: Motion
    sources: dict
    reach: StationReach | None = None  # the robot's arm (None: the workspace box only); set by the caller


def nominal_camera(cfg) -> CameraModel:
    """The nominal Tsai model of a camera from its driver file's ``lens`` (Tsai's sensor data;
    the simulator renders with the same fields as its truth, :mod:`labctl.sim.truth`)."""
    lens = cfg.lens
    return CameraModel(f=lens.f_mm, kappa1=lens.kappa1, sx=lens.sx,
                       cx=lens.cx if lens.cx is not None else (cfg.width - 1) / 2.0,
                       cy=lens.cy if lens.cy is not None else (cfg.height - 1) / 2.0,
                       dx=lens.dx_mm, dy=lens.dy_mm, ncx=lens.ncx, nfx=lens.nfx, width=cfg.width, height=cfg.height)


def _nominal_hand_eye(cfg) -> np.ndarray:
    rx, ry, rz = np.radians(cfg.hand_eye_rpy_deg)
    return make_T(rpy_willson(rx, ry, rz), cfg.hand_eye_mm)


def nominal_for(lab) -> Nominal:
    """Nominal values for planning ``lab``'s calibration (see :class:`Nominal`)."""
    cal = lab.calibration_dir
    src = {}
    fixed = nominal_camera(lab.fixed_camera)
    mobile = nominal_camera(lab.mobile_camera)
    try:
        T_w_table = store.load_table(cal)[0]
        src["table"] = "calibration/table.yaml"
    except store.CalibrationFileError:
        T_w_table = make_T(None, lab.table.origin_w_mm)
        src["table"] = "driver file origin_w_mm"
    try:
        X = store.load_mobile_camera(cal)[1]
        src["hand_eye"] = "calibration/mobile_camera.yaml"
    except store.CalibrationFileError:
        X = _nominal_hand_eye(lab.mobile_camera)
        src["hand_eye"] = "driver file hand_eye_*"
    try:
        T_w_c1 = store.load_fixed_camera(cal)[1]
        src["fixed_pose"] = "calibration/fixed_camera.yaml"
    except store.CalibrationFileError:
        cfg = lab.fixed_camera
        if cfg.eye_w_mm is not None and cfg.target_w_mm is not None:
            T_w_c1 = look_at(cfg.eye_w_mm, cfg.target_w_mm, up=(0.0, 1.0, 0.0))
            src["fixed_pose"] = "driver file eye_w_mm/target_w_mm"
        else:
            T_w_c1, src["fixed_pose"] = None, "unknown (not checked)"
    r = lab.robot
    motion = Motion(v_max_mm_s=r.v_max_mm_s, a_max_mm_s2=r.a_max_mm_s2, w_max_deg_s=r.w_max_deg_s,
                    table_timeout_s=max(30.0, 4 * lab.table.timeout_s),
                    poll_s=min(0.2, r.heartbeat_s) / 2)  # margin: the watchdog counts from request to request
    return Nominal(fixed, T_w_c1, mobile, X, T_w_table, tuple(lab.table.travel_mm),
                   (r.workspace_min_mm, r.workspace_max_mm), motion, src)


def make_plan(target: Target, nominal: Nominal, cameras: str) -> Plan:
    """The calibration plan for ``target`` and ``cameras`` under the lab's nominal geometry (mm, 4×4 poses)."""
    return plan_calibration(target, cameras=cameras, travel_mm=nominal.travel_mm, workspace=nominal.workspace,
                            T_w_table=nominal.T_w_table, nominal_mobile=nominal.mobile_camera, X_nominal=nominal.X,
                            nominal_fixed=nominal.fixed_camera, T_w_c1=nominal.T_w_c1, reach=nominal.reach)


def steps_for(plan: Plan) -> int:
    """Progress-bar length of a run: images taken plus the computing steps."""
    computing = (2 if plan.stations else 0) + (1 if plan.fixed else 0) + 1  # hand-eye, table, Tsai C1, write
    return len(plan.fixed) + len(plan.stations) + len(plan.registration) + computing


def lab_target(cal_dir: Path) -> Target:
    """The lab's ``calibration/target.yaml`` (the default plane target if the file is absent)."""
    path = Path(cal_dir) / TARGET_FILE
    return load_target(path) if path.exists() else PlaneTarget()


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()


def image_keeper(folder: Path) -> Callable[[str, np.ndarray], None]:
    """``keep(name, image)``: write ``folder/name.png`` atomically as each image is taken."""
    import cv2

    from ..fsutil import atomic_write_bytes

    folder = Path(folder)

    def keep(name: str, image: np.ndarray) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        ok, buf = cv2.imencode(".png", np.asarray(image))
        if ok:
            atomic_write_bytes(folder / f"{name}.png", buf.tobytes())

    return keep


def run_lab_calibration(cal_dir: Path, devs: Devices, prompt: Prompt, target: Target, nominal: Nominal, *,
                        cameras: str = "all", ros: bool = False, full: bool = False, truth: Truth | None = None,
                        progress: Callable[[str], None] | None = None, write: bool = True,
                        captures_dir: Path | None = None) -> dict:
    """Plan, capture (through ``devs``), calibrate C1 and/or C2 + hand-eye + table, write the files.

    Nothing is written (but the captured images) unless every requested step succeeded.
    Raises :class:`UserInputError` (exit 2) for a plan that does not fit the lab or images and
    poses that cannot be calibrated, DeviceError (exit 3) for a device fault.
    """
    tick = progress or (lambda _msg: None)
    cal_dir = Path(cal_dir)
    plan = make_plan(target, nominal, cameras)
    if plan.problems:
        raise UserInputError(f"the calibration plan does not fit the lab: {plan.problems[0]}")
    T_w_table_prev = None
    if cameras == "fixed":
        try:
            T_w_table_prev = store.load_table(cal_dir)[0]
        except store.CalibrationFileError:
            raise UserInputError("--camera fixed needs calibration/table.yaml: the table is registered through the "
                                 "robot, run `labctl calibrate` (all) first") from None
    captures_dir = captures_dir or cal_dir / CAPTURES_DIR / _now().replace(":", "")
    cap: Captures = capture(devs, prompt, plan, nominal.motion, keep=image_keeper(captures_dir), progress=tick)
    report: dict = {"cameras": cameras, "target": target.kind, "files": [], "captures": str(captures_dir),
                    "images": len(cap.fixed) + len(cap.stations) + len(cap.registration),
                    "nominal_from": nominal.sources, "robot_moves_recommanded": cap.robot_recovered}
    files: dict[str, str] = {}
    created = _now()
    plot_data: dict[str, np.ndarray] = {}
    try:
        T_w_table = T_w_table_prev
        if cameras in ("mobile", "all"):
            mc = calibrate_mobile(cap, target, nominal.mobile_camera, full=full)
            tick("mobile camera: hand-eye")
            ri = mc.intrinsics_view.result
            # calibrate_mobile sets both
            res = cast(np.ndarray, mc.refined_residuals_px)
            X_tsai_lenz = cast(np.ndarray, mc.T_f_c2_tsai_lenz)
            mobile_stats = {"rms_px": float(np.sqrt(np.mean(np.sum(res**2, axis=1)))),
                            "max_px": float(np.max(np.linalg.norm(res, axis=1))),
                            "method": f"tsai {ri.method} at one station + Tsai-Lenz hand-eye + reprojection refinement",
                            "n_points": int(len(res)), "n_stations": len(mc.T_b_f),
                            "intrinsics_station_rms_px": ri.rms_px, "created": created}
            files[store.MOBILE_FILE] = store.mobile_camera_text(mc.camera, mc.T_f_c2, mobile_stats)
            if ros:
                files["mobile_camera_info.yaml"] = store.ros_camera_info_text(mc.camera, "mobile_camera")
            report["mobile_camera"] = {**mobile_stats, "camera": mc.camera.to_dict(), "T_f_c": mc.T_f_c2,
                                       "skipped_stations": mc.skipped}
            plot_data["mobile camera C2 (all stations)"] = res
            if mc.T_f_c2_opencv is not None:
                report["mobile_camera"]["opencv_vs_tsai_lenz"] = hand_eye_error(mc.T_f_c2_opencv, X_tsai_lenz)
            tab = register_table(cap, target, mc, plan.robot_spacer_mm, plan.robot_table_xy)
            tick("table registration")
            T_w_table = tab.T_w_table
            table_stats = {"rms_mm": tab.rms_mm, "scale": list(tab.scale), "skew_deg": tab.skew_deg,
                           "n_positions": len(tab.residuals_mm), "created": created}
            files[store.TABLE_FILE] = store.table_text(T_w_table, table_stats)
            report["table"] = {**table_stats, "T_w_table": T_w_table}
            if truth is not None:
                err = {"hand_eye": hand_eye_error(mc.T_f_c2, truth.T_f_c2),
                       "hand_eye_tsai_lenz_only": hand_eye_error(X_tsai_lenz, truth.T_f_c2),
                       "f_mm": mc.camera.f - truth.mobile_camera.f,
                       "kappa1": mc.camera.kappa1 - truth.mobile_camera.kappa1}
                if mc.T_f_c2_opencv is not None:
                    err["hand_eye_opencv_tsai"] = hand_eye_error(mc.T_f_c2_opencv, truth.T_f_c2)
                report["mobile_camera"]["error_vs_truth"] = err
                rot, trans = hand_eye_error(T_w_table, truth.T_w_table).values()
                report["table"]["error_vs_truth"] = {"rotation_deg": rot, "origin_mm": trans}
        if cameras in ("fixed", "all"):
            fc = calibrate_fixed(cap, target, nominal.fixed_camera, full=full)
            tick("fixed camera: Tsai calibration")
            r = fc.view.result
            T_w_c1 = T_w_table @ fc.T_table_c1
            fixed_stats = {"rms_px": r.rms_px, "max_px": r.max_px, "method": r.method, "n_points": r.n_points,
                           "n_images": len(cap.fixed), "spacers_mm": sorted({h for h, _, _ in cap.fixed}),
                           "T_table_c": fc.T_table_c1, "created": created}
            files[store.FIXED_FILE] = store.fixed_camera_text(fc.camera, T_w_c1, fixed_stats)
            if ros:
                files["fixed_camera_info.yaml"] = store.ros_camera_info_text(fc.camera, "fixed_camera")
            report["fixed_camera"] = {**fixed_stats, "camera": fc.camera.to_dict(), "T_w_c": T_w_c1}
            plot_data["fixed camera C1"] = r.residuals_px
            if truth is not None:
                z = float(truth.T_w_table[2, 3])
                report["fixed_camera"]["error_vs_truth"] = {
                    "table_plane": table_plane_error(fc.camera, T_w_c1, truth.fixed_camera, truth.T_w_c1, z_w=z),
                    "table_plane_own_frame": table_plane_error(fc.camera, truth.T_w_table @ fc.T_table_c1,
                                                               truth.fixed_camera, truth.T_w_c1, z_w=z),
                    "f_mm": fc.camera.f - truth.fixed_camera.f}
    except (DotError, CalibrationInputError, HandEyeInputError, TableRegistrationError, TargetError) as exc:
        raise UserInputError(f"calibration failed: {exc} (images kept in {captures_dir})") from None
    tick("writing calibration files")
    if write:
        if not (cal_dir / TARGET_FILE).exists():
            files[TARGET_FILE] = target_yaml(target)
        written = store.write_files(cal_dir, files)
        from ..fsutil import atomic_write_bytes

        atomic_write_bytes(cal_dir / PLOT_FILE, residual_plot_png(plot_data))
        report["files"] = [str(p) for p in written] + [str(cal_dir / PLOT_FILE)]
    return report


def plan_report(target: Target, nominal: Nominal, cameras: str) -> dict:
    """``--dry-run``: the plan and its checks; nothing moves."""
    plan = make_plan(target, nominal, cameras)
    return {"cameras": cameras, "target": target.kind, "nominal_from": nominal.sources, **plan.to_dict(),
            "ok": not plan.problems}


def residual_plot_png(residuals: dict[str, np.ndarray]) -> bytes:
    """PNG of each camera's residual vectors (px) as a scatter and a histogram (matplotlib, Agg)."""
    import matplotlib

    matplotlib.use("Agg", force=False)
    from matplotlib.figure import Figure

    n = max(1, len(residuals))
    fig = Figure(figsize=(9, 3.9 * n), dpi=90)
    for i, (name, r) in enumerate(residuals.items()):
        r = np.asarray(r, float)
        ax = fig.add_subplot(n, 2, 2 * i + 1)
        ax.scatter(r[:, 0], r[:, 1], s=6, alpha=0.6)
        lim = max(1e-3, float(np.abs(r).max()) * 1.1)
        ax.set_xlim(-lim, lim)
        ax.set_ylim(-lim, lim)
        ax.set_aspect("equal")
        ax.axhline(0, lw=0.5, c="k")
        ax.axvline(0, lw=0.5, c="k")
        rms = float(np.sqrt(np.mean(np.sum(r**2, axis=1))))
        ax.set_title(f"{name}\nresiduals (px), RMS {rms:.4f}", fontsize=10)
        ax2 = fig.add_subplot(n, 2, 2 * i + 2)
        ax2.hist(np.linalg.norm(r, axis=1), bins=30)
        ax2.set_xlabel("|residual| (px)")
        ax2.set_title(f"{len(r)} points")
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    return buf.getvalue()


# --- correspondence files ---------------------------------------------------------------------------
def parse_points_text(text: str, source: str = "points") -> tuple[np.ndarray, np.ndarray]:
    """Parse lines ``xw yw zw Xf Yf`` (mm, px); ``#`` starts a comment; blank lines are skipped.

    Raises :class:`CalibrationInputError` naming the first bad line.
    """
    rows = []
    for n, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        parts = body.replace(",", " ").split()
        if len(parts) != 5:
            raise CalibrationInputError(f"{source}:{n}: expected 5 columns 'xw yw zw Xf Yf', got {len(parts)}")
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise CalibrationInputError(f"{source}:{n}: not a number in {body!r}") from None
        if not np.all(np.isfinite(vals)):
            raise CalibrationInputError(f"{source}:{n}: NaN or infinite value")
        rows.append(vals)
    if not rows:
        raise CalibrationInputError(f"{source}: no points")
    a = np.array(rows)
    return a[:, :3], a[:, 3:]


def calibrate_points_file(path: Path | str, *, ncx: float, nfx: float, dx: float, dy: float, cx: float, cy: float,
                          full: bool = False, coplanar: bool = False, width: int | None = None,
                          height: int | None = None) -> dict:
    """``labctl calibrate points``: Tsai on a correspondence file, with OpenCV's result beside it.

    Raises :class:`UserInputError` (exit 2) for unreadable files or points that cannot be calibrated.
    """
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserInputError(f"cannot read {path}: {exc}") from None
    if min(ncx, nfx, dx, dy) <= 0 or not np.all(np.isfinite([ncx, nfx, dx, dy, cx, cy])):
        raise UserInputError("--sensor NCX NFX DX DY must be positive numbers and --center finite")
    try:
        P, px = parse_points_text(text, str(path))
        w = int(width or round(nfx))
        h = int(height or max(round(2 * cy), int(np.ceil(px[:, 1].max())) + 1))
        sensor = Sensor(ncx=ncx, nfx=nfx, dx=dx, dy=dy, cx=cx, cy=cy, width=w, height=h)
        res = calibrate(P, px, sensor, coplanar=coplanar, full=full)
    except CalibrationInputError as exc:
        raise UserInputError(str(exc)) from None
    out = res.summary()
    try:
        out["opencv"] = calibrate_opencv(P, px, sensor)
    except Exception as exc:  # noqa: BLE001 - the baseline is advisory; report why it failed
        out["opencv"] = {"error": str(exc).splitlines()[0]}
    out["file"] = str(path)
    return out
