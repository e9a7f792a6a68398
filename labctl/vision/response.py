"""Camera response: how a camera maps scene radiance to pixel values, and its inverse.

Sub-pixel edge localisation (paper §3.1) needs pixel values *linear* in the fraction of the
pixel the marker covers. Most cameras encode their output (sRGB, a power-law gamma, or a
vendor curve), so frames are linearised with the camera's declared response before any
sub-pixel work. A camera's driver file states it (``response:``):

* ``linear`` — raw / machine-vision cameras with gamma off;
* ``srgb`` — webcams and most consumer cameras (IEC 61966-2-1 curve);
* ``gamma: G`` (or the string ``"gamma G"``, or a bare number G) — encoded value = linear^(1/G);
* a list of 256 numbers — a lookup table from each 8-bit code to linear radiance (any scale;
  it is normalised to [0, 1] by its maximum).

How a lab measures it: photograph a grey card (or the bare table) at 8–10 exposure times
spanning the camera's range, with gain and white balance fixed; the mean value of a patch
against exposure time is the response curve (fit G to value ∝ t^(1/G), or tabulate the inverse
as the LUT). A printed step wedge of known reflectances in one frame gives the same curve.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


class ResponseError(ValueError):
    """A response specification that cannot be understood."""


@dataclass(frozen=True)
class Response:
    """An inverse camera response: ``lut`` maps each 8-bit code to linear radiance in [0, 1]
    (float32, 256 entries); ``name`` says which curve it is."""

    name: str
    lut: np.ndarray
    gamma: float | None = None  # the power-law exponent when it is one (1 for linear)

    @property
    def is_linear(self) -> bool:
        """True for the identity (linear) response."""
        return self.name == "linear"

    def linearise(self, image: np.ndarray) -> np.ndarray:
        """Linear radiance (float32, [0, 1]) of an encoded uint8 or uint16 image (same shape)."""
        img = np.asarray(image)
        if img.dtype == np.uint8:
            return self.lut[img]
        if img.dtype == np.uint16:
            x = img.astype(np.float32) * np.float32(1.0 / 65535.0)
        else:
            x = np.clip(np.asarray(img, np.float32), 0.0, None)
            top = float(x.max(initial=0.0))
            if top > 1.0:
                x = x * np.float32(1.0 / 255.0)
        return self.apply(x)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """Inverse response of encoded values ``x`` in [0, 1] (float)."""
        if self.name == "linear":
            return x.astype(np.float32, copy=False)
        if self.name == "srgb":
            return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4)).astype(np.float32)
        if self.gamma is not None:
            return np.power(x, self.gamma).astype(np.float32)
        return np.interp(x * 255.0, np.arange(256), self.lut).astype(np.float32)


def _power_lut(g: float) -> np.ndarray:
    return np.power(np.arange(256) / 255.0, g).astype(np.float32)


def parse_response(spec) -> Response:
    """A :class:`Response` from a driver file's ``response`` entry (see the module doc)."""
    if isinstance(spec, Response):
        return spec
    if spec is None or (isinstance(spec, str) and spec.strip().lower() == "linear"):
        return Response("linear", _power_lut(1.0), 1.0)
    if isinstance(spec, str):
        s = spec.strip().lower()
        if s in ("srgb", "s-rgb"):
            x = np.arange(256) / 255.0
            lut = np.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4).astype(np.float32)
            return Response("srgb", lut)
        if s.startswith("gamma"):
            spec = s[5:].strip(" :=")
        try:
            spec = float(spec)
        except ValueError:
            raise ResponseError(f"unknown camera response {spec!r} (linear, srgb, 'gamma G' or a 256-entry LUT)") \
                from None
    if isinstance(spec, dict):
        if set(spec) != {"gamma"}:
            raise ResponseError(f"unknown camera response {spec!r} (linear, srgb, gamma: G or a 256-entry LUT)")
        spec = spec["gamma"]
    if isinstance(spec, bool):
        raise ResponseError(f"unknown camera response {spec!r}")
    if isinstance(spec, int | float):
        g = float(spec)
        if not (math.isfinite(g) and 0.2 <= g <= 5.0):
            raise ResponseError(f"camera response gamma must be within 0.2–5, got {spec!r}")
        return Response("linear" if g == 1.0 else f"gamma {g:g}", _power_lut(g), g)
    try:
        lut = np.asarray(spec, dtype=float).ravel()
    except (TypeError, ValueError):
        raise ResponseError(f"unknown camera response {spec!r}") from None
    if lut.shape != (256,) or not np.all(np.isfinite(lut)) or np.any(np.diff(lut) < 0) or not lut[-1] > lut[0]:
        raise ResponseError("a camera response LUT needs 256 finite, non-decreasing values (code 0…255 → radiance)")
    lut = (lut - lut[0]) / (lut[-1] - lut[0])
    return Response("lut", lut.astype(np.float32))


LINEAR = parse_response("linear")
