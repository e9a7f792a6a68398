"""``labctl vision pose``: detect, fit and pose markers in one image, or resolve the duality across two."""

from __future__ import annotations

from pathlib import Path

import click

from ._common import emit, json_option


def _verdict(mk: dict) -> str:
    """One marker's verdict for the pose table: trusted, kept for tracking only (``fit_for``), or suspect."""
    if mk["trusted"]:
        return "trusted"
    return ("fit for tracking: " if mk["fit_for"] else "suspect: ") + ", ".join(mk["flags"])


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
@click.option("--response", default="linear", show_default=True,
              help="Camera response: linear, srgb or 'gamma G' (frames are linearised before sub-pixel work).")
@json_option
def vision_pose(image: Path, image2: Path | None, radius_mm: float, camera_file: Path, out: Path | None,
                motion: str, plane_normal, min_margin_deg: float | None, hue_deg, min_saturation: float,
                response: str) -> None:
    """Pose the red markers in IMAGE; with IMAGE2, resolve the pose duality of one marker."""
    import math

    import cv2

    from ..errors import UserInputError
    from ..fsutil import atomic_write_bytes
    from ..geometry.camera_io import load_camera_file
    from ..vision import MarkerThresholds, ResponseError, parse_response
    from ..vision.duality import DEFAULT_MIN_MARGIN_RAD
    from ..vision.pose_images import ImagePoseError, annotate_posed, pose_images

    if not (radius_mm > 0 and math.isfinite(radius_mm)):
        raise UserInputError("--radius must be a positive number of mm")
    try:
        camera = load_camera_file(camera_file)
    except ValueError as exc:
        msg = str(exc)
        raise UserInputError(msg if str(camera_file) in msg else f"{camera_file}: not a camera file ({msg})") from None
    if motion == "planar" and not plane_normal:
        raise UserInputError("--motion planar needs --plane-normal X Y Z")
    try:
        resp = parse_response(response)
    except ResponseError as exc:
        raise UserInputError(f"--response: {exc}") from None

    paths = [image] + ([image2] if image2 else [])
    images = [_read_image(path) for path in paths]
    margin = DEFAULT_MIN_MARGIN_RAD if min_margin_deg is None else math.radians(min_margin_deg)
    try:
        posed = pose_images(images, camera, radius_mm, motion=motion, plane_normal=plane_normal or None,
                            min_margin_rad=margin,
                            thresholds=MarkerThresholds(hue_range_deg=tuple(hue_deg), min_saturation=min_saturation),
                            response=resp)
    except ImagePoseError as exc:
        raise UserInputError(f"{paths[exc.index]}: {exc}") from None
    result: dict = {"camera": str(camera_file), "radius_mm": radius_mm, **posed.to_dict([str(p) for p in paths])}

    out = out or paths[-1].with_name(paths[-1].stem + "_pose.png")
    ok, png = cv2.imencode(".png", annotate_posed(images[-1], posed, camera))
    if not ok:
        raise UserInputError(f"{out}: cannot encode the annotated image")
    atomic_write_bytes(out, png.tobytes())
    result["annotated"] = str(out)
    mismatched = sum("response_mismatch" in mk["flags"] for entry in result["images"] for mk in entry["markers"])
    if mismatched:
        # the edges of a blurred marker lean as a gamma-encoded frame read as linear does
        result["response_warning"] = (f"{mismatched} marker(s) look encoded with another camera response than "
                                      f"--response {response}: declare the camera's response (srgb, 'gamma G' or a "
                                      "lookup table) before trusting their poses")

    def human(console):
        from rich.table import Table

        for entry in result["images"]:
            t = Table("marker", "centroid px", "ellipse axes px", "candidate", "centre mm (camera)", "normal",
                      "σ normal", "quality", title=entry["image"])
            for k, mk in enumerate(entry["markers"]):
                for j, c in enumerate(mk["candidates"]):
                    t.add_row(str(k) if j == 0 else "",
                              "{:.2f}, {:.2f}".format(*mk["centroid_px"]) if j == 0 else "",
                              "{:.2f} × {:.2f}".format(*mk["ellipse"]["axes"]) if j == 0 else "", str(j),
                              "{:.1f}, {:.1f}, {:.1f}".format(*c["center_mm"]),
                              "{:.3f}, {:.3f}, {:.3f}".format(*c["normal"]),
                              f"{mk['normal_sigma_deg'][j]:.2f}°",
                              _verdict(mk) if j == 0 else "")
            console.print(t)
        if "duality" in result:
            d = result["duality"]
            if d["resolved"]:
                console.print(f"duality ({d['motion']}): candidate {d['index']} of the second image, "
                              f"margin {d['margin_deg']:.2f}°")
            else:
                console.print(f"duality ({d['motion']}): [yellow]ambiguous[/] (margin {d['margin_deg']:.3f}° < "
                              f"{d['threshold_deg']:.3f}° needed over the noise); no candidate chosen")
        if "response_warning" in result:
            console.print(f"[yellow]{result['response_warning']}[/]")
        console.print(f"annotated image: {result['annotated']}")

    emit(result, human)


def _set_yaml_keys(text: str, values: dict) -> str:
    """``text`` (a driver file) with top-level ``key: value`` lines replaced (or appended),
    keeping every other line and comment as it was."""
    import re

    lines = text.splitlines()
    for key, val in values.items():
        pat = re.compile(rf"^{re.escape(key)}\s*:")
        for i, line in enumerate(lines):
            if pat.match(line):
                comment = line[line.index(" #") + 1:] if " #" in line else ""
                lines[i] = f"{key}: {val}" + (f"  {comment}" if comment else "")
                # a block value (an indented mapping or a `- ` list) continues on the next lines: replaced too
                j = i + 1
                while j < len(lines) and lines[j].strip() and (lines[j][0] in " \t" or lines[j].startswith("- ")):
                    j += 1
                del lines[i + 1:j]
                break
        else:
            lines.append(f"{key}: {val}")
    return "\n".join(lines) + "\n"


@vision_group.command("learn-color")
@click.argument("image", type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--camera", "role", type=click.Choice(["fixed", "mobile"]), required=True,
              help="Whose driver file gets the window (fixed_camera or mobile_camera).")
@click.option("--near-hue", "nominal", type=float, default=0.0, show_default=True,
              help="Nominal marker hue (degrees) to search around.")
@click.option("--dry-run", is_flag=True, help="Measure and check, but do not write the driver file.")
@json_option
def vision_learn_color(image: Path, role: str, nominal: float, dry_run: bool) -> None:
    """Learn the marker hue/saturation window from IMAGE of the lab's markers and write it into
    the camera's driver file (marker_hue_deg, marker_min_saturation)."""
    from ..errors import LabctlError, UserInputError
    from ..fsutil import atomic_write_text
    from ..vision import MarkerThresholds, find_markers
    from ..vision.colour import ColourLearnError, learn_marker_colour
    from ._common import get_ctx

    img = _read_image(image)
    lab = get_ctx().lab()
    key = f"{role}_camera"
    cam_cfg = getattr(lab, key)
    path = lab.driver_paths[key]
    try:
        learned = learn_marker_colour(img, nominal_hue_deg=nominal)
    except ColourLearnError as exc:
        raise UserInputError(f"{image}: {exc}") from None
    lo, hi = learned["hue_range_deg"]
    search = find_markers(img, thresholds=MarkerThresholds(hue_range_deg=(lo, hi),
                                                           min_saturation=learned["min_saturation"]),
                          response=cam_cfg.response)
    before = find_markers(img, thresholds=MarkerThresholds(hue_range_deg=tuple(cam_cfg.marker_hue_deg),
                                                           min_saturation=cam_cfg.marker_min_saturation),
                          response=cam_cfg.response)
    result = {"image": str(image), "driver_file": str(path), **learned,
              "markers_found": len(search.markers), "trusted": sum(m.trusted for m in search.markers),
              "markers_found_before": len(before.markers), "written": False}
    if not search.markers:
        raise LabctlError(f"{image}: the learned window (hue {lo:g}…{hi:g}°, saturation ≥ "
                          f"{learned['min_saturation']:g}) finds no marker ({search.reason}); driver file unchanged")
    if not dry_run:
        text = path.read_text(encoding="utf-8")
        atomic_write_text(path, _set_yaml_keys(text, {"marker_hue_deg": f"[{lo:g}, {hi:g}]",
                                                      "marker_min_saturation": f"{learned['min_saturation']:g}"}))
        result["written"] = True

    def human(console):
        console.print(f"marker colour: hue {lo:g}…{hi:g}° (peak {learned['peak_hue_deg']:g}°), saturation ≥ "
                      f"{learned['min_saturation']:g}; {learned['blobs']} blob(s), {learned['pixels']} px")
        console.print(f"markers found with it: {result['markers_found']} ({result['trusted']} trusted); "
                      f"with the old window: {result['markers_found_before']}")
        console.print(f"written to {path}" if result["written"] else "dry run: driver file unchanged")

    emit(result, human)


def _numbers(text: str | None, what: str) -> list[float] | None:
    """A comma-separated list of numbers from the command line (None stays None); UserInputError otherwise."""
    from ..errors import UserInputError

    if text is None:
        return None
    try:
        return [float(v) for v in text.replace(" ", "").split(",") if v]
    except ValueError:
        raise UserInputError(f"{what}: expected numbers separated by commas, got {text!r}") from None


def _exif_exposure_s(path: Path) -> float | None:
    """The exposure time (s) an image's EXIF records (tag 33434 ExposureTime), or None."""
    try:
        from PIL import Image
    except ImportError:  # Pillow comes with matplotlib; without it the times come from --times
        return None
    try:
        with Image.open(path) as im:
            exif = im.getexif()
            value = exif.get_ifd(0x8769).get(33434) or exif.get(33434)
    except (OSError, ValueError):
        return None
    try:
        return float(value) if value is not None else None
    except (TypeError, ValueError, ZeroDivisionError):
        return None


@vision_group.command("learn-response")
@click.argument("images", nargs=-1, required=True, type=click.Path(exists=True, dir_okay=False, path_type=Path))
@click.option("--camera", "role", type=click.Choice(["fixed", "mobile"]), required=True,
              help="Whose driver file gets the response (fixed_camera or mobile_camera).")
@click.option("--times", "times", default=None,
              help="Exposure series: each image's exposure time, s, comma-separated (default: the images' EXIF).")
@click.option("--wedge", "wedge", default=None,
              help="Step wedge: one image; the wedge's box x0,y0,x1,y1 (px), patches in order along its long side.")
@click.option("--reflectances", default=None, help="Step wedge: each patch's reflectance, comma-separated, in order.")
@click.option("--dry-run", is_flag=True, help="Measure and print what would be written; leave the driver file.")
@json_option
def vision_learn_response(images: tuple[Path, ...], role: str, times: str | None, wedge: str | None,
                          reflectances: str | None, dry_run: bool) -> None:
    """Measure the camera's response from IMAGES and write it into its driver file (``response:``, with
    ``response_source: learned``): frames of one static scene at different exposure times (gain and white
    balance fixed), or one image of a printed grey step wedge (--wedge, --reflectances)."""
    from ..errors import UserInputError
    from ..fsutil import atomic_write_text
    from ..vision.response_learn import ResponseLearnError, learn_from_exposures, learn_from_wedge, wedge_codes
    from ._common import get_ctx

    lab = get_ctx().lab()
    key = f"{role}_camera"
    path = lab.driver_paths[key]
    refl = _numbers(reflectances, "--reflectances")
    try:
        if wedge is not None or refl is not None:
            box = _numbers(wedge, "--wedge")
            if box is None or len(box) != 4 or refl is None:
                raise UserInputError("a step wedge needs --wedge x0,y0,x1,y1 and --reflectances r1,r2,…")
            if len(images) != 1:
                raise UserInputError(f"a step wedge is measured in one image, got {len(images)}")
            codes = wedge_codes(_read_image(images[0]), (int(box[0]), int(box[1]), int(box[2]), int(box[3])),
                                len(refl))
            learned = learn_from_wedge(codes, refl)
            source = {"wedge_codes": [round(float(c), 1) for c in codes], "reflectances": refl}
        else:
            t = _numbers(times, "--times")
            if t is None:
                exif = [_exif_exposure_s(p) for p in images]
                missing = [str(p) for p, v in zip(images, exif) if v is None]
                if missing:
                    raise UserInputError(f"{missing[0]}: no exposure time in its EXIF; pass --times t1,t2,… (s)")
                t = [float(v) for v in exif if v is not None]
            learned = learn_from_exposures([_read_image(p) for p in images], t)
            source = {"exposure_times_s": t}
    except ResponseLearnError as exc:
        raise UserInputError(f"learn-response: {exc}") from None
    spec = learned.spec
    value = spec if isinstance(spec, str) else "[" + ", ".join(f"{v:.6g}" for v in spec) + "]"
    result = {"images": [str(p) for p in images], "driver_file": str(path), "method": learned.method,
              "response": spec, "gamma": learned.gamma, "max_deviation": round(learned.error, 5),
              "codes": list(learned.codes), **source, "written": False}
    if not dry_run:
        text = path.read_text(encoding="utf-8")
        # response_source: learned makes the lab count it as declared (pose is no longer conservative)
        atomic_write_text(path, _set_yaml_keys(text, {"response": value if isinstance(spec, list) or spec in
                                                      ("linear", "srgb") else f'"{spec}"',
                                                      "response_source": "learned"}))
        result["written"] = True
    nxt = "labctl devices  (checks the response against a frame of each camera)"
    result["next"] = nxt

    def human(console):
        name = spec if isinstance(spec, str) else "a 256-entry LUT (no power law within tolerance)"
        console.print(f"camera response ({learned.method}, codes {learned.codes[0]}…{learned.codes[1]}): {name}"
                      + (f", within {learned.error:.3f} of the measured curve" if isinstance(spec, str) else ""),
                      highlight=False)
        console.print(f"written to {path} (response, response_source: learned)" if result["written"]
                      else f"dry run: would write `response: {value if isinstance(spec, str) else name}` and "
                           f"`response_source: learned` to {path}", highlight=False)
        console.print(f"next: {nxt}", highlight=False)

    emit(result, human)
