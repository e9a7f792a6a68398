"""The robot controller of docs/protocols/robot.md, on an injectable clock.

Task-space segments are quintic polynomials (the paper's time-optimal task-space quintics,
§4.2): position p(τ) per axis and orientation R(τ) = R0·exp([φ(τ)]×) with φ a quintic vector
from 0 to log(R0ᵀR1), each from the current state (position, velocity, acceleration) to the
target with the requested end velocity and zero end acceleration over the given duration.
Limits (workspace box along the whole path, peak linear speed and acceleration, peak angular
speed) are checked before a segment is accepted. A watchdog stops the robot — a quintic to
rest — when no request arrives for ``watchdog_s`` while it moves, and latches a fault until
``CLEAR``. Units: mm, s, rad.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ...drivers.robot_protocol import ERROR_CODES, MAX_LINE, Request, add_checksum, parse_request
from ...geometry import make_T, matrix_to_rotvec, rotvec_to_matrix

IDENT = "labctl-robot 1.0"
QUEUE_SIZE = 8
MAX_DURATION_S = 60.0
HOME_RPY = (math.pi, 0.0, 0.0)  # flange z pointing down at the table


def quintic_coeffs(p0, v0, a0, p1, v1, a1, T: float) -> np.ndarray:
    """Coefficients c[0..5] (rows) of p(τ)=Σ c_k τ^k meeting position/velocity/acceleration at τ=0 and τ=T.

    Works per column for vector quantities. Paper §4.2 (task-space quintic polynomials).
    """
    p0, v0, a0, p1, v1, a1 = (np.asarray(x, float) for x in (p0, v0, a0, p1, v1, a1))
    T2, T3, T4, T5 = T * T, T ** 3, T ** 4, T ** 5
    c0, c1, c2 = p0, v0, a0 / 2.0
    h = p1 - p0
    c3 = (20 * h - (8 * v1 + 12 * v0) * T - (3 * a0 - a1) * T2) / (2 * T3)
    c4 = (-30 * h + (14 * v1 + 16 * v0) * T + (3 * a0 - 2 * a1) * T2) / (2 * T4)
    c5 = (12 * h - 6 * (v1 + v0) * T - (a0 - a1) * T2) / (2 * T5)
    return np.stack([c0, c1, c2, c3, c4, c5])


def poly_eval(c: np.ndarray, tau: float, deriv: int = 0) -> np.ndarray:
    """Value (deriv 0), velocity (1) or acceleration (2) of a quintic at τ."""
    out = np.zeros(c.shape[1:])
    for k in range(deriv, 6):
        f = math.factorial(k) / math.factorial(k - deriv)
        out = out + f * c[k] * tau ** (k - deriv)
    return out


@dataclass
class Segment:
    """One quintic segment from t0 to t1 (controller time)."""

    seg_id: int
    t0: float
    t1: float
    pos: np.ndarray  # 6×3 coefficients
    R0: np.ndarray
    rot: np.ndarray  # 6×3 coefficients of φ
    done_reported: bool = False

    def state(self, t: float):
        """(p, v, a, R, ω) at time t, clamped to the segment."""
        tau = min(max(t - self.t0, 0.0), self.t1 - self.t0)
        p = poly_eval(self.pos, tau)
        v = poly_eval(self.pos, tau, 1)
        a = poly_eval(self.pos, tau, 2)
        phi = poly_eval(self.rot, tau)
        R = self.R0 @ rotvec_to_matrix(phi)
        w = self.R0 @ poly_eval(self.rot, tau, 1)  # approximately the angular velocity (base frame)
        return p, v, a, R, w


class RobotEmulator:
    """The robot controller: ``receive(data, t)`` request bytes, ``read_output()`` reply bytes."""

    def __init__(self, clock: Callable[[], float], limits=None, *, queue_size: int = QUEUE_SIZE,
                 start_pose: np.ndarray | None = None):
        from ...config import RobotConfig

        cfg = limits if limits is not None else RobotConfig()
        self.clock = clock
        self.box_min = np.asarray(cfg.workspace_min_mm, float)
        self.box_max = np.asarray(cfg.workspace_max_mm, float)
        self.v_max = float(cfg.v_max_mm_s)
        self.a_max = float(cfg.a_max_mm_s2)
        self.w_max = math.radians(cfg.w_max_deg_s)
        self.watchdog_s = float(cfg.watchdog_s)
        self.home_T = make_T(_rpy(*HOME_RPY), cfg.home_mm)
        self.queue_size = queue_size
        self.now = float(clock())
        T0 = self.home_T if start_pose is None else np.asarray(start_pose, float)
        self._rest_p = T0[:3, 3].copy()
        self._rest_R = T0[:3, :3].copy()
        self.segments: list[Segment] = []  # scheduled and recent ones, in time order
        self.history_s = 600.0
        self.last_request_t = self.now
        self.fault: str | None = None
        self.last_segment_id = 0
        self.watchdog_trips = 0
        self.out = bytearray()
        self._line = bytearray()
        self._overlong = False
        self._write(f"@BOOT {IDENT}\n")

    def power_cycle(self) -> None:
        """Controller reset: the brakes stop the arm where it is; queue, fault and line are lost."""
        self.advance(max(self.now, self.clock()))
        if self._moving_at(self.now):
            self._stop_at(self.now)
        self.fault = None
        self._line.clear()
        self._write(f"@BOOT {IDENT}\n")

    # --- wire -------------------------------------------------------------------------------
    def _write(self, text: str) -> None:
        """Send lines, each with its ``*HH`` checksum."""
        for line in text.splitlines():
            self.out += (add_checksum(line) + "\n").encode("ascii")

    def read_output(self) -> bytes:
        self.advance(max(self.now, self.clock()))
        data = bytes(self.out)
        self.out.clear()
        return data

    def receive(self, data: bytes, t: float | None = None) -> None:
        self.advance(max(self.now, self.clock() if t is None else t))
        for b in bytes(data):
            if b == 0x0A:
                line = self._line.decode("ascii", errors="replace")
                overlong = self._overlong
                self._line.clear()
                self._overlong = False
                if overlong:
                    self._write("@ERR E04 line too long\n")
                elif line.strip():
                    self._handle(line)
            elif b == 0x0D:
                continue
            elif len(self._line) >= MAX_LINE:
                self._overlong = True
            else:
                self._line.append(b)

    # --- time -------------------------------------------------------------------------------
    def advance(self, t: float) -> None:
        """Run the controller up to time t: segment completions (@DONE) and the watchdog."""
        if t <= self.now:
            return
        while True:
            trip = self.last_request_t + self.watchdog_s
            pending = [s for s in self.segments if not s.done_reported]
            next_done = min((s.t1 for s in pending), default=math.inf)
            if trip < next_done and trip <= t and self._moving_at(trip) and self.fault is None:
                self.now = max(self.now, trip)
                self.watchdog_trips += 1
                self._stop_at(self.now)
                self.fault = "watchdog"
                self._write(f"@WATCHDOG {self.watchdog_s:g}\n")
                continue
            if next_done <= t:
                self.now = max(self.now, next_done)
                for s in pending:
                    if s.t1 <= next_done:
                        s.done_reported = True
                        if s.seg_id >= 0:
                            self._write(f"@DONE {s.seg_id}\n")
                        _, v, _, _, w = s.state(s.t1)
                        followed = any(o.t0 >= s.t1 and o is not s for o in self.segments)
                        if not followed and (np.linalg.norm(v) > 1e-9 or np.linalg.norm(w) > 1e-9):
                            self._stop_at(s.t1)  # no next segment to carry the end velocity: come to rest
                continue
            break
        self.now = t
        horizon = t - self.history_s
        while len(self.segments) > 1 and self.segments[0].t1 < horizon and self.segments[0].done_reported:
            self.segments.pop(0)

    def _moving_at(self, t: float) -> bool:
        return any(s.t0 <= t < s.t1 for s in self.segments) or any(s.t0 > t for s in self.segments)

    @property
    def moving(self) -> bool:
        self.advance(max(self.now, self.clock()))
        return self._moving_at(self.now)

    def state_at(self, t: float):
        """(p, v, a, R, ω) of the flange at time t (mm, mm/s, mm/s², 3×3, rad/s)."""
        seg = None
        for s in self.segments:
            if s.t0 <= t:
                seg = s
            else:
                break
        if seg is None:
            first = self.segments[0] if self.segments else None
            if first is not None and t < first.t0:
                p, _, _, R, _ = first.state(first.t0)
                return p, np.zeros(3), np.zeros(3), R, np.zeros(3)
            return self._rest_p.copy(), np.zeros(3), np.zeros(3), self._rest_R.copy(), np.zeros(3)
        p, v, a, R, w = seg.state(t)
        if t > seg.t1:  # at rest after the last segment
            v, a, w = np.zeros(3), np.zeros(3), np.zeros(3)
        return p, v, a, R, w

    def flange_pose_at(self, t: float) -> np.ndarray:
        """``T_base_flange`` (4×4, mm) at time t (exact for t up to now; planned motion beyond)."""
        if t <= self.clock():
            self.advance(max(self.now, t))
        p, _, _, R, _ = self.state_at(t)
        return make_T(R, p)

    @property
    def segment_id(self) -> int:
        sid = 0
        for s in self.segments:
            if s.t0 <= self.now and s.seg_id >= 0:
                sid = s.seg_id
        return sid

    # --- motion -----------------------------------------------------------------------------
    def _cut_at(self, t: float) -> None:
        """Drop everything scheduled after t; the running segment ends at t."""
        kept = []
        for s in self.segments:
            if s.t0 >= t and not (s.t0 == t and s.t1 == t):
                continue
            kept.append(s)
        self.segments = kept

    def _plan(self, seg_id: int, p1, R1, T: float, v1, w1, t0: float, start) -> Segment | int:
        p0, v0, a0, R0, w0 = start
        pos = quintic_coeffs(p0, v0, a0, p1, v1, np.zeros(3), T)
        phi1 = matrix_to_rotvec(R0.T @ R1)
        rot = quintic_coeffs(np.zeros(3), R0.T @ w0, np.zeros(3), phi1, R0.T @ w1, np.zeros(3), T)
        taus = np.linspace(0.0, T, 81)
        for tau in taus:
            p = poly_eval(pos, tau)
            if np.any(p < self.box_min - 1e-6) or np.any(p > self.box_max + 1e-6):
                return 10
        speeds = [float(np.linalg.norm(poly_eval(pos, tau, 1))) for tau in taus]
        if max(speeds) > self.v_max * (1 + 1e-6):
            return 12
        accels = [float(np.linalg.norm(poly_eval(pos, tau, 2))) for tau in taus]
        if max(accels) > self.a_max * (1 + 1e-6):
            return 13
        omegas = [float(np.linalg.norm(poly_eval(rot, tau, 1))) for tau in taus]
        if max(omegas) > self.w_max * (1 + 1e-6):
            return 14
        return Segment(seg_id, t0, t0 + T, pos, R0, rot)

    def _stop_at(self, t: float) -> None:
        """Bring the flange to rest from its state at t with a short quintic (no limit checks)."""
        p, v, a, R, w = self.state_at(t)
        self._cut_at(t)
        for s in self.segments:
            if s.t1 > t:
                s.t1 = t
                s.done_reported = True
        speed = float(np.linalg.norm(v))
        T = max(2.0 * speed / self.a_max, 1.5 * float(np.linalg.norm(w)) / max(self.w_max, 1e-6), 0.05)
        p1 = p + v * T / 2.0
        R1 = R @ rotvec_to_matrix(R.T @ w * T / 2.0)
        pos = quintic_coeffs(p, v, a, p1, np.zeros(3), np.zeros(3), T)
        rot = quintic_coeffs(np.zeros(3), R.T @ w, np.zeros(3), matrix_to_rotvec(R.T @ R1), np.zeros(3),
                             np.zeros(3), T)
        self.segments.append(Segment(-1, t, t + T, pos, R, rot))

    # --- commands ---------------------------------------------------------------------------
    def _reply(self, seq: int, fields: str = "") -> None:
        self._write(f"${seq} ok{(' ' + fields) if fields else ''}\n")

    def _error(self, seq: int, code: int) -> None:
        self._write(f"${seq} E{code:02d} {ERROR_CODES.get(code, 'error')}\n")

    def _handle(self, line: str) -> None:
        req = parse_request(line)
        if isinstance(req, int):
            seq = line.strip()[1:].split(" ", 1)[0]
            if req == 5 and seq.isdigit() and len(seq) <= 5:
                self._error(int(seq), 5)  # the sender learns at once that its line was damaged
            else:
                self._write(f"@ERR E{req:02d} {ERROR_CODES[req]}\n")
            return
        self.last_request_t = self.now
        handler = getattr(self, "_cmd_" + req.command.lower(), None) if req.command.isalpha() else None
        if handler is None:
            self._error(req.seq, 1)
            return
        handler(req)

    def _cmd_hello(self, req: Request) -> None:
        self._reply(req.seq, f"{IDENT} queue={self.queue_size}")

    def _cmd_hb(self, req: Request) -> None:
        self._reply(req.seq)

    def _cmd_clear(self, req: Request) -> None:
        self.fault = None
        self._reply(req.seq)

    def _cmd_stop(self, req: Request) -> None:
        if self._moving_at(self.now):
            self._stop_at(self.now)
        self._reply(req.seq)

    def _cmd_limits(self, req: Request) -> None:
        vals = [*self.box_min, *self.box_max, self.v_max, self.a_max, math.degrees(self.w_max), self.watchdog_s]
        self._reply(req.seq, " ".join(f"{v:g}" for v in vals))

    def _cmd_status(self, req: Request) -> None:
        p, _, _, R, _ = self.state_at(self.now)
        rv = matrix_to_rotvec(R)
        moving = 1 if self._moving_at(self.now) else 0
        queued = sum(1 for s in self.segments if s.t0 > self.now)
        fault = self.fault or "none"
        self._reply(req.seq, " ".join(f"{v:.4f}" for v in (*p, *rv))
                    + f" {moving} {self.segment_id} {queued} {self.now:.4f} {fault}")

    def _cmd_home(self, req: Request) -> None:
        if self.fault:
            self._error(req.seq, 40 if self.fault == "watchdog" else 41)
            return
        p0 = self.state_at(self.now)[0]
        d = float(np.linalg.norm(self.home_T[:3, 3] - p0))
        # a rest-to-rest quintic peaks at 1.875·d/T in speed and 5.77·d/T² in acceleration
        T = max(1.0, 1.875 * d / (0.5 * self.v_max), math.sqrt(5.78 * d / (0.5 * self.a_max)), 3.0)
        self._queue_segment(req.seq, 0, self.home_T[:3, 3], self.home_T[:3, :3], T, np.zeros(3), np.zeros(3),
                            replace=True)

    def _parse_segment(self, req: Request):
        if len(req.args) not in (8, 14):
            return 2
        try:
            vals = [float(a) for a in req.args]
        except ValueError:
            return 2
        if not all(math.isfinite(v) for v in vals) or vals[0] != int(vals[0]) or vals[0] < 0:
            return 2
        seg_id = int(vals[0])
        p1 = np.array(vals[1:4])
        R1 = rotvec_to_matrix(np.array(vals[4:7]))
        T = vals[7]
        if not (0.0 < T <= MAX_DURATION_S):
            return 11
        v1 = np.array(vals[8:11]) if len(vals) == 14 else np.zeros(3)
        w1 = np.array(vals[11:14]) if len(vals) == 14 else np.zeros(3)
        return seg_id, p1, R1, T, v1, w1

    def _cmd_seg(self, req: Request, replace: bool = False) -> None:
        if self.fault:
            self._error(req.seq, 40 if self.fault == "watchdog" else 41)
            return
        parsed = self._parse_segment(req)
        if isinstance(parsed, int):
            self._error(req.seq, parsed)
            return
        self._queue_segment(req.seq, *parsed, replace=replace)

    def _cmd_segnow(self, req: Request) -> None:
        self._cmd_seg(req, replace=True)

    def _queue_segment(self, seq, seg_id, p1, R1, T, v1, w1, replace: bool) -> None:
        if replace:
            t0 = self.now
            start = self.state_at(t0)
        else:
            queued = sum(1 for s in self.segments if s.t0 > self.now)
            if queued >= self.queue_size:
                self._error(seq, 20)
                return
            last = max((s.t1 for s in self.segments), default=-math.inf)
            t0 = max(self.now, last)
            start = self._end_state() if last > self.now else self.state_at(self.now)
        seg = self._plan(seg_id, p1, R1, T, v1, w1, t0, start)
        if isinstance(seg, int):
            self._error(seq, seg)
            return
        if replace:
            self._cut_at(t0)
            for s in self.segments:
                if s.t1 > t0:
                    s.t1 = t0
                    s.done_reported = True
        self.segments.append(seg)
        self.last_segment_id = seg_id
        self._reply(seq, f"{seg.t0:.4f} {seg.t1:.4f}")

    def _end_state(self):
        last = max(self.segments, key=lambda s: s.t1)
        p, v, a, R, w = last.state(last.t1)
        return p, v, np.zeros(3), R, w


def _rpy(rx: float, ry: float, rz: float) -> np.ndarray:
    from ...geometry import rot_x, rot_y, rot_z

    return rot_z(rz) @ rot_y(ry) @ rot_x(rx)
