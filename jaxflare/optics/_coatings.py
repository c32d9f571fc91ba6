"""Anti-reflection coating presets and custom thin-film stacks for the surfaces of a lens.

A scene chooses one of :data:`COATING_PRESETS` and applies it with :func:`with_coating`; a custom
stack goes on with :func:`with_coating_layers`. Both return a new :class:`~jaxflare.Lens` whose
``coating_indices`` / ``coating_thicknesses_nm`` arrays (the quantities a fit optimises) are
ordinary differentiable leaves; thicknesses in nm, indices real (non-absorbing films).

Orientation. The lens stores the layers of a surface in the order a *forward* ray (travelling
towards the sensor) meets them, and the tracer reverses them for backward rays. Stacks are given
here from the AIR side inwards (outermost layer first, the layer touching the glass last), as a
coating is specified. On an air-to-glass surface that is the forward order; on a glass-to-air
surface a forward ray leaves the glass and meets the glass-side layer first, so the stack is
stored reversed. A cemented (glass-glass) interface has no air side: its stack is taken in the
forward order (object side first). Arrays grow with zero-thickness layers (an exact identity)
when a stack has more layers than the lens has room for; dtypes are kept.

Preset designs (all at normal incidence; reflectances computed with the characteristic-matrix
code in :mod:`jaxflare.optics._thin_film`, figures for glass of n = 1.6 unless noted):

- ``"mgf2"``: one quarter-wave MgF2 layer (n = 1.38) at 550 nm, the lens-file default. Minimum
  R = 0.76 % at 550 nm on n = 1.6, rising to 1.31 % at 450 nm and 1.03 % at 650 nm (bare: 5.3 %);
  mean over 450-650 nm 0.89 %.
- ``"multilayer"``: the classic quarter-half-quarter broadband AR design (Lockhart & King 1947;
  H. A. Macleod, *Thin-Film Optical Filters*, 4th ed., sec. 4.3 "quarter-half-quarter"): from the
  air side MgF2 (1.38, quarter wave), ZrO2 (2.05, half wave), and a medium-index quarter wave next
  to the glass, all at 530 nm. The half-wave layer is absentee at the design wavelength and
  flattens the reflectance on both sides of it; the stack has zero reflectance there when
  ``n_M = n_MgF2 sqrt(n_glass)`` (``n_0 n_M^2 = n_L^2 n_glass`` with quarter waves), so, as a
  coater does, the medium layer's index is matched to each surface's glass at 530 nm (1.75 on
  n = 1.6, e.g. an Al2O3-ZrO2 mixture or CeF3; 1.63, pure Al2O3, suits n = 1.40). A single fixed
  Al2O3 layer (1.63) would give 0.47 % peak on n = 1.6 but about 1 % mean on n = 1.8 glass,
  worse than single-layer MgF2 there. Result on n = 1.5 / 1.6 / 1.7 / 1.8: max R over 450-650 nm
  0.38 / 0.41 / 0.45 / 0.50 %, mean 0.17 / 0.16 / 0.15 / 0.15 %.
- ``"amber"``: a vintage single MgF2 quarter wave tuned short (430 nm): the reflectance minimum
  sits in the blue, so the residual reflection (and the ghosts) are warm amber: on n = 1.6,
  R = 0.78 % at 450 nm and 1.97 % at 650 nm, R(650) / R(450) = 2.5.
- ``"blue"``: a single MgF2 quarter wave tuned long (650 nm): minimum in the red, residual
  reflection blue-purple: on n = 1.6, R = 2.70 % at 450 nm and 0.76 % at 650 nm, R(650) / R(450) = 0.28.
"""

from __future__ import annotations

import math
import operator
from collections.abc import Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from ._lens import Lens, _default_coating

__all__ = ["COATING_PRESETS", "with_coating", "with_coating_layers"]

COATING_PRESETS: dict[str, str] = {
    "lens": "the coatings of the lens file (MgF2 on glass-air interfaces unless the file says otherwise)",
    "uncoated": "bare glass on every interface",
    "mgf2": "single quarter-wave MgF2 (n = 1.38) at 550 nm on every glass-air interface",
    "multilayer": "3-layer broadband AR (quarter-half-quarter at 530 nm: MgF2 / ZrO2 / glass-matched medium index) on every glass-air interface",
    "amber": "vintage single-layer MgF2 tuned short (quarter wave at 430 nm): warm amber residual reflection",
    "blue": "single-layer MgF2 tuned long (quarter wave at 650 nm): blue-purple residual reflection",
}
"""Coating presets a scene can choose: name -> one-line description."""

MGF2_INDEX = 1.38
ZRO2_INDEX = 2.05
MULTILAYER_DESIGN_NM = 530.0
_SINGLE_LAYER_DESIGN_NM = {"mgf2": 550.0, "amber": 430.0, "blue": 650.0}


def _quarter_wave(index: float, design_wavelength_nm: float) -> tuple[float, float]:
    return index, design_wavelength_nm / (4.0 * index)


def _preset_stack(preset: str, n_glass: float) -> list[tuple[float, float]]:
    """``(index, thickness_nm)`` layers of a preset from the air side inwards, for glass of index
    ``n_glass`` at :data:`MULTILAYER_DESIGN_NM` (only the multilayer design depends on it)."""
    if preset == "uncoated":
        return []
    if preset in _SINGLE_LAYER_DESIGN_NM:
        return [_quarter_wave(MGF2_INDEX, _SINGLE_LAYER_DESIGN_NM[preset])]
    if preset == "multilayer":
        n_medium = MGF2_INDEX * math.sqrt(n_glass)
        return [
            _quarter_wave(MGF2_INDEX, MULTILAYER_DESIGN_NM),
            (ZRO2_INDEX, MULTILAYER_DESIGN_NM / (2.0 * ZRO2_INDEX)),
            _quarter_wave(n_medium, MULTILAYER_DESIGN_NM),
        ]
    raise AssertionError(preset)  # callers check the name first


def _check_preset(preset: str) -> None:
    if preset not in COATING_PRESETS:
        raise ValueError(f"unknown coating preset {preset!r}; valid presets: {', '.join(COATING_PRESETS)}")


def _glass_air_surfaces(lens: Lens) -> tuple[int, ...]:
    air = np.asarray(lens.medium_is_air)
    return tuple(s for s in range(lens.num_surfaces) if air[s] != air[s + 1])


def _check_surfaces(lens: Lens, surfaces: Sequence[int]) -> tuple[int, ...]:
    """Validate explicit surface indices: in range, and an interface (index changes across it)."""
    if isinstance(surfaces, (str, bytes)) or not isinstance(surfaces, Sequence | np.ndarray):
        raise TypeError(f"surfaces must be a sequence of surface indices, got {surfaces!r}")
    interfaces = set(lens.interface_surfaces)
    checked: list[int] = []
    for surface in surfaces:
        try:
            s = operator.index(surface)
        except TypeError:
            raise TypeError(f"surface indices must be integers, got {surface!r}") from None
        if not 0 <= s < lens.num_surfaces:
            raise ValueError(f"surface {s} is out of range: '{lens.name}' has surfaces 0 to {lens.num_surfaces - 1}")
        if s not in interfaces:
            raise ValueError(
                f"surface {s} of '{lens.name}' is a stop or dummy surface (the same medium on both sides): "
                f"it cannot carry a coating; interfaces are {list(lens.interface_surfaces)}"
            )
        if s not in checked:
            checked.append(s)
    return tuple(checked)


def _leaves_glass(lens: Lens, surface: int) -> bool:
    """True where a forward ray goes from glass into air (the stack is stored reversed)."""
    air = np.asarray(lens.medium_is_air)
    return (not air[surface]) and bool(air[surface + 1])


def _glass_index(lens: Lens, surface: int, wavelength_nm: float) -> float:
    """Index of the glass side of a glass-air surface (the medium behind a cemented one)."""
    n = lens.refractive_indices(wavelength_nm)
    return float(n[surface] if _leaves_glass(lens, surface) else n[surface + 1])


def _is_traced(*values) -> bool:
    return any(isinstance(v, jax.core.Tracer) for v in values)


def _write_rows(lens: Lens, rows: dict[int, tuple[jax.Array, jax.Array]]) -> Lens:
    """Replace the stacks of some surfaces (forward order, shape (m,) each), growing L if needed."""
    indices, thicknesses = lens.coating_indices, lens.coating_thicknesses_nm
    dtype_n, dtype_t = indices.dtype, thicknesses.dtype
    num, room = indices.shape
    need = max([0] + [row_n.shape[0] for row_n, _ in rows.values()])
    if need > room:
        indices = jnp.concatenate([indices, jnp.ones((num, need - room), dtype_n)], axis=1)
        thicknesses = jnp.concatenate([thicknesses, jnp.zeros((num, need - room), dtype_t)], axis=1)
        room = need
    for s, (row_n, row_t) in rows.items():
        pad = room - row_n.shape[0]
        indices = indices.at[s].set(jnp.concatenate([row_n.astype(dtype_n), jnp.ones(pad, dtype_n)]))
        thicknesses = thicknesses.at[s].set(jnp.concatenate([row_t.astype(dtype_t), jnp.zeros(pad, dtype_t)]))
    return eqx.tree_at(lambda l: (l.coating_indices, l.coating_thicknesses_nm), lens, (indices, thicknesses))


def _oriented(lens: Lens, surface: int, row_n: jax.Array, row_t: jax.Array) -> tuple[jax.Array, jax.Array]:
    """A stack given from the air side, in the forward order the lens stores."""
    if _leaves_glass(lens, surface):
        return row_n[::-1], row_t[::-1]
    return row_n, row_t


def with_coating(lens: Lens, preset: str, surfaces: Sequence[int] | None = None) -> Lens:
    """The lens with a coating preset (see :data:`COATING_PRESETS`) on some surfaces.

    Args:
        lens: the lens.
        preset: a name in :data:`COATING_PRESETS`.
        surfaces: surface indices to coat. Default: every glass-air interface (exactly one side
            is air), leaving cemented interfaces as they are; ``"uncoated"`` and ``"lens"``
            default to every interface (cemented ones included). Cemented interfaces may be
            listed explicitly; a stop or dummy surface (same medium on both sides) may not.

    ``"lens"`` restores the coatings the lens file gives (for a lens fresh from
    :func:`jaxflare.load_lens` it returns the lens itself). Raises ``ValueError`` for an unknown
    preset (naming the valid ones) or an invalid surface (naming the valid range).
    """
    _check_preset(preset)
    if surfaces is None:
        targets = lens.interface_surfaces if preset in ("lens", "uncoated") else _glass_air_surfaces(lens)
    else:
        targets = _check_surfaces(lens, surfaces)
    dtype = lens.coating_indices.dtype
    rows: dict[int, tuple[jax.Array, jax.Array]] = {}
    if preset == "lens":
        media = (None,) + tuple(lens.media)
        for s in targets:
            spec = _default_coating(media[s], media[s + 1], lens.prescription.surfaces[s].coating)
            rows[s] = (
                jnp.asarray([layer.index for layer in spec.layers], dtype),
                jnp.asarray([layer.thickness_nm for layer in spec.layers], dtype),
            )  # a CoatingSpec is already in the forward order
        result = _write_rows(lens, rows)
        old = (lens.coating_indices, lens.coating_thicknesses_nm)
        new = (result.coating_indices, result.coating_thicknesses_nm)
        if not _is_traced(*old) and all(a.shape == b.shape and bool(jnp.all(a == b)) for a, b in zip(old, new)):
            return lens
        return result
    for s in targets:
        stack = _preset_stack(preset, _glass_index(lens, s, MULTILAYER_DESIGN_NM) if preset == "multilayer" else 1.5)
        row_n = jnp.asarray([n for n, _ in stack], dtype)
        row_t = jnp.asarray([t for _, t in stack], dtype)
        rows[s] = _oriented(lens, s, row_n, row_t)
    return _write_rows(lens, rows)


def with_coating_layers(lens: Lens, surfaces: Sequence[int], layers: Sequence[tuple[float, float]]) -> Lens:
    """The lens with a custom thin-film stack on the listed surfaces.

    Args:
        lens: the lens.
        surfaces: surface indices (glass-air or cemented interfaces; not a stop or dummy surface).
        layers: ``(index, thickness_nm)`` pairs from the AIR side inwards: the outermost layer
            first, the one touching the glass last (on a cemented interface: from the object side).
            An empty sequence makes the surfaces bare. Indices must be >= 1 and thicknesses
            >= 0, both finite.

    The stack is stored reversed on glass-to-air surfaces (see the module docstring). Layer
    values may be JAX arrays, also traced ones (then they are not validated), so a fit can
    differentiate through this function as well as through the returned coating arrays.
    """
    targets = _check_surfaces(lens, surfaces)
    dtype = lens.coating_indices.dtype
    pairs = list(layers)
    for k, pair in enumerate(pairs):
        if len(pair) != 2:
            raise ValueError(f"layer {k} must be an (index, thickness_nm) pair, got {pair!r}")
        index, thickness = pair
        if _is_traced(index, thickness):
            continue
        index, thickness = float(index), float(thickness)
        if not (math.isfinite(index) and index >= 1.0):
            raise ValueError(f"layer {k}: refractive index must be finite and >= 1, got {index}")
        if not (math.isfinite(thickness) and thickness >= 0.0):
            raise ValueError(f"layer {k}: thickness_nm must be finite and >= 0, got {thickness}")
    if pairs:
        row_n = jnp.stack([jnp.asarray(n, dtype) for n, _ in pairs])
        row_t = jnp.stack([jnp.asarray(t, dtype) for _, t in pairs])
    else:
        row_n = row_t = jnp.zeros((0,), dtype)
    return _write_rows(lens, {s: _oriented(lens, s, row_n, row_t) for s in targets})
