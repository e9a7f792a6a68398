"""Fake serial devices for tests: the real emulators on real ptys, with fault injection.

``fake_grbl(...)`` / ``fake_robot(...)`` are context managers yielding a :class:`FakeDevice`
(``.path`` to open like a serial port, ``.emulator``, ``.wire`` for faults, ``.stop()``).
:class:`Wire` injects faults on the bytes in either direction: dropped, corrupted or delayed
bytes, a device that stops answering (``mute``), one that answers garbage, and resets
mid-stream (``reset_after``: the board power-cycles after some seconds).
"""

from __future__ import annotations

import contextlib
import random
import threading
import time
from dataclasses import dataclass, field

from labctl.config import RobotConfig
from labctl.drivers.clock import MONOTONIC
from labctl.sim.emulators.grbl import GrblEmulator
from labctl.sim.emulators.pty import PtyDevice
from labctl.sim.emulators.robot import RobotEmulator


@dataclass
class Wire:
    """Fault injection on a pty link. Rates are per byte; ``seed`` makes them reproducible."""

    drop_in: float = 0.0  # host -> device
    drop_out: float = 0.0  # device -> host
    corrupt_in: float = 0.0
    corrupt_out: float = 0.0
    delay_out_s: float = 0.0  # extra latency on every device -> host chunk
    mute: bool = False  # the device stops answering (output swallowed)
    deaf: bool = False  # the device stops listening (input swallowed)
    garbage: bool = False  # every answer replaced by random bytes
    seed: int = 0
    log: list = field(default_factory=list)

    def __post_init__(self):
        self.rng = random.Random(self.seed)
        self._delayed: list[tuple[float, bytes]] = []

    def _mangle(self, data: bytes, drop: float, corrupt: float) -> bytes:
        out = bytearray()
        for b in data:
            r = self.rng.random()
            if r < drop:
                self.log.append(("drop", b))
                continue
            if r < drop + corrupt:
                b2 = b ^ (1 << self.rng.randrange(7))
                self.log.append(("corrupt", b, b2))
                b = b2
            out.append(b)
        return bytes(out)

    def inbound(self, t: float, data: bytes) -> bytes:
        if self.deaf:
            return b""
        return self._mangle(data, self.drop_in, self.corrupt_in)

    def outbound(self, t: float, data: bytes) -> bytes:
        if self.mute:
            return b""
        if self.garbage:
            return bytes(self.rng.randrange(256) for _ in range(len(data))).replace(b"\n", b"\n?")
        data = self._mangle(data, self.drop_out, self.corrupt_out)
        if self.delay_out_s:
            self._delayed.append((t + self.delay_out_s, data))
            ready = b"".join(d for (tt, d) in self._delayed if tt <= t)
            self._delayed = [(tt, d) for (tt, d) in self._delayed if tt > t]
            return ready
        return data


class FakeDevice:
    def __init__(self, emulator, baud: int, wire: Wire | None):
        self.emulator = emulator
        self.wire = wire or Wire()
        self.pty = PtyDevice(emulator, baud, on_inbound=self.wire.inbound, on_outbound=self.wire.outbound)
        self.path = self.pty.path
        self._timers: list[threading.Timer] = []

    @property
    def lock(self):
        return self.pty.lock

    def reset_after(self, seconds: float) -> None:
        """Power-cycle the device ``seconds`` from now (a board reset mid-stream)."""
        def fire():
            with self.pty.lock:
                self.emulator.power_cycle()

        timer = threading.Timer(seconds, fire)
        timer.daemon = True
        timer.start()
        self._timers.append(timer)

    def stop(self) -> None:
        for t in self._timers:
            t.cancel()
        self.pty.stop()


class _Silent:
    """A device that never says anything (nothing connected to the port)."""

    def receive(self, data: bytes, t: float | None = None) -> None:
        pass

    def read_output(self) -> bytes:
        return b""

    def advance(self, t: float) -> None:
        pass


@contextlib.contextmanager
def fake_grbl(baud: int = 115200, wire: Wire | None = None, **emu_kwargs):
    emu_kwargs.setdefault("strict", False)
    dev = FakeDevice(GrblEmulator(time.monotonic, **emu_kwargs), baud, wire)
    try:
        yield dev
    finally:
        dev.stop()


@contextlib.contextmanager
def fake_robot(baud: int = 115200, wire: Wire | None = None, limits: RobotConfig | None = None, **emu_kwargs):
    dev = FakeDevice(RobotEmulator(time.monotonic, limits or robot_test_limits(), **emu_kwargs), baud, wire)
    try:
        yield dev
    finally:
        dev.stop()


@contextlib.contextmanager
def silent_port(baud: int = 115200):
    dev = FakeDevice(_Silent(), baud, None)
    try:
        yield dev
    finally:
        dev.stop()


def robot_test_limits() -> RobotConfig:
    """Fixed limits for robot tests (independent of the sample lab's defaults)."""
    return RobotConfig(workspace_min_mm=(-300.0, -700.0, 80.0), workspace_max_mm=(900.0, 700.0, 1200.0),
                       v_max_mm_s=500.0, a_max_mm_s2=1500.0, w_max_deg_s=120.0, watchdog_s=0.5,
                       home_mm=(300.0, -450.0, 900.0))


def run_cli(capsys, *args) -> tuple[int, str, str]:
    """``labctl ARGS`` in process: (exit status, stdout, stderr)."""
    from labctl.cli import main

    code = 0
    try:
        main(list(args))
    except SystemExit as exc:
        code = exc.code or 0
    out, err = capsys.readouterr()
    return code, out, err


class StillRobot:
    """The whole :class:`labctl.drivers.interfaces.Robot` protocol for a controller that runs only the quintic
    profile, reports no ``@DONE`` and no latched fault, and stands at ``pose`` (4×4; the identity unless set):
    the base of the tests' fake robots, which override what their test is about."""

    pose = None
    done_ids: tuple = ()
    latched = None
    while_reconnecting = None
    clock = MONOTONIC

    def open(self):
        pass

    def close(self):
        pass

    def status(self):
        import numpy as np

        from labctl.drivers.interfaces import RobotStatus

        pose = np.eye(4) if self.pose is None else self.pose
        return RobotStatus(T_base_flange=pose, moving=False, segment_id=0, t=0.0)

    def segment(self, T_base_flange, duration_s, segment_id, **kw):
        return float("nan"), float("nan")

    def choose_profile(self, wanted):
        return "quintic"

    def segment_defaults(self, profile, limits=None):
        return False  # an older session: segments keep naming their profile

    holds = False  # an older session: no held segments

    def go(self, segment_id):
        raise AssertionError("no segment is held by a controller that holds none")

    def poll(self):
        pass

    def clear(self):
        pass

    def stop(self):
        pass

    def emergency_stop(self):
        pass

    def ensure_ready(self):
        return self.status()

    def home(self):
        pass

    def heartbeat(self):
        pass

    def maybe_heartbeat(self):
        pass


class SegmentRobot(StillRobot):
    """A robot controller on its own clock that takes every segment and stands at ``pose`` (4×4) until then:
    for the predictor's planning, where no motion is wanted. ``segments``: (T_end, duration) as sent."""

    def __init__(self, pose):
        self.pose, self.segments = pose, []

    def segment(self, T_end, duration, seg_id, replace=True, **kw):
        import numpy as np

        self.segments.append((np.array(T_end), float(duration)))
        return float("nan"), float("nan")


def debian_tool(binary: str, package: str | None = None) -> str:
    """The path of ``binary``, installing Debian's ``package`` (default: the binary's name) with apt-get when
    it is missing and this user is root; otherwise the test is skipped with the reason."""
    import os
    import shutil
    import subprocess

    import pytest

    exe = shutil.which(binary) or next((p for p in (f"/usr/sbin/{binary}", f"/usr/bin/{binary}")
                                        if os.path.isfile(p)), None)
    if exe:
        return exe
    package = package or binary
    if not hasattr(os, "geteuid") or os.geteuid() != 0 or not shutil.which("apt-get"):
        pytest.skip(f"{binary} is not installed (Debian: apt-get install {package}) and this user cannot install it")
    env = {**os.environ, "DEBIAN_FRONTEND": "noninteractive"}
    done = subprocess.run(["apt-get", "install", "-y", "-q", package], capture_output=True, text=True, timeout=900,
                          env=env)
    if done.returncode != 0:  # a stale package index: refresh it once
        subprocess.run(["apt-get", "update", "-q"], capture_output=True, timeout=600, env=env)
        done = subprocess.run(["apt-get", "install", "-y", "-q", package], capture_output=True, text=True,
                              timeout=900, env=env)
    exe = shutil.which(binary)
    if done.returncode != 0 or not exe:
        pytest.skip(f"{package} could not be installed: {done.stderr.strip().splitlines()[-1:]}")
    return exe
