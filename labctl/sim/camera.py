"""Simulated cameras: frames rendered from the world at the configured rate, and a frame server.

:class:`SimCamera` implements :class:`labctl.drivers.interfaces.Camera`. Frame ``k`` is exposed
at ``t_k = k / fps`` on the world's clock (the stamp is the exposure's middle); ``grab()``
returns the latest frame whose time has come and, if that one was already delivered, waits for
the next (virtual clock: time jumps; real clock: sleeps). Each frame's noise comes from
``default_rng([seed, role, k])``, so a frame depends only on the seed, the world and ``k`` —
not on who grabbed what before (deterministic virtual-time trials).

:class:`FrameServer` serves any cameras to other processes over
``multiprocessing.connection`` (TCP on localhost by default, HMAC-authenticated with a random
key); :class:`FrameClient` is the matching Camera for the worker processes.
"""

from __future__ import annotations

import math
import os
import threading
from multiprocessing import AuthenticationError
from multiprocessing.connection import Client, Connection, Listener
from typing import Any, cast

import numpy as np

from ..drivers.interfaces import Camera, Frame, OpenClose
from ..errors import DeviceError
from .world import CAMERA_ROLES, SimWorld, WorldError

_ROLE_CODE = {"fixed": 1, "mobile": 2}


class SimCamera(OpenClose):
    """A camera of the simulated world (``role`` ``fixed`` or ``mobile``) on ``clock``."""

    def __init__(self, world: SimWorld, role: str, clock, *, fps: float = 30.0, seed: int = 0,
                 truth: bool = False, window: str | None = None, supersample: int | None = None):
        if role not in CAMERA_ROLES:
            raise WorldError(f"unknown camera role {role!r}; expected one of {CAMERA_ROLES}")
        if not (math.isfinite(fps) and fps > 0):
            raise WorldError(f"fps must be positive, got {fps}")
        self.world, self.role, self.clock = world, role, clock
        self.fps = float(fps)
        self.seed = int(seed)
        self.truth = truth
        # what each frame renders (:meth:`SimWorld.render`): ``window="object"`` with ``supersample=1`` is the
        # object's footprint without anti-aliasing, the rest flat table grey — all a marker tracker reads
        self.window, self.supersample = window, supersample
        self._open = False
        self._last_seq: int | None = None
        self._lock = threading.Lock()
        self.frames_rendered = 0

    def open(self) -> None:
        """Start delivering frames (from the next frame the clock reaches)."""
        self._open = True
        self._last_seq = None

    def close(self) -> None:
        """Stop delivering frames."""
        self._open = False

    def frame_time(self, seq: int) -> float:
        """Exposure time (s, run clock) of frame number ``seq``."""
        return seq / self.fps

    def render_frame(self, seq: int) -> Frame:
        """Frame ``seq`` (exposed at ``seq / fps``), independent of the camera's state."""
        t = self.frame_time(seq)
        rng = np.random.default_rng([self.seed, _ROLE_CODE[self.role], int(seq)])
        res = self.world.render(self.role, t, rng, truth=self.truth, window=self.window, supersample=self.supersample)
        self.frames_rendered += 1
        meta: dict[str, Any] = {"camera": self.role}
        if self.truth:
            meta.update(mask=res.mask, depth=res.depth, markers_c=res.markers_c, marker_pixels=res.marker_pixels,
                        T_w_c=self.world.T_w_c(self.role, t))
        return Frame(image=res.image, t=t, seq=int(seq), meta=meta)

    def grab(self) -> Frame:
        """The latest frame; if it was already delivered, wait (on the clock) for the next one."""
        with self._lock:
            if not self._open:
                raise DeviceError(f"sim {self.role} camera is not open")
            seq = int(math.floor(self.clock.now() * self.fps + 1e-9))
            if self._last_seq is not None and seq <= self._last_seq:
                seq = self._last_seq + 1
                self.clock.sleep_until(self.frame_time(seq))
            self._last_seq = seq
            return self.render_frame(seq)

    def grab_recent(self, max_frames: int) -> list[Frame]:
        """The frames exposed since the last one delivered, oldest first: the newest ``max_frames`` of them
        (the camera's frames are on a fixed grid, so the ones a busy caller missed are rendered now)."""
        with self._lock:
            last = self._last_seq
        newest = self.grab()
        first = newest.seq if last is None else max(last + 1, newest.seq - max(1, int(max_frames)) + 1)
        return [self.render_frame(seq) for seq in range(first, newest.seq)] + [newest]

    def info(self) -> dict:
        """Kind, role, image size, fps, noise sigma (grey levels) and the camera model of the rig."""
        rig = self.world.rigs[self.role]
        return {"kind": "sim", "role": self.role, "width": rig.model.width, "height": rig.model.height,
                "fps": self.fps, "noise_sigma": rig.noise_sigma, "camera_model": rig.model.to_dict()}


# ------------------------------------------------------------------------------------------
# frame server
# ------------------------------------------------------------------------------------------
class FrameServer:
    """Serve cameras (by role) to other processes. Use as a context manager or start()/stop().

    Requests on a connection: ``("grab", role)`` → a header ``{"frames": [{t, seq, shape, dtype}]}`` then
    the raw image bytes; ``("grab_recent", role, n)`` → the same for up to n frames, then each one's
    bytes; ``("info", role)`` → the camera's info dict; ``("bye",)`` closes. Errors come back as
    ``{"error": "..."}``.
    """

    def __init__(self, cameras: dict[str, Camera], address=("127.0.0.1", 0), authkey: bytes | None = None):
        self.cameras = dict(cameras)
        self.authkey = authkey if authkey is not None else os.urandom(16)
        self._listener = Listener(address, authkey=self.authkey)
        self.address = self._listener.address
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._accept_thread: threading.Thread | None = None

    def start(self) -> FrameServer:
        """Start accepting clients in a background thread; returns the server."""
        self._accept_thread = threading.Thread(target=self._accept_loop, name="frame-server", daemon=True)
        self._accept_thread.start()
        return self

    def stop(self) -> None:
        """Stop accepting, close every client and join the threads (idempotent)."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        if self._accept_thread is not None and self._accept_thread.is_alive():
            # closing a socket does not wake a thread blocked in accept(): knock once to release it
            # (from a daemon thread: if the accept loop is already leaving, nobody answers the knock,
            # and closing the listener below resets it)
            threading.Thread(target=self._knock, name="frame-server-knock", daemon=True).start()
            self._accept_thread.join(timeout=2.0)
        try:
            self._listener.close()
        except OSError:
            pass
        for th in self._threads:
            th.join(timeout=2.0)

    def _knock(self) -> None:
        try:
            Client(self.address, authkey=self.authkey).close()
        except (OSError, EOFError, AuthenticationError):
            pass

    def __enter__(self) -> FrameServer:
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _accept_loop(self) -> None:
        while not self._stopping.is_set():
            try:
                conn = self._listener.accept()
            except (OSError, EOFError, AuthenticationError):
                if self._stopping.is_set():
                    return
                continue  # a client that failed authentication or vanished mid-handshake
            if self._stopping.is_set():
                conn.close()
                return
            th = threading.Thread(target=self._serve, args=(conn,), name="frame-client", daemon=True)
            self._threads.append(th)
            th.start()

    @staticmethod
    def _send_frames(conn, frames: list[Frame]) -> None:
        images = [np.ascontiguousarray(f.image) for f in frames]
        conn.send({"frames": [{"t": f.t, "seq": f.seq, "shape": img.shape, "dtype": str(img.dtype)}
                              for f, img in zip(frames, images)]})
        for img in images:
            conn.send_bytes(img.reshape(-1))

    def _serve(self, conn) -> None:
        with conn:
            while not self._stopping.is_set():
                try:
                    if not conn.poll(0.2):
                        continue
                    req = conn.recv()
                except (EOFError, OSError):
                    return
                try:
                    if not isinstance(req, tuple) or not req or req[0] == "bye":
                        return
                    kind, role = req[0], req[1] if len(req) > 1 else None
                    cam = self.cameras.get(role) if role is not None else None
                    if cam is None:
                        conn.send({"error": f"no camera {role!r} (have {sorted(self.cameras)})"})
                    elif kind == "info":
                        conn.send(cam.info())
                    elif kind == "grab":
                        self._send_frames(conn, [cam.grab()])
                    elif kind == "grab_recent":
                        self._send_frames(conn, cam.grab_recent(int(req[2])))
                    else:
                        conn.send({"error": f"unknown request {kind!r}"})
                except (EOFError, OSError, BrokenPipeError):
                    return
                except Exception as exc:  # report to the client rather than die silently
                    try:
                        conn.send({"error": f"{type(exc).__name__}: {exc}"})
                    except OSError:
                        return


class FrameClient(OpenClose):
    """A Camera served by a :class:`FrameServer` (in another process or on another host)."""

    def __init__(self, address, role: str, authkey: bytes, *, timeout_s: float = 5.0):
        self.address, self.role, self.authkey = address, role, authkey
        self.timeout_s = timeout_s
        self._conn: Connection | None = None

    def open(self) -> None:
        """Connect to the frame server with its key; raises DeviceError when it is unreachable or refuses the key."""
        try:
            self._conn = Client(self.address, authkey=self.authkey)
        except AuthenticationError:
            raise DeviceError(f"the frame server at {self.address} rejected the key") from None
        except (OSError, EOFError) as exc:
            raise DeviceError(f"cannot reach the frame server at {self.address}: {exc}") from None

    def close(self) -> None:
        """Say goodbye to the server and close the connection."""
        if self._conn is not None:
            try:
                self._conn.send(("bye",))
            except OSError:
                pass
            self._conn.close()
            self._conn = None

    def _ask(self, request):
        if self._conn is None:
            raise DeviceError(f"frame client for {self.role} is not open")
        try:
            self._conn.send(request)
            if not self._conn.poll(self.timeout_s):
                raise DeviceError(f"frame server did not answer within {self.timeout_s} s")
            reply = self._conn.recv()
        except (OSError, EOFError) as exc:
            raise DeviceError(f"frame server connection lost: {exc}") from None
        if isinstance(reply, dict) and "error" in reply:
            raise DeviceError(f"frame server: {reply['error']}")
        return reply

    def grab(self) -> Frame:
        """The latest frame the server renders for this role (raises DeviceError after ``timeout_s`` without one)."""
        return self._frames(("grab", self.role))[-1]

    def grab_recent(self, max_frames: int) -> list[Frame]:
        """The frames the server's camera exposed since the last one delivered, oldest first (at most
        ``max_frames``)."""
        return self._frames(("grab_recent", self.role, int(max_frames)))

    def _frames(self, request) -> list[Frame]:
        heads = self._ask(request)["frames"]
        conn = cast(Connection, self._conn)  # _ask checked that it is open
        frames = []
        for head in heads:
            try:
                if not conn.poll(self.timeout_s):
                    raise DeviceError(f"frame server sent no image within {self.timeout_s} s")
                data = conn.recv_bytes()
            except (OSError, EOFError) as exc:
                raise DeviceError(f"frame server connection lost: {exc}") from None
            image = np.frombuffer(bytearray(data), dtype=np.dtype(head["dtype"])).reshape(head["shape"])
            frames.append(Frame(image=image, t=float(head["t"]), seq=int(head["seq"]), meta={"camera": self.role}))
        if not frames:
            raise DeviceError("frame server sent no frame")
        return frames

    def info(self) -> dict:
        """The server's info for this camera role."""
        return self._ask(("info", self.role))
