"""``labctl vision pose``: detect, fit and pose markers in one image, or resolve the duality across two."""

from __future__ import annotations

from pathlib import Path

import click

from ._common import emit, json_option


@click.group("vision")
def vision_group() -> None:
    """Marker vision: detection, ellipse fit, circle pose and its duality (paper §3)."""


def _read_image(path: Path):
    import cv2

    from ..errors import UserInputError

    img = cv2.imread(str(path), cv2.IMREAD_COLOR)
    if img is None:
        raise UserInputError(f"{path}: cannot read image")
    return img


@vision_group.command("pose")
@click.argument("image", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.argument("image2", required=False, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--radius", "radius_mm", type=float, required=True, help="Marker radius (mm).")
@click.option("--camera", "camera_file", type=click.Path(exists=True, dir_okay=False, path_type=Path), required=True,
              help="Camera file: labctl calibration YAML or ROS camera_info YAML.")
@click.option("--out", type=click.Path(dir_okay=False, path_type=Path), default=None,
              help="Annotated PNG to write (default: <IMAGE>_pose.png beside the last image).")
@click.option("--motion", type=click.Choice(["translation", "planar"]), default="translation", show_default=True,
              help="Motion between the two images (duality resolution, paper §3.3).")
@click.option("--plane-normal", nargs=3, type=float, default=None,
              help="Planar motion: the motion plane's normal in the camera frame.")
@click.option("--min-margin-deg", type=float, default=None, help="Below this margin the duality is ambiguous.")
@click.option("--hue", "hue_deg", nargs=2, type=float, default=(-15.0, 15.0), show_default=True,
              help="Marker hue window (degrees).")
@click.option("--min-saturation", type=float, default=0.45, show_default=True)
@json_option
def vision_pose(image: Path, image2: Path | None, radius_mm: float, camera_file: Path, out: Path | None,
                motion: str, plane_normal, min_margin_deg: float | None, hue_deg, min_saturation: float) -> None:
    """Pose the red markers in IMAGE; with IMAGE2, resolve the pose duality of one marker."""
    import math

    import cv2

    from ..errors import UserInputError
    from ..fsutil import atomic_write_bytes
    from ..geometry.camera_io import load_camera_file
    from ..vision import (
        CirclePoseError,
        EllipseFitError,
        detect_markers,
        marker_pose_candidates,
        resolve_duality_detailed,
    )
    from ..vision.annotate import annotate_marker, circle_centre_pixel
    from ..vision.duality import DEFAULT_MIN_MARGIN_RAD

    if not (radius_mm > 0 and math.isfinite(radius_mm)):
        raise UserInputError("--radius must be a positive number of mm")
    try:
        camera = load_camera_file(camera_file)
    except ValueError as exc:
        msg = str(exc)
        raise UserInputError(msg if str(camera_file) in msg else f"{camera_file}: not a camera file ({msg})") from None
    if motion == "planar" and not plane_normal:
        raise UserInputError("--motion planar needs --plane-normal X Y Z")

    paths = [image] + ([image2] if image2 else [])
    images, per_image = [], []
    for path in paths:
        img = _read_image(path)
        if img.shape[1] != camera.width or img.shape[0] != camera.height:
            raise UserInputError(f"{path}: image is {img.shape[1]}×{img.shape[0]}, camera file says "
                                 f"{camera.width}×{camera.height}")
        markers = detect_markers(img, hue_range_deg=tuple(hue_deg), min_saturation=min_saturation)
        if not markers:
            raise UserInputError(f"{path}: no marker found")
        if image2 and len(markers) > 1:
            raise UserInputError(f"{path}: {len(markers)} markers found; resolving the duality needs exactly one")
        posed = []
        for m in markers:
            try:
                posed.append((m, marker_pose_candidates(m, camera, radius_mm)))
            except (CirclePoseError, EllipseFitError) as exc:
                raise UserInputError(f"{path}: marker at {m.centroid[0]:.1f}, {m.centroid[1]:.1f}: {exc}") from None
        images.append(img)
        per_image.append(posed)

    result: dict = {"camera": str(camera_file), "radius_mm": radius_mm, "images": []}
    for path, posed in zip(paths, per_image, strict=True):
        result["images"].append({"image": str(path), "markers": [
            {**m.to_dict(), "candidates": [c.to_dict() for c in cands]} for m, cands in posed]})
    chosen = None
    if image2:
        margin = DEFAULT_MIN_MARGIN_RAD if min_margin_deg is None else math.radians(min_margin_deg)
        res = resolve_duality_detailed(per_image[0][0][1], per_image[1][0][1], motion=motion,
                                       plane_normal=plane_normal or None, min_margin_rad=margin)
        result["duality"] = {**res.to_dict(), "motion": motion}
        chosen = res

    # annotate the last image (Fig. 5(a)): ellipse, axes, centre, and where the circle's centre projects
    drawn = images[-1]
    for k, (m, cands) in enumerate(per_image[-1]):
        pose = chosen.best if chosen is not None else cands[0]
        tag = f"#{k} z={pose.center[2]:.0f}mm"
        if chosen is not None:
            tag += " (ambiguous)" if chosen.ambiguous else f" margin {math.degrees(chosen.margin_rad):.2f} deg"
        drawn = annotate_marker(drawn, m.ellipse, boundary=m.boundary, label=tag,
                                circle_centre_px=circle_centre_pixel(pose, camera))
    out = out or paths[-1].with_name(paths[-1].stem + "_pose.png")
    ok, png = cv2.imencode(".png", drawn)
    if not ok:
        raise UserInputError(f"{out}: cannot encode the annotated image")
    atomic_write_bytes(out, png.tobytes())
    result["annotated"] = str(out)

    def human(console):
        from rich.table import Table

        for entry in result["images"]:
            t = Table("marker", "centroid px", "ellipse axes px", "candidate", "centre mm (camera)", "normal",
                      title=entry["image"])
            for k, mk in enumerate(entry["markers"]):
                for j, c in enumerate(mk["candidates"]):
                    t.add_row(str(k) if j == 0 else "",
                              "{:.2f}, {:.2f}".format(*mk["centroid_px"]) if j == 0 else "",
                              "{:.2f} × {:.2f}".format(*mk["ellipse"]["axes"]) if j == 0 else "", str(j),
                              "{:.1f}, {:.1f}, {:.1f}".format(*c["center_mm"]),
                              "{:.3f}, {:.3f}, {:.3f}".format(*c["normal"]))
            console.print(t)
        if "duality" in result:
            d = result["duality"]
            if d["resolved"]:
                console.print(f"duality ({d['motion']}): candidate {d['index']} of the second image, "
                              f"margin {d['margin_deg']:.2f}°")
            else:
                console.print(f"duality ({d['motion']}): [yellow]ambiguous[/] (margin {d['margin_deg']:.3f}°); "
                              "no candidate chosen")
        console.print(f"annotated image: {result['annotated']}")

    emit(result, human)
