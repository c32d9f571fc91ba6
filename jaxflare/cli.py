"""The ``jaxflare`` command line.

    jaxflare lens list                      bundled lenses with EFL, f-number, interfaces, ghost paths
    jaxflare lens info NAME [--zoom K]      one lens: data, surfaces, ghost paths ranked by strength
    jaxflare lens plot NAME -o OUT.png      cross-section with primary rays and a ghost path
    jaxflare lens convert IN OUT            between the jaxflare TOML format and Zemax .zmx
    jaxflare render SCENE.toml -o OUT.exr   render a scene's flares to a multi-layer EXR (--png: preview)
    jaxflare fit PLATE --scene S -o F.json  fit coating colours / dirt / light gains to a plate
    jaxflare demo [--out DIR]               the demo: lens table, cross-section, demo scene render
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import warnings


def _load(name: str, zoom: int = 0):
    from .io import load_lens

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lens = load_lens(name, zoom)
    for warning in caught:
        print(f"note: {warning.message}", file=sys.stderr)
    return lens


def _lens_table(names: list[str]) -> str:
    rows = [("lens", "EFL mm", "stated", "f/#", "interfaces", "ghost paths", "zoom pos.")]
    for name in names:
        lens = _load(name)
        n = lens.num_interfaces
        if lens.num_zoom_positions > 1:
            efls = [lens.at_zoom(k).focal_length() for k in range(lens.num_zoom_positions)]
            efl = "-".join(f"{f:.1f}" for f in (efls[0], efls[-1]))
            stated = "-".join(f"{f:g}" for f in (lens.prescription.stated_focal_lengths_mm[0], lens.prescription.stated_focal_lengths_mm[-1])) if lens.prescription.stated_focal_lengths_mm else ""
        else:
            efl = f"{lens.focal_length():.2f}"
            stated = f"{lens.prescription.stated_focal_length_mm:g}" if lens.prescription.stated_focal_length_mm else ""
        efl_x = lens.focal_length(plane="x")
        if abs(efl_x - lens.focal_length()) > 1e-6 * abs(efl_x):
            efl += f" (x {efl_x:.1f})"
        rows.append((name, efl, stated, f"{lens.widest_f_number:.2f}", str(n), str(n * (n - 1) // 2), str(lens.num_zoom_positions)))
    widths = [max(len(row[k]) for row in rows) for k in range(len(rows[0]))]
    return "\n".join("  ".join(cell.ljust(width) for cell, width in zip(row, widths)) for row in rows)


def _lens_info(name: str, zoom: int, top: int) -> str:
    from .optics import rank_ghost_paths

    lens = _load(name, zoom)
    lines = [lens.describe()]
    z_ep, r_ep = lens.entrance_pupil()
    z_xp, r_xp = lens.exit_pupil()
    lines.append(f"  back focal length: {lens.back_focal_length():.3f} mm; sensor at z = {float(lens.sensor_z_mm):.3f} mm")
    lines.append(f"  entrance pupil: z = {z_ep:.2f} mm, radius {r_ep:.2f} mm; exit pupil: z = {z_xp:.2f} mm, radius {r_xp:.2f} mm")
    lines.append(f"  aperture: {'circular' if lens.aperture_blades == 0 else f'{lens.aperture_blades} blades'}, stop surface {lens.stop_index}")
    for note in lens.notes:
        lines.append(f"  note: {note}")
    lines.append("")
    lines.append("  surf  radius mm    thick mm   semi-ap mm  medium after")
    for s, surface in enumerate(lens.prescription.surfaces):
        radius = "flat" if math.isinf(surface.radius_mm) else f"{surface.radius_mm:.4g}"
        glass = lens.media[s]
        medium = "air" if glass is None else f"{glass.catalog}:{glass.name} (n_d {glass.n_d:.4f})"
        flags = (" STOP" if surface.is_stop else "") + (f" {surface.kind}" if surface.kind != "spherical" else "")
        lines.append(f"  {s:>4}  {radius:>10}  {float(lens.thickness_mm[s]):>9.3f}  {float(lens.semi_aperture_mm[s]):>10.3f}  {medium}{flags}")
    lines.append("")
    ranked = rank_ghost_paths(lens)
    lines.append(f"  ghost paths ranked by on-axis Fresnel factor at 550 nm (top {min(top, len(ranked))} of {len(ranked)}):")
    for path, factor in ranked[:top]:
        lines.append(f"    {str(path):>10}  {factor:.3e}")
    return "\n".join(lines)


def _demo(out_dir: str, samples: int | None = None) -> int:
    from .io import bundled_lens_names, save_cross_section
    from .scenes import demo_scene_path

    names = bundled_lens_names()
    print("Bundled lenses:")
    print(_lens_table(names))
    lens = _load("zeiss_biotar" if "zeiss_biotar" in names else names[0])
    png = save_cross_section(lens, os.path.join(out_dir, "cross_section.png"))
    print(f"\nwrote {os.path.abspath(png)}")
    print(f"\nRendering the demo scene {demo_scene_path()}")
    return _render(demo_scene_path(), os.path.join(out_dir, "demo.exr"), None, 0, True, samples, None)


def _render(scene_path: str, output: str, quality, seed: int, png: bool, samples, method, estimator=None) -> int:
    from .rendering import render

    if not output.lower().endswith(".exr"):
        raise ValueError(f"-o/--output must end in .exr, got {output!r}")
    result = render(scene_path, quality=quality, seed=seed, samples=samples, method=method, progress=True, estimator=estimator)
    exr = result.write_exr(output)
    stats = result.statistics
    print(f"wrote {os.path.abspath(exr)}")
    if png:
        preview = result.write_png(os.path.splitext(output)[0] + ".png")
        print(f"wrote {os.path.abspath(preview)}")
    own = [layer["layer"] for layer in stats["layers"]]
    print(
        f"{stats['lens']}: {stats['samples']:,} samples ({stats['sampling']}), {stats['paths_rendered']} paths "
        f"({stats['polynomial_paths']} polynomial, {stats['exact_paths']} exact, {stats['culled_paths']} culled); "
        f"sensor hit rate {100 * stats['sensor_hit_rate']:.1f} % of flare samples"
    )
    print(f"layers: {', '.join(own)}")
    print(
        f"time: {stats['total_seconds']:.1f} s (set-up {stats['setup_seconds']:.1f} s, "
        f"first batch incl. compile {stats['compile_seconds']:.1f} s, render {stats['render_seconds']:.1f} s)"
    )
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="jaxflare", description="Physically based lens flares in JAX.")
    commands = parser.add_subparsers(dest="command", required=True)

    lens = commands.add_parser("lens", help="inspect, plot and convert lenses").add_subparsers(dest="lens_command", required=True)
    lens.add_parser("list", help="bundled lenses")
    info = lens.add_parser("info", help="one lens in detail")
    info.add_argument("name", help="bundled lens name, .toml or .zmx path")
    info.add_argument("--zoom", type=int, default=0, help="zoom position (default 0)")
    info.add_argument("--top", type=int, default=15, help="how many ghost paths to list")
    plot = lens.add_parser("plot", help="cross-section PNG")
    plot.add_argument("name")
    plot.add_argument("-o", "--output", required=True, help="PNG path")
    plot.add_argument("--zoom", type=int, default=0)
    plot.add_argument("--ghost", default="strongest", help="ghost path as J,I, 'strongest' or 'none'")
    convert = lens.add_parser("convert", help="convert between .toml and .zmx")
    convert.add_argument("source")
    convert.add_argument("target")

    render = commands.add_parser("render", help="render a scene's flares to a multi-layer OpenEXR")
    render.add_argument("scene", help="scene TOML file (format: jaxflare/scenes/FORMAT.md), or 'demo'")
    render.add_argument("-o", "--output", required=True, help="output .exr path")
    render.add_argument("--quality", choices=["preview", "production"], default=None, help="default: the scene's [render] quality")
    render.add_argument("--seed", type=int, default=0, help="random seed (default 0); the same seed gives the same image")
    render.add_argument("--png", action="store_true", help="also write a tone-mapped PNG preview beside the EXR")
    render.add_argument("--samples", type=int, default=None, help="total Monte Carlo samples (default: the quality's)")
    render.add_argument("--method", choices=["auto", "polynomial", "exact"], default=None, help="path evaluation (default: the scene's)")
    render.add_argument("--estimator", choices=["monte-carlo", "grid"], default=None, help="monte-carlo or the deterministic grid (default: the scene's)")

    fit = commands.add_parser("fit", help="fit coating colours, dirt and light gains to a plate (package fitting)")
    fit.add_argument("plate", help="plate image: EXR (any layer), 16-bit PNG or TIFF, linear")
    fit.add_argument("--scene", required=True, help="scene TOML that matches the plate")
    fit.add_argument("-o", "--output", required=True, help="fitted parameters .json (dirt map and renders are written beside it)")
    fit.add_argument("--params", default="coatings,dirt", help="comma-separated subset of coatings,dirt,lights (default coatings,dirt)")
    fit.add_argument("--solver", default=None, help="levenberg-marquardt (default), gauss-newton or bfgs")
    fit.add_argument("--layer", default=None, help="EXR layer of the plate (default: the default layer)")
    fit.add_argument("--mask", default=None, help="mask image: 1 where the plate shows flare to fit, 0 to ignore")
    fit.add_argument("--samples", type=int, default=None, help="render samples of the fit's model (default 2^22 with path images, 2^19 with samples)")
    fit.add_argument("--seed", type=int, default=0)
    fit.add_argument("--model", default="auto", help="auto (default), path-images (coatings and lights only) or samples")
    fit.add_argument("--method", default="exact", help="how the model's samples are traced: exact (default), polynomial or auto")
    fit.add_argument("--block", type=int, default=1, help="compare sums over BLOCK x BLOCK pixels (default 1; 4-8 for noisy plates)")
    fit.add_argument("--dirt-resolution", type=int, default=16, help="dirt map cells per side (default 16)")
    fit.add_argument("--max-steps", type=int, default=100)

    demo = commands.add_parser("demo", help="run the demo")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.add_argument("--samples", type=int, default=None, help="render samples (default: the demo scene's preview quality)")
    return parser


def _parse_ghost(text: str):
    if text == "strongest":
        return "strongest"
    if text == "none":
        return None
    try:
        j, i = (int(v) for v in text.split(","))
    except ValueError:
        raise SystemExit(f"jaxflare: --ghost must be J,I (e.g. 5,2), 'strongest' or 'none', got {text!r}") from None
    return (j, i)


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    from .optics import LensFormatError

    try:
        if args.command == "demo":
            return _demo(args.out, args.samples)
        if args.command == "fit":
            return _fit(args)
        if args.command == "render":
            return _render(args.scene, args.output, args.quality, args.seed, args.png, args.samples, args.method, args.estimator)
        if args.lens_command == "list":
            from .io import bundled_lens_names

            print(_lens_table(bundled_lens_names()))
        elif args.lens_command == "info":
            print(_lens_info(args.name, args.zoom, args.top))
        elif args.lens_command == "plot":
            from .io import save_cross_section

            print(save_cross_section(_load(args.name, args.zoom), args.output, ghost_path=_parse_ghost(args.ghost)))
        elif args.lens_command == "convert":
            _convert(args.source, args.target)
        return 0
    except (LensFormatError, FileNotFoundError, ValueError, KeyError) as error:
        message = error.args[0] if isinstance(error, KeyError) and error.args else error
        print(f"jaxflare: error: {message}", file=sys.stderr)
        return 2


def _fit(args) -> int:
    import fitting

    from .scenes import load_scene

    scene = load_scene(args.scene)
    params = tuple(p.strip() for p in args.params.split(",") if p.strip())
    if not args.output.lower().endswith(".json"):
        raise ValueError(f"-o/--output must end in .json, got {args.output!r}")
    plate = fitting.load_plate(args.plate, layer=args.layer, mask=args.mask, expected_size=tuple(scene.camera.resolution))

    def report(step, loss):
        print(f"  step {step:>4}  loss {loss:.6g}", file=sys.stderr)

    result = fitting.fit(
        scene, plate, params=params, solver=args.solver or fitting.DEFAULT_SOLVER, model=args.model, method=args.method, samples=args.samples,
        seed=args.seed, block=args.block, dirt_resolution=args.dirt_resolution, max_steps=args.max_steps, progress=report,
    )
    path = fitting.save_fit(result, args.output)
    print(f"wrote {os.path.abspath(path)}")
    verdict = result.status if result.converged else f"{result.status} (returned the best parameters)"
    print(f"{result.solver} on {result.model} ({result.samples} samples): {verdict}, {result.steps} steps in {result.seconds:.1f} s; "
          f"loss {result.loss_history[0]:.6g} -> {min(result.loss_history):.6g}")
    if result.tint_std is not None:
        observable = result.as_dict()["observable_interfaces"]
        print(f"interfaces the plate determines (tint standard error < {fitting.OBSERVABLE_STD}): {observable or 'none'}")
    return 0 if result.converged else 1


def _convert(source: str, target: str) -> None:
    from .io import lens_toml_text, read_prescription, write_text_atomic

    prescription = read_prescription(source)
    if target.lower().endswith(".zmx"):
        from .io import zmx_text

        write_text_atomic(target, zmx_text(prescription))
    elif target.lower().endswith(".toml"):
        write_text_atomic(target, lens_toml_text(prescription))
    else:
        raise ValueError(f"target must end in .toml or .zmx, got {target!r}")
    print(f"wrote {target}")


if __name__ == "__main__":
    raise SystemExit(main())
