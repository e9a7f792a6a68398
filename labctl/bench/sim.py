"""Simulated-lab benchmark: frame rendering rate and virtual-time trial speed.

* ``render fixed/<object>``: one 640×480 frame of the fixed camera C1 (1.8 m, 25 mm lens) seeing
  the object on the table: z-buffer, Tsai distortion, anti-aliased silhouettes, analytic markers,
  textured table, noise. Baseline, timed in the same run: the cheapest possible picture of the
  same scene — OpenCV ``fillConvexPoly`` of the depth-sorted projected triangles (painter's
  algorithm, no z-buffer, no distortion, no markers, no texture) plus the same noise. Target:
  ≥ 60 frames/s (``fps`` column; ``meets_60fps``).
* ``render mobile/<object>``: the robot camera C2 at the 600 mm standard-view stand-off.
* ``virtual trial 10 s``: build the virtual lab, stream a G-code line move at 8 mm/s to the GRBL
  emulator, then grab 300 fixed-camera frames at 30 Hz (each advances the virtual clock and the
  table) with a status poll every 6 frames. Baseline: 10 s of real time. Target ratio ≥ 5. The
  process's first trial (building the texture, noise and ray caches, ~0.5 s) is run and reported
  apart; ``cpu_s`` is the process CPU time, which a machine busy with other work inflates less.
* ``render … realistic camera``: the same frames with the ``realistic`` preset's effects (issue
  14, ``labctl.sim.effects``: shadow, highlights, texture, Bayer, sRGB, JPEG 80) against the same
  frames without, timed alternately in one loop (``ratio`` < 1: the effects' cost): the fixed
  camera's object window as trials render it, its full frame, and the mobile camera's frame.
* ``one virtual trial``: whole ``simulate_run`` trials, the fixed camera rendered only
  in the object's window against full frames in the same run; simulated s per CPU s
  (``virtual_time_factor_cpu``, target ≥ 15) and whether the results are identical.
"""

from __future__ import annotations

import contextlib
import json
import time
from unittest import mock

import cv2
import numpy as np

from ..geometry import invert, look_at
from ._timing import median_time, row


def _median_wall_cpu(fn, repeat: int, warmup: int = 2) -> tuple[float, float]:
    """Median wall and process-CPU seconds of ``fn()``."""
    for _ in range(warmup):
        fn()
    walls, cpus = [], []
    for _ in range(repeat):
        w0, c0 = time.perf_counter(), time.process_time()
        fn()
        walls.append(time.perf_counter() - w0)
        cpus.append(time.process_time() - c0)
    return float(np.median(walls)), float(np.median(cpus))


def _objects() -> dict:
    """The sample objects (library samples) with markers on their largest flat faces, plus a 512-face cylinder."""
    import trimesh

    from ..sim.world import SimMarker, SimObject, builtin_test_object

    objs = {"test_block": builtin_test_object()}
    try:
        from ..library.samples import sample_objects

        meshes = sample_objects()
    except Exception:  # the library may be unavailable in a stripped install; the block still runs
        meshes = {}
    meshes["cylinder_512"] = trimesh.creation.cylinder(radius=35.0, height=60.0, sections=128)
    for name, mesh in meshes.items():
        markers = []
        facets = sorted(range(len(mesh.facets)), key=lambda i: -mesh.facets_area[i])[:6]
        for k, i in enumerate(facets):
            faces = mesh.facets[i]
            w = mesh.area_faces[faces]
            centre = (mesh.triangles_center[faces] * w[:, None]).sum(0) / w.sum()
            markers.append(SimMarker(k, centre, mesh.facets_normal[i], 8.0))
        objs[name] = SimObject.from_trimesh(name, mesh, markers)
    return objs


def _painter_baseline(camera, T_w_c, meshes, rng) -> np.ndarray:
    """The cheap, wrong picture: depth-sorted filled triangles, pinhole only, flat table, noise."""
    img = np.full((camera.height, camera.width, 3), 50, np.uint8)
    T_c_w = invert(T_w_c)
    K = camera.K
    for m in meshes:
        Pc = (m.vertices @ T_c_w[:3, :3].T + T_c_w[:3, 3])[m.faces]
        n = np.cross(Pc[:, 1] - Pc[:, 0], Pc[:, 2] - Pc[:, 0])
        front = np.einsum("ij,ij->i", n, Pc[:, 0]) < 0
        order = np.argsort(-Pc[front, :, 2].mean(axis=1))
        uv = (Pc[front][..., :2] / Pc[front][..., 2:3]) * [K[0, 0], K[1, 1]] + K[:2, 2]
        for tri in uv[order]:
            cv2.fillConvexPoly(img, np.round(tri * 16).astype(np.int32), (185, 185, 185), cv2.LINE_8, 4)
    noise = np.empty(img.shape, np.int16)
    cv2.randn(noise, 0, 2.0)  # type: ignore[call-overload]  # OpenCV takes scalars; its stubs want arrays
    return cv2.add(img, noise, dtype=cv2.CV_8U)


def _trial(lab, seconds: float = 10.0) -> tuple[float, float, float]:
    """A virtual-time trial of ``seconds`` simulated seconds; returns (wall_s, cpu_s, sim_s)."""
    from ..sim.clock import VirtualClock
    from ..sim.lab import Scene, SimLab

    t0 = time.perf_counter()
    c0 = time.process_time()
    vl = SimLab.build(lab, VirtualClock(0.0), scene=Scene.test_block(lab, seed=1), seed=1)
    g = vl.grbl
    g.receive(b"$X\n")
    g.receive(b"G90 G1 X%.1f Y200 F480\n" % (300 + 8.0 * seconds))  # 8 mm/s along +x
    cam = vl.cameras["fixed"]
    cam.open()
    n = int(round(seconds * cam.fps))
    for i in range(n):
        cam.grab()
        if i % 6 == 0:
            g.receive(b"?")
            g.read_output()
    return time.perf_counter() - t0, time.process_time() - c0, vl.clock.now()


@contextlib.contextmanager
def _full_fixed_frames(on: bool):
    """With ``on``, ``simulate_run``'s fixed-camera frames rendered whole and anti-aliased (the world's
    defaults) instead of in the object's window: the baseline the windowed trials are timed against."""
    if not on:
        yield
        return
    from ..sim.world import SimWorld

    render = SimWorld.render

    def full(self, role, t, rng=None, *, window=None, supersample=None, **kw):
        if role == "fixed":
            window = supersample = None
        return render(self, role, t, rng, window=window, supersample=supersample, **kw)

    with mock.patch.object(SimWorld, "render", full):
        yield


def _virtual_trials(lab, quick: bool) -> dict:
    """Whole trials (``simulate_run``: tracker, planner, emulators, link codec, recogniser) with the
    fixed camera windowed and, as the baseline in the same run, with full frames: simulated
    seconds per process-CPU second of each, and whether the results are identical."""
    from ..decisions.context import RunContext
    from ..runtime.virtual import TrialSpec, simulate_run

    ctx = RunContext.load(lab)
    seeds = [1, 2] if quick else [1, 2, 3, 4]
    simulate_run(lab, ctx, TrialSpec(seed=0))  # caches (texture, rays, noise bank) out of the timing
    cpu: dict[bool, list[float]] = {False: [], True: []}
    sim: dict[bool, list[float]] = {False: [], True: []}
    results: dict[bool, list[dict]] = {False: [], True: []}
    for seed in seeds:
        for full in (True, False):
            with _full_fixed_frames(full):
                c0 = time.process_time()
                r = simulate_run(lab, ctx, TrialSpec(seed=seed))
                cpu[full].append(time.process_time() - c0)
            sim[full].append(r["sim_time_s"])
            results[full].append(r)
    same = [json.dumps(a, sort_keys=True, default=str) == json.dumps(b, sort_keys=True, default=str)
            for a, b in zip(results[False], results[True])]
    return {"n": len(seeds), "cpu_s": float(np.median(cpu[False])), "cpu_s_full": float(np.median(cpu[True])),
            "factor": round(sum(sim[False]) / sum(cpu[False]), 2),
            "factor_full": round(sum(sim[True]) / sum(cpu[True]), 2), "identical": all(same)}


def _effects_rows(lab, world, obj, repeat: int) -> list[dict]:
    """Per-frame cost of the realistic-camera preset: each case with and without the effects,
    alternated so machine load hits both alike."""
    from ..config.lab import SimCameraConfig
    from ..sim.effects import CameraEffects
    from ..sim.world import random_placement

    fx = CameraEffects(response="srgb", **SimCameraConfig(preset="realistic").settings())
    world.place(obj, random_placement(obj, np.random.default_rng(3)))
    cases = (("fixed camera, object window (trials)", "fixed", "object", 1),
             ("fixed camera, full frame", "fixed", None, None), ("mobile camera, full frame", "mobile", None, None))
    out = []
    for label, role, window, ss in cases:
        rig = world.rigs[role]
        times: dict = {True: [], False: []}
        for k in range(repeat + 2):
            for on in (False, True):
                rig.effects = fx if on else None
                t0 = time.perf_counter()
                world.render(role, 0.05 * k, np.random.default_rng(k), window=window, supersample=ss)
                if k >= 2:  # warm-up: caches
                    times[on].append(time.perf_counter() - t0)
        rig.effects = None
        on_s, off_s = float(np.median(times[True])), float(np.median(times[False]))
        out.append(row(f"render {label}, realistic camera", on_s, baseline="same frame, no effects",
                       baseline_s=off_s, ms=round(1000 * on_s, 2), ms_plain=round(1000 * off_s, 2)))
    return out


def run(quick: bool = False) -> dict:
    """Frame rendering rate against the fillConvexPoly baseline and virtual-time trial speed, on one core."""
    from ..config import load_lab
    from ..workspace import sample_lab_path

    lab = load_lab(sample_lab_path())
    repeat = 5 if quick else 30
    rows: list[dict] = []
    fps: dict[str, float] = {}
    cpu_fps: dict[str, float] = {}
    threads = cv2.getNumThreads()
    cv2.setNumThreads(1)  # the target is for one core: no OpenCV worker threads
    try:
        return _run(lab, quick, repeat, rows, fps, cpu_fps)
    finally:
        cv2.setNumThreads(threads)


def _run(lab, quick, repeat, rows, fps, cpu_fps) -> dict:
    from ..sim.render import render
    from ..sim.world import SimWorld, random_placement

    objs = _objects()
    if quick:
        objs = {k: objs[k] for k in list(objs)[:2] + ["cylinder_512"]}
    world = SimWorld.from_lab(lab)
    rng = np.random.default_rng(0)
    for name, obj in objs.items():
        world.place(obj, random_placement(obj, np.random.default_rng(3)))
        meshes = world.meshes_at(0.0)
        faces = len(obj.faces)
        for role in ("fixed", "mobile"):
            rig = world.rigs[role]
            if role == "fixed":
                T_w_c = world.T_w_c1
            else:  # the standard view: 600 mm along the object's most upward-facing marker normal
                tr = world.truth(0.0)
                _, c, n = max(tr.markers_w, key=lambda m: m[2][2])
                up = (0, 1, 0) if abs(n[1]) < 0.9 else (1, 0, 0)
                T_w_c = look_at(c + lab.config.viewing.standoff_mm * n, c, up=up)

            def frame(rig=rig, T_w_c=T_w_c, meshes=meshes):
                return render(rig.model, T_w_c, meshes, table=world.table_surface(0.0), noise_sigma=rig.noise_sigma,
                              rng=rng)

            med, med_cpu = _median_wall_cpu(frame, repeat)
            if role == "fixed":
                def painter(rig=rig, T_w_c=T_w_c, meshes=meshes):
                    return _painter_baseline(rig.model, T_w_c, meshes, rng)

                base = median_time(painter, repeat)
            else:
                base = None
            fps[f"{role}/{name}"] = 1.0 / med
            cpu_fps[f"{role}/{name}"] = 1.0 / max(med_cpu, 1e-9)
            rows.append(row(f"render {role}/{name} ({faces} faces)", med,
                            baseline="painter's fillConvexPoly" if base else None, baseline_s=base,
                            fps=round(1.0 / med, 1), cpu_fps=round(1.0 / max(med_cpu, 1e-9), 1),
                            meets_60fps=bool(med <= 1 / 60)))
    rows.extend(_effects_rows(lab, world, objs["test_block"], repeat))
    cold_wall, _, _ = _trial(lab, 1.0)  # first trial in a process: texture, noise and ray caches
    trial_runs = [_trial(lab, 3.0 if quick else 10.0) for _ in range(1 if quick else 3)]
    wall = float(np.median([w for w, _, _ in trial_runs]))
    cpu = float(np.median([c for _, c, _ in trial_runs]))
    sim_s = trial_runs[0][2]
    rows.append(row(f"virtual trial {sim_s:.1f} s (fixed camera 30 Hz + GRBL)", wall, baseline="real time",
                    baseline_s=sim_s, faster_than_real_time=round(sim_s / wall, 2),
                    faster_than_real_time_cpu=round(sim_s / cpu, 2), cpu_s=round(cpu, 3)))
    trial = _virtual_trials(lab, quick)
    rows.append(row(f"one virtual trial (simulate_run, {trial['n']} seeds), fixed camera windowed", trial["cpu_s"],
                    baseline="same trials, full fixed frames", baseline_s=trial["cpu_s_full"],
                    virtual_time_factor_cpu=trial["factor"], virtual_time_factor_cpu_full=trial["factor_full"],
                    identical=trial["identical"], note="times are process CPU seconds per trial"))
    fixed_fps = [v for k, v in fps.items() if k.startswith("fixed/")]
    return {
        "rows": rows,
        "fixed_fps_min": round(min(fixed_fps), 1),
        "fixed_fps_median": round(float(np.median(fixed_fps)), 1),
        "fixed_cpu_fps_median": round(float(np.median([v for k, v in cpu_fps.items() if k.startswith("fixed/")])), 1),
        "mobile_fps_median": round(float(np.median([v for k, v in fps.items() if k.startswith("mobile/")])), 1),
        "mobile_fps_min": round(min(v for k, v in fps.items() if k.startswith("mobile/")), 1),
        "trial_speedup": round(sim_s / wall, 2),
        "trial_speedup_cpu_time": round(sim_s / cpu, 2),
        "first_trial_setup_s": round(cold_wall, 3),
        "virtual_time_factor_cpu": trial["factor"],
        "virtual_time_factor_cpu_full_frames": trial["factor_full"],
        "windowed_trials_identical": trial["identical"],
        "targets": {"fixed_fps": 60, "trial_speedup": 5, "virtual_time_factor_cpu": 15},
    }
