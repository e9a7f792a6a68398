"""A soak of the live loop's long-lived parts in virtual time: is memory flat over an hour?

Everything that runs for the whole of a live run, with the vision taken out (it allocates per
frame and frees per frame; the buffers that grow are elsewhere):

* the GRBL and robot emulators behind the real drivers (:meth:`~labctl.sim.lab.SimLab.build`),
  the table re-streaming the zigzag program whenever it comes to rest, the robot sent a new
  segment every few seconds (``@DONE`` reports accumulate in ``SerialRobot.done_ids``), status
  reports at the drivers' rate, robot heartbeats;
* the host link: a local pipe pair carrying both workers' heartbeats every ``heartbeat_s``, each
  side's :class:`~labctl.runtime.live.PeerWatch`;
* the run record: one event per 30 Hz tick, durable (the writer thread batches the fsyncs).

Resident set size (``/proc/self/statm``) is sampled after a warm-up minute and at the end.
``python -m labctl.experiments.soak [--hours H] [--lab DIR]`` prints the result as JSON.
"""

from __future__ import annotations

import gc
import json
import os
import tempfile
import time
from pathlib import Path

import numpy as np


def rss_bytes() -> int:
    """This process's resident set size (bytes), from /proc/self/statm."""
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def soak(lab, hours: float = 1.0, runs_dir: Path | str | None = None, *, fps: float = 30.0,
         warmup_s: float = 60.0, segment_every_s: float = 3.0, segment_mm: float = 20.0,
         sample_every_s: float = 300.0) -> dict:
    """Run the live loop's long-lived parts for ``hours`` of virtual time; RSS and buffer sizes."""
    from ..decisions import messages as m
    from ..geometry import make_T
    from ..records import RunRecord
    from ..runtime.live import PeerWatch
    from ..runtime.simlab import trajectory_program
    from ..runtime.stopping import stop_devices
    from ..runtime.transport import local_pair
    from ..sim.clock import VirtualClock
    from ..sim.lab import SimLab
    from ..sim.world import home_flange_pose

    clock = VirtualClock()
    start, program = trajectory_program("zigzag", 10.0, lab)
    sim = SimLab.build(lab, clock, devices=("table", "robot"), table_start_mm=start)
    sim.open()
    a, b = local_pair()
    hl = lab.host_link
    watch = {"predictor": PeerWatch("recognizer", hl.dead_after_s, hl.start_timeout_s, clock=clock.now),
             "recognizer": PeerWatch("predictor", hl.dead_after_s, hl.start_timeout_s, clock=clock.now)}
    own_dir = None
    if runs_dir is None:
        own_dir = tempfile.TemporaryDirectory(prefix="labctl-soak-")
        runs_dir = own_dir.name
    record = RunRecord.create(runs_dir, {"command": "soak", "hours": hours})
    T_home = home_flange_pose(lab)
    dt = 1.0 / fps
    t_end = clock.now() + 3600.0 * hours
    next_beat = next_status = next_segment = 0.0
    seg_id = 0
    lost = []
    rss_start = None
    samples = []
    wall0 = time.perf_counter()
    sim.table.stream(program)
    n = 0
    try:
        while clock.now() < t_end:
            n += 1
            t = clock.advance(dt)
            sim.advance(t)
            if t >= next_beat:
                next_beat = t + hl.heartbeat_s
                sim.robot.heartbeat()
                a.send(m.Heartbeat(role="predictor", seq=n % 65536, t=t))
                b.send(m.Heartbeat(role="recognizer", seq=n % 65536, t=t))
                for end, role in ((a, "predictor"), (b, "recognizer")):
                    while end.recv(timeout=0) is not None:
                        watch[role].heard()
                for role, w in watch.items():
                    why = w.lost()
                    if why:
                        lost.append((t, role, why))
            if t >= next_status:
                next_status = t + 0.2
                st = sim.table.status()
                if st.state == "Idle":  # the program ended: run it again
                    sim.table.stream(program)
            if t >= next_segment:
                next_segment = t + segment_every_s
                seg_id += 1
                offset = np.array([segment_mm if seg_id % 2 else -segment_mm, 0.0, 0.0])
                T = make_T(T_home[:3, :3], T_home[:3, 3] + offset)
                sim.robot.segment(T, segment_every_s * 0.6, seg_id)
            sim.robot.poll()
            record.event("tick", t=t, n=n)
            if rss_start is None and t >= warmup_s:
                gc.collect()
                rss_start = rss_bytes()
            if n % int(fps * sample_every_s) == 0:
                samples.append((round(t), rss_bytes()))
        gc.collect()
        rss_end = rss_bytes()
        # measured before the final stop: the stop itself leaves its own (expected) fault report
        buffers = {"robot.done_ids": len(sim.robot.done_ids), "robot.faults": len(sim.robot.faults),
                   "table.messages": len(sim.table.messages), "table.link.buffered": sim.table.link.buffered_bytes,
                   "robot.link.buffered": sim.robot.link.buffered_bytes}
    finally:
        stop_devices(sim.drivers())
        record.close()
        a.close()
        b.close()
    out = {
        "virtual_s": round(clock.now(), 1), "ticks": n, "wall_s": round(time.perf_counter() - wall0, 1),
        "rss_start_mb": round((rss_start or rss_end) / 2**20, 2), "rss_end_mb": round(rss_end / 2**20, 2),
        "rss_growth_mb": round((rss_end - (rss_start or rss_end)) / 2**20, 2),
        "rss_samples_mb": [(t, round(r / 2**20, 2)) for t, r in samples],
        "record_fsyncs": record.fsyncs, "record_events": n, "segments": seg_id,
        "buffers": buffers,
        "peer_lost": lost[:5],
    }
    if own_dir is not None:
        own_dir.cleanup()
    return out


def main(argv=None) -> None:
    """Command line: soak the sample lab (or ``--lab``) for ``--hours`` of virtual time and print the result as JSON."""
    import argparse

    from ..config import load_lab
    from ..workspace import sample_lab_path

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--hours", type=float, default=1.0)
    ap.add_argument("--lab", default=None)
    args = ap.parse_args(argv)
    lab = load_lab(args.lab or sample_lab_path())
    print(json.dumps(soak(lab, args.hours), indent=2))


if __name__ == "__main__":
    main()
