"""The object library on disk: ``object_library/NAME/`` (README "The lab workspace").

One folder per object, written atomically (:func:`labctl.fsutil.atomic_dir`)::

    NAME/
      object.yaml          name, format version, source model, placement and viewing summary
      model.stl            the CAD model, mm, object frame O
      markers.yaml         markers: id, center (mm), normal (unit), radius (mm), all in O
      stable_poses.yaml    stable resting poses: T (4×4, places O on the table z = 0), probability
      views/<id>.png       the standard view of marker <id> (BGR, cropped to the object + margin)
      views/<id>.json      its features (eccentricity, size, chain code, angle-of-sight signature…)
      contact_sheet.png    all standard views side by side

:func:`load_library` reads a whole library; an object folder that is missing a file or has a
malformed one is skipped with one warning line naming the object, the file and the problem
(:func:`load_object` raises that line as a :class:`LibraryError`). ``library.yaml`` beside the
object folders holds the library-wide initial viewing angle (paper §4.1).
"""

from __future__ import annotations

import json
import os
import re
import shutil
import sys
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np
import yaml

from ..errors import UserInputError
from ..fsutil import (
    atomic_dir,
    atomic_write_bytes,
    atomic_write_text,
    cached_arrays,
    file_digest,
    recover_dir,
    recover_dirs,
)
from ..vision.shape import ShapeError, ShapeFeatures, silhouette_mask
from .placement import Marker
from .views import StandardView, contact_sheet

if TYPE_CHECKING:  # the mesh is read when first asked for: a run's workers and command never need trimesh
    import trimesh

FORMAT_VERSION = 1
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class LibraryError(UserInputError):
    """A library folder that cannot be read, or a bad object name."""


@dataclass
class LibraryObject:
    """An object of the library: model (trimesh, mm, frame O), markers, stable poses, standard views."""

    name: str
    # the model, or None until :attr:`mesh` first reads ``path``/model.stl (checked readable and
    # watertight when the object was loaded)
    loaded_mesh: trimesh.Trimesh | None
    markers: list[Marker]
    stable_poses: list[tuple[np.ndarray, float]]
    views: dict[int, StandardView]
    info: dict = field(default_factory=dict)
    path: Path | None = None

    @property
    def mesh(self) -> trimesh.Trimesh:
        """The model (trimesh, mm, frame O), read from the object's folder on first use."""
        if self.loaded_mesh is None:
            self.loaded_mesh = _read_mesh(self.folder / "model.stl", self.name)
        return self.loaded_mesh

    def mesh_arrays(self) -> tuple[np.ndarray, np.ndarray]:
        """The model's vertices (V, 3) float64 mm in frame O and faces (F, 3) int64, exactly as :attr:`mesh`
        holds them; for a stored object read from the disk cache when its ``model.stl`` (same bytes, same
        trimesh) was read before, so that drawing it (the simulated lab) needs no trimesh import (~1 s)."""
        if self.loaded_mesh is not None or self.path is None:
            return np.asarray(self.mesh.vertices), np.asarray(self.mesh.faces)
        from importlib.metadata import version

        model = self.folder / "model.stl"
        try:
            key = ("library_mesh", file_digest(model, __file__), version("trimesh"), np.__version__)
        except OSError:
            return np.asarray(self.mesh.vertices), np.asarray(self.mesh.faces)  # its own error, from the reader

        def read() -> dict:
            return {"vertices": np.asarray(self.mesh.vertices), "faces": np.asarray(self.mesh.faces)}

        out = cached_arrays("library", key, ("vertices", "faces"), read)
        return out["vertices"], out["faces"]

    @property
    def folder(self) -> Path:
        """The object's folder (``path``); TypeError for an object that is not stored in a library."""
        if self.path is None:
            raise TypeError(f"{self.name} is not stored in a library folder")
        return self.path

    def marker(self, marker_id: int) -> Marker:
        """The marker with id ``marker_id``; raises KeyError if the object has none."""
        for m in self.markers:
            if m.id == marker_id:
                return m
        raise KeyError(f"{self.name} has no marker {marker_id}")

    def view_image(self, marker_id: int) -> np.ndarray:
        """The stored standard-view image (loaded on first use)."""
        v = self.views[marker_id]
        if v.image is None and self.path is not None:
            v.image = cv2.imread(str(self.path / "views" / f"{marker_id}.png"), cv2.IMREAD_COLOR)
        if v.image is None:
            raise LibraryError(f"{self.name}: standard view {marker_id} has no image")
        return v.image


def _crop_to_object(image: np.ndarray, margin: int = 24) -> np.ndarray:
    """The view cropped to the silhouette's bounding box plus a margin (keeps the library small)."""
    try:
        mask = silhouette_mask(image)
    except ShapeError:
        return image
    ys, xs = np.nonzero(mask)
    y0, y1 = max(0, ys.min() - margin), min(image.shape[0], ys.max() + margin + 1)
    x0, x1 = max(0, xs.min() - margin), min(image.shape[1], xs.max() + margin + 1)
    return image[y0:y1, x0:x1]


def check_name(name: str) -> str:
    """``name`` if it is a valid object name (:data:`NAME_RE`), else raise LibraryError."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise LibraryError(f"bad object name {name!r}: use letters, digits, '_', '-', '.' (max 64)")
    return name


def face_label(normal) -> str:
    """The face a marker sits on, in words: ``+x`` … ``-z`` when the normal is within 5° of an axis of O,
    else the rounded normal."""
    n = np.asarray(normal, float)
    i = int(np.argmax(np.abs(n)))
    if abs(n[i]) >= np.cos(np.radians(5.0)):
        return f"{'+' if n[i] > 0 else '-'}{'xyz'[i]} face"
    return "face n=(" + ",".join(f"{v:+.2f}" for v in n) + ")"


def _sheet(obj: LibraryObject, images: dict[int, np.ndarray], groups: dict) -> np.ndarray:
    """Contact sheet: each view labelled with its marker (id, radius) and face; views in an ambiguity
    group (``groups``: marker id → (group number, other members)) get the group's tag."""
    imgs, labels, tags = [], [], []
    for mid, img in sorted(images.items()):
        m = obj.marker(mid)
        imgs.append(img)
        labels.append(f"{obj.name} #{mid} r{m.radius:g}")
        g = groups.get(mid) or groups.get(str(mid))
        tags.append(f"{face_label(m.normal)}" + (f"  G{g['group']}: {', '.join(g['with'][:2])}" if g else ""))
    return contact_sheet(imgs, labels, sublabels=tags, highlight=[bool(groups.get(mid) or groups.get(str(mid)))
                                                                 for mid in sorted(images)])


def save_object(library_dir: Path | str, obj: LibraryObject) -> Path:
    """Write ``library_dir/NAME/`` atomically (an existing folder is replaced only when complete)."""
    check_name(obj.name)
    target = Path(library_dir) / obj.name
    with atomic_dir(target) as tmp:
        obj.mesh.export(tmp / "model.stl")
        (tmp / "markers.yaml").write_text(yaml.safe_dump({"markers": [m.to_dict() for m in obj.markers]},
                                                         sort_keys=False))
        poses = [{"T": np.round(T, 6).tolist(), "probability": round(float(p), 6)} for T, p in obj.stable_poses]
        (tmp / "stable_poses.yaml").write_text(yaml.safe_dump({"stable_poses": poses}, sort_keys=False))
        (tmp / "views").mkdir()
        imgs = {}
        for mid, v in sorted(obj.views.items()):
            if v.image is not None:
                if not cv2.imwrite(str(tmp / "views" / f"{mid}.png"), _crop_to_object(v.image),
                                   [cv2.IMWRITE_PNG_COMPRESSION, 9]):
                    raise LibraryError(f"cannot write view image {mid}.png")
                imgs[mid] = v.image
            (tmp / "views" / f"{mid}.json").write_text(json.dumps(v.features.to_dict()))
        groups = obj.info.get("ambiguity_groups") or {}
        cv2.imwrite(str(tmp / "contact_sheet.png"), _sheet(obj, imgs, groups))
        info = {"name": obj.name, "format": FORMAT_VERSION, **obj.info}
        (tmp / "object.yaml").write_text(yaml.safe_dump(_plain(info), sort_keys=False))
    return target


def _plain(x):
    """numpy scalars and arrays → plain Python for YAML."""
    if isinstance(x, dict):
        return {str(k) if not isinstance(k, int | str) else k: _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, np.ndarray):
        return _plain(x.tolist())
    if isinstance(x, np.generic):
        return x.item()
    return x


def _read_mesh(model: Path, name: str) -> trimesh.Trimesh:
    """``model`` (an STL file, mm) as a mesh; LibraryError if unreadable, empty or not watertight."""
    import trimesh  # heavy (scipy, networkx, shapely): only where a mesh is used (the simulated lab, teaching)

    try:
        mesh = trimesh.load(model, force="mesh")
    except Exception as exc:  # trimesh raises many kinds on broken files
        raise LibraryError(f"{name}: cannot read model.stl ({exc.__class__.__name__})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or not mesh.is_watertight:
        raise LibraryError(f"{name}: model.stl is empty or not watertight")
    return mesh


STL_MERGE_DIGITS = 8  # trimesh's vertex-merge precision (``tol.merge`` 1e-8): the same merge as its loader's


def _binary_stl_watertight(model: Path, name: str) -> bool:
    """True when ``model`` is a binary STL (the library writes those) whose triangles, vertices merged as
    trimesh merges them, close into a watertight surface: every edge shared by exactly two triangles (trimesh's
    ``is_watertight``). LibraryError when it is binary but empty or open; False when it is not binary STL, so the
    caller reads it with trimesh. Numpy alone: checking a library for a run costs no trimesh import."""
    try:
        data = model.read_bytes()
    except OSError as exc:
        raise LibraryError(f"{name}: cannot read model.stl ({exc.__class__.__name__})") from None
    if len(data) < 84:
        return False
    n = int(np.frombuffer(data, "<u4", 1, 80)[0])
    if len(data) != 84 + 50 * n or n == 0:
        return False  # ASCII STL, or not an STL at all: trimesh decides
    tri = np.frombuffer(data, np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("a", "<u2")]), n, 84)["v"]
    v = tri.reshape(-1, 3).astype(np.float64)
    if not np.isfinite(v).all():
        raise LibraryError(f"{name}: model.stl is empty or not watertight")
    as_int = (v * 10**STL_MERGE_DIGITS).round().astype(np.int64)
    _, index = np.unique(as_int, axis=0, return_inverse=True)
    faces = index.reshape(-1, 3)
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    if not (counts == 2).all():
        raise LibraryError(f"{name}: model.stl is empty or not watertight")
    return True


# libyaml's safe loader where PyYAML was built with it: the same documents, parsed in a ninth of the pure-Python
# loader's time (a library's 21 YAML files, 11 ms instead of 77; every process of a run reads them)
YAML_LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def _read_yaml(path: Path, key: str):
    try:
        data = yaml.load(path.read_text(), Loader=YAML_LOADER)  # a safe loader either way
    except FileNotFoundError:
        raise LibraryError(f"{path.parent.name}: missing {path.name}") from None
    except (yaml.YAMLError, UnicodeDecodeError) as exc:
        raise LibraryError(f"{path.parent.name}: {path.name} is not valid YAML ({exc.__class__.__name__})") from None
    except OSError as exc:
        raise LibraryError(f"{path.parent.name}: cannot read {path.name} ({exc.strerror})") from None
    if not isinstance(data, dict) or key not in data:
        raise LibraryError(f"{path.parent.name}: {path.name} has no {key!r} entry")
    return data, data[key]


def _features(name: str, fj: Path, mid: int) -> ShapeFeatures:
    try:
        f = ShapeFeatures.from_dict(json.loads(fj.read_text()))
    except FileNotFoundError:
        raise LibraryError(f"{name}: missing views/{fj.name} (standard view of marker {mid})") from None
    except (KeyError, TypeError, ValueError, UnicodeDecodeError) as exc:
        raise LibraryError(f"{name}: views/{fj.name} is malformed ({exc})") from None
    if f.hu.shape != (7,) or f.fd.ndim != 1 or not all(np.isfinite(a).all() for a in (f.aos, f.fd, f.hu)):
        raise LibraryError(f"{name}: views/{fj.name} is malformed (feature arrays of the wrong shape or not finite)")
    if not (f.size_mm > 0 and f.perimeter_mm > 0 and 0 <= f.eccentricity <= 1):
        raise LibraryError(f"{name}: views/{fj.name} is malformed (size, perimeter or eccentricity out of range)")
    return f


def load_object(folder: Path | str) -> LibraryObject:
    """Read one object folder; raise :class:`LibraryError` (one line naming the object and file) if it is corrupt."""
    folder = Path(folder)
    name = folder.name
    recover_dir(folder)  # a save that crashed between its two renames left the old version aside
    if not folder.is_dir():
        raise LibraryError(f"library object {name!r} not found in {folder.parent}")
    meta, info = _read_yaml(folder / "object.yaml", "name")
    if info != name:
        raise LibraryError(f"{name}: object.yaml names it {info!r}")
    if meta.get("format") != FORMAT_VERSION:
        raise LibraryError(f"{name}: object.yaml: unsupported library format {meta.get('format')!r}")
    model = folder / "model.stl"
    if not model.is_file():
        raise LibraryError(f"{name}: missing model.stl")
    mesh = None if _binary_stl_watertight(model, name) else _read_mesh(model, name)
    try:
        _, items = _read_yaml(folder / "markers.yaml", "markers")
        markers = [Marker.from_dict(d) for d in items]
    except (KeyError, TypeError, ValueError) as exc:
        raise LibraryError(f"{name}: markers.yaml is malformed ({exc})") from None
    if not markers:
        raise LibraryError(f"{name}: markers.yaml lists no markers")
    if len({m.id for m in markers}) != len(markers):
        raise LibraryError(f"{name}: markers.yaml repeats a marker id")
    try:
        poses = []
        _, items = _read_yaml(folder / "stable_poses.yaml", "stable_poses")
        for d in items:
            T = np.asarray(d["T"], float)
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise ValueError("T must be a finite 4×4 matrix")
            poses.append((T, float(d["probability"])))
        if not poses:
            raise ValueError("no poses")
    except (KeyError, TypeError, ValueError) as exc:
        raise LibraryError(f"{name}: stable_poses.yaml is malformed ({exc})") from None
    views = {m.id: StandardView(m.id, _features(name, folder / "views" / f"{m.id}.json", m.id)) for m in markers}
    meta.pop("name", None)
    return LibraryObject(name, mesh, markers, poses, views, info=meta, path=folder)


def object_folders(root: Path) -> list[Path]:
    """The object folders of a library (hidden and temporary folders — atomic writes — are not objects)."""
    return [d for d in sorted(root.iterdir()) if d.is_dir() and not d.name.startswith(".")]


def load_library_checked(library_dir: Path | str) -> tuple[dict[str, LibraryObject], dict[str, str]]:
    """All loadable objects by name, and a one-line problem per object folder that cannot be loaded."""
    root = Path(library_dir)
    if not root.is_dir():
        raise LibraryError(f"object library folder not found: {root}")
    recover_dirs(root)  # saves that crashed half-way (labctl.fsutil.atomic_dir)
    out, bad = {}, {}
    for d in object_folders(root):
        try:
            out[d.name] = load_object(d)
        except LibraryError as exc:
            bad[d.name] = str(exc)
    return out, bad


def warn_stderr(message: str) -> None:
    """Write ``warning: MESSAGE`` as one line to stderr (the default ``warn`` of :func:`load_library`)."""
    sys.stderr.write(f"warning: {message}\n")


def load_library(library_dir: Path | str, *, warn: Callable[[str], None] | None = warn_stderr
                 ) -> dict[str, LibraryObject]:
    """All objects of a library folder by name. A broken object is skipped with one line to
    ``warn`` (default: stderr) naming it, the file and the problem; it never blocks the others."""
    out, bad = load_library_checked(library_dir)
    for msg in bad.values():
        if warn is not None:
            warn(f"object library: skipped {msg}")
    return out


def remove_object(library_dir: Path | str, name: str) -> Path:
    """Delete ``library_dir/NAME`` (renamed aside first, so a crash leaves it whole or gone)."""
    check_name(name)
    target = Path(library_dir) / name
    if not target.is_dir():
        raise LibraryError(f"no object {name!r} in {library_dir}")
    aside = target.with_name(f".{name}.removed.tmp")
    shutil.rmtree(aside, ignore_errors=True)
    os.replace(target, aside)
    shutil.rmtree(aside, ignore_errors=True)
    return target


# --- the library's own settings: one initial viewing angle for the whole library (paper §4.1) ------
LIBRARY_FILE = "library.yaml"


def library_angle(library_dir: Path | str, default_deg: float) -> float:
    """The library's initial viewing angle (deg): ``library.yaml``'s, else ``default_deg`` (lab.yaml)."""
    try:
        data = yaml.safe_load((Path(library_dir) / LIBRARY_FILE).read_text())
        a = float(data["initial_angle_deg"])
        if 0.0 < a <= 90.0:
            return a
    except (OSError, yaml.YAMLError, KeyError, TypeError, ValueError):
        pass
    return float(default_deg)


def update_library_angle(library_dir: Path | str, view, library: dict[str, LibraryObject] | None = None) -> dict:
    """Re-choose the library-wide initial viewing angle from every object's coverage-versus-angle
    curve and return ``{"initial_angle_deg", "previous_deg", "coverage": {name: probability}}``.

    ``view``: the lab's :class:`~labctl.library.placement.ViewingGeometry` (its ``angle_deg`` is the
    lab.yaml default used before the library has its own). Curves come from ``object.yaml``
    (written when taught); for objects taught before curves were recorded they are computed from
    the object's markers (not written back)."""
    from .placement import coverage_vs_angle, library_viewing_angle

    root = Path(library_dir)
    lib = library if library is not None else load_library(root, warn=None)
    current = library_angle(root, view.angle_deg)
    curves = {}
    for n, o in lib.items():
        c = o.info.get("coverage_vs_angle")
        if not (isinstance(c, dict) and c.get("coverage")):
            c = coverage_vs_angle(o.mesh, o.stable_poses, o.markers, view, n_yaw=36)
        curves[n] = c
    angle, cov = library_viewing_angle(curves, current)
    return {"format": FORMAT_VERSION, "initial_angle_deg": float(angle), "previous_deg": float(current),
            "chosen_from": "worst object's initial-view coverage, then the mean, then nearest the previous angle",
            "coverage": cov}


def refresh_library(library_dir: Path | str, view, *, threshold: float | None = None) -> dict:
    """After an object is added or removed: re-choose the library-wide initial viewing angle
    (:func:`update_library_angle`), recompute the ambiguity groups over all standard views
    (:func:`labctl.library.matching.ambiguity_groups`), record them in ``library.yaml`` and in each
    object's ``object.yaml``, and redraw the contact sheets whose groups changed (atomic writes)."""
    from .matching import DEFAULT_THRESHOLD, LibraryIndex, ambiguity_groups

    root = Path(library_dir)
    lib = load_library(root, warn=None)
    data = update_library_angle(root, view, library=lib)
    groups_out: list[list[str]] = []
    per_obj: dict[str, dict] = {n: {} for n in lib}
    if lib:
        index = LibraryIndex.from_library(lib)
        for k, g in enumerate(ambiguity_groups(index, threshold or DEFAULT_THRESHOLD), start=1):
            members = [f"{index.names[i]}#{int(index.marker_ids[i])}" for i in g]
            groups_out.append(members)
            for i, tag in zip(g, members, strict=True):
                per_obj[index.names[i]][int(index.marker_ids[i])] = {
                    "group": k, "with": [t for t in members if t != tag]}
    data["ambiguity_groups"] = groups_out
    atomic_write_text(root / LIBRARY_FILE, yaml.safe_dump(_plain(data), sort_keys=False))
    for name, obj in lib.items():
        new = per_obj[name]
        old = {int(k): v for k, v in (obj.info.get("ambiguity_groups") or {}).items()}
        if old == new:
            continue
        obj.info["ambiguity_groups"] = new
        images = {}
        for mid in obj.views:
            try:
                images[mid] = obj.view_image(mid)
            except LibraryError:
                pass
        sheet = _sheet(obj, images, new)
        ok, png = cv2.imencode(".png", sheet)
        if ok:
            atomic_write_bytes(obj.folder / "contact_sheet.png", png.tobytes())
        atomic_write_text(obj.folder / "object.yaml",
                          yaml.safe_dump(_plain({"name": name, **obj.info}), sort_keys=False))
    return data


def check_library(library_dir: Path | str, min_coverage: float | None = None) -> tuple[list[str], list[str]]:
    """Validate every object folder: (names that are fine, one line per problem naming object and file).

    Beyond what loading checks: every standard-view image is readable, the stored model matches the
    content hash recorded when it was taught, stable-pose probabilities sum to 1, ``library.yaml``
    is readable, and (with ``min_coverage``) the object's coverage probability reaches it unless it
    was taught with ``--accept-partial``."""
    import hashlib

    root = Path(library_dir)
    objs, bad = load_library_checked(root)
    problems = [f"{msg}" for msg in bad.values()]
    ok = []
    for name, obj in objs.items():
        errs = []
        for mid in obj.views:
            png = obj.folder / "views" / f"{mid}.png"
            if not png.is_file():
                errs.append(f"{name}: missing views/{mid}.png")
            elif cv2.imread(str(png), cv2.IMREAD_COLOR) is None:
                errs.append(f"{name}: views/{mid}.png is not a readable image")
        want = (obj.info.get("source") or {}).get("stored_model_sha256") if isinstance(obj.info.get("source"),
                                                                                       dict) else None
        if want and hashlib.sha256((obj.folder / "model.stl").read_bytes()).hexdigest() != want:
            errs.append(f"{name}: model.stl differs from the model it was taught with (content hash)")
        total = sum(p for _, p in obj.stable_poses)
        if abs(total - 1.0) > 1e-3:
            errs.append(f"{name}: stable_poses.yaml probabilities sum to {total:.4f}, not 1")
        cov = obj.info.get("coverage")
        if min_coverage is not None and isinstance(cov, dict) and not obj.info.get("accepted_partial"):
            kept = 1.0 - float((obj.info.get("resting_poses") or {}).get("dropped_probability", 0.0))
            covered = float(cov.get("probability", 1.0)) * kept
            if covered < min_coverage:
                errs.append(f"{name}: coverage {100 * covered:.1f} % is below library.min_coverage "
                            f"({100 * min_coverage:.0f} %); re-teach it with a fix from its warnings, or with "
                            f"--accept-partial")
        problems += errs
        if not errs:
            ok.append(name)
    lf = root / LIBRARY_FILE
    if lf.exists():
        try:
            data = yaml.safe_load(lf.read_text())
            float(data["initial_angle_deg"])
        except (yaml.YAMLError, KeyError, TypeError, ValueError, UnicodeDecodeError):
            problems.append(f"{LIBRARY_FILE}: malformed (no valid initial_angle_deg); re-teach or remove it")
    return ok, problems
