"""A bridge skeleton: labctl's robot dialect (docs/protocols/robot.md) in front of an arm's own API.

Start from the reference controller, ``labctl.sim.emulators.robot.RobotEmulator``: it already
parses the dialect, checks every segment exactly (box, stop ramp, speed, acceleration, angular
speed), keeps the queue, the stop ramp, the latched faults, the watchdog and the clock. A bridge
adds the arm: it streams the trajectory to it as pose setpoints at the arm's servo rate — most arm
SDKs have such a streaming mode (UR ``servoL`` over RTDE, ABB EGM, KUKA RSI, Franka's Cartesian
pose control) — and lets the arm's own protective stop act when the bridge itself fails.

Replace the bodies of :class:`ArmAPI` with your SDK's calls, then check the bridge:

    python docs/protocols/robot_bridge_example.py                  # serves a pty, prints its path
    python docs/protocols/robot_bridge_example.py --port /dev/ttyS0 --baud 9600
    labctl robot conformance --port <that port>

Units: mm, s, rad; poses are ``T_base_flange`` (4×4).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from labctl.geometry import make_T, rot_x
from labctl.sim.emulators.robot import RobotEmulator


class ArmAPI:
    """The arm's own API, stubbed: replace each body with a call to your SDK."""

    def __init__(self, start_pose: np.ndarray):
        self.pose = np.asarray(start_pose, float)
        self.setpoints: list[tuple[float, np.ndarray]] = []  # what the stub was told, for tests

    def read_pose(self) -> np.ndarray:
        """Current ``T_base_flange`` (SDK: e.g. ``rtde_r.getActualTCPPose()`` converted to 4×4, mm)."""
        return self.pose

    def servo(self, T_base_flange: np.ndarray, t: float) -> None:
        """Send one setpoint for controller time ``t`` (SDK: e.g. ``rtde_c.servoL(pose, …)``)."""
        self.setpoints.append((t, T_base_flange))
        self.pose = T_base_flange

    def protective_stop(self) -> None:
        """The arm's own stop, for when the bridge itself fails (SDK: e.g. ``rtde_c.stopL(a)``)."""


class Bridge(RobotEmulator):
    """The reference controller, streaming its trajectory to an :class:`ArmAPI` every ``servo_period_s``.

    The dialect's trajectory (segments, stop ramps, HOME) is the bridge's command; the arm follows it
    setpoint by setpoint. If your arm lags its setpoints, report ``arm.read_pose()`` in STATUS
    (override ``_cmd_status``) so the host sees where the arm really is.
    """

    def __init__(self, arm: ArmAPI, clock=time.monotonic, limits=None, servo_period_s: float = 0.008):
        super().__init__(clock, limits, start_pose=arm.read_pose())
        self.arm = arm
        self.servo_period_s = servo_period_s
        self._next_servo = self.now

    def advance(self, t: float) -> None:
        super().advance(t)
        while self._next_servo <= self.now:  # every setpoint up to now, on the servo grid
            p, _, _, R, _ = self.state_at(self._next_servo)
            self.arm.servo(make_T(R, p), self._next_servo)
            self._next_servo += self.servo_period_s


def serve_serial(bridge: Bridge, port: str, baud: int) -> None:
    """Run the bridge on a real serial port until Ctrl-C (pyserial; one 2 ms loop)."""
    import serial

    with serial.serial_for_url(port, baudrate=baud, timeout=0) as ser:
        try:
            while True:
                data = ser.read(4096)
                if data:
                    bridge.receive(data)
                bridge.advance(bridge.clock())
                out = bridge.read_output()
                if out:
                    ser.write(out)
                time.sleep(0.002)
        finally:
            bridge.arm.protective_stop()


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", help="serial port of the host link (default: serve a pseudo-terminal)")
    ap.add_argument("--baud", type=int, default=9600)
    args = ap.parse_args(argv)
    arm = ArmAPI(make_T(rot_x(np.pi), [300.0, -450.0, 900.0]))
    bridge = Bridge(arm)
    if args.port:
        serve_serial(bridge, args.port, args.baud)
        return
    from labctl.sim.emulators.pty import run_on_pty

    with run_on_pty(bridge, args.baud) as dev:
        print(dev.path, flush=True)
        try:
            while True:
                time.sleep(1.0)
        except KeyboardInterrupt:
            arm.protective_stop()


if __name__ == "__main__":
    main()
