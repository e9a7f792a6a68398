"""The simulated lab as the runtimes serve it, and trajectories.

The lab itself is built by :meth:`labctl.sim.lab.SimLab.build`; this module holds what belongs to
the runtimes around it:

* :class:`LiveSimLab` — real time, for ``labctl run``: the emulators on pseudo-terminals paced at
  the baud rate, and a frame server rendering both cameras from the world;
  :class:`ServedLab` — the same for ``labctl sim serve``, cameras as MJPEG streams;
* :class:`Conveyor` — the simulator moving the table by itself;
* :func:`trajectory_program` — where the table starts (``run.trajectory_start_mm``) and the G-code
  it runs for a trajectory.
"""

from __future__ import annotations

import contextlib
import os
import shutil
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from ..config import Lab
from ..drivers.programs import program
from ..errors import UserInputError

if TYPE_CHECKING:
    from ..sim.lab import Ports


def trajectory_program(name: str, speed_mm_s: float, lab: Lab) -> tuple[tuple[float, float], list[str]]:
    """``(start_xy, gcode_lines)`` of a named trajectory, or of a G-code file (started at the centre).

    ``external`` (labctl does not drive the motion): where the simulator's conveyor starts, and no lines."""
    from ..sim.lab import table_config  # light: the simulator's modules are imported only when it is built

    starts = lab.config.run.trajectory_start_mm
    if name == "external":
        return starts.line, []
    if (start := starts.get(name)) is not None:
        return start, program(name, speed_mm_s, start=start, travel_mm=table_config(lab).travel_mm)
    from ..drivers.programs import load_trajectory

    table = table_config(lab)
    lines = load_trajectory(name, travel_mm=table.travel_mm, max_feed_mm_min=table.max_feed_mm_min)
    travel = table.travel_mm
    return (travel[0] / 2, travel[1] / 2), lines


def _sim_object(lab: Lab, spec: dict, rng: np.random.Generator):
    from ..library.storage import load_library
    from ..sim.world import SimObject, random_placement

    library = load_library(lab.library_dir)
    names = sorted(library)
    if not names:
        raise UserInputError(f"the object library {lab.library_dir} is empty")
    name = spec.get("object_name") or names[int(rng.integers(len(names)))]
    obj = SimObject.from_library(library[name])
    return name, obj, random_placement(obj, rng)


class Conveyor:
    """Moves the simulated table by itself — parts on a conveyor that labctl does not drive.

    The program goes straight into the GRBL emulator (no client on its port) once the fixed
    camera has been watched without a pause for ``delay_s``: the part arrives while a run looks,
    and a single ``labctl devices`` grab does not set it off.
    """

    def __init__(self, grbl, lock, lines: list[str], delay_s: float = 1.0, gap_s: float = 0.5):
        self.grbl, self.lock, self.lines = grbl, lock, lines
        self.delay_s, self.gap_s = delay_s, gap_s
        self.started_at: float | None = None
        self._streak: tuple[float, float] | None = None  # (first, last) grab of the current streak

    def watch(self, camera):
        """``camera`` with every grab reported to :meth:`seen` (the conveyor starts once watched long enough)."""
        conveyor = self

        class Watched:
            def __getattr__(self, name):
                return getattr(camera, name)

            def grab(self):
                frame = camera.grab()
                conveyor.seen(frame.t)
                return frame

            def grab_recent(self, max_frames):
                frames = camera.grab_recent(max_frames)
                conveyor.seen(frames[-1].t)
                return frames

        return Watched()

    def seen(self, t: float) -> None:
        """A fixed-camera grab at time ``t`` (s): start the program once grabs have come without a pause for
        ``delay_s``."""
        if self.started_at is not None:
            return
        first, last = self._streak or (t, t)
        if t - last > self.gap_s:
            first = t
        self._streak = (first, t)
        if t - first >= self.delay_s:
            with self.lock:
                self.grbl.receive(("\n".join(self.lines) + "\n").encode(), t=t)
            self.started_at = t


class LiveSimLab:
    """The simulated lab in real time: emulators on ptys, cameras behind a frame server."""

    #: render each camera's first frame (seconds: it builds the scene) before serving; a live run's
    #: server sets this False and calls :meth:`warm_up` once it has said ready, so the first renders
    #: overlap the workers' device connections instead of delaying them
    warm_on_enter = True
    #: the fixed camera renders only the object's footprint, without anti-aliasing, the rest of the frame flat
    #: table grey, as the virtual runtime renders it: the predictor's marker tracker reads only the red markers,
    #: all on the object, and a whole anti-aliased frame with the arm in view cost 7–50 ms of the lab's CPU per
    #: frame against ~2 ms (docs/notes/run.md, "2026-12-02 (c)"). The served lab, which stands in for real
    #: cameras, renders whole frames
    fixed_object_window = True

    def __init__(self, lab: Lab, spec: dict):
        self.lab, self.spec = lab, spec
        self._stack = contextlib.ExitStack()
        self._cams: dict = {}
        #: called with the devices' ports and the clock's origin (:meth:`endpoints` without the frame server) as
        #: soon as the emulators serve them, before the world and the cameras are built: a live run's table and
        #: robot connect at 9600 bps meanwhile
        self.on_ports: Callable[[dict], None] | None = None

    def __enter__(self) -> LiveSimLab:
        from ..sim.camera import FrameServer

        try:
            cams = self._start_world()
            self.server = FrameServer(cams).start()
            self._stack.callback(self.server.stop)
        except BaseException:
            self._stack.close()
            raise
        return self

    def _start_world(self) -> dict:
        """The simulated lab on a real clock (:meth:`labctl.sim.lab.SimLab.build`: both emulators on ptys,
        the world, both sim cameras, opened), by camera role; the conveyor if the simulator moves the parts."""
        from ..sim.clock import RealClock
        from ..sim.lab import SimLab, table_config

        lab = self.lab
        rng = np.random.default_rng(self.spec.get("seed", 0))

        def scene():  # after the ports are out: the library read and the object's mesh overlap the connections
            self.object_name, obj, placement = _sim_object(lab, self.spec, rng)
            self.obj, self.placement = obj, placement
            return self._scene(obj, placement)

        start = self.spec.get("table_start_mm") or trajectory_program(
            self.spec["trajectory"], self.spec["speed_mm_s"], lab)[0]
        self.origin = time.monotonic()
        clock = RealClock(origin=self.origin)
        on_ports = self.on_ports
        self.sim = sim = SimLab.build(lab, clock, ports=self._ports(), scene=scene,
                                      seed=int(self.spec.get("seed", 0)), baud=self.spec.get("baud"),
                                      table_start_mm=start, fps=self.spec.get("fps"),
                                      on_ports=None if on_ports is None else
                                      (lambda s: on_ports({**s.endpoints(), "origin": self.origin})))
        self._stack.callback(sim.close)
        self.grbl, self.robot_emu, self.world = sim.grbl, sim.robot_emu, sim.world
        cams = dict(sim.cameras)
        if self.fixed_object_window and "fixed" in cams:
            cams["fixed"].window, cams["fixed"].supersample = "object", 1
        for cam in cams.values():
            cam.open()
        self._cams = dict(cams)
        if self.warm_on_enter:
            self.warm_up()
        self.clock = clock
        self.conveyor = None
        if self.spec.get("trajectory") == "external" or self.spec.get("conveyor"):
            # parts on a conveyor labctl does not drive: the simulator runs the table itself
            # the conveyor is the simulator's own: it clears GRBL's power-up alarm itself ($X)
            lines = ["$X"] + program(self.spec.get("conveyor") or "line", self.spec["speed_mm_s"], start=start,
                                     travel_mm=table_config(lab).travel_mm, rapid_to_start=False)
            delay = float(self.spec.get("conveyor_delay_s", 1.0))
            self.conveyor = Conveyor(self.grbl, sim.ptys["table"].lock, lines, delay)
            cams["fixed"] = self.conveyor.watch(cams["fixed"])
        return cams

    def warm_up(self) -> None:
        """Render each camera's first frame: it builds the scene (the table texture, ~0.5 s), which
        should not fall in a client's wait. Under each camera's lock, so a grab meanwhile waits for it."""
        for cam in self._cams.values():
            with cam._lock:
                cam.render_frame(0)

    def _ports(self) -> Ports:
        """The emulators' ports: ptys (the served lab can bridge them to TCP)."""
        return "pty"

    def _scene(self, obj, placement):
        from ..sim.lab import Scene

        return Scene(obj, placement)

    def __exit__(self, *exc) -> None:
        self._stack.close()

    def endpoints(self) -> dict:
        """Where the workers reach the lab: table and robot pty paths, the run clock's origin, the frame server."""
        return {**self.sim.endpoints(), "origin": self.origin,
                "frame_server": (self.server.address, self.server.authkey)}

    def truth(self) -> dict:
        """The ground truth for the result: the object placed."""
        return {"true_identity": self.object_name}


class ServedLab(LiveSimLab):
    """``labctl sim serve``: the whole simulated lab out of process, in real time, from one world.

    The GRBL table and robot controller emulators on ptys (or, ``spec["tcp"]``, on TCP ports
    bridged as ser2net would), and both cameras as MJPEG-over-HTTP streams on localhost
    (:class:`labctl.sim.mjpeg.MjpegServer`) rendering the world whose table and flange poses
    are read from those same emulators. Spec keys: ``seed``, ``object_name``, ``trajectory``
    and ``speed_mm_s`` (only where the table starts), ``table_start_mm``, ``tcp``, ``baud``,
    ``http_port``, ``jpeg_quality``, ``fps`` (both cameras; default the driver files'), ``scene``
    (``"object"``, default, or ``"calibration"``: the lab's calibration target on the carriage).

    The world holds both the object and the lab's calibration target (``calibration/target.yaml``,
    :func:`labctl.sim.rigs.target_world`); the HTTP server's control endpoint
    ``POST /control/scene?calibration=1&spacer_mm=H`` (:meth:`set_scene`) switches between them and
    puts the target on a spacer — what a person does at a real lab when ``labctl calibrate`` prompts.
    With ``tcp``, ``/control/link`` (:meth:`set_link`) stops and restarts a device's bridge as
    ser2net is stopped and restarted (a link dropped mid-run).
    """

    fixed_object_window = False  # real cameras' stand-ins: whole frames, as a person watching the stream expects

    def __init__(self, lab: Lab, spec: dict):
        super().__init__(lab, spec)
        self.bridges: dict[str, Any] = {}  # the devices' TCP bridges, by role: filled on entry with ``tcp``

    def _ports(self) -> Ports:
        """TCP ports as ser2net would serve them with ``spec["tcp"]``, else ptys."""
        return "tcp" if self.spec.get("tcp") else "pty"

    def _scene(self, obj, placement):
        from ..calibration.run import lab_target
        from ..sim.lab import Scene

        self.target = lab_target(self.lab.calibration_dir)
        return Scene(obj, placement, target=self.target, calibration=self.spec.get("scene") == "calibration")

    def set_scene(self, params: dict) -> dict:
        """The control endpoint ``/control/scene``: with ``calibration`` (1/0, yes/no, true/false,
        or ``scene=calibration|object``) and ``spacer_mm`` (≥ 0, mm) change the scene for every
        frame exposed from now on; without parameters report it. Returns the scene and the time
        of the change (``t``: the served clock, s; ``t_wall``: wall clock, s). Raises ValueError
        for a bad parameter (the server answers 400)."""
        now = self.clock.now()
        calibration, spacer = self.world.scene_at(now)
        if params:
            unknown = set(params) - {"calibration", "scene", "spacer_mm"}
            if unknown:
                raise ValueError(f"unknown parameter(s) {', '.join(sorted(unknown))} (have: calibration, scene, "
                                 "spacer_mm)")
            if "scene" in params:
                if params["scene"] not in ("calibration", "object"):
                    raise ValueError(f"scene must be calibration or object, got {params['scene']!r}")
                calibration = params["scene"] == "calibration"
            if "calibration" in params:
                word = params["calibration"].strip().lower()
                if word not in ("1", "0", "yes", "no", "true", "false"):
                    raise ValueError(f"calibration must be 1 or 0, got {params['calibration']!r}")
                calibration = word in ("1", "yes", "true")
            if "spacer_mm" in params:
                try:
                    spacer = float(params["spacer_mm"])
                except ValueError:
                    raise ValueError(f"spacer_mm must be a number, got {params['spacer_mm']!r}") from None
                if not (np.isfinite(spacer) and 0 <= spacer <= 1000):
                    raise ValueError(f"spacer_mm must be between 0 and 1000 mm, got {spacer:g}")
            self.world.set_scene(now, calibration, spacer)
        return {"scene": "calibration" if calibration else "object", "spacer_mm": spacer, "t": now,
                "t_wall": time.time() - (self.clock.now() - now)}

    def set_link(self, params: dict) -> dict:
        """The control endpoint ``/control/link``: ``device`` (table or robot) with ``up`` (1/0) stops
        or restarts that device's ser2net-style bridge (down: its client's connection and the port
        close, connecting is refused, what the controller sends meanwhile is lost); ``reset=1`` also
        power-cycles the controller while the link is down (a ser2net restart that pulses DTR resets
        an Arduino's GRBL). Without ``up`` it reports. Returns ``{device, up, drops, resets, t,
        t_wall}`` (served clock and wall clock, s). ValueError (400) for a bad parameter or without
        ``tcp``."""
        if not self.bridges:
            raise ValueError("link control needs the devices on TCP ports (sim serve --tcp)")
        unknown = set(params) - {"device", "up", "reset"}
        if unknown:
            raise ValueError(f"unknown parameter(s) {', '.join(sorted(unknown))} (have: device, up, reset)")
        device = params.get("device")
        if device not in self.bridges:
            raise ValueError(f"device must be one of {', '.join(self.bridges)}, got {device!r}")
        assert device is not None

        def flag(name: str) -> bool | None:
            if name not in params:
                return None
            word = params[name].strip().lower()
            if word not in ("1", "0", "yes", "no", "true", "false"):
                raise ValueError(f"{name} must be 1 or 0, got {params[name]!r}")
            return word in ("1", "yes", "true")

        up, reset = flag("up"), flag("reset")
        bridge = self.bridges[device]
        if up is not None and not up and not bridge.set_up(False):
            raise RuntimeError(f"the {device} bridge did not stop")
        if reset:
            dev, emu = self.sim.ptys[device], self.sim.emulator(device)
            with dev.lock:
                emu.power_cycle()
            self.resets[device] += 1
        if up and not bridge.set_up(True):
            raise RuntimeError(f"the {device} bridge did not start again")
        return {"device": device, "up": bridge.is_up, "drops": bridge.drops, "resets": self.resets[device],
                "t": self.clock.now(), "t_wall": time.time()}

    def __enter__(self) -> ServedLab:
        from ..sim.mjpeg import MjpegServer

        try:
            cams = self._start_world()
            self.ports = self.sim.endpoints()
            self.bridges = self.sim.bridges
            self.resets = {"table": 0, "robot": 0}
            self.mjpeg = MjpegServer(cams, self.clock.now, port=int(self.spec.get("http_port") or 0),
                                     quality=int(self.spec.get("jpeg_quality") or 90),
                                     controls={"scene": self.set_scene, "link": self.set_link}).start()
            self._stack.callback(self.mjpeg.stop)
        except BaseException:
            self._stack.close()
            raise
        return self

    def endpoints(self) -> dict:
        """Where clients reach the served lab: table and robot ports, the MJPEG stream URLs, the scene control URL."""
        return {"table": self.ports["table"], "robot": self.ports["robot"],
                "fixed_camera": self.mjpeg.url("fixed"), "mobile_camera": self.mjpeg.url("mobile"),
                "scene_control": self.mjpeg.control_url("scene"), "link_control": self.mjpeg.control_url("link")}

    def log_truth(self, path, period_s: float = 0.01):
        """Start logging the served devices' motion to ``path`` as JSON lines every ``period_s``
        (:class:`labctl.sim.lab.TruthLogger` into a :class:`labctl.sim.lab.TruthFile`); stopped on exit.
        Returns the logger."""
        from ..sim.lab import TruthFile, TruthLogger

        sink = TruthFile(path, self.origin)
        logger = TruthLogger(self.sim, sink.write, period_s=period_s).start()

        def stop() -> None:
            logger.stop()
            sink.close(logger)

        self._stack.callback(stop)
        return logger

    def check_alive(self) -> None:
        """Raise if an emulator's thread died (the served lab would silently stop answering)."""
        self.sim.check_alive()

    def truth(self) -> dict:
        """The served world's ground truth (mm, rad; 4×4 poses ``T_<to>_<from>``), for checks."""
        from ..sim import truth
        from ..sim.lab import table_config

        lab = self.lab
        return {
            "true_identity": self.object_name,
            "seed": int(self.spec.get("seed", 0)),
            "placement": {"pose_index": self.placement.pose_index, "yaw_rad": self.placement.yaw,
                          "offset_xy_mm": list(self.placement.offset_xy)},
            "T_t_o": self.placement.T_t_o(self.obj).tolist(),
            "table_origin_w_mm": list(table_config(lab).origin_w_mm),
            "conveyor": None if self.conveyor is None else {"program": self.conveyor.lines},
            "fixed_camera": {"T_w_c": truth.fixed_camera_pose(lab.fixed_camera).tolist(),
                             "model": truth.camera_model(lab.fixed_camera).to_dict()},
            "mobile_camera": {"T_f_c": truth.hand_eye(lab.mobile_camera).tolist(),
                              "model": truth.camera_model(lab.mobile_camera).to_dict()},
            "T_w_b": np.eye(4).tolist(),
            "endpoints": self.endpoints(),
            "timestamps": "the cameras' X-Timestamp is the exposure time on the wall clock (time.time, s)",
            "scene": self.spec.get("scene") or "object",
            "calibration_target": self.target.kind,
        }


def write_served_lab(lab: Lab, out, served: ServedLab, *, force: bool = False):
    """Write ``out``: a lab whose driver files use only real kinds (grbl, serial, stream) pointing
    at ``served``'s endpoints, plus ``served_truth.json`` (the served world's ground truth).

    Calibration and object library are copied from ``lab`` (the served world is rendered from
    ``lab``'s driver files, so its calibration describes it; ``labctl calibrate`` on the written
    lab measures it again through the devices). The sim-only ground-truth fields are left out
    of the driver files. Written to a temporary folder and renamed: never half-written.
    Refuses a non-empty ``out`` unless it is an earlier served lab and ``force``.
    """
    import dataclasses
    import json
    from pathlib import Path

    import yaml

    from ..config.lab import DriverFiles

    out = Path(out).resolve()
    if out.exists() and any(out.iterdir()):
        if not (force and (out / "served_truth.json").is_file()):
            raise UserInputError(f"{out} is not empty; not overwriting it"
                                 + (" (--force replaces an earlier served lab)" if force or
                                    (out / "served_truth.json").is_file() else ""))
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)

    def plain(o):
        if isinstance(o, dict):
            return {k: plain(v) for k, v in o.items()}
        if isinstance(o, list | tuple):
            return [plain(v) for v in o]
        return o

    def dump(path, data, comment):
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(f"# {comment}\n" + yaml.safe_dump(plain(data), sort_keys=False))

    ep = served.endpoints()
    try:
        no_table = served.conveyor is not None  # the conveyor moves the parts: the lab has no table
        drivers = DriverFiles(table=None) if no_table else DriverFiles()
        config = dataclasses.replace(lab.config, drivers=drivers, name=f"served lab ({lab.config.name})")
        if no_table:
            config = dataclasses.replace(config, run=dataclasses.replace(config.run, trajectory="external"))
        dump(tmp / "lab.yaml", dataclasses.asdict(config), "written by `labctl sim serve --lab-out`")
        real = "written by `labctl sim serve --lab-out`: real driver kinds on the served endpoints"
        if not no_table:
            assert lab.table is not None
            table = dataclasses.replace(lab.table, kind="grbl", port=ep["table"], origin_w_mm=(0.0, 0.0, 0.0))
            dump(tmp / "drivers/table.yaml", dataclasses.asdict(table), real)
        robot = dataclasses.replace(lab.robot, kind="serial", port=ep["robot"])
        if robot.arm is not None:  # the arm's data file goes with it: the served lab stands on its own
            arm_src = lab.driver_paths["arm"]
            (tmp / "drivers/arms").mkdir(parents=True, exist_ok=True)
            shutil.copyfile(arm_src, tmp / "drivers/arms" / arm_src.name)
            robot = dataclasses.replace(robot, arm=f"arms/{arm_src.name}")
        dump(tmp / "drivers/robot.yaml", dataclasses.asdict(robot), real)
        for role in ("fixed_camera", "mobile_camera"):
            cfg = dataclasses.replace(getattr(lab, role), kind="stream", url=ep[role], timestamps="header",
                                      eye_w_mm=None, target_w_mm=None)
            if cfg.response_source is None and lab.response_declared(role):
                # the served frames are rendered with this response: the stream's file states it (else a stream
                # camera left at `linear` would count as undeclared and pose would turn conservative)
                cfg = dataclasses.replace(cfg, response_source="declared")
            if served.spec.get("fps"):
                cfg = dataclasses.replace(cfg, fps=float(served.spec["fps"]))
            d = dataclasses.asdict(cfg)
            for sim_only in ("noise_sigma", "hand_eye_mm", "hand_eye_rpy_deg"):
                d.pop(sim_only, None)
            dump(tmp / f"drivers/{role}.yaml", d, real)
        link = dataclasses.replace(lab.host_link, transport="tcp", port=None)
        dump(tmp / "drivers/host_link.yaml", dataclasses.asdict(link), "written by `labctl sim serve --lab-out`")
        for item in ("calibration", "object_library"):
            if (lab.root / item).is_dir():
                shutil.copytree(lab.root / item, tmp / item, ignore=shutil.ignore_patterns(".*", "__pycache__"))
        (tmp / "runs").mkdir()
        (tmp / "served_truth.json").write_text(json.dumps({**served.truth(), "pid": os.getpid()}, indent=2))
        if out.exists():
            shutil.rmtree(out)
        os.replace(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
