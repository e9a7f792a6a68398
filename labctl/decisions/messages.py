"""Typed, compact messages between the two workers, and their binary codec.

The paper's system (He, Hujic, Mills & Benhabib 1996, §5.1, Fig. 3) splits the work over two
PCs joined by a 9600-bps RS-232 line: Host 1 runs the object-motion predictor and robot-motion
planner, Host 2 the recognizer. At 9600 bps (10 bits per byte with start and stop bits) every
byte costs ~1.04 ms, so each message here is a frozen dataclass with a fixed little-endian
``struct`` layout behind a one-byte type tag: float32 for positions (mm), directions and
scores (float32 keeps 7 significant digits: 0.1 µm at 1 m), float64 only for clock times
(float32 would lose milliseconds after a few hours of monotonic clock), small unsigned ints
for ids. A marker pose is 32 bytes.

Construction validates every field and rounds float32 fields to float32, so
``decode(encode(m)) == m`` holds exactly. Anything wrong — an out-of-range id, a NaN, a
truncated or garbage buffer — raises :class:`MessageError`, never a bare struct/Unicode error.

Library objects travel as small integer ids (their index in the library the two workers
share); mapping names to ids is the workers' business.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass
from typing import ClassVar, Literal

import numpy as np

from ..errors import LabctlError

__all__ = [
    "MessageError", "Message", "Hello", "Heartbeat", "CaptureRequest", "FrameTaken", "MarkerPose",
    "StandardViewRequest", "Identity", "Ambiguous", "Failure", "Stop", "Discard", "MESSAGE_TYPES", "ROLES",
    "CAPTURE_KINDS", "FailureCode", "MAX_TEXT_BYTES", "MAX_CANDIDATES", "encode", "decode", "size_of",
]


class MessageError(LabctlError):
    """A message that cannot be built, encoded or decoded (bad field, garbage bytes)."""


ROLES: tuple[str, ...] = ("supervisor", "predictor", "recognizer")
CAPTURE_KINDS: tuple[str, ...] = ("initial1", "initial2", "standard")
#: what a captured image is for: the two initial images of a marker, or a standard view
CaptureKind = Literal["initial1", "initial2", "standard"]
MAX_TEXT_BYTES = 96  # Failure/Stop text, UTF-8: ~0.1 s at 9600 bps
MAX_CANDIDATES = 32
NO_MARKER = 0xFF  # Ambiguous.next_marker "no hint" on the wire


class FailureCode:
    """Failure codes (one byte on the wire). Workers may use others in 0..255."""

    INTERNAL = 1
    MARKER_LOST = 2
    VIEW_UNREACHABLE = 3
    LEFT_FIELD = 4
    TIMEOUT = 5
    NO_MARKER_FOUND = 6
    NO_MATCH = 7
    DEVICE = 8
    VIEW_MISALIGNED = 9  # a standard view whose marker is off the image centre or oblique: the aim missed


# ---- field helpers (validation + float32 rounding) -------------------------------------------

_F32 = struct.Struct("<f")


def _f32(name: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise MessageError(f"{name}: not a number: {value!r}") from exc
    if not math.isfinite(x):
        raise MessageError(f"{name}: not finite: {x}")
    try:
        return _F32.unpack(_F32.pack(x))[0]
    except (OverflowError, struct.error) as exc:
        raise MessageError(f"{name}: out of float32 range: {x}") from exc


def _f64(name: str, value) -> float:
    try:
        x = float(value)
    except (TypeError, ValueError) as exc:
        raise MessageError(f"{name}: not a number: {value!r}") from exc
    if not math.isfinite(x):
        raise MessageError(f"{name}: not finite: {x}")
    return x


def _uint(name: str, value, bits: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise MessageError(f"{name}: not an integer: {value!r}")
    v = int(value)
    if not 0 <= v < (1 << bits):
        raise MessageError(f"{name}: {v} outside 0..{(1 << bits) - 1}")
    return v


def _vec3(name: str, value) -> tuple[float, float, float]:
    try:
        if isinstance(value, tuple | list):  # the common case, without a numpy round trip
            seq = [float(v) for v in value]
        else:
            seq = [float(v) for v in np.asarray(value, dtype=float).reshape(-1)]
    except (TypeError, ValueError) as exc:
        raise MessageError(f"{name}: not a 3-vector: {value!r}") from exc
    if len(seq) != 3:
        raise MessageError(f"{name}: needs 3 values, got {len(seq)}")
    return tuple(_f32(f"{name}[{i}]", v) for i, v in enumerate(seq))  # type: ignore[return-value]


def _ids(name: str, value) -> tuple[int, ...]:
    try:
        items = tuple(value)
    except TypeError as exc:
        raise MessageError(f"{name}: not a sequence of ids: {value!r}") from exc
    if len(items) > MAX_CANDIDATES:
        raise MessageError(f"{name}: {len(items)} ids, at most {MAX_CANDIDATES}")
    return tuple(_uint(f"{name}[{i}]", v, 16) for i, v in enumerate(items))


def _text(name: str, value) -> str:
    if not isinstance(value, str):
        raise MessageError(f"{name}: not a string: {value!r}")
    if len(value.encode("utf-8", errors="strict")) > MAX_TEXT_BYTES:
        raise MessageError(f"{name}: longer than {MAX_TEXT_BYTES} UTF-8 bytes (use .short())")
    return value


def _clip_text(text: str) -> str:
    """Cut ``text`` to at most MAX_TEXT_BYTES of UTF-8 on a character boundary."""
    data = str(text).encode("utf-8", errors="replace")[:MAX_TEXT_BYTES]
    return data.decode("utf-8", errors="ignore")


def _choice(name: str, value, options: tuple[str, ...]) -> str:
    if value not in options:
        raise MessageError(f"{name}: {value!r} not one of {', '.join(options)}")
    return value


def _set(obj, name, value) -> None:
    object.__setattr__(obj, name, value)


class _Msg:
    """Base: each subclass has a unique ``TAG`` and ``_pack()`` / ``_unpack(body)``."""

    TAG: ClassVar[int]

    def _pack(self) -> bytes:  # pragma: no cover - abstract
        raise NotImplementedError

    @classmethod
    def _unpack(cls, body: memoryview):  # pragma: no cover - abstract
        raise NotImplementedError


def _unpack_exact(fmt: struct.Struct, body: memoryview, what: str) -> tuple:
    if len(body) != fmt.size:
        raise MessageError(f"{what}: body is {len(body)} bytes, expected {fmt.size}")
    return fmt.unpack(body)


# ---- the messages -------------------------------------------------------------------------------


@dataclass(frozen=True)
class Hello(_Msg):
    """First message on a link: who is talking. ``role`` in ROLES, ``pid`` the OS process id."""

    role: Literal["supervisor", "predictor", "recognizer"]
    pid: int

    TAG: ClassVar[int] = 1
    _FMT: ClassVar[struct.Struct] = struct.Struct("<BI")

    def __post_init__(self):
        _set(self, "role", _choice("role", self.role, ROLES))
        _set(self, "pid", _uint("pid", self.pid, 32))

    def _pack(self):
        return self._FMT.pack(ROLES.index(self.role), self.pid)

    @classmethod
    def _unpack(cls, body):
        role, pid = _unpack_exact(cls._FMT, body, "Hello")
        if role >= len(ROLES):
            raise MessageError(f"Hello: unknown role code {role}")
        return cls(ROLES[role], pid)


@dataclass(frozen=True)
class Heartbeat(_Msg):
    """I am alive: ``seq`` counts up (wraps at 2**32), ``t`` the sender's clock (s)."""

    role: Literal["supervisor", "predictor", "recognizer"]
    seq: int
    t: float

    TAG: ClassVar[int] = 2
    _FMT: ClassVar[struct.Struct] = struct.Struct("<BId")

    def __post_init__(self):
        _set(self, "role", _choice("role", self.role, ROLES))
        _set(self, "seq", _uint("seq", self.seq, 32))
        _set(self, "t", _f64("t", self.t))

    def _pack(self):
        return self._FMT.pack(ROLES.index(self.role), self.seq, self.t)

    @classmethod
    def _unpack(cls, body):
        role, seq, t = _unpack_exact(cls._FMT, body, "Heartbeat")
        if role >= len(ROLES):
            raise MessageError(f"Heartbeat: unknown role code {role}")
        return cls(ROLES[role], seq, t)


@dataclass(frozen=True)
class CaptureRequest(_Msg):
    """Host 1 -> Host 2: grab a mobile-camera image at ``t_capture`` (s) with the camera at pose
    ``T_w_c2`` (paper §5.2: the two initial marker images, then the standard view).

    The pose is sent compactly as ``position`` (mm, world frame) and ``rotvec`` (rad, axis·angle
    of R_w_c2), both float32; use :meth:`from_pose` / :meth:`pose` to go to and from 4×4.
    """

    view_id: int
    kind: CaptureKind
    t_capture: float
    position: tuple[float, float, float]
    rotvec: tuple[float, float, float]

    TAG: ClassVar[int] = 3
    _FMT: ClassVar[struct.Struct] = struct.Struct("<HBd6f")

    def __post_init__(self):
        _set(self, "view_id", _uint("view_id", self.view_id, 16))
        _set(self, "kind", _choice("kind", self.kind, CAPTURE_KINDS))
        _set(self, "t_capture", _f64("t_capture", self.t_capture))
        _set(self, "position", _vec3("position", self.position))
        rv = _vec3("rotvec", self.rotvec)
        if math.hypot(*rv) > math.pi + 1e-3:
            raise MessageError(f"rotvec: angle {math.hypot(*rv):.4f} rad exceeds pi")
        _set(self, "rotvec", rv)

    @classmethod
    def from_pose(cls, view_id: int, kind: CaptureKind, t_capture: float, T_w_c2: np.ndarray) -> CaptureRequest:
        """Build from a 4×4 pose T_w_c2 (mobile camera C2 -> world W, mm)."""
        from ..geometry.transforms import matrix_to_rotvec

        T = np.asarray(T_w_c2, dtype=float)
        if T.shape != (4, 4) or not np.all(np.isfinite(T)):
            raise MessageError("T_w_c2: needs a finite 4x4 matrix")
        return cls(view_id, kind, t_capture, tuple(T[:3, 3]), tuple(matrix_to_rotvec(T[:3, :3])))

    def pose(self) -> np.ndarray:
        """The requested camera pose T_w_c2 as a 4×4 matrix (mm)."""
        from ..geometry.transforms import make_T, rotvec_to_matrix

        return make_T(rotvec_to_matrix(np.array(self.rotvec)), np.array(self.position))

    def _pack(self):
        return self._FMT.pack(self.view_id, CAPTURE_KINDS.index(self.kind), self.t_capture,
                              *self.position, *self.rotvec)

    @classmethod
    def _unpack(cls, body):
        view_id, kind, t, *v = _unpack_exact(cls._FMT, body, "CaptureRequest")
        if kind >= len(CAPTURE_KINDS):
            raise MessageError(f"CaptureRequest: unknown kind code {kind}")
        return cls(view_id, CAPTURE_KINDS[kind], t, tuple(v[:3]), tuple(v[3:]))


@dataclass(frozen=True)
class FrameTaken(_Msg):
    """Host 2 -> Host 1: the image for ``view_id`` was grabbed at ``t`` (s); the robot may move."""

    view_id: int
    t: float

    TAG: ClassVar[int] = 4
    _FMT: ClassVar[struct.Struct] = struct.Struct("<Hd")

    def __post_init__(self):
        _set(self, "view_id", _uint("view_id", self.view_id, 16))
        _set(self, "t", _f64("t", self.t))

    def _pack(self):
        return self._FMT.pack(self.view_id, self.t)

    @classmethod
    def _unpack(cls, body):
        return cls(*_unpack_exact(cls._FMT, body, "FrameTaken"))


@dataclass(frozen=True)
class MarkerPose(_Msg):
    """Host 2 -> Host 1: the marker's pose from the two initial images (paper §3.2, §5.2):
    centre ``center_w`` (mm) and unit outward normal ``normal_w`` in the world frame W.

    ``ambiguous`` is set when the two-image test could not separate the two ellipse
    back-projection solutions; ``margin`` is how clearly it did (larger = clearer).
    """

    view_id: int
    center_w: tuple[float, float, float]
    normal_w: tuple[float, float, float]
    ambiguous: bool
    margin: float

    TAG: ClassVar[int] = 5
    _FMT: ClassVar[struct.Struct] = struct.Struct("<H6fBf")

    def __post_init__(self):
        _set(self, "view_id", _uint("view_id", self.view_id, 16))
        _set(self, "center_w", _vec3("center_w", self.center_w))
        n = _vec3("normal_w", self.normal_w)
        if abs(math.sqrt(sum(c * c for c in n)) - 1.0) > 1e-3:
            raise MessageError("normal_w: not a unit vector")
        _set(self, "normal_w", n)
        if not isinstance(self.ambiguous, bool | np.bool_):
            raise MessageError(f"ambiguous: not a bool: {self.ambiguous!r}")
        _set(self, "ambiguous", bool(self.ambiguous))
        _set(self, "margin", _f32("margin", self.margin))

    def _pack(self):
        return self._FMT.pack(self.view_id, *self.center_w, *self.normal_w, int(self.ambiguous), self.margin)

    @classmethod
    def _unpack(cls, body):
        view_id, *v, amb, margin = _unpack_exact(cls._FMT, body, "MarkerPose")
        if amb > 1:
            raise MessageError(f"MarkerPose: ambiguous flag {amb} is not 0/1")
        return cls(view_id, tuple(v[:3]), tuple(v[3:6]), bool(amb), margin)


@dataclass(frozen=True)
class StandardViewRequest(_Msg):
    """Host 1 -> Host 2: the next view ``view_id`` is the standard view of marker ``marker_index``."""

    view_id: int
    marker_index: int

    TAG: ClassVar[int] = 6
    _FMT: ClassVar[struct.Struct] = struct.Struct("<HB")

    def __post_init__(self):
        _set(self, "view_id", _uint("view_id", self.view_id, 16))
        _set(self, "marker_index", _uint("marker_index", self.marker_index, 8))

    def _pack(self):
        return self._FMT.pack(self.view_id, self.marker_index)

    @classmethod
    def _unpack(cls, body):
        return cls(*_unpack_exact(cls._FMT, body, "StandardViewRequest"))


_IDS_HEAD = struct.Struct("<B")


def _pack_ids(ids: tuple[int, ...]) -> bytes:
    return _IDS_HEAD.pack(len(ids)) + struct.pack(f"<{len(ids)}H", *ids)


def _unpack_ids(body: memoryview, what: str) -> tuple[tuple[int, ...], memoryview]:
    if len(body) < 1:
        raise MessageError(f"{what}: truncated id list")
    (n,) = _IDS_HEAD.unpack(body[:1])
    if n > MAX_CANDIDATES:
        raise MessageError(f"{what}: {n} ids, at most {MAX_CANDIDATES}")
    end = 1 + 2 * n
    if len(body) < end:
        raise MessageError(f"{what}: truncated id list")
    return struct.unpack(f"<{n}H", body[1:end]), body[end:]


@dataclass(frozen=True)
class Identity(_Msg):
    """Host 2 -> Host 1: the object is ``object_id`` with match ``score`` after comparing
    ``n_candidates`` library objects; ``candidates`` lists the ids still in contention, best first
    (paper §3.3: matching the standard-view 2D signature against the library)."""

    object_id: int
    score: float
    n_candidates: int
    candidates: tuple[int, ...] = ()

    TAG: ClassVar[int] = 7
    _FMT: ClassVar[struct.Struct] = struct.Struct("<HfH")

    def __post_init__(self):
        _set(self, "object_id", _uint("object_id", self.object_id, 16))
        _set(self, "score", _f32("score", self.score))
        _set(self, "n_candidates", _uint("n_candidates", self.n_candidates, 16))
        _set(self, "candidates", _ids("candidates", self.candidates))

    def _pack(self):
        return self._FMT.pack(self.object_id, self.score, self.n_candidates) + _pack_ids(self.candidates)

    @classmethod
    def _unpack(cls, body):
        if len(body) < cls._FMT.size:
            raise MessageError("Identity: truncated")
        head = cls._FMT.unpack(body[: cls._FMT.size])
        ids, rest = _unpack_ids(body[cls._FMT.size:], "Identity")
        if len(rest):
            raise MessageError(f"Identity: {len(rest)} trailing bytes")
        object_id, score, n_candidates = head
        return cls(object_id, score, n_candidates, ids)


@dataclass(frozen=True)
class Ambiguous(_Msg):
    """Host 2 -> Host 1: the standard view left several ``candidates``; ``next_marker`` (or None)
    is the marker whose standard view would separate them best (paper §3.3, next view)."""

    candidates: tuple[int, ...]
    next_marker: int | None = None

    TAG: ClassVar[int] = 8

    def __post_init__(self):
        _set(self, "candidates", _ids("candidates", self.candidates))
        if self.next_marker is not None:
            nm = _uint("next_marker", self.next_marker, 8)
            if nm == NO_MARKER:
                raise MessageError(f"next_marker: {NO_MARKER} is reserved for None")
            _set(self, "next_marker", nm)

    def _pack(self):
        return _pack_ids(self.candidates) + bytes([NO_MARKER if self.next_marker is None else self.next_marker])

    @classmethod
    def _unpack(cls, body):
        ids, rest = _unpack_ids(body, "Ambiguous")
        if len(rest) != 1:
            raise MessageError("Ambiguous: bad length")
        return cls(ids, None if rest[0] == NO_MARKER else rest[0])


def _unpack_text(body: memoryview, what: str) -> str:
    if len(body) < 1 or len(body) != 1 + body[0]:
        raise MessageError(f"{what}: bad text length")
    try:
        return bytes(body[1:]).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MessageError(f"{what}: text is not UTF-8") from exc


def _pack_text(text: str) -> bytes:
    data = text.encode("utf-8")
    return bytes([len(data)]) + data


@dataclass(frozen=True)
class Failure(_Msg):
    """Either worker: a stage failed with ``code`` (see FailureCode) and a short ``text``."""

    code: int
    text: str = ""

    TAG: ClassVar[int] = 9

    def __post_init__(self):
        _set(self, "code", _uint("code", self.code, 8))
        _set(self, "text", _text("text", self.text))

    @classmethod
    def short(cls, code: int, text: str) -> Failure:
        """A Failure whose text is cut to MAX_TEXT_BYTES (for exception messages of any length)."""
        return cls(code, _clip_text(text))

    def _pack(self):
        return bytes([self.code]) + _pack_text(self.text)

    @classmethod
    def _unpack(cls, body):
        if len(body) < 1:
            raise MessageError("Failure: truncated")
        return cls(body[0], _unpack_text(body[1:], "Failure"))


@dataclass(frozen=True)
class Stop(_Msg):
    """Supervisor or either worker: stop everything now (robot and table), with a short reason."""

    reason: str = ""

    TAG: ClassVar[int] = 10

    def __post_init__(self):
        _set(self, "reason", _text("reason", self.reason))

    @classmethod
    def short(cls, reason: str) -> Stop:
        """A Stop whose reason is clipped to what a message may carry."""
        return cls(_clip_text(reason))

    def _pack(self):
        return _pack_text(self.reason)

    @classmethod
    def _unpack(cls, body):
        return cls(_unpack_text(body, "Stop"))


@dataclass(frozen=True)
class Discard(_Msg):
    """Host 1 -> Host 2: forget the image of ``view_id`` and everything it changed (its arrival was not confirmed).

    An image is requested at the robot controller's promised arrival, before its ``@DONE`` has crossed the line;
    if that ``@DONE`` does not come, the image may show a robot that had not arrived, so the recognizer goes
    back to its state before that request (docs/notes/planning.md "2026-12-02 (c)")."""

    view_id: int

    TAG: ClassVar[int] = 11
    _FMT: ClassVar[struct.Struct] = struct.Struct("<H")

    def __post_init__(self):
        _set(self, "view_id", _uint("view_id", self.view_id, 16))

    def _pack(self):
        return self._FMT.pack(self.view_id)

    @classmethod
    def _unpack(cls, body):
        return cls(*_unpack_exact(cls._FMT, body, "Discard"))


Message = (Hello | Heartbeat | CaptureRequest | FrameTaken | MarkerPose | StandardViewRequest | Identity
           | Ambiguous | Failure | Stop | Discard)

MESSAGE_TYPES: dict[int, type[_Msg]] = {
    cls.TAG: cls
    for cls in (Hello, Heartbeat, CaptureRequest, FrameTaken, MarkerPose, StandardViewRequest, Identity,
                Ambiguous, Failure, Stop, Discard)
}


def encode(msg: Message) -> bytes:
    """The wire form of ``msg``: one type-tag byte, then the message's fixed layout (little-endian)."""
    if not isinstance(msg, _Msg) or type(msg) not in MESSAGE_TYPES.values():
        raise MessageError(f"not a message: {type(msg).__name__}")
    return bytes([msg.TAG]) + msg._pack()


def decode(data: bytes | bytearray | memoryview) -> Message:
    """Parse one message from exactly ``data``; any malformed input raises :class:`MessageError`."""
    try:
        view = memoryview(bytes(data))
    except TypeError as exc:
        raise MessageError(f"cannot decode {type(data).__name__}") from exc
    if len(view) == 0:
        raise MessageError("empty message")
    cls = MESSAGE_TYPES.get(view[0])
    if cls is None:
        raise MessageError(f"unknown message tag {view[0]}")
    try:
        return cls._unpack(view[1:])
    except MessageError:
        raise
    except (struct.error, ValueError, TypeError, IndexError, OverflowError) as exc:
        raise MessageError(f"{cls.__name__}: {exc}") from exc


def size_of(msg: Message) -> int:
    """Encoded size of ``msg`` in bytes (payload, without link framing)."""
    return len(encode(msg))
