"""Build the device a lab's driver file names, and check devices (``labctl devices``).

This is where drivers and the simulator meet (hence it lives above both, in ``workers``).

``open_device(role, lab)`` returns an unopened device for ``table``, ``robot``,
``fixed_camera`` or ``mobile_camera``: the real driver for real kinds; for ``kind: sim`` the
same driver wired to an in-process emulator on a virtual clock (tables and robots) or the
simulated camera. ``check_device`` opens, identifies and queries one device and returns a
verdict; it never raises for a device fault.
"""

from __future__ import annotations

import time

from ..drivers.cameras import open_camera
from ..errors import LabctlError

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
            from ..sim.clock import VirtualClock
            from ..sim.emulators.grbl import GrblEmulator
            from ..sim.emulators.link import EmulatorPort

            clock = VirtualClock()
            emu = GrblEmulator(clock, travel_mm=cfg.travel_mm, max_feed_mm_min=cfg.max_feed_mm_min,
                               accel_mm_s2=cfg.accel_mm_s2)
            dev = GrblTable.from_config(cfg, serial_port=EmulatorPort(emu, clock, baud or cfg.baud, name="sim://table"),
                                        clock=clock, sleep=clock.sleep)
            dev.emulator = emu
            return dev
        return GrblTable.from_config(cfg, port=port or cfg.port, baud=baud or cfg.baud)
    if role == "robot":
        from ..drivers.robot import SerialRobot

        cfg = lab.robot
        if cfg.kind == "sim" and port is None:
            from ..sim.clock import VirtualClock
            from ..sim.emulators.link import EmulatorPort
            from ..sim.emulators.robot import RobotEmulator

            clock = VirtualClock()
            emu = RobotEmulator(clock, cfg)
            dev = SerialRobot.from_config(cfg, serial_port=EmulatorPort(emu, clock, baud or cfg.baud, name="sim://robot"),
                                          clock=clock, sleep=clock.sleep)
            dev.emulator = emu
            return dev
        return SerialRobot.from_config(cfg, port=port or cfg.port, baud=baud or cfg.baud)
    if role in ("fixed_camera", "mobile_camera", "fixed", "mobile"):
        role = role if role.endswith("_camera") else f"{role}_camera"
        if getattr(lab, role).kind == "sim":
            from ..sim.virtual import build_virtual_lab

            return build_virtual_lab(lab).cameras[role.removesuffix("_camera")]
        return open_camera(role, lab, **({"clock": clock} if clock is not None else {}))
    raise LabctlError(f"unknown device role {role!r} (have: {', '.join(ROLES)})")


def _where(role: str, lab) -> tuple[str, str]:
    cfg = getattr(lab, role)
    kind = cfg.kind
    if role in ("table", "robot"):
        return kind, ("in-process emulator" if kind == "sim" else f"{cfg.port} @ {cfg.baud} bps")
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
    out = {"role": role, "kind": kind, "where": where, "ok": False, "identity": None, "status": None}
    t0 = time.perf_counter()
    dev = None
    try:
        dev = open_device(role, lab)
        dev.open()
        if role == "table":
            st = dev.status()
            out["identity"] = f"Grbl {dev.info.get('version', '?')} (rx buffer {dev.rx_limit + 1} B, " \
                              f"connected by {dev.connected_by})"
            out["status"] = {"state": st.state, "position": dict(zip("xyz", st.position))}
        elif role == "robot":
            st = dev.status()
            out["identity"] = dev.ident
            out["status"] = {"moving": st.moving, "segment_id": st.segment_id,
                             "position": dict(zip("xyz", (float(v) for v in st.T_base_flange[:3, 3])))}
        else:
            frame = dev.grab()
            info = dev.info()
            out["identity"] = f"{info.get('kind')} {info.get('width', frame.image.shape[1])}×" \
                              f"{info.get('height', frame.image.shape[0])}"
            out["status"] = {"frame": list(frame.image.shape), "t": frame.t, "seq": frame.seq}
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


def check_devices(lab) -> list[dict]:
    """Check every device the lab has (a lab without a table has three)."""
    return [check_device(role, lab) for role in ROLES if getattr(lab, role) is not None]
