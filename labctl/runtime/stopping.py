"""Stopping the robot and the table on every exit path, and confirming it (docs/architecture.md "Runtimes").

A machine controller's first promise is that motion stops when the controller stops. Three
layers, each used by whoever holds the devices at that moment:

* :func:`stop_devices` — a process that has the drivers open (a worker, a CLI command) stops
  each one through its driver — GRBL feed hold then soft reset, the robot's ``STOP`` — and
  reads the status back. Every device is tried; each outcome is returned, none is swallowed.
* :func:`send_stop_bytes` — the supervisor's first move when a worker dies, hangs or the user
  interrupts: the stop bytes written straight to the ports (GRBL feed hold ``!``, a newline then
  the robot's ``STOP``), without waiting for any reply, so motion ends within milliseconds
  whatever state the worker holding the ports is in. (The soft reset follows in
  :func:`confirm_stopped`, once the hold has completed, so GRBL keeps its position.)
* :func:`confirm_stopped` — once no worker holds the ports any more, the supervisor opens them
  with the real drivers, stops each device again and reads its status back.

An outcome is a dict ``{"device", "stopped", "confirmed", "state", "error"}``: ``stopped`` means
the stop command went out, ``confirmed`` that a status read afterwards shows no motion (GRBL
``Idle``/``Alarm``/``Hold:0``/``Sleep``/``Door:0``, robot ``moving == 0``).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Mapping
from typing import Any

#: GRBL states in which no axis moves (a reset during motion leaves ``Alarm``)
TABLE_STILL_STATES = ("Idle", "Alarm", "Hold:0", "Sleep", "Door:0", "Check")


#: how long pyserial's RFC 2217 client waits for the server to acknowledge each option it sets (s)
RFC2217_NEGOTIATION_S = 3.0


def _err(exc: BaseException) -> str:
    return f"{type(exc).__name__}: {exc}"


def stop_table(table) -> dict:
    """Feed hold, soft reset (``GrblTable.stop``), then one status read: the table's outcome."""
    out: dict[str, Any] = {"device": "table", "stopped": False, "confirmed": False, "state": None, "error": None}
    try:
        table.stop()
        out["stopped"] = True
    except Exception as exc:  # noqa: BLE001 — recorded in the outcome, and we still try to read the state
        out["error"] = f"stop: {_err(exc)}"
        try:  # the reset may have failed where the hold did not; a hold alone still stops motion
            table.feed_hold()
            out["stopped"] = True
        except Exception as exc2:  # noqa: BLE001
            out["error"] += f"; feed hold: {_err(exc2)}"
    try:
        st = table.status()
        out["state"] = st.state
        out["confirmed"] = st.state in TABLE_STILL_STATES
        if not out["confirmed"] and out["error"] is None:
            out["error"] = f"still in state {st.state} after the stop"
    except Exception as exc:  # noqa: BLE001
        out["error"] = (out["error"] + "; " if out["error"] else "") + f"status: {_err(exc)}"
    return out


#: how long a robot may take to brake after STOP before it counts as not stopped (s); the simulated
#: controller's stop ramp (docs/protocols/robot.md §Stopping) lasts max(|v_i|/a_stop, ‖ω‖/alpha_stop)
ROBOT_BRAKE_LIMIT_S = 3.0


def stop_robot(robot, brake_limit_s: float = ROBOT_BRAKE_LIMIT_S) -> dict:
    """The robot's ``STOP`` (acknowledged), then ``STATUS`` reads until it reports no motion (it
    brakes on its own profile) or ``brake_limit_s`` passes: the robot's outcome."""
    out: dict[str, Any] = {"device": "robot", "stopped": False, "confirmed": False, "state": None, "error": None}
    try:
        robot.stop()
        out["stopped"] = True
    except Exception as exc:  # noqa: BLE001 — recorded; fall back to the unacknowledged STOP
        out["error"] = f"stop: {_err(exc)}"
        try:
            robot.emergency_stop()
        except Exception as exc2:  # noqa: BLE001
            out["error"] += f"; emergency stop: {_err(exc2)}"
    sleep = robot.clock.sleep  # the simulated lab's virtual clock, or wall time
    try:
        polls = max(1, int(brake_limit_s / 0.05))
        for i in range(polls):
            st = robot.status()
            if not st.moving or i == polls - 1:
                break
            sleep(0.05)
        out["state"] = "moving" if st.moving else "still"
        out["confirmed"] = not st.moving
        if st.moving and out["error"] is None:
            out["error"] = f"still moving {brake_limit_s:g} s after STOP"
    except Exception as exc:  # noqa: BLE001
        out["error"] = (out["error"] + "; " if out["error"] else "") + f"status: {_err(exc)}"
    return out


def clear_own_stop(robot, outcome: dict) -> None:
    """``CLEAR`` the STOP a run latched itself at its normal end, once ``outcome`` (of
    :func:`stop_robot`) confirms the arm still, so that the next run can start; recorded in
    ``outcome["cleared"]``. Never raises."""
    outcome["cleared"] = False
    if not outcome.get("confirmed"):
        return
    try:
        robot.clear()
        outcome["cleared"] = True
    except Exception as exc:  # noqa: BLE001 — recorded; the latch then stays for the operator
        outcome["error"] = f"clear: {_err(exc)}"


def stop_devices(devices: Mapping[str, Any]) -> list[dict]:
    """Stop and confirm each open device (``{"robot": r, "table": t}``; ``None`` entries skipped).

    First every device gets its immediate stop, without waiting for any reply (GRBL feed hold, the
    robot's unacknowledged STOP), so that no device keeps moving while another one's round trips
    run; then each is stopped properly and its status read back. Never raises: every device is
    tried and every outcome returned, in the order given."""
    quick_errors: dict[str, str] = {}
    for name, dev in devices.items():
        if dev is None:
            continue
        try:
            if name == "table":
                dev.feed_hold()
            elif name == "robot":
                dev.emergency_stop()
        except Exception as exc:  # noqa: BLE001 — recorded below; the full stop still follows
            quick_errors[name] = f"immediate stop: {_err(exc)}"
    out = []
    for name, dev in devices.items():
        if dev is None:
            continue
        if name == "table":
            out.append(stop_table(dev))
        elif name == "robot":
            out.append(stop_robot(dev))
        else:
            continue
        if name in quick_errors:
            out[-1]["error"] = "; ".join(filter(None, [quick_errors[name], out[-1]["error"]]))
    return out


def close_all(devices) -> list[str]:
    """Close every device; return the errors (one string each) instead of hiding them."""
    errors = []
    for dev in devices:
        if dev is None:
            continue
        try:
            dev.close()
        except Exception as exc:  # noqa: BLE001 — reported by the caller
            errors.append(f"closing {type(dev).__name__}: {_err(exc)}")
    return errors


def confirmed(outcomes: list[dict]) -> list[str]:
    """The devices stopped and confirmed still."""
    return [o["device"] for o in outcomes if o["confirmed"]]


def summary(outcomes: list[dict]) -> str:
    """One phrase for the user: ``robot and table stopped (confirmed)`` or which device failed and why."""
    if not outcomes:
        return "no device to stop"
    ok = confirmed(outcomes)
    bad = [o for o in outcomes if not o["confirmed"]]
    parts = []
    if ok:
        parts.append(" and ".join(ok) + " stopped (confirmed)")
    for o in bad:
        parts.append(f"{o['device']} NOT confirmed stopped ({o['error'] or 'no status'})")
    parts += [latch_note(o["latched"]) for o in outcomes if o.get("latched")]
    return "; ".join(parts)


def latch_note(fault: str) -> str:
    """The phrase for a fault the stop left latched on the robot controller: what to run before the next job."""
    from ..drivers.robot import CLEAR_HINT

    return f"the robot controller holds its '{fault}' latched (the next run or calibration refuses): {CLEAR_HINT}"


# ---- the supervisor's side: the ports, not the drivers --------------------------------------------

def _ports(lab, endpoints: Mapping) -> dict[str, tuple[str | None, int]]:
    ports = {"robot": (endpoints.get("robot") or lab.robot.port, lab.robot.baud)}
    if lab.table is not None:  # a lab whose parts ride a conveyor it does not drive has no table
        ports["table"] = (endpoints.get("table") or lab.table.port, lab.table.baud)
    return ports


def open_stop_lines(lab, endpoints: Mapping) -> dict[str, int]:
    """Write-only descriptors on the table's and robot's device files, opened while the run starts so
    that an emergency stop is one ``write`` with nothing to open (the worker keeps the port settings;
    nothing here ever reads, so no reply is taken from the worker). Ports that are URLs or cannot be
    opened are left out (:func:`send_stop_bytes` then opens them)."""
    import os

    fds = {}
    for name, (port, _baud) in _ports(lab, endpoints).items():
        if port and port.startswith("/dev/"):
            try:
                fds[name] = os.open(port, os.O_WRONLY | os.O_NOCTTY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
            except OSError:
                continue
    return fds


def send_stop_bytes(lab, endpoints: Mapping, timeout_s: float = 0.3, fds: Mapping[str, int] | None = None
                    ) -> list[dict]:
    """Write the stop bytes straight to the table's and robot's ports, in parallel, without waiting
    for replies (the emergency stop of paper §5.1's supervisor role), through ``fds`` from
    :func:`open_stop_lines` where given. Returns one outcome per device with ``stopped`` (bytes
    written) and ``error``; nothing is confirmed here."""
    import os

    import serial

    from ..drivers.robot import STOP_LINE
    from ..drivers.serial_link import open_port

    # "\n" first: ends any half-written line a killed worker left in the controller's buffer
    payloads = {"table": [b"!"], "robot": [b"\n" + STOP_LINE]}
    results: dict[str, dict] = {}
    fds = fds or {}

    def send(name: str, port: str, baud: int) -> None:
        out: dict[str, Any] = {"device": name, "stopped": False, "confirmed": False, "state": None, "error": None}
        results[name] = out
        if name in fds:
            try:
                for p in payloads[name]:
                    os.write(fds[name], p)
                out["stopped"] = True
                return
            except OSError as exc:  # fall back to opening the port
                out["error"] = f"stop bytes on the open line: {_err(exc)}"
        try:
            with open_port(port, write_timeout_s=timeout_s, baudrate=baud, timeout=timeout_s) as s:
                for p in payloads[name]:
                    s.write(p)
                    s.flush()
            out["stopped"] = True
        except (serial.SerialException, OSError, ValueError) as exc:
            out["error"] = "; ".join(filter(None, [out["error"], f"stop bytes: {_err(exc)}"]))

    threads = []
    for name, (port, baud) in _ports(lab, endpoints).items():
        if not port:
            results[name] = {"device": name, "stopped": False, "confirmed": False, "state": None,
                             "error": "no port configured"}
            continue
        th = threading.Thread(target=send, args=(name, port, baud), daemon=True)
        th.start()
        threads.append(th)
    # an RFC 2217 port negotiates its options before the first byte can go (about 0.6 s on loopback,
    # each option waited for up to pyserial's 3 s): the bytes are worth that wait
    rfc2217 = any((port or "").startswith("rfc2217://") for port, _ in _ports(lab, endpoints).values())
    budget_s = timeout_s + 0.5 + (RFC2217_NEGOTIATION_S if rfc2217 else 0.0)
    t_end = time.monotonic() + budget_s
    for th in threads:
        th.join(timeout=max(0.0, t_end - time.monotonic()))
    for name in _ports(lab, endpoints):
        results.setdefault(name, {"device": name, "stopped": False, "confirmed": False, "state": None,
                                  "error": "stop bytes: the write did not return"})
    return [results[n] for n in ("table", "robot")]


def confirm_stopped(lab, endpoints: Mapping) -> list[dict]:
    """Open the table and robot with their real drivers (no reset on open), stop each again and read
    its status back. Call only when no other process reads these ports (the workers have exited)."""
    from ..drivers.grbl import GrblTable
    from ..drivers.robot import SerialRobot

    ports = _ports(lab, endpoints)
    out = []
    for name in ("table", "robot"):
        port, baud = ports[name]
        if not port:
            out.append({"device": name, "stopped": False, "confirmed": False, "state": None,
                        "error": "no port configured"})
            continue
        t0 = time.monotonic()
        dev: GrblTable | SerialRobot
        try:
            if name == "table":
                dev = GrblTable.from_config(lab.table, port=port, baud=baud)
                dev.reset_on_open = False
            else:
                dev = SerialRobot.from_config(lab.robot, port=port, baud=baud)
            dev.open()
        except Exception as exc:  # noqa: BLE001 — the outcome says the device could not be reached
            out.append({"device": name, "stopped": False, "confirmed": False, "state": None,
                        "error": f"open: {_err(exc)}"})
            continue
        try:
            res = stop_table(dev) if name == "table" else stop_robot(dev)
            if isinstance(dev, SerialRobot) and lab.robot.kind != "sim":  # a built-in simulated one ends with the run
                res["latched"] = dev.latched
        finally:
            errs = close_all([dev])
        if errs:
            res["error"] = "; ".join(filter(None, [res["error"], *errs]))
        res["seconds"] = round(time.monotonic() - t0, 3)
        out.append(res)
    return out


# ---- reading the simulator's ground truth back (tests, notes) ----------------------------------------

def still_after(events: list[dict], t_stop: float) -> dict[str, float]:
    """Seconds after the first stop command ``t_stop`` (s, the run's clock) at which the simulator's
    ground truth saw each device come to rest for good: ``{"robot": s, "table": s}``, 0 if it was
    already still. ``events`` are ``sim_truth`` transitions (``t``, ``robot_moving``,
    ``table_moving``; others ignored), from the live simulated lab's record or a served lab's truth
    log (:class:`labctl.sim.lab.TruthLogger`) put on the run's clock. The robot counts as
    still only when its controller's stop ramp has ended (the flange at rest), not when ``STOP``
    arrived. Also, where the truth carries the robot's stop ramps (``robot_stop`` = [start, end]):
    ``robot_stop_received_s``, from ``t_stop`` to the first ramp that began after it, and
    ``robot_braking_s``, that ramp's length. Raises ValueError if a device is still moving at the
    end of the log (the fault table of docs/notes/link_and_records.md)."""
    from ..records.events import spec

    truth_ev = spec("sim_truth")
    truth = [e for e in events if e["event"] == truth_ev.name]
    out: dict[str, float] = {}
    for dev in ("robot", "table"):
        moving = [i for i, e in enumerate(truth) if truth_ev.get(e, f"{dev}_moving")]
        if not moving:
            out[dev] = 0.0
            continue
        last = moving[-1]
        if last + 1 >= len(truth):
            raise ValueError(f"the {dev} is still moving at the end of the ground truth")
        out[dev] = max(0.0, truth_ev.get(truth[last + 1], "t") - t_stop)
    stops = [truth_ev.get(e, "robot_stop") for e in truth]
    ramps = sorted({tuple(r) for r in stops if r and r[0] >= t_stop - 0.05})
    if ramps:
        out["robot_stop_received_s"] = max(0.0, ramps[0][0] - t_stop)
        out["robot_braking_s"] = ramps[0][1] - ramps[0][0]
    return out
