"""The virtual-time runtime: one process, a simulated clock, as fast as the CPU allows.

The world, the GRBL table emulator, the robot-controller emulator and both cameras run on one
:class:`~labctl.sim.clock.VirtualClock`; the two workers' logic (:class:`PredictorPlanner`,
:class:`Recognizer`) is the same code the live runtime runs in two processes, and every message
between them goes through the binary codec, so its bytes are counted as on the 9600-bps link.
The drivers talk to the emulators through in-process ports in the real protocols. Deterministic
for a given seed. This is what ``labctl trials`` and most tests use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import cast

import numpy as np

from ..config import Lab
from ..decisions import messages as m
from ..decisions.context import RunContext
from ..decisions.predictor import PredictorPlanner
from ..decisions.recognizer import Recognizer
from ..decisions.segment_defaults import set_segment_defaults
from ..drivers.interfaces import Frame
from ..timebase import wire_time_s


@dataclass(frozen=True)
class TrialSpec:
    """One virtual trial: trajectory, table speed (mm/s), object (None: chosen by the seed), seed and the
    robot's segment profile (None: lab.yaml's ``run.profile``)."""
    trajectory: str = "line"
    speed_mm_s: float = 8.0
    object_name: str | None = None
    seed: int = 0
    profile: str | None = None


class LinkMeter:
    """Byte and message counts of the host link, per message type (9600 bps: 10 bits a byte)."""

    def __init__(self):
        self.bytes: dict[str, int] = {}
        self.count: dict[str, int] = {}

    def carry(self, msg: m.Message) -> m.Message:
        """Encode and decode ``msg`` as the host link would, counting its bytes by message type."""
        data = m.encode(msg)
        name = type(msg).__name__
        self.bytes[name] = self.bytes.get(name, 0) + len(data)
        self.count[name] = self.count.get(name, 0) + 1
        return m.decode(data)

    def summary(self, duration_s: float, baud: int = 9600) -> dict:
        """Bytes and messages by type, the total, and the link utilisation at ``baud`` over ``duration_s`` (s)."""
        total = sum(self.bytes.values())
        return {"bytes": dict(self.bytes), "messages": dict(self.count), "total_bytes": total,
                "utilisation": wire_time_s(total, baud) / duration_s if duration_s > 0 else 0.0}


def choose_object(ctx: RunContext, spec: TrialSpec, rng: np.random.Generator) -> str:
    """The object of the trial: the one named in ``spec`` (checked against the library), else one drawn with ``rng``."""
    if spec.object_name is not None:
        if spec.object_name not in ctx.library:
            from ..errors import UserInputError

            raise UserInputError(f"no object {spec.object_name!r} in the library (have: {', '.join(ctx.names)})")
        return spec.object_name
    return ctx.names[int(rng.integers(len(ctx.names)))]


def simulate_run(lab: Lab, ctx: RunContext, spec: TrialSpec, record=None, *, heartbeat_s: float = 0.2) -> dict:
    """One complete run in virtual time; returns the result with the simulator's ground truth.

    The fixed camera's frames go only to the marker tracker, which reads red pixels, all of them
    on the object: they are rendered in the object's window, without silhouette anti-aliasing,
    the rest a flat table grey (``labctl bench sim`` times it against whole anti-aliased frames;
    the results are the same).
    """
    from ..sim.clock import VirtualClock
    from ..sim.lab import Scene, SimLab
    from ..sim.world import SimObject, random_placement
    from .simlab import trajectory_program
    from .stopping import stop_devices

    rng = np.random.default_rng(spec.seed)
    name = choose_object(ctx, spec, rng)
    sim_obj = SimObject.from_library(ctx.library[name])
    placement = random_placement(sim_obj, rng)
    start_xy, program = trajectory_program(spec.trajectory, spec.speed_mm_s, lab)
    clock = VirtualClock()
    sim = SimLab.build(lab, clock, scene=Scene(sim_obj, placement), table_start_mm=start_xy)
    sim.open()  # opening the drivers takes virtual time (banner, queries)
    world = sim.world
    rest = sim.robot.ensure_ready()  # as the live run does when it opens the robot, before its start
    set_segment_defaults(sim.robot, lab, spec.profile)  # as the live run does, before its start
    t0 = clock.now()

    record_event = record.event if record is not None else (lambda *a, **k: None)
    counts = {"track_bridged": 0, "marker_lost": 0}

    def log(event, **fields):  # the tracker's bridges and losses counted for the result, as recorded
        if event in counts:
            counts[event] += 1
        record_event(event, **fields)

    save = record.save_image if record is not None else None
    meter = LinkMeter()
    outbox: list[m.Message] = []
    predictor = PredictorPlanner(ctx, sim.robot, outbox.append, log, t_start=t0, clock=clock.now,
                                 profile=spec.profile, rest=rest, shared_clock=True,
                                 family=None if lab.table is None else spec.trajectory)
    seq = {"mobile": 0}

    mobile_period = 1.0 / float(lab.mobile_camera.fps or 30.0)

    def grab_mobile() -> Frame:
        # exposed now (the robot stands still), delivered one frame time later: exposure and read-out
        # take a frame period, which the honest bound counts too (tti_bound)
        seq["mobile"] += 1
        t = clock.now()
        sim.advance(t)
        image = world.render("mobile", t, rng).image
        sim.advance(clock.advance(mobile_period))
        return Frame(image, t, seq["mobile"])

    recognizer = Recognizer(ctx, grab_mobile, log, save)
    log("truth", t=t0, object=name, placement=world.truth(t0).to_dict()["placement"], seed=spec.seed)
    from ..decisions.predictor import ProgramProgress

    progress = ProgramProgress(sim.table.start_program(program), log)  # pumped by the loop, never waited on

    dt = 1.0 / ctx.lab.config.run.fps
    catch_up = ctx.lab.config.run.catch_up_frames
    # Until the first sighting, a frame comes one period after the predictor is free; from then on the fixed
    # camera exposes frame k at grid0 + k·dt, whether or not the predictor is free to take it, and the
    # predictor catches up on the ones exposed while it was busy (run.catch_up_frames; a robot command's round
    # trip is 5-6 frames). Catching up before the first sighting too moved the start by up to a frame and
    # made the predictor commit on more frames of the object standing while the table's program started:
    # 50 of 60 trials at 50 mm/s failed (docs/notes/planning.md, "Frames caught up").
    grid0: float | None = None
    n = fixed_seq = 0
    hid_any = hid_all = 0  # fixed-camera frames in which the arm hides a facing marker / every facing marker
    next_beat = 0.0
    def deliver() -> None:
        while outbox:
            for reply in recognizer.handle(meter.carry(outbox.pop(0))):
                predictor.on_message(meter.carry(reply), clock.now())

    while not predictor.finished:
        t_frame = clock.now() + dt if grid0 is None else max(grid0 + (n + 1) * dt, clock.now())
        wake = predictor.wake_at()
        if wake is not None and clock.now() < cast(float, predictor.t1c) + 1e-4 < t_frame <= wake:
            # the arrival falls before the next frame and its @DONE reaches the host after it: the controller
            # still sends it at the arrival, so its port is read there (the line is queued when it is read)
            clock.sleep_until(cast(float, predictor.t1c) + 1e-4)
            sim.advance(clock.now())
            sim.robot.poll()
        if wake is not None and clock.now() < wake < t_frame:
            # the robot's arrival (run.image_at_arrival: its image is requested then) or its @DONE falls between
            # two frames: act on it then, not at the next frame. The emulator sends the @DONE when it is
            # advanced past the arrival, so it is advanced to the arrival first (+0.1 ms: the reply
            # gives the arrival to 1 µs, rounded either way).
            clock.sleep_until(min(cast(float, predictor.t1c) + 1e-4, wake))  # set: an arrival is awaited
            sim.advance(clock.now())
            sim.robot.poll()
            clock.sleep_until(wake)
            sim.advance(wake)
            progress.pump(wake)
            predictor.tick(wake)
            deliver()
        clock.sleep_until(t_frame)
        t = clock.now()
        if grid0 is None:
            times = [t]
        else:
            newest = int(math.floor((t - grid0) / dt + 1e-9))
            times = [grid0 + k * dt for k in range(max(n + 1, newest - catch_up + 1), newest + 1)]
            n = newest
        sim.advance(t)
        progress.pump(t)
        frames = []
        for tk in times:
            # the tracker reads only the red markers, all on the object: render its footprint only
            image = world.render("fixed", tk, rng, window="object", supersample=1).image
            facing, hidden = world.arm_hides_markers("fixed", tk)
            hid_any += hidden > 0
            hid_all += facing > 0 and hidden == facing
            fixed_seq += 1
            frames.append(Frame(image, tk, fixed_seq))
        predictor.on_frames(frames)
        if grid0 is None and predictor.t_first_seen is not None:
            grid0, n = predictor.t_first_seen, 0
        deliver()
        # both workers' heartbeats, carried like the real ones, after the frame's decisions as the live loop sends
        # them (before them, a beat due on the first sighting held the first leg's command ~20 ms); the robot's
        # waits for an arrival within its round trip
        now = clock.now()
        if now >= next_beat and not predictor.finished and not predictor.heartbeat_can_wait(now, now - next_beat):
            for role in ("predictor", "recognizer"):
                meter.carry(m.Heartbeat(role=role, seq=fixed_seq % 65536, t=now))
            sim.robot.heartbeat()
            next_beat = now + heartbeat_s
        if t - t0 > ctx.lab.config.run.timeout_s + 5:
            predictor.fail(t, "virtual run exceeded its time-out")
    t_end = clock.now()
    stop_devices(sim.drivers())
    result = predictor.result(t_end)
    if record is not None and result.get("identity") is None:  # the report leads with what the camera saw
        # a whole frame (the run's own are the object's window only), drawn with its own noise: the run's
        # random stream is left as it was
        record.save_image("fixed_last", world.render("fixed", t_end, np.random.default_rng(0)).image)
    truth = world.truth(t_end)
    result.update({
        "true_identity": name,
        "correct": result["identity"] == name,
        "seed": spec.seed,
        "trajectory": spec.trajectory,
        "speed_mm_s": spec.speed_mm_s,
        "profile": predictor.profile,  # the robot segment profile the run used
        "sim_time_s": t_end - t0,
        "link": meter.summary(t_end - t0),
        "truth": {"placement": truth.to_dict()["placement"]},
        # the simulated arm's occlusions of the markers in the fixed camera (ground truth) and the tracker's answer
        "arm_occlusion": {"fixed_frames": fixed_seq, "frames_any_hidden": hid_any, "frames_all_hidden": hid_all,
                          "bridges": counts["track_bridged"], "tracks_lost": counts["marker_lost"],
                          "ik_failures": world.arm.ik_failures if world.arm is not None else 0},
    })
    pose_err = marker_pose_error(predictor, world)
    if pose_err is not None:
        result["marker_pose_error"] = pose_err
    return result


def marker_pose_error(predictor: PredictorPlanner, world) -> dict | None:
    """Error of the resolved marker pose against the nearest true marker at the time it was measured."""
    mp, t = predictor.marker_pose, predictor.t_marker_pose
    if mp is None:
        return None
    truth = world.truth(t)
    if not truth.markers_w:
        return None
    c = np.asarray(mp.center_w)
    i = int(np.argmin([np.linalg.norm(c - tc) for _, tc, _ in truth.markers_w]))
    _, tc, tn = truth.markers_w[i]
    n = np.asarray(mp.normal_w)
    ang = float(np.degrees(np.arctan2(np.linalg.norm(np.cross(n, tn)), float(n @ tn))))
    return {"marker": int(truth.markers_w[i][0]), "center_mm": float(np.linalg.norm(c - tc)), "normal_deg": ang}
