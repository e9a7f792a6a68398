"""Could a real arm have flown these runs? The commanded motion of run records checked against an arm model.

A run record's ``segment`` events hold every command the robot controller accepted: the target pose
(``p``, ``rotvec``: the wire's values), the controller's start and end times (``t0c``, ``t1c``). The
controller's exact trajectory is recovered by sending the same ``SEGNOW`` lines, at the same controller
times, to a fresh reference controller (:class:`labctl.sim.emulators.robot.RobotEmulator`) with the
lab's limits, started at the lab's home pose: it splices each segment in from its own state as it did
in the run. Ruckig segments run under the limits the run's segments carried
(:func:`labctl.planning.ruckig_interception.ruckig_limits`, on the wire against the controller's own);
a segment the host planned as a quintic (its ruckig fallback) is recognised by the host's planned
positions in the record (the ``robot`` events with ``planned``), which it then matches. The trajectory is
sampled every ``dt_s`` and followed in joint space by :meth:`labctl.planning.arm.ArmModel.follow`.

Per trial: every commanded target reachable (IK from 24 seeds), the whole path followable from the home
configuration (no configuration change, within joint limits), and the peak joint-speed ratio.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import UserInputError
from ..geometry import make_T, rotvec_to_matrix

DT_S = 0.004  # the sampling of the recovered trajectory (a 250-Hz servo)
PROFILE_MATCH_MM = 5.0  # the host's copy of the plan is re-timed by its latency estimate: a few ms off


@dataclass
class Trajectory:
    """The controller's trajectory of one run: sample times (s), ``T_w_F`` poses (N×4×4), the kind of
    segment (the run's stage: initial1, standard, …) running at each sample, and the commanded targets."""

    t: np.ndarray
    poses: np.ndarray
    kinds: list[str]
    targets: list[np.ndarray]
    profiles: list[str] = field(default_factory=list)
    max_end_error_s: float = 0.0  # largest |t1 replayed − t1c recorded| over the segments


@dataclass
class TrialFeasibility:
    """One run record against one arm."""

    name: str
    trajectory: str | None
    speed_mm_s: float | None
    n_targets: int
    n_reachable: int
    followed: bool
    reason: str | None
    failed_kind: str | None
    speed_ratio: list[float]
    n_samples: int

    @property
    def within_speeds(self) -> bool:
        """Followed, with every joint within its speed limit."""
        return self.followed and max(self.speed_ratio) <= 1.0


def read_events(path: Path) -> list[dict]:
    """The events of a run record (``events.jsonl``)."""
    with path.open(encoding="utf-8") as fh:
        return [json.loads(line) for line in fh if line.strip()]


def find_records(runs_dir: Path) -> list[Path]:
    """Every run record folder under ``runs_dir`` (a trials sweep, a runs folder, or one record)."""
    runs_dir = Path(runs_dir)
    if not runs_dir.is_dir():
        raise UserInputError(f"{runs_dir}: not a folder")
    found = sorted(p.parent for p in runs_dir.rglob("events.jsonl"))
    if not found:
        raise UserInputError(f"{runs_dir}: no run records (events.jsonl) in it")
    return found


def _segnow(seq: int, e: dict, duration: float, profile: str, wire: dict[str, float]) -> bytes:
    from ..drivers.robot_protocol import fmt_num

    nums = [*e["p"], *e["rotvec"], duration]
    words = [f"#{seq}", "SEGNOW", str(int(e["id"])), *(fmt_num(float(x)) for x in nums)]
    if profile == "ruckig":
        words += ["profile=ruckig", *(f"{k}={fmt_num(v)}" for k, v in wire.items())]
    return (" ".join(words) + "\n").encode("ascii")


def recover_trajectory(events: list[dict], lab, dt_s: float = DT_S) -> Trajectory:
    """The reference controller's exact trajectory for a record's commands (see the module docstring)."""
    from ..planning.ruckig_interception import controller_limits, ruckig_limits
    from ..sim.emulators.robot import RobotEmulator
    from ..sim.world import home_flange_pose

    segs = [e for e in events if e.get("event") == "segment"]
    planned = [(e["t"], np.asarray(e["p"], float)) for e in events if e.get("event") == "robot" and e.get("planned")]
    home = home_flange_pose(lab)
    # the heartbeat is not in the record; the watchdog never tripped in a run that carried on
    cfg = dataclasses.replace(lab.robot, watchdog_s=1e9)
    now = [0.0]
    emu = RobotEmulator(lambda: now[0], cfg, start_pose=home)
    emu.receive(b"#1 HELLO 1.2\n", 0.0)
    emu.read_output()
    wire = ruckig_limits(lab.robot, lab.config.run.robot_stop_budget_s).wire(controller_limits(lab.robot))
    profiles, seq, worst = [], 1, 0.0
    spans: list[tuple[float, str]] = []
    for k, e in enumerate(segs):
        t0, t1 = float(e["t0c"]), float(e["t1c"])
        t_next = float(segs[k + 1]["t0c"]) if k + 1 < len(segs) else math.inf
        checks = [(t, p) for t, p in planned if t0 <= t < min(t_next, t1)]
        best = None
        for profile in ("ruckig", "quintic"):
            seq += 1
            now[0] = t0
            emu.receive(_segnow(seq, e, round(t1 - t0, 4), profile, wire), t0)
            reply = next((ln.split() for ln in emu.read_output().decode("ascii", "replace").splitlines()
                          if ln.startswith(f"${seq} ")), [])
            if len(reply) < 4 or reply[1] != "ok":
                continue
            err = max((float(np.linalg.norm(emu.state_at(t)[0] - p)) for t, p in checks), default=0.0)
            end_err = abs(float(reply[3].partition("*")[0]) - t1)
            if best is None or err < best[0] - 1e-9:
                best = (err, profile, end_err)
            if err <= PROFILE_MATCH_MM:
                break
        if best is None:
            raise UserInputError(f"segment {e['id']} at t={t0:.4f} s: the reference controller refuses it")
        if best[1] != profile:  # the earlier profile matched better: send it again (SEGNOW replaces at t0)
            seq += 1
            emu.receive(_segnow(seq, e, round(t1 - t0, 4), best[1], wire), t0)
            emu.read_output()
        profiles.append(best[1])
        worst = max(worst, best[2])
        spans.append((t0, str(e.get("kind", ""))))
    if not segs:
        t = np.array([0.0])
        return Trajectory(t, home[None], [""], [home], [], 0.0)
    t_start = float(segs[0]["t0c"])
    t_end = max(s.t1 for s in emu.segments)
    t = np.arange(t_start, t_end + dt_s, dt_s)
    t[-1] = min(t[-1], t_end)
    poses = np.empty((len(t), 4, 4))
    for i, ti in enumerate(t):
        p, _, _, R, _ = emu.state_at(float(ti))
        poses[i] = make_T(R, p)
    starts = np.array([s for s, _ in spans])
    kinds = [spans[max(int(np.searchsorted(starts, ti, side="right")) - 1, 0)][1] for ti in t]
    targets = [home] + [make_T(rotvec_to_matrix(np.asarray(e["rotvec"], float)), e["p"]) for e in segs]
    return Trajectory(t, poses, kinds, targets, profiles, worst)


def home_configurations(arm, lab) -> list[np.ndarray]:
    """The arm's configurations at the lab's home pose, one per branch (joints within ±π), nearest its home."""
    from ..sim.world import home_flange_pose

    sols = [q for q in arm.ik_solutions(home_flange_pose(lab)) if np.all(np.abs(q) <= math.pi + 1e-9)]
    seen, out = set(), []
    for q in sols:
        b = arm.configuration(q)
        if b not in seen:
            seen.add(b)
            out.append(q)
    return out


def check_trial(arm, traj: Trajectory, q0, name: str, meta: dict, reach_cache: dict | None = None) -> TrialFeasibility:
    """One trial's targets and path against ``arm`` from start configuration ``q0`` (None: home unreachable)."""
    cache = {} if reach_cache is None else reach_cache
    n_ok = 0
    for T in traj.targets:
        key = tuple(np.round(T[:3, :4].ravel(), 6))
        if key not in cache:
            cache[key] = arm.reachable(T)
        n_ok += cache[key]
    reason: str | None
    failed_kind: str | None
    if q0 is None:
        followed, reason, failed_kind, ratio, qs = False, "unreachable", traj.kinds[0], [0.0] * 6, np.empty((0, 6))
    else:
        res = arm.follow(traj.poses, q0)
        followed, reason = res.ok, res.reason
        failed_kind = None if res.ok else traj.kinds[res.failed_at]
        qs = res.qs
        if not res.ok:
            reason = f"{reason} ({near_singularity(arm, qs[-1] if len(qs) else q0)})"
        n = len(qs)
        ratio = [float(x) for x in arm.joint_speed_ratio(qs, traj.t[:n])]  # poses[0] is the home pose, at q0
    return TrialFeasibility(name, meta.get("trajectory"), meta.get("speed_mm_s"), len(traj.targets), n_ok, followed,
                            reason, failed_kind, ratio, len(qs))


def near_singularity(arm, q) -> str:
    """Which singularity configuration ``q`` is nearest, by its margins (:meth:`ArmModel.singularity_margins`):
    shoulder within 50 mm of the base-axis cylinder, elbow or wrist within sin 6° of aligned; else none."""
    m = arm.singularity_margins(q)
    near = [name for name, close in (("shoulder singularity", m["shoulder_mm"] < 50.0),
                                     ("elbow singularity", m["elbow"] < 0.1), ("wrist singularity", m["wrist"] < 0.1))
            if close]
    return ", ".join(near) if near else "no singularity near"


def feasibility(runs_dir: Path, arm, lab, *, dt_s: float = DT_S, log=None) -> dict:
    """Every record under ``runs_dir`` against ``arm``: the summary table's numbers and each trial's.

    The start configuration is the one of the home pose's branches that follows the most trials (a lab
    keeps its arm in one)."""
    records = find_records(runs_dir)
    trajs = []
    for rec in records:
        meta_path = rec / "meta.json"
        meta = json.loads(meta_path.read_text(encoding="utf-8")) if meta_path.is_file() else {}
        trajs.append((rec.name, meta, recover_trajectory(read_events(rec / "events.jsonl"), lab, dt_s)))
        if log:
            log(f"recovered {rec.name}: {len(trajs[-1][2].t)} samples")
    starts: list[np.ndarray | None] = [*home_configurations(arm, lab)] or [None]
    cache: dict = {}
    best = None
    for q0 in starts:
        rows = [check_trial(arm, tr, q0, name, meta, cache) for name, meta, tr in trajs]
        score = (sum(r.within_speeds for r in rows), sum(r.followed for r in rows))
        if log:
            log(f"start {None if q0 is None else np.round(np.degrees(q0), 1).tolist()}: "
                f"{score[1]} followed, {score[0]} within speeds")
        if best is None or score > best[0]:
            best = (score, q0, rows)
    assert best is not None  # starts is never empty
    _, q0, rows = best
    return summarise(rows, q0, arm, [tr for _, _, tr in trajs])


def summarise(rows: list[TrialFeasibility], q0, arm, trajs: list[Trajectory]) -> dict:
    """The table's numbers: percentages, failure causes and joint-speed ratios."""
    n = len(rows)
    n_targets = sum(r.n_targets for r in rows)
    causes = Counter(f"{r.reason} during {r.failed_kind}" for r in rows if not r.followed)
    fast = Counter(f"joint {int(np.argmax(r.speed_ratio)) + 1}" for r in rows if r.followed and not r.within_speeds)
    over = [max(r.speed_ratio) for r in rows if r.followed and not r.within_speeds]
    return {
        "arm": arm.name,
        "base_xyz_mm": [float(x) for x in arm.T_w_base[:3, 3]],
        "trials": n,
        "targets": n_targets,
        "targets_reachable_pct": 100.0 * sum(r.n_reachable for r in rows) / max(n_targets, 1),
        "followed_pct": 100.0 * sum(r.followed for r in rows) / max(n, 1),
        "within_speeds_pct": 100.0 * sum(r.within_speeds for r in rows) / max(n, 1),
        "start_deg": None if q0 is None else [round(float(x), 2) for x in np.degrees(q0)],
        "start_branch": None if q0 is None else list(arm.configuration(q0)),
        "failures": dict(causes.most_common()),
        "over_speed": dict(fast.most_common()),
        "median_over_speed_ratio": float(np.median(over)) if over else None,
        "peak_speed_ratio": [float(x) for x in np.max([r.speed_ratio for r in rows if r.followed], axis=0)]
        if any(r.followed for r in rows) else None,  # per joint, over the trials followed
        "profiles": dict(Counter(p for tr in trajs for p in tr.profiles)),
        "max_end_error_s": max((tr.max_end_error_s for tr in trajs), default=0.0),
        "samples": int(sum(len(tr.t) for tr in trajs)),
        "per_trial": [{**dataclasses.asdict(r), "within_speeds": r.within_speeds} for r in rows],
    }
