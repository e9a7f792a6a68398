"""Build the device a lab's driver file names, and check devices (``labctl devices``).

This is where drivers and the simulator meet (hence it lives above both, in ``workers``).

``open_device(role, lab)`` returns an unopened device for ``table``, ``robot``,
``fixed_camera`` or ``mobile_camera``: the real driver for real kinds; for ``kind: sim`` the
same driver wired to an in-process emulator on a virtual clock (tables and robots) or the
simulated camera. ``check_device`` opens, identifies and queries one device and returns a
verdict; it never raises for a device fault.
"""

from __future__ import annotations

import math
import time
from typing import Any

from ..drivers.cameras import open_camera
from ..errors import DeviceError, LabctlError

ROLES = ("table", "robot", "fixed_camera", "mobile_camera")


def open_device(role: str, lab, *, port: str | None = None, baud: int | None = None, clock=None):
    """The (unopened) device serving ``role`` in ``lab``; ``port``/``baud`` override the driver file.

    ``clock`` (cameras): the clock frames are stamped on (default ``time.monotonic``)."""
    if role == "table":
        from ..drivers.grbl import GrblTable

        cfg = lab.table
        if cfg is None:
            raise LabctlError("this lab has no table (lab.yaml drivers.table: null)")
        if cfg.kind == "sim" and port is None:
            return _sim_device("table", lab, baud)
        return GrblTable.from_config(cfg, port=port or cfg.port, baud=baud or cfg.baud)
    if role == "robot":
        from ..drivers.robot import SerialRobot

        cfg = lab.robot
        if cfg.kind == "sim" and port is None:
            return _sim_device("robot", lab, baud)
        return SerialRobot.from_config(cfg, port=port or cfg.port, baud=baud or cfg.baud)
    if role in ("fixed_camera", "mobile_camera", "fixed", "mobile"):
        role = role if role.endswith("_camera") else f"{role}_camera"
        if getattr(lab, role).kind == "sim":
            return _sim_device(role.removesuffix("_camera"), lab)
        return open_camera(role, lab, **({"clock": clock} if clock is not None else {}))
    raise LabctlError(f"unknown device role {role!r} (have: {', '.join(ROLES)})")


def _sim_device(role: str, lab, baud: int | None = None):
    """One simulated device of ``lab`` on a fresh virtual clock, without the rest of the lab.

    A table or robot: the real driver on an in-process port to its emulator (``.emulator``), at machine
    zero / the controller's home, as a board powers up. A camera (``fixed``, ``mobile``): the world with
    the built-in test block (seed 0) and the table and robot at rest where a whole lab's emulators start
    them (the travel's centre; the mobile camera at ``robot.home_mm`` looking at the table's centre)."""
    from ..sim.clock import VirtualClock
    from ..sim.lab import Scene, SimLab

    if role in ("table", "robot"):
        sim = SimLab.build(lab, VirtualClock(), devices=(role,), baud=baud, table_start_mm=(0.0, 0.0),
                           robot_start="controller")
        dev = sim.table if role == "table" else sim.robot
        dev.emulator = sim.emulator(role)
        return dev
    return SimLab.build(lab, VirtualClock(0.0), devices=(role,), scene=Scene.test_block(lab, 0)).cameras[role]


def robot_limits_problem(cfg, controller: dict) -> str | None:
    """Where the lab's robot driver file ``cfg`` (:class:`labctl.config.RobotConfig`) promises more than the
    controller's own ``LIMITS`` (``controller``, as :meth:`labctl.drivers.robot.SerialRobot.limits` returns them):
    one line naming the file's key for every mismatch, or None.

    The host plans every segment from the driver file (:func:`labctl.planning.ruckig_profile.controller_limits`:
    vmax, amax, wmax, jmax, the stop ramp's a_stop = amax/√3 and angular 4·wmax per second, the box), and the
    controller checks each against its own (docs/protocols/robot.md §5-§6, E10-E16): a file above them plans
    moves the controller refuses mid-run. Lower is safe (the host asks for less). The heartbeat must also beat
    the controller's watchdog, not only the file's."""
    from ..planning.ruckig_profile import controller_limits

    host = controller_limits(cfg)

    def above(mine: float, theirs: float) -> bool:
        return mine > theirs * (1.0 + 1e-9) + 1e-6  # LIMITS prints up to 6 decimals

    # (driver-file key, what the host plans with, LIMITS field, its name, unit, the key's largest safe value)
    checks = [("v_max_mm_s", host.v_max, "v_max_mm_s", "vmax", "mm/s", 1.0),
              ("a_max_mm_s2", host.a_max, "a_max_mm_s2", "amax", "mm/s²", 1.0),
              ("w_max_deg_s", math.degrees(host.w_max), "w_max_deg_s", "wmax", "deg/s", 1.0),
              ("j_max_mm_s3", host.j_max, "j_max_mm_s3", "jmax", "mm/s³", 1.0),
              ("a_max_mm_s2", host.a_stop, "a_stop_mm_s2", "a_stop (amax/√3)", "mm/s²", math.sqrt(3.0)),
              ("w_max_deg_s", math.degrees(host.alpha_max), "alpha_stop_deg_s2", "alpha_stop (4·wmax per second)",
               "deg/s²", 0.25)]
    problems, named = [], set()
    for key, mine, field, name, unit, to_key in checks:
        # the stop ramps follow from amax and wmax: one line per driver-file key
        if key not in named and field in controller and above(mine, theirs := float(controller[field])):
            named.add(key)
            problems.append(f"{key}: the host would plan with {name} {mine:g} {unit}, above the controller's "
                            f"{theirs:g} (LIMITS), which refuses such moves; set {key} to at most {theirs * to_key:g}")
    lo, hi = controller["workspace_min_mm"], controller["workspace_max_mm"]
    for key, mine, outside in (("workspace_min_mm", cfg.workspace_min_mm, lambda a, b: a < b - 1e-6),
                               ("workspace_max_mm", cfg.workspace_max_mm, lambda a, b: a > b + 1e-6)):
        if any(outside(float(a), float(b)) for a, b in zip(mine, lo if key.endswith("min_mm") else hi)):
            problems.append(f"{key}: {list(mine)} reaches outside the controller's box {list(lo)} .. {list(hi)} "
                            "(LIMITS), which refuses moves there")
    if not cfg.heartbeat_s < float(controller["watchdog_s"]):
        problems.append(f"heartbeat_s: {cfg.heartbeat_s:g} s is not shorter than the controller's watchdog "
                        f"{float(controller['watchdog_s']):g} s (LIMITS), which would stop the arm between beats")
    return _joined(problems)


def _joined(problems: list[str]) -> str | None:
    """Every mismatch on one line (the verdict's), each starting with its driver-file key; None if none."""
    return " | ".join(problems) or None


def check_robot_limits(robot, lab) -> dict:
    """Read an open robot's ``LIMITS`` and raise DeviceError, one line naming the driver file's key, if the
    lab's driver file promises more (:func:`robot_limits_problem`). Returns the controller's limits."""
    limits = robot.limits()
    _refuse(robot_limits_problem(lab.robot, limits), robot, lab, "robot")
    return limits


def table_settings_problem(cfg, settings: dict[int, float]) -> str | None:
    """Where the lab's table driver file ``cfg`` (:class:`labctl.config.TableConfig`) disagrees with GRBL's own
    settings (``$$``, as :meth:`labctl.drivers.grbl.GrblTable.settings` returns them): one line naming the file's
    key for every mismatch, or None.

    labctl writes every program inside the file's ``travel_mm`` and bounds ``--speed`` by its ``max_feed_mm_min``;
    GRBL moves by its own: a travel beyond ``$130``/``$131`` trips soft limits (or reaches the end stops) mid-run,
    a feed above ``$110``/``$111`` is clamped without a word. (``accel_mm_s2`` is not checked: only the simulator
    and the off-by-default ``tracking.stop_corners`` read it.)"""
    problems = []
    for axis, (rate, travel) in enumerate(((110, 130), (111, 131))):
        name = "XY"[axis]
        if rate in settings and cfg.max_feed_mm_min > settings[rate] * (1 + 1e-9):
            problems.append(f"max_feed_mm_min: {cfg.max_feed_mm_min:g} mm/min is above GRBL's ${rate} ({name} max "
                            f"rate) {settings[rate]:g}, which clamps faster feeds; set at most {settings[rate]:g}")
        if travel in settings and cfg.travel_mm[axis] > settings[travel] * (1 + 1e-9):
            problems.append(f"travel_mm: {cfg.travel_mm[axis]:g} mm in {name} is beyond GRBL's ${travel} ({name} max "
                            f"travel) {settings[travel]:g}, where programs planned inside the file's travel would stop "
                            f"or collide; set at most {settings[travel]:g}")
    return _joined(problems)


def check_table_settings(table, lab) -> dict[int, float]:
    """Read an open table's ``$$`` and raise DeviceError, one line naming the driver file's key, if the lab's
    driver file disagrees (:func:`table_settings_problem`). Returns GRBL's settings."""
    settings = table.settings()
    _refuse(table_settings_problem(lab.table, settings), table, lab, "table")
    return settings


def _refuse(problem: str | None, device, lab, role: str) -> None:
    """DeviceError (exit 3) naming the device, the lab's driver file for ``role`` and ``problem``, if any."""
    if problem is not None:
        raise DeviceError(f"{device.link.name}: {lab.driver_paths.get(role, f'the {role} driver file')}: {problem}")


def _where(role: str, lab) -> tuple[str, str]:
    cfg = getattr(lab, role)
    kind = cfg.kind
    if role in ("table", "robot"):
        if kind == "sim":
            return kind, "in-process emulator"
        from ..drivers.serial_link import baud_words

        # the robot's link keeps an RFC 2217 server's own rate (its file has no set_remote_baud)
        remote = cfg.set_remote_baud if role == "table" else False
        return kind, f"{cfg.port} {baud_words(cfg.port, cfg.baud, remote)}"
    if kind == "v4l2":
        return kind, str(cfg.device)
    if kind == "replay":
        return kind, str(cfg.folder)
    if kind == "stream":
        return kind, str(cfg.url)
    return kind, "simulated camera (in-process world)"


def check_device(role: str, lab) -> dict:
    """Open, identify and query one device: {role, kind, where, ok, verdict, identity, status, seconds}."""
    kind, where = _where(role, lab)
    out: dict[str, Any] = {"role": role, "kind": kind, "where": where, "ok": False, "identity": None, "status": None}
    t0 = time.perf_counter()
    dev = None
    try:
        dev = open_device(role, lab)
        dev.open()
        if role == "table":
            st = dev.status()
            check_table_settings(dev, lab)
            out["identity"] = f"Grbl {dev.info.get('version', '?')} (rx buffer {dev.rx_limit + 1} B, " \
                              f"connected by {dev.connected_by})"
            out["status"] = {"state": st.state, "position": dict(zip("xyz", st.position))}
        elif role == "robot":
            st = dev.status()
            check_robot_limits(dev, lab)
            out["identity"] = dev.ident
            out["status"] = {"moving": st.moving, "segment_id": st.segment_id,
                             "position": dict(zip("xyz", (float(v) for v in st.T_base_flange[:3, 3])))}
        else:
            frame = dev.grab()
            info = dev.info()
            out["identity"] = f"{info.get('kind')} {info.get('width', frame.image.shape[1])}×" \
                              f"{info.get('height', frame.image.shape[0])}"
            out["status"] = {"frame": list(frame.image.shape), "t": frame.t, "seq": frame.seq}
            out["response"] = response_check(frame.image, lab, role)
        out["ok"] = True
        out["verdict"] = "OK" + (" (simulated: checked against an in-process emulator)" if kind == "sim"
                                 and role in ("table", "robot") else " (simulated)" if kind == "sim" else "")
        if kind == "sim" and not lab.is_simulated and (problem := lab.mixed_kinds_problem()) is not None:
            out["verdict"] += f" — {problem}"  # it answers, but `labctl run` refuses this mix
    except Exception as exc:  # the verdict reports any failure; the command itself goes on
        out["verdict"] = f"FAIL: {type(exc).__name__}: {exc}"
    finally:
        if dev is not None:
            try:
                dev.close()
            except Exception:  # a failed device may not close cleanly
                pass
    out["seconds"] = round(time.perf_counter() - t0, 3)
    return out


def response_check(image, lab, role: str) -> str | None:
    """One line on the camera ``role``'s response, from one frame, or None when there is nothing to say.

    The frame's markers (the driver file's colour window and response) are detected; when some carry
    ``response_mismatch`` (their blurred edges lean as a frame encoded with another response does,
    docs/notes/vision.md) the line says so and names ``labctl vision learn-response``. A response nobody
    declared is said to be undeclared (pose is then conservative), "not checked" with no marker in view.
    A declared response with no leaning marker (or none in view) says nothing."""
    from ..decisions.context import marker_thresholds
    from ..vision import find_markers

    cfg = getattr(lab, role)
    declared = lab.response_declared(role)
    markers = find_markers(image, thresholds=marker_thresholds(cfg), response=cfg.response,
                           response_declared=declared).markers
    bad = sum(m.quality is not None and "response_mismatch" in m.quality.flags for m in markers)
    resp = cfg.response if isinstance(cfg.response, str | int | float) else "a LUT"
    learn = f"run `labctl vision learn-response --camera {role.removesuffix('_camera')} …`"
    if bad:
        return (f"{bad} of {len(markers)} markers look encoded with another response than `response: {resp}` "
                f"in {lab.driver_paths.get(role, role)}: {learn}")
    if not declared:
        return (f"response undeclared (`{resp}` by default; pose is conservative): "
                + ("not checked (no marker in view); " if not markers else "") + f"{learn} or declare it")
    return None


def check_devices(lab) -> list[dict]:
    """Check every device the lab has (a lab without a table has three)."""
    return [check_device(role, lab) for role in ROLES if getattr(lab, role) is not None]
