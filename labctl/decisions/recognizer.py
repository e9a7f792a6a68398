"""Host 2: the object recognizer (paper §3, Fig. 1 Module 1).

On each :class:`~labctl.decisions.messages.CaptureRequest` it grabs the mobile camera's frame and

* ``initial1`` — picks one marker and keeps both candidate poses (§3.2), in the world frame;
* ``initial2`` — finds the same marker again and resolves the two-fold ambiguity (§3.3): the
  object only translated, so the true world normal is the one both images share;
* ``standard`` — extracts the silhouette, computes the shape features and matches them against
  the library (§3.4), keeping the candidate set across views when one view is ambiguous.

Driven from outside (``handle``); it owns no clock, thread or process. ``grab()`` returns the
mobile camera's latest :class:`~labctl.drivers.interfaces.Frame`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import replace
from typing import Any

import numpy as np

from ..drivers.interfaces import Frame
from ..geometry import make_T, rotvec_to_matrix
from ..library.marker_height import measure_marker_height
from ..library.matching import (
    DEFAULT_THRESHOLD,
    MARGIN,
    UP_NZ,
    evidence_leader,
    match,
    needs_top_marker,
    view_scores,
)
from ..library.views import mm_per_px
from ..vision import CirclePose, CirclePoseError, EllipseFitError, MarkerPoses, detect_markers, marker_poses
from ..vision.duality import DEFAULT_K_SIGMA, DEFAULT_MIN_MARGIN_RAD, pose_pair_consistency, resolve_duality_detailed
from ..vision.shape import ShapeError, features_from_image, silhouette_mask
from . import messages as m
from .context import RunContext, marker_thresholds

#: after the common shift, a marker of the second image pairs with one of the first if their centres lie
#: this close (mm, W); the two candidate centres of one marker differ by a few mm
PAIR_MAX_MM = 12.0
#: a standard view's marker farther than this fraction of the image width from the image centre was not flown to:
#: the table turned a corner during the flight (docs/notes/run.md, "Missed standard views": the views that missed
#: had the marker 15 % of the width or more off the centre)
STANDARD_VIEW_MAX_OFFSET_FRAC = 0.15
#: along the marker's normal the marker's image is a circle: a smaller minor/major axis ratio is an oblique view
#: (cos 32°), whose silhouette is not the standard view's
STANDARD_VIEW_MIN_AXIS_RATIO = 0.85
#: older frames a capture skips to reach one stamped at or after its request (a free-running camera's latest frame
#: is at most a period old; a few more for a stream's jitter)
MAX_STALE_GRABS = 3


def _mid(poses) -> np.ndarray:
    return 0.5 * (np.asarray(poses[0].center) + np.asarray(poses[1].center))


def pair_markers(first: list, second: list, tol_mm: float = PAIR_MAX_MM) -> list[tuple[int, int]]:
    """Pairs (k, j) of the same markers seen in two images of an object that translated between them.

    Every pairing of a first-image marker with a second-image one proposes the shift; the shift that
    pairs the most markers within ``tol_mm`` (then the smallest residual) wins; pairs are one-to-one
    and ordered as ``first``. Works for any speed of the table (the shift is not assumed small).
    """
    if not first or not second:
        return []
    a, b = np.asarray(first, float), np.asarray(second, float)
    best, best_key = [], None
    for d in (b[None, :, :] - a[:, None, :]).reshape(-1, 3):
        dist = np.linalg.norm(a[:, None, :] + d - b[None, :, :], axis=2)
        pairs, used, cost = [], set(), 0.0
        for k in range(len(a)):
            j = int(np.argmin(dist[k]))
            if dist[k, j] <= tol_mm and j not in used:
                pairs.append((k, j))
                used.add(j)
                cost += float(dist[k, j])
        key = (-len(pairs), cost, float(np.linalg.norm(d)))
        if best_key is None or key < best_key:
            best, best_key = pairs, key
    return best


_LAST_RESORT_FLAGS = {"rough", "blurred"}
# ... and only with a normal σ (vision.marker_poses) within 0.6°, 1.5× a trusted marker's here (0.42–0.47°):
# suspects in realistic-camera frames at 0.64–0.77° gave standard views 60 mm off target
_LAST_RESORT_MAX_SIGMA_RAD = float(np.radians(0.6))


def _to_world(T_w_c: np.ndarray, pose: CirclePose) -> CirclePose:
    return CirclePose(T_w_c[:3, :3] @ pose.center + T_w_c[:3, 3], T_w_c[:3, :3] @ pose.normal)


def _ellipse_row(e) -> list[float]:
    """[cx, cy, a, b, θ] (px, px, semi-axes px, rad) as the run report draws it."""
    return [float(e.center[0]), float(e.center[1]), float(e.axes[0]), float(e.axes[1]), float(e.angle)]


def _height_misfit(z: float, z_table: float, max_height_mm: float = 130.0) -> float:
    """How far (mm) a marker centre at height ``z`` lies outside the band an object on the table can
    reach, [z_table, z_table + max_height_mm] (0 inside)."""
    return max(z_table - z, 0.0, z - (z_table + max_height_mm))


def _angle(u, v) -> float:
    return float(np.arctan2(np.linalg.norm(np.cross(u, v)), float(np.dot(u, v))))


class _Candidates(tuple):
    """A marker's two world-frame pose candidates, with ``sigma_rad``: their normal's noise (rad), and
    ``camera_poses`` / ``R_w_c``: the camera-frame poses with covariances and the camera's rotation (for the
    two-view consistency check)."""

    sigma_rad: float = 0.0
    camera_poses: MarkerPoses | None = None
    R_w_c: np.ndarray | None = None


class Recognizer:
    """Host 2's logic. ``save_image(name, image)`` and ``log(event, **fields)`` go to the record."""

    def __init__(self, ctx: RunContext, grab: Callable[[], Frame], log: Callable[..., None],
                 save_image: Callable[[str, np.ndarray], None] | None = None):
        self.ctx, self.grab, self.log = ctx, grab, log
        self.save_image = save_image or (lambda name, image: None)
        self.radius = ctx.lab.config.marker.radius_mm
        # the surface the parts ride on (z in W): the table's, or W's z = 0 plane for a conveyor lab with no table
        self.z_table = float(ctx.lab.table.origin_w_mm[2]) if ctx.lab.table is not None else 0.0
        self.threshold = ctx.lab.config.run.ambiguity_threshold or DEFAULT_THRESHOLD
        self.first: list | None = None  # (marker, (pose, pose) in W) of the first image, preferred first
        self._response_seen: list[int] = [0, 0, 0]  # markers, mismatched, refused: the last capture's check
        self.resolved_normals: list[np.ndarray] = []
        self.remaining: list[str] | None = None
        self.totals: dict[str, float] = {}  # each candidate's score summed over the matched standard views
        self.n_matched = 0
        self.n_standard = 0
        self.n_initial_seen = 0  # initial images in which the object's markers were seen
        self.saw_top_marker = False  # did any initial image show a marker facing up?
        cam_cfg = ctx.lab.mobile_camera
        # frames are linearised by the camera's declared response before any sub-pixel work; a response nobody
        # declared (lab.response_declared) makes pose conservative: a marker not fit for pose is refused
        self.response_declared = ctx.lab.response_declared("mobile_camera")
        self.detect_kw: dict[str, Any] = dict(thresholds=marker_thresholds(cam_cfg), response=cam_cfg.response)
        if not self.response_declared:  # (the default stays out of the arguments: detect_markers' own is True)
            self.detect_kw["response_declared"] = False
        # (view id, the state before its image): what a Discard of that view goes back to
        self._before: tuple[int, dict[str, Any]] | None = None

    def _state(self) -> dict[str, Any]:
        """What an image changes (copies): the first image's markers, resolved normals, candidates and totals."""
        return {"first": self.first, "resolved_normals": list(self.resolved_normals),
                "remaining": None if self.remaining is None else list(self.remaining), "totals": dict(self.totals),
                "n_matched": self.n_matched, "n_standard": self.n_standard, "n_initial_seen": self.n_initial_seen,
                "saw_top_marker": self.saw_top_marker}

    def handle(self, msg: m.Message) -> list[m.Message]:
        """Answer one message from the predictor: a capture request is taken, posed or matched; a ``Discard`` of the
        last one undoes what its image changed; anything else gets no answer."""
        if isinstance(msg, m.Discard):
            if self._before is not None and self._before[0] == msg.view_id:
                for name, value in self._before[1].items():
                    setattr(self, name, value)
            self._before = None
            return []
        if not isinstance(msg, m.CaptureRequest):
            return []
        self._before = (msg.view_id, self._state())
        frame = self._grab_after(msg.t_capture)
        self.save_image(f"view_{msg.view_id}", frame.image)  # raw, for `labctl replay`
        T_w_c2 = make_T(rotvec_to_matrix(msg.rotvec), msg.position)
        if msg.kind == "standard":
            return [self._standard(msg, frame)]
        return self._initial(msg, frame, T_w_c2)

    def _grab_after(self, t_capture: float) -> Frame:
        """The camera's first frame stamped at or after ``t_capture`` (s): from then on the robot stands still. A
        free-running camera's latest frame can be up to a frame period older than the request (the simulated
        lab's live cameras, a V4L2 stream); a triggered one (the virtual runtime's) is exposed on request. At most
        :data:`MAX_STALE_GRABS` older frames are skipped."""
        frame = self.grab()
        for _ in range(MAX_STALE_GRABS):
            if frame.t >= t_capture:
                break
            frame = self.grab()
        return frame

    # -- marker pose (paper §3.1–3.3) -------------------------------------------------------------
    def _candidates(self, frame: Frame, T_w_c2: np.ndarray):
        """Every complete marker in the frame with its two world-frame candidate poses.

        Each pair carries ``sigma_rad``, its normal standard deviation (rad, the larger of the two;
        rotation-invariant, so the camera frame's holds in W), for the duality test."""
        out = []
        # markers flagged only as rough or blurred (small oblique markers in JPEG 4:2:0 frames: their
        # normals are ~1° off instead of ~0.3°) with a small normal σ are a last resort: preferred only
        # when more novel than every trusted marker or none is trusted, else spares (measured in realistic-camera
        # trials, docs/notes/vision.md); the noise-aware duality test and the standard view's check still guard
        every = detect_markers(frame.image, include_suspect=True, **self.detect_kw)
        # the camera response check of this capture (docs/notes/vision.md): markers whose edges lean as another
        # response's would, and those an undeclared response's conservative covariance refused for pose
        self._response_seen = [len(every), sum("response_mismatch" in mk.quality.flags for mk in every
                                                if mk.quality is not None), 0]
        for mk in (mk for mk in every
                   if mk.trusted or (mk.quality is not None and set(mk.quality.flags) <= _LAST_RESORT_FLAGS)):
            best = None
            # an ellipse fixes a circle's distance only up to its radius: with several marker sizes in the
            # library, take the size that puts the marker on the object, i.e. near the table
            for r in self.ctx.marker_radii_mm or (self.radius,):
                try:
                    mp = marker_poses(mk, self.ctx.mobile_camera, r)
                except (CirclePoseError, EllipseFitError, ValueError):
                    continue
                a, b = mp.candidates
                poses = _Candidates((_to_world(T_w_c2, a), _to_world(T_w_c2, b)))
                poses.sigma_rad = max(mp.normal_sigma_rad)
                poses.camera_poses, poses.R_w_c = mp, T_w_c2[:3, :3]
                off = _height_misfit(float(poses[0].center[2]), self.z_table)
                if best is None or off < best[0] - 1e-9:
                    best = (off, poses)
            if best is not None and not self.response_declared and best[1].camera_poses is not None \
                    and "pose" not in best[1].camera_poses.fit_for:
                self._response_seen[2] += 1  # its pose could be gross under the response nobody declared
                continue
            if best is not None and (mk.trusted or best[1].sigma_rad <= _LAST_RESORT_MAX_SIGMA_RAD):
                out.append((mk, best[1]))
        return out

    def _duality_threshold(self, poses1, poses2) -> float:
        """The margin a duality decision must reach (rad): k·√2·σ of the two images' normal noise
        (vision.duality.resolve_duality_noise_aware), never below the fixed floor."""
        s1, s2 = poses1.sigma_rad, poses2.sigma_rad
        t = DEFAULT_K_SIGMA * float(np.sqrt(2.0 * (s1 * s1 + s2 * s2)))
        return max(t, DEFAULT_MIN_MARGIN_RAD) if np.isfinite(t) else float("inf")

    @staticmethod
    def _consistency(poses1, poses2):
        """Two-view check of one marker's poses (vision.pose_pair_consistency, paper §3.3's two images): the
        normals, the second image's rotated into the first camera's frame, must agree within the poses'
        covariances. None when either pose has no covariance."""
        if poses1.camera_poses is None or poses2.camera_poses is None or poses1.R_w_c is None or poses2.R_w_c is None:
            return None
        return pose_pair_consistency(poses1.camera_poses, poses2.camera_poses,
                                     R_first_second=poses1.R_w_c.T @ poses2.R_w_c)

    def _sees_top_marker(self, frame: Frame, T_w_c2: np.ndarray) -> bool:
        """True if any red blob of this initial image (suspects and blobs cut by the border included) may
        be a marker facing up: one of its two pose candidates has a normal within ~25° of vertical. Seen
        from above at the library's viewing angle, a marker facing up is the one hardest to miss."""
        every = detect_markers(frame.image, include_suspect=True, keep_border=True, **self.detect_kw)
        for mk in every:
            try:
                poses = marker_poses(mk, self.ctx.mobile_camera, self.radius).candidates
            except (CirclePoseError, EllipseFitError, ValueError):
                return True  # a blob with no pose could be anything: never count it as absent
            if any(float(T_w_c2[2, :3] @ p.normal) > UP_NZ for p in poses):
                return True
        return False

    def _initial(self, msg: m.CaptureRequest, frame: Frame, T_w_c2: np.ndarray) -> list[m.Message]:
        found = self._candidates(frame, T_w_c2)
        n_markers, n_mismatch, n_refused = self._response_seen
        if n_mismatch or not self.response_declared:
            self.log("response_check", t=frame.t, view_id=msg.view_id, declared=self.response_declared,
                     markers=n_markers, mismatched=n_mismatch, refused=n_refused)
        if found:
            self.n_initial_seen += 1
            self.saw_top_marker = self.saw_top_marker or self._sees_top_marker(frame, T_w_c2)
        if not found:
            self.log("no_marker", t=frame.t, view_id=msg.view_id, kind=msg.kind)
            return [m.Failure(code=m.FailureCode.NO_MARKER_FOUND, text=f"no marker in mobile image {msg.view_id}")]
        if msg.kind == "initial1" or self.first is None:
            centre = np.array([self.ctx.mobile_camera.width, self.ctx.mobile_camera.height]) / 2.0

            def novelty(item):  # prefer markers whose normals differ from markers already used
                _, poses = item
                if not self.resolved_normals:
                    return 0.0
                return -min(_angle(p.normal, n) for p in poses for n in self.resolved_normals)

            def upness(item):  # a marker facing up has a standard view the robot can reach
                return -round(min(float(p.normal[2]) for p in item[1]), 1)

            found.sort(key=lambda it: (round(novelty(it), 1), not it[0].trusted, upness(it),
                                       float(np.hypot(*(np.asarray(it[0].centroid) - centre)))))
            self.first = found  # every marker of the first image, the preferred one first
            self.save_image("initial1", frame.image)
            marker, poses = found[0]
            self.log("marker_candidates", t=frame.t, view_id=msg.view_id, ellipse=marker.ellipse.to_dict(),
                     candidates=[p.to_dict() for p in poses], markers=len(found))
            return [m.FrameTaken(view_id=msg.view_id, t=frame.t)]
        # initial2: the object translated between the images; pair the markers under one common shift
        self.save_image("initial2", frame.image)
        replies: list[m.Message] = [m.FrameTaken(view_id=msg.view_id, t=frame.t)]
        suspects: list[m.Message] = []
        for k, j in pair_markers([_mid(p) for _, p in self.first], [_mid(p) for _, p in found]):
            mk1, poses1 = self.first[k]
            mk2, poses2 = found[j]
            res = resolve_duality_detailed(poses1, poses2, motion="translation",
                                           min_margin_rad=self._duality_threshold(poses1, poses2))
            pose = res.best
            # the two views must agree with each other (vision.pose_pair_consistency, normals only: the object
            # translated, by an amount the recogniser is not told): a pair that does not is suspect
            chk = self._consistency(poses1, poses2)
            ellipses = {"initial1": _ellipse_row(mk1.ellipse), "initial2": _ellipse_row(mk2.ellipse)}
            self.log("marker_pose", t=frame.t, view_id=msg.view_id, marker=k, ellipses=ellipses,
                     center_w=pose.center, normal_w=pose.normal, **res.to_dict(),
                     consistency=None if chk is None else chk.to_dict())
            if not res.ambiguous:
                self.resolved_normals.append(np.asarray(pose.normal))
            elif k > 0:
                continue  # only the preferred marker is worth reporting unresolved
            reply = m.MarkerPose(view_id=msg.view_id, center_w=tuple(pose.center), normal_w=tuple(pose.normal),
                                 ambiguous=bool(res.ambiguous), margin=float(res.margin_rad))
            # an inconsistent pair is treated as a suspect marker: a last resort behind every consistent one
            (suspects if chk is not None and not chk.consistent and not res.ambiguous else replies).append(reply)
        replies += suspects
        if len(replies) == 1:
            return [m.Failure(code=m.FailureCode.MARKER_LOST, text=f"marker not found again in image {msg.view_id}")]
        return replies

    # -- standard view (paper §3.4) -----------------------------------------------------------------
    def _misaligned(self, image: np.ndarray) -> str | None:
        """Why this is no standard view, or None: along the marker's normal the marker is a circle
        (axis ratio ≥ :data:`STANDARD_VIEW_MIN_AXIS_RATIO`) at the image centre (within
        :data:`STANDARD_VIEW_MAX_OFFSET_FRAC` of the width)."""
        cam = self.ctx.mobile_camera
        centre = np.array([cam.width, cam.height]) / 2.0
        markers = detect_markers(image, **self.detect_kw)
        if not markers:
            return "no marker in view"
        mk = min(markers, key=lambda mk: float(np.hypot(*(np.asarray(mk.centroid) - centre))))
        off = float(np.hypot(*(np.asarray(mk.centroid) - centre)))
        ratio = float(mk.ellipse.axes[1] / mk.ellipse.axes[0])
        if off > STANDARD_VIEW_MAX_OFFSET_FRAC * cam.width:
            return f"marker {off:.0f} px from the image centre"
        if ratio < STANDARD_VIEW_MIN_AXIS_RATIO:
            return f"marker seen obliquely (axis ratio {ratio:.2f})"
        return None

    def _marker_height(self, msg: m.CaptureRequest) -> float:
        """Height (mm) above the table of the marker this standard view was planned for (logged beside
        the measured one; the gate uses the measurement, this is only as good as the initial pose): the view is planned
        ``viewing.standoff_mm`` out along the marker's normal from its estimated centre, and the table
        moves only in x and y, so the centre's z is the camera's plus the stand-off along the optical
        axis (``planning.targets.standard_view_pose``)."""
        R = rotvec_to_matrix(msg.rotvec)
        z = float(msg.position[2]) + self.ctx.lab.config.viewing.standoff_mm * float(R[2, 2])
        return z - self.z_table

    def _measured_height(self, msg: m.CaptureRequest, frame: Frame):
        """(the viewed marker's height measured in this standard view, :class:`MarkerHeight` or None;
        the gate's tolerance in mm, 0: no gate) — ``labctl.library.marker_height``, camera pose from the
        robot's reported flange, policy from ``run.height_gate_*``."""
        run = self.ctx.lab.config.run
        if run.height_gate_mm <= 0:
            return None, 0.0
        T_w_c2 = make_T(rotvec_to_matrix(msg.rotvec), msg.position)
        h = measure_marker_height(frame.image, self.ctx.mobile_camera, T_w_c2,
                                  self.ctx.marker_radii_mm or (self.radius,), z_table_mm=self.z_table,
                                  standoff_mm=self.ctx.lab.config.viewing.standoff_mm, **self.detect_kw)
        if h is None:
            return None, 0.0
        return h, h.tolerance_mm(run.height_gate_mm, run.height_gate_sigmas, run.height_gate_depth_frac)

    def _refute_top_marker_hypotheses(self, res, features, msg: m.CaptureRequest, height, tol: float, t: float,
                                      k: int):
        """Drop the candidates that could show this view only in a resting pose with a marker facing up,
        when no initial image showed one (paper §3.4: a hypothesis predicting a marker where none was
        seen is refuted). Only between ≥ 2 candidates, with a measured marker height, a viewed marker
        that is not itself facing up, and never every candidate."""
        if len(res.candidates) < 2 or self.saw_top_marker or self.n_initial_seen == 0 or height is None:
            return res
        nz = -float(rotvec_to_matrix(msg.rotvec)[2, 2])  # the camera looks along the marker's normal
        if nz > 0.5:
            return res
        s = view_scores(features, self.ctx.index)
        bound = max(self.threshold, res.scores[res.candidates[0]] + MARGIN)
        refuted = [c for c in res.candidates
                   if needs_top_marker(self.ctx.index, c, s, bound, height.height_mm, tol, nz)]
        kept = [c for c in res.candidates if c not in refuted]
        if not refuted or not kept:
            return res
        self.log("refuted", t=t, view=k, candidates=refuted, reason="no marker facing up in the initial images")
        return replace(res, best=(kept[0], res.views[kept[0]]), candidates=kept, ambiguous=len(kept) > 1)

    def _standard(self, msg: m.CaptureRequest, frame: Frame) -> m.Message:
        self.n_standard += 1
        k = self.n_standard
        self.save_image(f"standard_{k}", frame.image)
        problem = self._misaligned(frame.image)
        if problem:  # a view not along the normal would be matched against the wrong standard view
            self.log("standard_view_misaligned", t=frame.t, view_id=msg.view_id, view=k, problem=problem)
            return m.Failure(code=m.FailureCode.VIEW_MISALIGNED,
                             text=f"standard view {k} is not along the marker normal")
        scale = mm_per_px(self.ctx.mobile_camera, self.ctx.lab.config.viewing.standoff_mm)
        try:
            mask = silhouette_mask(frame.image)
            features = features_from_image(frame.image, scale)
        except (ShapeError, ValueError) as exc:
            self.log("no_silhouette", t=frame.t, view_id=msg.view_id, error=str(exc))
            return m.Failure(code=m.FailureCode.NO_MATCH, text=f"no silhouette in standard view {k}")
        self.save_image(f"silhouette_{k}", (mask.astype(np.uint8) * 255))
        height, tol = self._measured_height(msg, frame)
        res = match(features, self.ctx.index, self.threshold, restrict=self.remaining,
                    height_mm=None if height is None else height.height_mm, height_tol_mm=tol)
        scores = {n: (s if np.isfinite(s) else None) for n, s in res.scores.items()}
        measured = {} if height is None else {"marker_height_mm": round(height.height_mm, 2),
                                              "marker_height_sigma_mm": round(height.sigma_mm, 3),
                                              "height_tol_mm": round(tol, 2)}
        self.log("match", t=frame.t, view_id=msg.view_id, view=k, scores=scores, candidates=res.candidates,
                 best=res.best[0] if res.best else None, planned_marker_height_mm=round(self._marker_height(msg), 2),
                 **measured)
        ids = {n: i for i, n in enumerate(self.ctx.names)}
        if res.best is None:
            return m.Failure(code=m.FailureCode.NO_MATCH, text=f"standard view {k} matches no library view")
        res = self._refute_top_marker_hypotheses(res, features, msg, height, tol, frame.t, k)
        self.n_matched += 1
        self.totals = {c: self.totals.get(c, 0.0) + res.scores[c] for c in res.scores if np.isfinite(res.scores[c])
                       and (self.n_matched == 1 or c in self.totals)}
        leader = evidence_leader({c: self.totals[c] for c in res.candidates if c in self.totals}, self.n_matched)
        if len(res.candidates) > 1 and leader is None:
            self.remaining = list(res.candidates)
            return m.Ambiguous(candidates=tuple(ids[c] for c in res.candidates[: m.MAX_CANDIDATES]))
        if leader is not None and len(res.candidates) > 1:
            self.log("evidence", t=frame.t, view=k, leader=leader, views=self.n_matched,
                     totals={c: round(self.totals[c], 4) for c in res.candidates if c in self.totals})
            res = replace(res, best=(leader, res.views[leader]), candidates=[leader], ambiguous=False)
        best = res.best[0]
        cands = res.candidates or [best]
        return m.Identity(object_id=ids[best], score=float(res.scores[best]), n_candidates=len(res.candidates),
                          candidates=tuple(ids[c] for c in cands[: m.MAX_CANDIDATES]))
