"""The main render's lens distortion, applied to flare samples in image space.

Pekkarinen & Balzer: "If the main render pass uses a separate lens distortion model, it is taken
into account by applying the distortion on the light samples in image space." A CG plate is
usually rendered through a pinhole camera and distorted afterwards (in comp) to match the real
lens; the flare must be distorted the same way to stay attached to its source.

Where it applies
----------------
The renderer traces each sample through the lens to the sensor, converts the sensor point to an
undistorted image position (column, row in pixels) and then moves that position with the
distortion model before splatting it. So the flare image comes out in the *distorted* plate's
pixels, ready to composite over the distorted plate; the lights themselves are still placed in the
undistorted (pinhole) frame of the main render's camera. Splatting moved samples conserves each
sample's energy: where the distortion compresses the image (the corners under barrel distortion)
pixels get brighter by the inverse of the local area change, as irradiance on a real sensor would. A
compositor's pull warp (an STMap node) keeps pixel values instead; the two differ by the Jacobian
determinant of the distortion, usually within a few percent. The sensor-bounds test belongs after
the distortion (barrel distortion pulls points from beyond the undistorted frame into the image).

Image coordinates
-----------------
Continuous pixel coordinates: column ``x`` in ``[0, W)`` from the left edge, row ``y`` in
``[0, H)`` from the top edge, pixel ``(i, j)`` covering ``[j, j+1) x [i, i+1)`` with its centre at
``(j + 0.5, i + 0.5)`` (the convention of the renderer's splat). The principal point (distortion
centre) is the image centre ``(W/2, H/2)``.

Brown-Conrady (:class:`BrownConrady`, :func:`distort`)
------------------------------------------------------
OpenCV's model and convention exactly, with square pixels (``fx = fy = f``): normalised coordinates
are ``x = (column - W/2) / f``, ``y = (row - H/2) / f``, x to the right and **y down** (rows used
directly), and

    r^2 = x^2 + y^2
    x_d = x (1 + k1 r^2 + k2 r^4 + k3 r^6) + 2 p1 x y + p2 (r^2 + 2 x^2)
    y_d = y (1 + k1 r^2 + k2 r^4 + k3 r^6) + p1 (r^2 + 2 y^2) + 2 p2 x y

maps an undistorted (pinhole) position to where it appears in the distorted plate
(``column_d = W/2 + f x_d``, ``row_d = H/2 + f y_d``). So coefficients from an OpenCV calibration
(``cv2.calibrateCamera``'s ``(k1, k2, p1, p2, k3)``) apply unchanged, p1 and p2 included, as long
as the image is the calibrated one and its principal point is at the centre (OpenCV puts pixel
centres at integers, so a centred principal point reads ``((W-1)/2, (H-1)/2)`` there). ``k1 < 0``
is barrel distortion (points move towards the centre), ``k1 > 0`` pincushion. ``f`` is the focal
length in pixels: ``focal_length_mm / pixel_pitch_mm`` of the main render's camera.

ST-map (:func:`load_st_map`, :func:`st_map_distort`)
----------------------------------------------------
An EXR with channels ``R = s`` and ``G = t`` (Nuke's STMap convention): normalised image positions,
``s = column / W`` from the left and ``t = 1 - row / H`` from the **bottom**, so the centre of pixel
``(i, j)`` is ``s = (j + 0.5) / W``, ``t = 1 - (i + 0.5) / H``. Direction: pixel ``(i, j)`` of the
map belongs to the *undistorted* flare render (the map covers the same frame at any resolution),
and its ``(s, t)`` is where that point lands in the *distorted* plate: a forward map, which is what
splatting needs. In Nuke's terms this is the map an STMap node would use to *undistort* the plate
(each undistorted pixel says where to sample the distorted plate), e.g. LensDistortion's undistort
STMap; the "redistort" map is its inverse and is not the one to give here. :func:`identity_st_map`
builds the map of no distortion. Store ST-maps as 32-bit float: half floats resolve ``s`` only to
about 1/2048 near 1, half a pixel or more at 2K.
"""

from __future__ import annotations

import abc
import math
import os

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ...io import read_exr_channels
from ._bilinear import bilinear

__all__ = ["AbstractDistortion", "BrownConrady", "STMap", "distort", "identity_st_map", "load_st_map", "st_map_distort"]



class AbstractDistortion(eqx.Module):
    """A distortion model of the main render: where an undistorted image position lands in the
    distorted plate."""

    @abc.abstractmethod
    def __call__(self, x_px: Array, y_px: Array, width: int, height: int) -> tuple[Array, Array]:
        """Distorted ``(column, row)`` of undistorted ``(x_px, y_px)`` in a ``width`` x ``height`` image."""


class BrownConrady(AbstractDistortion):
    """Brown-Conrady lens distortion in OpenCV's convention (x right, y down, normalised by ``f``);
    see the module docstring. Build one with :meth:`create`; apply it with :func:`distort`.

    - ``k1, k2, k3``: radial coefficients (``k1 < 0`` barrel, ``k1 > 0`` pincushion);
    - ``p1, p2``: tangential (decentring) coefficients, OpenCV's, y pointing down;
    - ``focal_length_px``: the normalisation ``f`` in pixels (square pixels).
    """

    k1: Float[Array, ""]
    k2: Float[Array, ""]
    k3: Float[Array, ""]
    p1: Float[Array, ""]
    p2: Float[Array, ""]
    focal_length_px: Float[Array, ""]

    @classmethod
    def create(
        cls,
        k1: float = 0.0,
        k2: float = 0.0,
        k3: float = 0.0,
        p1: float = 0.0,
        p2: float = 0.0,
        *,
        focal_length_px: float,
    ) -> BrownConrady:
        """A model from plain numbers, validated: finite coefficients, finite ``focal_length_px > 0``."""
        values = {"k1": k1, "k2": k2, "k3": k3, "p1": p1, "p2": p2, "focal_length_px": focal_length_px}
        checked = {}
        for name, value in values.items():
            try:
                number = float(value)
            except (TypeError, ValueError):
                raise ValueError(f"BrownConrady {name} must be a number, got {value!r}") from None
            if not math.isfinite(number):
                raise ValueError(f"BrownConrady {name} must be finite, got {number}")
            checked[name] = number
        if checked["focal_length_px"] <= 0:
            raise ValueError(f"BrownConrady focal_length_px must be positive, got {checked['focal_length_px']}")
        return cls(**{name: jnp.asarray(number) for name, number in checked.items()})

    def __call__(self, x_px, y_px, width, height):
        return distort(self, x_px, y_px, width, height)


def distort(
    model: BrownConrady, x_px: Float[Array, "*shape"], y_px: Float[Array, "*shape"], width: int, height: int
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"]]:
    """Where undistorted image positions ``(x_px, y_px)`` (column, row in pixels of a ``width`` x
    ``height`` image) appear in the distorted plate, in the same pixels: the forward Brown-Conrady
    model about the image centre (module docstring). Differentiable in the positions and the
    coefficients; jit and vmap friendly (``width``, ``height`` may be traced)."""
    x_px = jnp.asarray(x_px)
    y_px = jnp.asarray(y_px)
    cx = 0.5 * width
    cy = 0.5 * height
    f = model.focal_length_px
    x = (x_px - cx) / f
    y = (y_px - cy) / f  # OpenCV: y down, rows used directly
    r2 = x * x + y * y
    radial = 1 + r2 * (model.k1 + r2 * (model.k2 + r2 * model.k3))
    x_d = x * radial + 2 * model.p1 * x * y + model.p2 * (r2 + 2 * x * x)
    y_d = y * radial + model.p1 * (r2 + 2 * y * y) + 2 * model.p2 * x * y
    return cx + f * x_d, cy + f * y_d


# ------------------------------------------------------------------------------------- ST maps


def identity_st_map(width: int, height: int) -> np.ndarray:
    """The ST-map of no distortion, ``(height, width, 2)`` float32: ``s = (j + 0.5) / W``,
    ``t = 1 - (i + 0.5) / H`` at pixel ``(i, j)``."""
    width, height = int(width), int(height)
    if width < 2 or height < 2:
        raise ValueError(f"an ST-map must be at least 2 x 2 pixels, got {width} x {height}")
    s = (np.arange(width, dtype=np.float64) + 0.5) / width
    t = 1.0 - (np.arange(height, dtype=np.float64) + 0.5) / height
    st = np.empty((height, width, 2), np.float32)
    st[..., 0] = s[None, :]
    st[..., 1] = t[:, None]
    return st


def load_st_map(path: str | os.PathLike) -> np.ndarray:
    """Read an ST-map EXR: ``(H, W, 2)`` float32, ``[..., 0] = s`` (channel R), ``[..., 1] = t``
    (channel G), in the convention and direction of the module docstring. Other channels (B, A, other
    layers) are ignored. Raises ``FileNotFoundError`` for a missing file and ``ValueError`` for a
    file that is not a readable EXR, lacks R or G, holds non-finite values or is smaller than 2 x 2.
    """
    path = os.fspath(path)
    if not os.path.isfile(path):
        raise FileNotFoundError(f"no such ST-map file: {path!r}")
    try:
        channels, _ = read_exr_channels(path)
    except ValueError as error:
        raise ValueError(f"cannot read ST-map {path!r}: {error}; an ST-map is an EXR with channels R = s and G = t") from None
    missing = [name for name in ("R", "G") if name not in channels]
    if missing:
        raise ValueError(
            f"ST-map {path!r} has no channel {' or '.join(missing)} (channels: {sorted(channels)}); "
            "an ST-map stores s in R and t in G"
        )
    planes = [np.asarray(channels[name]).astype(np.float32) for name in ("R", "G")]
    st = np.stack(planes, axis=-1)
    if st.ndim != 3 or st.shape[0] < 2 or st.shape[1] < 2:
        raise ValueError(f"ST-map {path!r} has shape {st.shape[:-1]}; it must be at least 2 x 2 pixels")
    if not np.all(np.isfinite(st)):
        count = int(st.size - np.count_nonzero(np.isfinite(st)))
        raise ValueError(f"ST-map {path!r} has {count} non-finite (NaN or infinite) values")
    return np.ascontiguousarray(st)


def _bilinear_edge_extended(image: Array, column: Array, row: Array) -> Array:
    return bilinear(image, column, row, extend_edges=True)


def st_map_distort(
    st_map: Float[Array, "H W 2"], x_px: Float[Array, "*shape"], y_px: Float[Array, "*shape"], width: int, height: int
) -> tuple[Float[Array, "*shape"], Float[Array, "*shape"]]:
    """Where undistorted image positions ``(x_px, y_px)`` (column, row in pixels of the ``width`` x
    ``height`` render) land in the distorted plate, in the same pixels, looked up in ``st_map``.

    The map spans the whole frame whatever its own resolution: the position is normalised by
    ``width``, ``height``, interpolated bilinearly between the map's pixel centres, and its
    ``(s, t)`` converted back as ``(s W, (1 - t) H)``. Positions outside the frame are clamped onto
    its edge; in the outer half pixel the border slope is extended rather than held, so the
    identity map is exact everywhere in the frame. Differentiable in the map and the positions; jit
    and vmap friendly.
    """
    st_map = jnp.asarray(st_map)
    if st_map.ndim != 3 or st_map.shape[-1] != 2 or st_map.shape[0] < 2 or st_map.shape[1] < 2:
        raise ValueError(f"an ST-map must have shape (H, W, 2) with H, W >= 2, got {st_map.shape}")
    map_height, map_width = st_map.shape[:2]
    x_px = jnp.asarray(x_px)
    y_px = jnp.asarray(y_px)
    st = _bilinear_edge_extended(st_map, x_px / width * map_width, y_px / height * map_height)
    return st[..., 0] * width, (1 - st[..., 1]) * height


class STMap(AbstractDistortion):
    """An ST-map (:func:`load_st_map`) as a distortion model (:func:`st_map_distort`)."""

    st: Float[Array, "H W 2"]

    def __call__(self, x_px, y_px, width, height):
        return st_map_distort(self.st, x_px, y_px, width, height)
