"""``labctl calibrate`` end to end: run the procedure on a rig, check against ground truth when
there is one, and write ``calibration/*.yaml`` (atomically, and only once everything worked).

Also the correspondence-file path (``labctl calibrate points``): parse ``xw yw zw Xf Yf`` lines
and calibrate them with Tsai's method beside OpenCV's ``calibrateCamera``.
"""

from __future__ import annotations

import datetime as _dt
import io
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..errors import UserInputError
from ..geometry import CameraModel
from . import store
from .dots import DotError
from .handeye import HandEyeInputError
from .procedure import (
    Rig,
    calibrate_fixed,
    calibrate_mobile,
    hand_eye_error,
    plan_stations,
    register_table,
    table_plane_error,
)
from .table import TableRegistrationError
from .target import TARGET_FILE, RoofTarget, TargetError, load_target, target_yaml
from .tsai import CalibrationInputError, Sensor, calibrate, calibrate_opencv

PLOT_FILE = "residuals.png"


@dataclass(frozen=True)
class Truth:
    """The simulated lab's ground truth (None on hardware)."""

    fixed_camera: CameraModel
    T_w_c1: np.ndarray
    mobile_camera: CameraModel
    T_f_c2: np.ndarray
    T_w_table: np.ndarray


def steps_for(cameras: str, target: RoofTarget, n_stations: int) -> int:
    """Progress-bar length of a run: images taken plus the computing steps."""
    n = 0
    if cameras in ("fixed", "all"):
        n += len(target.placements) + len(target.table_positions_mm) + 1
    if cameras in ("mobile", "all"):
        n += n_stations + 1
    return n + 1


def lab_target(cal_dir: Path) -> RoofTarget:
    """The lab's target: ``calibration/target.yaml`` (the default target if the file is absent)."""
    path = Path(cal_dir) / TARGET_FILE
    return load_target(path) if path.exists() else RoofTarget()


def _now() -> str:
    return _dt.datetime.now(_dt.UTC).replace(microsecond=0).isoformat()


def run_lab_calibration(cal_dir: Path, rig: Rig, target: RoofTarget, *, nominal_fixed: CameraModel,
                        nominal_mobile: CameraModel, X_nominal: np.ndarray, robot_workspace=None,
                        cameras: str = "all", ros: bool = False, full: bool = False, truth: Truth | None = None,
                        progress: Callable[[str], None] | None = None, write: bool = True) -> dict:
    """Calibrate C1 (+ table) and/or C2 (+ hand-eye) on ``rig``; write the files; return a report.

    Nothing is written unless every requested step succeeded. Raises :class:`UserInputError`
    (exit 2) when the images or poses cannot be calibrated.
    """
    tick = progress or (lambda _msg: None)
    report: dict = {"cameras": cameras, "files": []}
    files: dict[str, str] = {}
    created = _now()
    plot_data = {}
    try:
        if cameras in ("fixed", "all"):
            fc = calibrate_fixed(rig, target, nominal_fixed, full=full, progress=tick)
            r = fc.view.result
            tick("fixed camera: Tsai calibration")
            tab = register_table(rig, target, fc.camera, fc.T_w_c1, progress=tick)
            fixed_stats = {"rms_px": r.rms_px, "max_px": r.max_px, "method": r.method, "n_points": r.n_points,
                           "n_images": len(target.placements), "created": created}
            table_stats = {"rms_mm": tab.rms_mm, "scale": list(tab.scale), "skew_deg": tab.skew_deg,
                           "n_positions": len(target.table_positions_mm), "created": created}
            files[store.FIXED_FILE] = store.fixed_camera_text(fc.camera, fc.T_w_c1, fixed_stats)
            files[store.TABLE_FILE] = store.table_text(tab.T_w_table, table_stats)
            if ros:
                files["fixed_camera_info.yaml"] = store.ros_camera_info_text(fc.camera, "fixed_camera")
            report["fixed_camera"] = {**fixed_stats, "camera": fc.camera.to_dict(), "T_w_c": fc.T_w_c1}
            report["table"] = {**table_stats, "T_w_table": tab.T_w_table}
            plot_data["fixed camera C1"] = r.residuals_px
            if truth is not None:
                report["fixed_camera"]["error_vs_truth"] = {
                    "table_plane": table_plane_error(fc.camera, fc.T_w_c1, truth.fixed_camera, truth.T_w_c1),
                    "f_mm": fc.camera.f - truth.fixed_camera.f}
                rot, trans = hand_eye_error(tab.T_w_table, truth.T_w_table).values()
                report["table"]["error_vs_truth"] = {"rotation_deg": rot, "origin_mm": trans}
        if cameras in ("mobile", "all"):
            stations = plan_stations(target, nominal_mobile, X_nominal, workspace=robot_workspace)
            if len(stations) < 3:
                raise UserInputError(f"only {len(stations)} robot stations see the whole target inside the robot's "
                                     "workspace; need at least 3 (move the target or change its size)")
            mc = calibrate_mobile(rig, target, nominal_mobile, stations, full=full, progress=tick)
            tick("mobile camera: hand-eye")
            ri = mc.intrinsics_view.result
            res = mc.refined_residuals_px
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
            if truth is not None:
                err = {"hand_eye": hand_eye_error(mc.T_f_c2, truth.T_f_c2),
                       "hand_eye_tsai_lenz_only": hand_eye_error(mc.T_f_c2_tsai_lenz, truth.T_f_c2),
                       "f_mm": mc.camera.f - truth.mobile_camera.f,
                       "kappa1": mc.camera.kappa1 - truth.mobile_camera.kappa1}
                if mc.T_f_c2_opencv is not None:
                    err["hand_eye_opencv_tsai"] = hand_eye_error(mc.T_f_c2_opencv, truth.T_f_c2)
                report["mobile_camera"]["error_vs_truth"] = err
            if mc.T_f_c2_opencv is not None:
                report["mobile_camera"]["opencv_vs_tsai_lenz"] = hand_eye_error(mc.T_f_c2_opencv, mc.T_f_c2_tsai_lenz)
            report["mobile_camera"]["target_pose_check"] = hand_eye_error(mc.T_b_t, target.T_w_t)
    except (DotError, CalibrationInputError, HandEyeInputError, TableRegistrationError, TargetError) as exc:
        raise UserInputError(f"calibration failed: {exc}") from None
    tick("writing calibration files")
    if write:
        cal_dir = Path(cal_dir)
        if not (cal_dir / TARGET_FILE).exists():
            files[TARGET_FILE] = target_yaml(target)
        written = store.write_files(cal_dir, files)
        from ..fsutil import atomic_write_bytes

        atomic_write_bytes(cal_dir / PLOT_FILE, residual_plot_png(plot_data))
        report["files"] = [str(p) for p in written] + [str(cal_dir / PLOT_FILE)]
    return report


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
