"""Standard-view matching (paper §3.4): minimum distance, ambiguity threshold, next standard view.

"The object is identified by matching its feature vector, consisting of a global eccentricity
measure and the shape signature, with the feature information of the standard views in the
database. The identity of the shape is determined by the minimum-distance rule. However, if the
measures of dissimilarity between the acquired shape and multiple standard views are below a
certain threshold, the object cannot be uniquely recognized ... the system will identify the
several candidates ... for the acquisition of an additional standard view."

Dissimilarity of a query q to a library view v (two-level matching, Tchoukanov et al. 1992):

1. gates: ``|ε_q² − ε_v²| ≤ ecc_gate`` (characteristic-ellipse eccentricity) and
   ``|ln(size_q/size_v)| ≤ size_gate`` (metric size known from the stand-off);
2. ``score = d_AOS(q, v) + w_s·|ln(size_q/size_v)| + w_e·|ε_q² − ε_v²| (+ w_p·|ln(perim_q/perim_v)|)``
   with ``d_AOS`` the RMS angle-of-sight difference (rad) minimised over circular shifts
   (:func:`labctl.vision.shape.signature_distance`); w_s = w_e = 2, w_p = 0 were chosen on two
   generated 30-object libraries (the eccentricity term separates rectangles of different
   aspect ratio, whose signatures differ little).

An object's score is its best view's. Objects scoring ≤ ``threshold``, or within ``margin`` of the
best score, are the candidates; two or more candidates make the result ambiguous. In
:func:`identify`, a planned view that finds no marker where hypothesis h predicts one refutes h.
Baseline methods ("hu", "fd") replace ``d_AOS`` by
the Hu-moment (``cv2.matchShapes`` I1) or Fourier-descriptor distance, same gates.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Protocol, cast

import numpy as np

from ..vision.shape import ShapeFeatures, hu_distance
from .placement import Marker

ECC_GATE = 0.15
SIZE_GATE = 0.12
SIZE_WEIGHT = 2.0
ECC_WEIGHT = 2.0
PERIMETER_WEIGHT = 0.0
MARGIN = 0.08  # objects within this of the best score are candidates too (relative ambiguity rule)
DEFAULT_THRESHOLD = 0.15
HEIGHT_TOL_MM = 4.0  # a view's marker height may differ this much from the measured one (pose error)


@dataclass
class LibraryIndex:
    """All standard views of a library stacked for batched matching."""

    names: list[str]  # object of each view
    marker_ids: np.ndarray  # (V,)
    aos: np.ndarray  # (V, S, N)
    ecc2: np.ndarray  # (V,) ε²
    log_size: np.ndarray  # (V,)
    log_perimeter: np.ndarray  # (V,)
    fd: np.ndarray  # (V, K)
    hu: np.ndarray  # (V, 7)
    # (V, P) height (mm) of each view's marker centre above the table in each stable pose of its
    # object (NaN-padded); None: unknown, the height gate passes every view
    heights: np.ndarray | None = None
    # (V, P) z of the view's marker normal in W in each stable pose, and whether the object then shows
    # a marker facing up (normal within ~25° of vertical); None with ``heights``
    normal_z: np.ndarray | None = None
    top_marker: np.ndarray | None = None
    _pair: np.ndarray | None = field(default=None, repr=False)
    _cache: dict = field(default_factory=dict, repr=False)

    def aos_spectra(self) -> tuple[np.ndarray, np.ndarray]:
        """The library's angle-of-sight spectra (V, S, N/2+1) and squared norms (V,), computed once
        (matching then needs one FFT of the query and one inverse FFT per gated-in view)."""
        if "fft" not in self._cache:
            self._cache["fft"] = np.fft.rfft(self.aos, axis=-1)
            self._cache["sq"] = np.sum(self.aos * self.aos, axis=(1, 2))
        return self._cache["fft"], self._cache["sq"]

    def name_ids(self) -> tuple[np.ndarray, np.ndarray]:
        """(unique object names, each view's index into them), computed once."""
        if "ids" not in self._cache:
            self._cache["uniq"], self._cache["ids"] = np.unique(np.array(self.names), return_inverse=True)
        return self._cache["uniq"], self._cache["ids"]

    @classmethod
    def from_views(cls, views: Sequence[tuple[str, int, ShapeFeatures]]) -> LibraryIndex:
        """Index of ``(object name, marker id, ShapeFeatures)`` standard views; raises ValueError if empty."""
        if not views:
            raise ValueError("the library has no standard views")
        return cls(
            names=[n for n, _, _ in views], marker_ids=np.array([m for _, m, _ in views]),
            aos=np.stack([f.aos for _, _, f in views]), ecc2=np.array([f.eccentricity ** 2 for _, _, f in views]),
            log_size=np.log([f.size_mm for _, _, f in views]),
            log_perimeter=np.log([max(f.perimeter_mm, 1e-9) for _, _, f in views]),
            fd=np.stack([f.fd for _, _, f in views]),
            hu=np.stack([f.hu for _, _, f in views]),
        )

    @classmethod
    def from_library(cls, library: Mapping) -> LibraryIndex:
        """From ``{name: LibraryObject}`` (objects with ``.views``: {marker_id: StandardView}); with
        the objects' ``stable_poses`` and ``markers``, also each view's marker heights."""
        items = [(name, mid, v.features) for name, obj in sorted(library.items())
                 for mid, v in sorted(obj.views.items())]
        index = cls.from_views(items)
        rows = [marker_heights(library[name], mid) for name, mid, _ in items]
        if any(r.size for r in rows):
            H = np.full((len(rows), max(r.size for r in rows)), np.nan)
            NZ = np.full(H.shape, np.nan)
            UP = np.zeros(H.shape, bool)
            for i, (r, (name, mid, _)) in enumerate(zip(rows, items, strict=True)):
                H[i, :r.size] = r
                nz, up = _pose_normals(library[name], mid)
                NZ[i, :nz.size], UP[i, :up.size] = nz, up
            index.heights, index.normal_z, index.top_marker = H, NZ, UP
        return index

    def __len__(self) -> int:
        return len(self.names)

    def view_index(self, name: str, marker_id: int) -> int:
        """Row of the standard view ``name``/``marker_id``; raises KeyError if the library has none."""
        for i, (n, m) in enumerate(zip(self.names, self.marker_ids, strict=True)):
            if n == name and m == marker_id:
                return i
        raise KeyError(f"no standard view {name}/{marker_id}")

    def features_of(self, i: int) -> ShapeFeatures:
        """A minimal feature record of view i (for view-to-view distances)."""
        return ShapeFeatures(eccentricity=float(np.sqrt(self.ecc2[i])), size_mm=float(np.exp(self.log_size[i])),
                             perimeter_mm=float(np.exp(self.log_perimeter[i])), chain_start=(0, 0),
                             chain_code=np.zeros(0, np.uint8),
                             aos=self.aos[i], fd=self.fd[i], hu=self.hu[i])

    def pairwise(self) -> np.ndarray:
        """(V, V) view-to-view scores (symmetrised), cached; used by the next-view planner."""
        if self._pair is None:
            D = np.stack([view_scores(self.features_of(i), self) for i in range(len(self))])
            self._pair = np.minimum(D, D.T)
        return self._pair


@dataclass
class MatchResult:
    """``best`` (name, marker_id) of the minimum-distance view or None if nothing passes the gates;
    ``candidates`` objects (best first) scoring ≤ threshold; ``scores`` each object's best score
    (inf when gated out); ``views`` each object's best-matching marker id; ``ambiguous`` when more
    than one candidate remains; ``shift`` the start-point offset of the best view (samples)."""

    best: tuple[str, int] | None
    candidates: list[str]
    scores: dict[str, float]
    views: dict[str, int]
    ambiguous: bool
    shift: int = 0

    @property
    def accepted(self) -> bool:
        """True when at least one object scored within the threshold."""
        return bool(self.candidates)


class PosedObject(Protocol):
    """What the height gate reads of a library object (:class:`labctl.library.storage.LibraryObject`)."""

    @property
    def markers(self) -> Sequence[Marker]:
        """The object's markers."""

    @property
    def stable_poses(self) -> Sequence[tuple[np.ndarray, float]]:
        """Its stable resting poses: (T placing O on the table z = 0, probability); may be empty."""

    def marker(self, marker_id: int) -> Marker:
        """The marker with id ``marker_id`` (KeyError if none)."""


def marker_heights(obj: PosedObject, marker_id: int) -> np.ndarray:
    """Heights (mm) above the table of marker ``marker_id``'s centre in each stable pose of ``obj``
    (a LibraryObject: its ``stable_poses`` place O on the table plane z = 0); empty if unknown."""
    poses = obj.stable_poses
    try:
        c = np.asarray(obj.marker(marker_id).center, float)
    except (AttributeError, KeyError, StopIteration):
        return np.zeros(0)
    return np.array([float(np.asarray(T, float)[2, :3] @ c + np.asarray(T, float)[2, 3]) for T, _ in poses])


UP_NZ = 0.9  # a marker whose normal's z exceeds this faces up (within 25.8° of vertical)


def _pose_normals(obj: PosedObject, marker_id: int) -> tuple[np.ndarray, np.ndarray]:
    """(z of marker ``marker_id``'s normal in each stable pose of ``obj``, whether any marker of ``obj``
    faces up in that pose); empty arrays if unknown."""
    poses = obj.stable_poses
    try:
        n = np.asarray(obj.marker(marker_id).normal, float)
        normals = np.array([np.asarray(mk.normal, float) for mk in obj.markers])
    except (AttributeError, KeyError, StopIteration, TypeError):
        return np.zeros(0), np.zeros(0, bool)
    R = [np.asarray(T, float)[:3, :3] for T, _ in poses]
    return (np.array([float(r[2] @ n) for r in R]),
            np.array([bool(np.any(normals @ r[2] > UP_NZ)) for r in R]))


def needs_top_marker(index: LibraryIndex, name: str, scores: np.ndarray, bound: float, height_mm: float,
                     tol_mm: float, normal_z: float, normal_tol: float = 0.35) -> bool:
    """True when object ``name`` could show this standard view only resting in stable poses in which
    one of its markers faces up: every (view, pose) of ``name`` whose silhouette score is ≤ ``bound``,
    whose marker rests ``height_mm`` ± ``tol_mm`` above the table and whose normal's z is within
    ``normal_tol`` of the measured ``normal_z`` has a marker facing up (:data:`UP_NZ`). False when
    unknown or when no (view, pose) fits (the height gate handles that).

    Paper §3.4: a hypothesis that predicts a marker where the camera saw none is refuted; here the
    initial images, taken from above at the library's viewing angle, saw no marker facing up.
    """
    if index.heights is None or index.top_marker is None or tol_mm <= 0:
        return False
    rows = np.flatnonzero((np.array(index.names) == name) & (np.asarray(scores) <= bound))
    all_normal_z = cast(np.ndarray, index.normal_z)  # set with heights
    fits = ((np.abs(index.heights[rows] - height_mm) <= tol_mm)
            & (np.abs(all_normal_z[rows] - normal_z) <= normal_tol))
    return bool(fits.any() and np.all(index.top_marker[rows][fits]))


def height_gate(index: LibraryIndex, height_mm: float | None, tol_mm: float = HEIGHT_TOL_MM) -> np.ndarray:
    """(V,) True where a view's marker can rest ``height_mm`` ± ``tol_mm`` above the table in some
    stable pose of its object (and where that is unknown). Standard views of plates of one footprint
    look alike; the marker's height, known from the run's marker pose, tells their thickness."""
    if height_mm is None or index.heights is None or not np.isfinite(height_mm) or tol_mm <= 0:
        return np.ones(len(index), bool)
    d = np.abs(index.heights - float(height_mm))
    d = np.where(np.isnan(d), np.inf, d).min(axis=1)
    return (d <= tol_mm) | np.all(np.isnan(index.heights), axis=1)


def view_scores(q: ShapeFeatures, index: LibraryIndex, *, method: str = "aos", ecc_gate: float = ECC_GATE,
                size_gate: float = SIZE_GATE, size_weight: float = SIZE_WEIGHT, ecc_weight: float = ECC_WEIGHT,
                perimeter_weight: float = PERIMETER_WEIGHT, with_shift: bool = False,
                height_mm: float | None = None, height_tol_mm: float = HEIGHT_TOL_MM):
    """Dissimilarity (V,) of a query to every view of ``index`` (inf where gated out).

    ``height_mm``: the viewed marker's centre height above the table (mm), if known; views whose
    marker cannot rest there (± ``height_tol_mm``) are gated out (:func:`height_gate`)."""
    dlog = np.abs(np.log(q.size_mm) - index.log_size)
    dper = np.abs(np.log(max(q.perimeter_mm, 1e-9)) - index.log_perimeter)
    decc = np.abs(q.eccentricity ** 2 - index.ecc2)
    ok = (np.abs(q.eccentricity ** 2 - index.ecc2) <= ecc_gate) & (dlog <= size_gate)
    ok &= height_gate(index, height_mm, height_tol_mm)
    shift = np.zeros(len(index), int)
    if method == "aos":
        d = np.full(len(index), np.inf)
        rows = np.flatnonzero(ok)  # the gates first: the signature distance only for views that pass them
        if rows.size:
            d[rows], shift[rows] = _aos_distance(q.aos, index, rows)
    elif method == "fd":
        d = np.linalg.norm(index.fd - q.fd[None], axis=1)
    elif method == "hu":
        d = hu_distance(q.hu, index.hu)
    else:
        raise ValueError(f"unknown matching method {method!r} (aos, fd, hu)")
    s = np.where(ok, d + size_weight * dlog + ecc_weight * decc + perimeter_weight * dper, np.inf)
    return (s, shift) if with_shift else s


def _aos_distance(q_aos: np.ndarray, index: LibraryIndex, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """:func:`labctl.vision.shape.signature_distance` of the query against views ``rows`` of the index,
    from the index's cached spectra (same formula: ‖a‖² + ‖b‖² − 2·max_s cross-correlation)."""
    fft, sq = index.aos_spectra()
    q = np.asarray(q_aos, float)
    n = q.shape[-1]
    corr = np.fft.irfft(np.einsum("vsk,sk->vk", fft[rows], np.conj(np.fft.rfft(q, axis=-1))), n=n, axis=-1)
    shift = np.argmax(corr, axis=1)
    best = corr[np.arange(len(rows)), shift]
    d = np.sqrt(np.maximum(np.sum(q * q) + sq[rows] - 2.0 * best, 0.0) / q.size)
    return d, shift


def match(features: ShapeFeatures, index: LibraryIndex, threshold: float = DEFAULT_THRESHOLD, *,
          method: str = "aos", restrict: Sequence[str] | None = None, margin: float = MARGIN,
          height_mm: float | None = None, height_tol_mm: float = HEIGHT_TOL_MM, **gates) -> MatchResult:
    """Minimum-distance identification of one standard view with the ambiguity rule (paper §3.4).

    With the viewed marker's height (``height_mm`` ± ``height_tol_mm``), the height only narrows the
    shape's candidates: an object stays a candidate if one of its views both matches the silhouette
    (score ≤ ``threshold`` or within ``margin`` of the best score over all views) and lets its marker
    rest at that height (:func:`height_gate`). A height no shape candidate fits is ignored, so a
    height error can never promote a far match to the answer (it can only leave the view ambiguous).
    """
    s, shift = view_scores(features, index, method=method, with_shift=True, **gates)
    uniq, ids = index.name_ids()
    if restrict is not None:
        s = np.where(np.isin(uniq, list(restrict))[ids], s, np.inf)
    result = _rank(s, shift, index, threshold, margin, None)
    if result.best is None or height_mm is None:
        return result
    g = height_gate(index, height_mm, height_tol_mm)
    if g.all():
        return result
    limit = max(threshold, result.scores[result.candidates[0]] + margin)
    gated = _rank(np.where(g, s, np.inf), shift, index, threshold, margin, limit)
    kept = [c for c in gated.candidates if c in result.candidates]
    if not kept:  # the height fits no shape candidate: trust the silhouette alone
        return result
    return MatchResult(gated.best, kept, gated.scores, gated.views, len(kept) > 1, gated.shift)


def _rank(s: np.ndarray, shift: np.ndarray, index: LibraryIndex, threshold: float, margin: float,
          limit: float | None) -> MatchResult:
    """Each object's best view of the view scores ``s`` (inf: gated out) and the candidates: objects
    scoring ≤ ``threshold`` or within ``margin`` of the best, or (``limit`` given) ≤ ``limit``."""
    uniq, ids = index.name_ids()
    order = np.argsort(s, kind="stable")
    _, first = np.unique(ids[order], return_index=True)  # each object's best view
    firsts = order[np.sort(first)]  # objects in order of their best score
    scores = {str(uniq[ids[i]]): float(s[i]) for i in firsts}
    views = {str(uniq[ids[i]]): int(index.marker_ids[i]) for i in firsts}
    i_best = int(order[0])
    if not np.isfinite(s[i_best]):
        return MatchResult(None, [], scores, views, False)
    best = float(s[i_best])
    bound = max(threshold, best + margin) if limit is None else limit
    cands = [n for n, v in scores.items() if v <= bound]
    return MatchResult((str(index.names[i_best]), int(index.marker_ids[i_best])), cands, scores, views,
                       len(cands) > 1, int(shift[i_best]))


def plan_next_view(candidates: Sequence[str], index: LibraryIndex,
                   viewed: Mapping[str, Sequence[int]] | None = None) -> tuple[str, int]:
    """Next standard view to resolve an ambiguity: ``(object, marker_id)``.

    For every not-yet-viewed marker j of every candidate h, its separation is the smallest
    score between h's view j and any view of another candidate; the marker with the largest
    separation is the one whose view best tells h apart from the rest (paper §3.4: "acquisition
    of an additional standard view to resolve the ambiguity").
    """
    if len(candidates) < 1:
        raise ValueError("no candidates to plan a view for")
    viewed = viewed or {}
    P = index.pairwise()
    names = np.array(index.names)
    best, best_sep = None, -np.inf
    for h in candidates:
        others = np.isin(names, [c for c in candidates if c != h])
        for i in np.flatnonzero(names == h):
            mid = int(index.marker_ids[i])
            if mid in viewed.get(h, ()):
                continue
            sep = float(P[i, others].min()) if others.any() else np.inf
            if sep > best_sep:
                best, best_sep = (h, mid), sep
    if best is None:
        raise ValueError("every marker of every candidate has been viewed")
    return best


@dataclass
class Identification:
    """Outcome of :func:`identify`.

    ``name`` the identified object (lowest accumulated score among the surviving candidates);
    ``resolved`` True when exactly one candidate survived, by the views or by the accumulated
    evidence (:func:`evidence_leader`) — a run answers only then; False: ``name`` is a best guess
    among ``candidates``, and a run fails "still ambiguous"; ``views_used`` standard views taken;
    ``requested`` the planned (object, marker).
    """

    name: str | None
    resolved: bool
    candidates: list[str]
    views_used: int
    steps: list[MatchResult]
    requested: list[tuple[str, int]]


def evidence_leader(totals: Mapping[str, float], n_views: int, margin: float = MARGIN) -> str | None:
    """The candidate whose score summed over ``n_views`` ≥ 2 standard views is lower than every other
    candidate's by more than ``margin·√n_views``, or None.

    One view leaves every object within ``threshold`` a candidate (paper §3.4). Over several views
    the per-view differences add up while their noise grows only as √n, so a lead beyond the
    single-view ``margin`` scaled by √n is evidence, not chance: without this, a part whose only
    markers face one way (a plate) stays "ambiguous" against a look-alike however often it is seen.
    """
    if n_views < 2 or not totals:
        return None
    order = sorted(totals, key=lambda c: totals[c])
    if len(order) == 1 or totals[order[1]] - totals[order[0]] > margin * np.sqrt(n_views):
        return order[0]
    return None


@dataclass(frozen=True)
class UnusableView:
    """What ``acquire`` returns when the camera reached a marker whose standard view shows no usable
    silhouette (e.g. cropped by the image edge): the view is spent, and no hypothesis is refuted."""

    reason: str = "no usable silhouette"


@dataclass(frozen=True)
class StandardViewQuery:
    """One standard view as a run has it: the silhouette's features and the viewed marker's centre
    height above the table (mm, from the marker pose; None if unknown) for :func:`height_gate`."""

    features: ShapeFeatures
    height_mm: float | None = None
    height_tol_mm: float | None = None  # None: the matcher's default tolerance


def split_query(q: ShapeFeatures | StandardViewQuery) -> tuple[ShapeFeatures, dict]:
    """(features, the height gate's keywords for :func:`view_scores` / :func:`match`) of a
    ShapeFeatures or a StandardViewQuery; no keywords when the marker height is unknown."""
    if isinstance(q, StandardViewQuery):
        if q.height_mm is None:
            return q.features, {}
        tol = {} if q.height_tol_mm is None else {"height_tol_mm": q.height_tol_mm}
        return q.features, {"height_mm": q.height_mm, **tol}
    return q, {}


def identify(first: ShapeFeatures | StandardViewQuery, index: LibraryIndex,
             acquire: Callable[[str, int], ShapeFeatures | StandardViewQuery | UnusableView | None], *,
             threshold: float = DEFAULT_THRESHOLD, max_views: int = 3, method: str = "aos",
             margin: float = MARGIN, **weights) -> Identification:
    """Recognise with extra standard views where ambiguous (paper §3.4, §2 stage 2).

    ``acquire(name, marker_id)`` moves the camera towards the standard view of marker
    ``marker_id`` *assuming* the object is ``name`` and returns the features of the standard view
    it then takes of the marker actually there (None if no marker is found there, which refutes
    hypothesis ``name``; an :class:`UnusableView` if the view has no usable silhouette). Hypothesis ``name`` stays
    a candidate if the view matches its view ``marker_id`` within ``threshold``; any other
    candidate if the view matches one of its views. Scores accumulate over the views; the
    surviving candidate with the lowest total is the answer.
    """
    first_f, first_h = split_query(first)
    r = match(first_f, index, threshold, method=method, margin=margin, **{**weights, **first_h})
    steps = [r]
    requested: list[tuple[str, int]] = []
    if r.best is None:
        return Identification(None, False, [], 1, steps, requested)
    remaining = list(r.candidates) or [r.best[0]]
    total = {c: r.scores[c] for c in remaining}
    viewed: dict[str, list[int]] = {c: [r.views[c]] for c in remaining}
    names = np.array(index.names)
    views_used = 1
    while len(remaining) > 1 and views_used < max_views:
        try:
            h, j = plan_next_view(remaining, index, viewed)
        except ValueError:  # every marker viewed: look again at the leader's (as a run does, from another side)
            h = min(remaining, key=lambda c: total[c])
            j = viewed[h][0]
        requested.append((h, j))
        viewed.setdefault(h, []).append(j)
        f = acquire(h, j)
        views_used += 1
        if f is None:
            # the marker hypothesis h predicts is not there: h is refuted (the others stay)
            remaining = [c for c in remaining if c != h] or remaining
            continue
        if isinstance(f, UnusableView):
            continue
        f, fh = split_query(f)
        fh = {**weights, **fh}  # the query's own height tolerance, if it has one, wins
        s = view_scores(f, index, method=method, **{k: v for k, v in fh.items() if not k.startswith("height")})
        step_score = _step_scores(s, remaining, h, index.view_index(h, j), names)
        best_step = min(step_score.values())
        keep = [c for c in remaining if step_score[c] <= threshold or step_score[c] <= best_step + margin]
        if fh.get("height_mm") is not None:  # the height narrows the shape's candidates, never widens them
            g = np.where(height_gate(index, fh["height_mm"], fh.get("height_tol_mm", HEIGHT_TOL_MM)), s, np.inf)
            gated = _step_scores(g, remaining, h, index.view_index(h, j), names)
            kept = [c for c in keep if gated[c] <= max(threshold, best_step + margin)]
            if kept:
                keep, step_score = kept, gated
        steps.append(match(f, index, threshold, method=method, restrict=remaining, margin=margin, **fh))
        for c in keep:
            total[c] += step_score[c]
        remaining = keep or [min(remaining, key=lambda c: step_score[c])]
        leader = evidence_leader({c: total[c] for c in remaining}, views_used, margin)
        if leader is not None:
            remaining = [leader]
    name = min(remaining, key=lambda c: total[c])
    return Identification(name, len(remaining) == 1, remaining, views_used, steps, requested)


def _step_scores(s: np.ndarray, remaining: Sequence[str], h: str, i_hj: int, names: np.ndarray) -> dict[str, float]:
    """Each remaining candidate's score for an extra view: hypothesis ``h`` by its planned view ``i_hj``
    (the marker the camera was sent to), any other candidate by its best view."""
    return {c: float(s[i_hj]) if c == h else float(np.min(s[names == c])) for c in remaining}


def ambiguity_groups(index: LibraryIndex, threshold: float = DEFAULT_THRESHOLD) -> list[list[int]]:
    """Views that look alike (paper §3.4): connected components of the view-to-view graph whose edges
    are pairwise scores ≤ ``threshold`` — the same scores :func:`plan_next_view` uses to pick the
    extra view that tells candidates apart. Returns the groups of ≥ 2 view indices, largest first."""
    P = index.pairwise()
    n = len(index)
    parent = list(range(n))

    def find(i):
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    for i, j in zip(*np.nonzero(np.triu(P <= threshold, k=1)), strict=True):
        parent[find(int(i))] = find(int(j))
    groups: dict[int, list[int]] = {}
    for i in range(n):
        groups.setdefault(find(i), []).append(i)
    return sorted((g for g in groups.values() if len(g) > 1), key=lambda g: (-len(g), g[0]))
