"""Lens cross-section drawings with traced primary and ghost rays (matplotlib)."""

from __future__ import annotations

import math
import os

import numpy as np

from .._atomic import atomic_output_path
from ..optics import GhostPath, Lens, active_event_count, path_events, strongest_ghost_path, surface_sag_mm, trace


def _fan(lens: Lens, field_angle_deg: float, count: int, start_z: float) -> tuple[np.ndarray, np.ndarray]:
    z_pupil, r_pupil = lens.entrance_pupil()
    angle = math.radians(field_angle_deg)
    heights = np.linspace(-0.95, 0.95, count) * r_pupil
    origins = np.column_stack([np.zeros(count), heights - (z_pupil - start_z) * math.tan(angle), np.full(count, start_z)])
    directions = np.tile([0.0, math.sin(angle), math.cos(angle)], (count, 1))
    return origins, directions


def _draw_rays(ax, lens: Lens, origins, directions, path, colour, wavelength_nm, width):
    result = trace(lens, origins, directions, wavelength_nm, path, record_events=True)
    active = active_event_count(path_events(lens, path))
    history = np.asarray(result.event_positions)[:active]
    valid = np.asarray(result.valid)
    sensor = np.asarray(result.positions)
    for k in np.flatnonzero(valid):
        points = np.vstack([origins[k], history[:, k], sensor[k]])
        ax.plot(points[:, 2], points[:, 1], color=colour, lw=width, alpha=0.8)
    return int(valid.sum())


def plot_cross_section(
    lens: Lens,
    ax=None,
    *,
    field_angles_deg: tuple[float, ...] | None = None,
    rays_per_field: int = 7,
    ghost_path: GhostPath | str | None = "strongest",
    wavelength_nm: float = 550.0,
):
    """Draw the lens in the y-z plane with fans of primary rays and one ghost path.

    ``field_angles_deg`` defaults to the axis and 70 % of the half field of the sensor diagonal.
    ``ghost_path`` is a path ``(j, i)``, ``"strongest"`` (largest on-axis Fresnel factor) or None.
    Returns the matplotlib Axes.
    """
    import matplotlib.pyplot as plt

    if ax is None:
        _, ax = plt.subplots(figsize=(11, 5))
    vertex_z = lens.vertex_z_mm
    semi = np.asarray(lens.semi_aperture_mm, np.float64)
    profiles = []
    for s in range(lens.num_surfaces):
        y = np.linspace(-semi[s], semi[s], 81)
        profiles.append((vertex_z[s] + np.asarray(surface_sag_mm(lens, s, np.zeros_like(y), y), np.float64), y))
    for s in range(lens.num_surfaces - 1):
        if lens.media[s] is None:
            continue
        (z0, y0), (z1, y1) = profiles[s], profiles[s + 1]
        outline_z = np.concatenate([z0, z1[::-1], z0[:1]])
        outline_y = np.concatenate([y0, y1[::-1], y0[:1]])
        ax.fill(outline_z, outline_y, color="#cfe3f5", ec="#5b7fa3", lw=0.8, zorder=1)
    for s, (z, y) in enumerate(profiles):
        if s != lens.stop_index and lens.media[s] is None and (s == 0 or lens.media[s - 1] is None):
            ax.plot(z, y, color="#999999", lw=0.6, ls=":")  # dummy surface in air
    stop_z = vertex_z[lens.stop_index]
    stop_r = float(lens.stop_radius_mm)
    outer = max(semi[lens.stop_index] * 1.2, stop_r * 1.3)
    for sign in (1, -1):
        ax.plot([stop_z, stop_z], [sign * stop_r, sign * outer], color="black", lw=2.5)
    sensor_z = float(lens.sensor_z_mm)
    half_height = 0.5 * lens.prescription.sensor_height_mm
    ax.plot([sensor_z, sensor_z], [-half_height, half_height], color="#333333", lw=2)

    efl = abs(lens.focal_length())
    half_field = math.degrees(math.atan(0.5 * math.hypot(lens.prescription.sensor_width_mm, lens.prescription.sensor_height_mm) / efl))
    if field_angles_deg is None:
        field_angles_deg = (0.0, 0.7 * half_field)
    start_z = -0.15 * max(sensor_z, 1.0)
    colours = ["#1f77b4", "#2ca02c", "#9467bd"]
    for k, angle in enumerate(field_angles_deg):
        _draw_rays(ax, lens, *_fan(lens, angle, rays_per_field, start_z), None, colours[k % 3], wavelength_nm, 0.8)
    title = f"{lens.name}: EFL {efl:.1f} mm, f/{lens.f_number():.2g}"
    if ghost_path == "strongest":
        ghost_path = strongest_ghost_path(lens, wavelength_nm)
    if ghost_path is not None:
        origins, directions = _fan(lens, field_angles_deg[-1] * 0.5, 15, start_z)
        _draw_rays(ax, lens, origins, directions, tuple(ghost_path), "#d62728", wavelength_nm, 1.0)
        title += f"; ghost path {tuple(ghost_path)} in red"
    ax.set_title(title, fontsize=10)
    ax.set_xlabel("z (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_aspect("equal", adjustable="datalim")
    ax.grid(alpha=0.2)
    return ax


def save_cross_section(lens: Lens, path: str | os.PathLike, **options) -> str:
    """Plot :func:`plot_cross_section` to a PNG (written atomically); returns the path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 5))
    plot_cross_section(lens, ax, **options)
    fig.tight_layout()
    with atomic_output_path(path) as temporary:
        fig.savefig(temporary, dpi=130)
    plt.close(fig)
    return os.fspath(path)
