"""Extended lights by convolution: a path's image for the light's centre, blurred by the light's disc.

A sphere or disc light moves a flare path's image as the point on the light moves; over the
light's small disc the move is linear, ``dx = J o`` (``o`` on the unit disc, ``J`` the 2 x 2
derivative the grid traces by finite differences). Drawing each sub-sample at its own point of
the disc (a Kronecker point, :mod:`._grid_splat`) integrates that blur by sampling: with a few
sub-samples per pixel and a blur of tens of pixels every pixel is a handful of random-looking
arrivals, and the image is speckled (measured on the demo: a focused ghost and the caustic of
the star ghost at 20-50 % pixel noise, the same at 4 and 64 sub-samples per blurred pixel).

Here a *blurred* job draws every sub-sample at the light's centre into its own *slot* (its image
at its level, with a border as wide as the blur) and the slot is convolved with the disc's image
under ``J`` (the job's mean over the vertices that pass the apertures), by FFT, then added to the
job's layer. To first order in the light's size this is the same integral (in paraxial optics a
light's move translates a path's whole image, iris clip included), with no noise at all.

Jobs whose blur is below :data:`BLUR_MIN_PX` level pixels keep the sampled disc (a blur that
small adds little noise), as do jobs beyond :data:`BLUR_MAX_PX` (the linear model is poor there
and the slot would be larger than its image).
"""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Int

from ._grid_trace import FLUX, NUM_QUANTITIES, SENSOR, VALID

__all__ = ["BLUR_MAX_PX", "BLUR_MIN_PX", "BLUR_SPACING", "BlurSlots", "add_blurred_slots", "blur_border", "blur_slots", "blurred_slots", "disc_kernel", "light_jacobian_px"]

BLUR_MIN_PX = 1.0
"""Least blur (level pixels, the light disc's largest move of the path's image) drawn by convolution."""
BLUR_MAX_PX = 128.0
"""Most blur (level pixels) drawn by convolution."""
BLUR_SPACING = 0.2
"""A blurred job's sub-sample spacing may grow to this fraction of the narrowest half-width of its
disc's image: the kernel smooths the lattice's ripple (see :func:`disc_kernel`)."""
FFT_NOISE_FLOOR = 1e-5
"""Relative to a slot's brightest pixel (before the convolution, per channel): float32 FFT
convolution leaves about 1e-7 of it everywhere; below this a convolved pixel is rounding."""
KERNEL_SUPERSAMPLING = 16
"""Points per pixel side when a kernel's ellipse is rasterised."""
MIN_KERNEL_WIDTH_PX = 0.25
"""Narrowest half-width (level px) of a kernel rasterised through the Jacobian's inverse."""
DISC_POINTS = (64, 256)
"""Radial and angular strata of the unit disc when a kernel is binned (16384 equal-area points)."""


def light_jacobian_px(job, host_rows: np.ndarray, traced: int, passing: np.ndarray, pitch_mm: float, level_px: int) -> np.ndarray | None:
    """The job's image move per unit move on the light's disc (2 x 2, level pixels: columns, rows;
    per disc axis s, t): the flux-weighted mean of its traced finite differences at the middle
    traced wavelength over the vertices that pass every aperture (``passing``, (K, n+1, n+1));
    None when no vertex passes."""
    if job.variants != 3:
        return None
    n = job.cells
    block = host_rows[job.row0 : job.row0 + 3 * traced * job.vertices].reshape(3, traced, n + 1, n + 1, NUM_QUANTITIES)
    middle = traced // 2
    base, along_s, along_t = block[0, middle], block[1, middle], block[2, middle]
    use = passing[middle] & (along_s[..., VALID] > 0.5) & (along_t[..., VALID] > 0.5)
    weight = np.where(use, np.maximum(base[..., FLUX], 0.0), 0.0)
    if not np.any(weight > 0):
        return None
    d_s = (along_s[..., SENSOR : SENSOR + 2] - base[..., SENSOR : SENSOR + 2]) / job.step
    d_t = (along_t[..., SENSOR : SENSOR + 2] - base[..., SENSOR : SENSOR + 2]) / job.step
    mean_s = np.einsum("ij,ijk->k", weight, d_s) / weight.sum()
    mean_t = np.einsum("ij,ijk->k", weight, d_t) / weight.sum()
    jacobian_mm = np.stack([mean_s, mean_t], axis=1)  # rows: sensor x, y; columns: disc s, t
    # image columns run against sensor x (the image is upright): :func:`._records.image_position`
    return np.diag([-1.0, 1.0]) @ jacobian_mm / (pitch_mm * level_px)


def blur_border(jacobian_px: np.ndarray) -> int:
    """The slot border (level pixels, a power of two >= 2) that holds the disc's image whole."""
    reach = float(np.max(np.linalg.norm(jacobian_px, axis=1)))
    return max(2, 2 ** math.ceil(math.log2(math.ceil(reach) + 1)))


def disc_kernel(jacobian_px: np.ndarray, border: int) -> np.ndarray:
    """The unit disc's image under ``jacobian_px`` as a (2 border + 1)^2 kernel summing to 1: the
    share of the ellipse's area in each pixel (index ``border`` is no move), from
    :data:`KERNEL_SUPERSAMPLING`^2 points per pixel (every pixel inside the ellipse gets exactly
    the same weight). A (nearly) singular ``jacobian_px``, a move along a line, is binned from
    :data:`DISC_POINTS` equal-area points of the disc instead (no inversion)."""
    jacobian = np.asarray(jacobian_px, np.float64)
    size = 2 * border + 1
    if np.linalg.svd(jacobian, compute_uv=False)[-1] >= MIN_KERNEL_WIDTH_PX:
        fine = (np.arange(size * KERNEL_SUPERSAMPLING) + 0.5) / KERNEL_SUPERSAMPLING - border - 0.5
        x, y = np.meshgrid(fine, fine)
        o = np.linalg.solve(jacobian, np.stack([x.ravel(), y.ravel()]))
        inside = (np.sum(o * o, axis=0) <= 1.0).reshape(size, KERNEL_SUPERSAMPLING, size, KERNEL_SUPERSAMPLING)
        kernel = inside.sum(axis=(1, 3)).astype(np.float64)
    else:
        radial, angular = DISC_POINTS
        r = np.sqrt((np.arange(radial) + 0.5) / radial)
        phi = 2 * np.pi * (np.arange(angular) + 0.5) / angular
        o = np.stack([np.outer(r, np.cos(phi)).ravel(), np.outer(r, np.sin(phi)).ravel()], axis=-1)
        moves = o @ jacobian.T  # (N, 2): column, row
        index = np.clip(np.floor(moves + border + 0.5).astype(np.int64), 0, size - 1)
        kernel = np.zeros((size, size))
        np.add.at(kernel, (index[:, 1], index[:, 0]), 1.0)
    if kernel.sum() == 0:  # an ellipse narrower than the supersampling: all of it in its centre pixel
        kernel[border, border] = 1.0
    return kernel / kernel.sum()


class BlurSlots(eqx.Module):
    """Where each blurred job's slot lies in the atlas (a flat array of slot pixels), and the
    kernels. Slots are grouped by level; a group's slots share one shape (the level's image with a
    border of ``border`` level pixels all round) and one FFT."""

    base: Int[Array, " J"]
    """The flat index of the job's slot's first pixel in the atlas (-1: the job is not blurred)."""
    width: Int[Array, " J"]
    """Slot width and height (level pixels, border included)."""
    height: Int[Array, " J"]
    border: Float[Array, " J"]
    kernels: tuple
    """Per group, (count, 2 border + 1, 2 border + 1) float32."""
    slot_job: tuple
    """Per group, (count,) the job of each slot (its layer is read at composition)."""
    groups: tuple = eqx.field(static=True)
    """Per group: (level index, border, count, first atlas pixel)."""
    size: int = eqx.field(static=True)
    """Atlas pixels."""


def _bucket_count(count: int) -> int:
    return 1 if count <= 1 else 2 ** math.ceil(math.log2(count))


def blur_slots(jobs, jacobians: list, width: int, height: int, levels: tuple[int, ...], level_layout) -> BlurSlots | None:
    """The atlas of the blurred jobs (``jacobians[j]`` None: job j is not blurred), or None when
    none is. Group sizes are rounded up to powers of two (one compiled program for renders of
    similar structure); the extra slots stay black."""
    layout = level_layout(width, height)
    total = len(jobs)
    base, slot_w, slot_h, border_of = np.full(total, -1), np.ones(total, np.int64), np.ones(total, np.int64), np.zeros(total)
    by_level: dict[int, list[int]] = {}
    for j, jac in enumerate(jacobians):
        if jac is not None:
            by_level.setdefault(jobs[j].level, []).append(j)
    if not by_level:
        return None
    groups, kernels, slot_jobs = [], [], []
    offset = 0
    for level_index in sorted(by_level):
        members = by_level[level_index]
        border = max(blur_border(jacobians[j]) for j in members)
        _, _, h, w = layout[level_index]
        hs, ws = h + 2 * border, w + 2 * border
        count = _bucket_count(len(members))
        kernel = np.zeros((count, 2 * border + 1, 2 * border + 1), np.float32)
        slot_job = np.zeros(count, np.int32)
        for s, j in enumerate(members):
            kernel[s] = disc_kernel(jacobians[j], border)
            slot_job[s] = j
            base[j] = offset + s * hs * ws
            slot_w[j], slot_h[j], border_of[j] = ws, hs, border
        groups.append((level_index, border, count, offset))
        kernels.append(jnp.asarray(kernel))
        slot_jobs.append(jnp.asarray(slot_job))
        offset += count * hs * ws
    return BlurSlots(
        base=jnp.asarray(base, jnp.int32), width=jnp.asarray(slot_w, jnp.int32), height=jnp.asarray(slot_h, jnp.int32),
        border=jnp.asarray(border_of, jnp.float32), kernels=tuple(kernels), slot_job=tuple(slot_jobs), groups=tuple(groups), size=offset,
    )


def blurred_slots(atlas: Float[Array, "A 3"], slots: BlurSlots, width: int, height: int, level_layout) -> list:
    """Per group, every slot of ``atlas`` convolved with its kernel (FFT; the border keeps the
    circular convolution from wrapping into the image) and cropped to its level's image:
    (count, h, w, 3). Values below :data:`FFT_NOISE_FLOOR` of the slot's peak (per channel) are
    the FFT's rounding, set to zero (so is anything negative)."""
    layout = level_layout(width, height)
    images = []
    for (level_index, border, count, offset), kernels in zip(slots.groups, slots.kernels):
        _, _, h, w = layout[level_index]
        hs, ws = h + 2 * border, w + 2 * border
        slot_images = atlas[offset : offset + count * hs * ws].reshape(count, hs, ws, atlas.shape[-1])
        size = 2 * border + 1
        padded = jnp.zeros((count, hs, ws), atlas.dtype).at[:, :size, :size].set(kernels.astype(atlas.dtype))
        padded = jnp.roll(padded, (-border, -border), axis=(1, 2))  # index 0: no move
        spectrum = jnp.fft.rfft2(slot_images, axes=(1, 2)) * jnp.fft.rfft2(padded, axes=(1, 2))[..., None]
        blurred = jnp.fft.irfft2(spectrum, s=(hs, ws), axes=(1, 2))[:, border : border + h, border : border + w]
        # the FFT's rounding spreads ~1e-7 of a slot's peak over its whole image (along the peak's
        # row and column): a core 1e7 times brighter than the flares would lay lines across them
        floor = FFT_NOISE_FLOOR * jnp.max(jnp.abs(slot_images), axis=(1, 2), keepdims=True)
        images.append(jnp.where(blurred > floor, blurred, 0.0))
    return images


def add_blurred_slots(
    buffer: Float[Array, "Y H W 3"], atlas: Float[Array, "C A 3"], slots: BlurSlots, layer: Int[Array, " J"], width: int, height: int, level_layout,
):
    """The blurred slots (:func:`blurred_slots`) of each of the ``C`` copies of the atlas added to
    the packed ``buffer``: copy ``k`` of job ``j``'s slot into layer ``layer[j] * C + k`` at its
    level (one copy: a render; ``C`` copies: the one-hot dirt cells of a fit)."""
    copies = atlas.shape[0]
    layout = level_layout(width, height)
    images = jax.vmap(lambda a: blurred_slots(a, slots, width, height, level_layout))(atlas)
    for (level_index, _, count, _), slot_job, group in zip(slots.groups, slots.slot_job, images):
        row0, column0, h, w = layout[level_index]
        target = (layer[slot_job][None, :] * copies + jnp.arange(copies)[:, None]).reshape(-1)
        buffer = buffer.at[target, row0 : row0 + h, column0 : column0 + w].add(group.reshape(copies * count, h, w, buffer.shape[-1]).astype(buffer.dtype))
    return buffer
