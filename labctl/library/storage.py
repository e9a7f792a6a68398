"""The object library on disk: ``object_library/NAME/`` (DESIGN §2).

One folder per object, written atomically (:func:`labctl.fsutil.atomic_dir`)::

    NAME/
      object.yaml          name, format version, source model, placement and viewing summary
      model.stl            the CAD model, mm, object frame O
      markers.yaml         markers: id, center (mm), normal (unit), radius (mm), all in O
      stable_poses.yaml    stable resting poses: T (4×4, places O on the table z = 0), probability
      views/<id>.png       the standard view of marker <id> (BGR, cropped to the object + margin)
      views/<id>.json      its features (eccentricity, size, chain code, angle-of-sight signature…)
      contact_sheet.png    all standard views side by side

:func:`load_library` reads a whole library and fails with one clear :class:`LibraryError`
naming the folder and file when anything is missing or malformed.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np
import trimesh
import yaml

from ..errors import UserInputError
from ..fsutil import atomic_dir, recover_dir, recover_dirs
from ..vision.shape import ShapeError, ShapeFeatures, silhouette_mask
from .placement import Marker
from .views import StandardView, contact_sheet

FORMAT_VERSION = 1
NAME_RE = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class LibraryError(UserInputError):
    """A library folder that cannot be read, or a bad object name."""


@dataclass
class LibraryObject:
    """An object of the library: model (trimesh, mm, frame O), markers, stable poses, standard views."""

    name: str
    mesh: trimesh.Trimesh
    markers: list[Marker]
    stable_poses: list[tuple[np.ndarray, float]]
    views: dict[int, StandardView]
    info: dict = field(default_factory=dict)
    path: Path | None = None

    def marker(self, marker_id: int) -> Marker:
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
    if not isinstance(name, str) or not NAME_RE.match(name):
        raise LibraryError(f"bad object name {name!r}: use letters, digits, '_', '-', '.' (max 64)")
    return name


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
        imgs, labels = [], []
        for mid, v in sorted(obj.views.items()):
            if v.image is not None:
                if not cv2.imwrite(str(tmp / "views" / f"{mid}.png"), _crop_to_object(v.image),
                                   [cv2.IMWRITE_PNG_COMPRESSION, 9]):
                    raise LibraryError(f"cannot write view image {mid}.png")
                imgs.append(v.image)
                labels.append(f"{obj.name} #{mid}")
            (tmp / "views" / f"{mid}.json").write_text(json.dumps(v.features.to_dict()))
        cv2.imwrite(str(tmp / "contact_sheet.png"), contact_sheet(imgs, labels))
        info = {"name": obj.name, "format": FORMAT_VERSION, **obj.info}
        (tmp / "object.yaml").write_text(yaml.safe_dump(info, sort_keys=False))
    return target


def _read_yaml(path: Path, key: str):
    try:
        data = yaml.safe_load(path.read_text())
    except FileNotFoundError:
        raise LibraryError(f"{path.parent.name}: missing {path.name}") from None
    except yaml.YAMLError as exc:
        raise LibraryError(f"{path.parent.name}: {path.name} is not valid YAML ({exc.__class__.__name__})") from None
    if not isinstance(data, dict) or key not in data:
        raise LibraryError(f"{path.parent.name}: {path.name} has no {key!r} entry")
    return data[key] if key != "." else data


def load_object(folder: Path | str) -> LibraryObject:
    """Read one object folder; raise :class:`LibraryError` (naming folder and file) if it is corrupt."""
    folder = Path(folder)
    name = folder.name
    recover_dir(folder)  # a save that crashed between its two renames left the old version aside
    if not folder.is_dir():
        raise LibraryError(f"library object {name!r} not found in {folder.parent}")
    info = _read_yaml(folder / "object.yaml", "name")
    meta = yaml.safe_load((folder / "object.yaml").read_text())
    if info != name:
        raise LibraryError(f"{name}: object.yaml names it {info!r}")
    if meta.get("format") != FORMAT_VERSION:
        raise LibraryError(f"{name}: unsupported library format {meta.get('format')!r}")
    model = folder / "model.stl"
    try:
        mesh = trimesh.load(model, force="mesh")
    except Exception as exc:
        raise LibraryError(f"{name}: cannot read model.stl ({exc})") from None
    if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0 or not mesh.is_watertight:
        raise LibraryError(f"{name}: model.stl is empty or not watertight")
    try:
        markers = [Marker.from_dict(d) for d in _read_yaml(folder / "markers.yaml", "markers")]
    except (KeyError, TypeError, ValueError) as exc:
        raise LibraryError(f"{name}: markers.yaml is malformed ({exc})") from None
    try:
        poses = []
        for d in _read_yaml(folder / "stable_poses.yaml", "stable_poses"):
            T = np.asarray(d["T"], float)
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise ValueError("T must be a finite 4×4 matrix")
            poses.append((T, float(d["probability"])))
    except (KeyError, TypeError, ValueError) as exc:
        raise LibraryError(f"{name}: stable_poses.yaml is malformed ({exc})") from None
    views = {}
    for m in markers:
        fj = folder / "views" / f"{m.id}.json"
        try:
            views[m.id] = StandardView(m.id, ShapeFeatures.from_dict(json.loads(fj.read_text())))
        except FileNotFoundError:
            raise LibraryError(f"{name}: missing views/{m.id}.json (standard view of marker {m.id})") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise LibraryError(f"{name}: views/{m.id}.json is malformed ({exc})") from None
    if not markers:
        raise LibraryError(f"{name}: no markers")
    meta.pop("name", None)
    return LibraryObject(name, mesh, markers, poses, views, info=meta, path=folder)


def load_library(library_dir: Path | str) -> dict[str, LibraryObject]:
    """All objects of a library folder by name (hidden and temporary folders are skipped)."""
    root = Path(library_dir)
    if not root.is_dir():
        raise LibraryError(f"object library folder not found: {root}")
    recover_dirs(root)  # saves that crashed half-way (labctl.fsutil.atomic_dir)
    out = {}
    for d in sorted(root.iterdir()):
        if d.is_dir() and not d.name.startswith("."):
            out[d.name] = load_object(d)
    return out
