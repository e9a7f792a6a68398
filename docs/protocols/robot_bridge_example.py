"""A bridge skeleton: labctl's robot dialect (docs/protocols/robot.md) in front of an arm's own API.

Start from the reference controller, ``labctl.sim.emulators.robot.RobotEmulator``: it already
parses the dialect, checks every segment exactly (box, stop ramp, speed, acceleration, angular
speed), keeps the queue, the stop ramp, the latched faults, the watchdog and the clock. Given the
arm's kinematic model (its data file, ``drivers/arms/*.yaml``, at its mount) it also keeps the arm's
joint state, refuses before moving every segment the arm cannot fly (dialect 1.3: E30–E34) and
reports the joints in STATUS.

A bridge adds the arm: it streams the trajectory to it at the arm's servo rate, as **joint setpoints**
— the mode most arm SDKs offer for streaming (UR ``servoJ`` over RTDE, ABB EGM joint mode, KUKA RSI
axis correction, Franka's joint position control). The joints come from the same kinematic model
the segments were checked with, in the configuration the arm is in, so what the arm is told is what
was checked; the arm's own interpolator never picks another inverse-kinematics solution. Without an
arm model it streams pose setpoints instead (``servoL``, EGM pose mode), as a dialect 1.2 bridge.
The arm's own protective stop acts when the bridge itself fails.

Replace the bodies of :class:`ArmAPI` with your SDK's calls, then check the bridge:

    python docs/protocols/robot_bridge_example.py                  # serves a pty, prints its path
    python docs/protocols/robot_bridge_example.py --port /dev/ttyS0 --baud 9600
    labctl robot conformance --port <that port>

Units: mm, s, rad; poses are ``T_base_flange`` (4×4; the robot's base frame is labctl's world W).
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from labctl.geometry import make_T, rot_x
from labctl.sim.emulators.arm_servo import ArmServo
from labctl.sim.emulators.robot import RobotEmulator


class ArmAPI:
    """The arm's own API, stubbed: replace each body with a call to your SDK."""

    def __init__(self, start_pose: np.ndarray, start_joints: np.ndarray | None = None):
        self.pose = np.asarray(start_pose, float)
        self.joints = None if start_joints is None else np.asarray(start_joints, float)
        self.setpoints: list[tuple[float, np.ndarray]] = []  # what the stub was told (pose mode), for tests
        self.joint_setpoints: list[tuple[float, np.ndarray]] = []  # (joint mode), for tests

    def read_pose(self) -> np.ndarray:
        """Current ``T_base_flange`` (SDK: e.g. ``rtde_r.getActualTCPPose()`` converted to 4×4, mm)."""
        return self.pose

    def read_joints(self) -> np.ndarray | None:
        """Current joint angles, rad (SDK: e.g. ``rtde_r.getActualQ()``); None if the stub has none."""
        return self.joints

    def servo(self, T_base_flange: np.ndarray, t: float) -> None:
        """Send one pose setpoint for controller time ``t`` (SDK: e.g. ``rtde_c.servoL(pose, …)``)."""
        self.setpoints.append((t, T_base_flange))
        self.pose = T_base_flange

    def servo_joints(self, q: np.ndarray, t: float) -> None:
        """Send one joint setpoint (rad) for controller time ``t`` (SDK: e.g. ``rtde_c.servoJ(q, 0, 0,
        period, lookahead_time, gain)``)."""
        self.joint_setpoints.append((t, np.asarray(q, float)))
        self.joints = np.asarray(q, float)

    def protective_stop(self) -> None:
        """The arm's own stop, for when the bridge itself fails (SDK: e.g. ``rtde_c.servoStop()``)."""


class Bridge(RobotEmulator):
    """The reference controller, streaming its trajectory to an :class:`ArmAPI` every ``servo_period_s``:
    joint setpoints when it has the arm's model (``arm``), else pose setpoints.

    The dialect's trajectory (segments, stop ramps, HOME) is the bridge's command; the arm follows it
    setpoint by setpoint. If your arm lags its setpoints, report where it really is in STATUS
    (override ``_cmd_status``) so the host sees it.
    """

    def __init__(self, sdk: ArmAPI, clock=time.monotonic, limits=None, servo_period_s: float = 0.008,
                 arm: ArmServo | None = None):
        super().__init__(clock, limits, start_pose=sdk.read_pose(), arm=arm,
                         start_joints=sdk.read_joints() if arm is not None else None)
        self.sdk = sdk
        self.servo_period_s = servo_period_s
        self._next_servo = self.now

    def advance(self, t: float) -> None:
        super().advance(t)
        while self._next_servo <= self.now:  # every setpoint up to now, on the servo grid
            if self.arm is not None:
                self.sdk.servo_joints(self.joints_at(self._next_servo), self._next_servo)
            else:
                p, _, _, R, _ = self.state_at(self._next_servo)
                self.sdk.servo(make_T(R, p), self._next_servo)
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
            bridge.sdk.protective_stop()


def lab_arm(lab_dir: str | None):
    """The arm (model and the controller's policy) of the lab's ``drivers/robot.yaml``, or None without one."""
    from labctl.config import load_lab
    from labctl.sim.lab import arm_servo
    from labctl.workspace import sample_lab_path

    lab = load_lab(lab_dir or sample_lab_path())
    return lab, arm_servo(lab)


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--port", help="serial port of the host link (default: serve a pseudo-terminal)")
    ap.add_argument("--baud", type=int, default=9600)
    ap.add_argument("--lab", help="lab whose drivers/robot.yaml names the arm (default: the sample lab)")
    args = ap.parse_args(argv)
    lab, arm = lab_arm(args.lab)
    start = make_T(rot_x(np.pi), lab.robot.home_mm)
    sdk = ArmAPI(start, None if arm is None else arm.initial(start))  # a real arm: its own pose and joints
    bridge = Bridge(sdk, limits=lab.robot, arm=arm)
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
            sdk.protective_stop()


if __name__ == "__main__":
    main()
