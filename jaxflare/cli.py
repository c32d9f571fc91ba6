"""The ``jaxflare`` command line.

    jaxflare lens list                      bundled lenses with EFL, f-number, interfaces, ghost paths
    jaxflare lens info NAME [--zoom K]      one lens: data, surfaces, ghost paths ranked by strength
    jaxflare lens plot NAME -o OUT.png      cross-section with primary rays and a ghost path
    jaxflare lens convert IN OUT            any lens file (also .lens, .json, .xml, .dat) to TOML or Zemax .zmx
    jaxflare render SCENE.toml -o OUT.exr   render a scene's flares to a multi-layer EXR (--png: preview)
    jaxflare fit PLATE [PLATE ...] --scene S -o F.json  fit coating colours / dirt / light gains to plates
    jaxflare demo [--out DIR]               the demo: lens table, cross-section, demo scene render

Errors are one line on stderr, ``jaxflare: error: ...``, and exit with status 2 (bad input or
arguments); an unexpected failure is one line ``jaxflare: internal error: ...`` with status 70
(``JAXFLARE_TRACEBACK=1`` shows the traceback). Ctrl-C exits with 130 and a termination signal
(SIGTERM) with 143, one line each, after removing the temporary files of unfinished outputs; a
closed pipe (``jaxflare lens list | head -1``) ends quietly with 141. ``--help`` and the ``lens``
commands that only read and write lens files import no JAX.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import sys
import warnings

from ._limits import MAX_SAMPLES, MAX_SEED

EXIT_ERROR, EXIT_INTERNAL, EXIT_INTERRUPTED, EXIT_PIPE, EXIT_TERMINATED = 2, 70, 130, 141, 143


class _Terminated(BaseException):
    """Raised by the SIGTERM handler, so that unfinished outputs remove their temporary files."""


class _Parser(argparse.ArgumentParser):
    """argparse, but a usage error is one line on stderr (``jaxflare ...: error: ...``), status 2."""

    def error(self, message: str):
        self.exit(EXIT_ERROR, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _int_range(low: int, high: int, what: str):
    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what} must be an integer, got {text!r}") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{what} must be from {low} to {high:,}, got {text}")
        return value

    return parse


def _glass_alias(text: str) -> tuple[str, str]:
    name, sep, target = text.partition("=")
    if not sep or not name.strip() or not target.strip():
        raise argparse.ArgumentTypeError(f"--glass takes NAME=CATALOG:GLASS (e.g. L-TIM28_MOLD=OHARA:L-TIM28), got {text!r}")
    return name.strip(), target.strip()


def _lens_options(args) -> dict:
    options = {}
    if getattr(args, "semi_aperture", None):
        options["semi_aperture"] = args.semi_aperture
    if getattr(args, "glass", None):
        options["glass_aliases"] = dict(args.glass)
    return options


def _load(name: str, zoom: int = 0, options: dict | None = None):
    from .io import load_lens

    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        lens = load_lens(name, zoom, **(options or {}))
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


def _lens_info(name: str, zoom: int, top: int, options: dict | None = None) -> str:
    from .optics import rank_ghost_paths

    lens = _load(name, zoom, options)
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


def _check_output(output: str, extension: str) -> None:
    """Refuse an output path that cannot be written before any work is done."""
    if not output.lower().endswith(extension):
        raise ValueError(f"-o/--output must end in {extension}, got {output!r}")
    if os.path.isdir(output):
        raise ValueError(f"-o/--output {output!r} is a directory; give a file name ending in {extension}")
    folder = os.path.dirname(os.path.abspath(output))
    existing = folder
    while not os.path.exists(existing):
        existing = os.path.dirname(existing)
    if not os.path.isdir(existing):
        raise ValueError(f"-o/--output {output!r}: {existing!r} is a file, so the folder cannot be created")
    if not os.access(existing, os.W_OK | os.X_OK):
        raise ValueError(f"-o/--output {output!r}: the folder {existing!r} is not writable")


def _render(scene_path: str, output: str, quality, seed: int, png: bool, samples, method, estimator=None) -> int:
    from .rendering import render

    _check_output(output, ".exr")
    result = render(scene_path, quality=quality, seed=seed, samples=samples, method=method, progress=True, estimator=estimator)
    written = result.write_files(output, png=png)
    stats = result.statistics
    for path in written:
        print(f"wrote {os.path.abspath(path)}")
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
    parser = _Parser(prog="jaxflare", description="Physically based lens flares in JAX.")
    commands = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    lens = commands.add_parser("lens", help="inspect, plot and convert lenses").add_subparsers(dest="lens_command", required=True, parser_class=_Parser)
    lens.add_parser("list", help="bundled lenses")

    def lens_file_options(command):
        command.add_argument(
            "--semi-aperture", choices=["file", "auto", "diameter", "clip"], default=None,
            help="how to take the file's semi-apertures: as given (file, the default), derived from the stop and the marginal and "
            "chief rays (auto), halved because the column holds diameters (diameter), clipped to the sphere (clip)",
        )
        command.add_argument(
            "--glass", type=_glass_alias, action="append", metavar="NAME=CATALOG:GLASS",
            help="read the glass NAME as a catalog glass (repeatable), e.g. --glass L-TIM28_MOLD=OHARA:L-TIM28",
        )

    info = lens.add_parser("info", help="one lens in detail")
    info.add_argument("name", help="bundled lens name or lens file (.toml, .zmx, .lens, .json, .xml, .dat)")
    info.add_argument("--zoom", type=_int_range(0, 1000, "--zoom"), default=0, help="zoom position (default 0)")
    info.add_argument("--top", type=_int_range(0, 100000, "--top"), default=15, help="how many ghost paths to list")
    lens_file_options(info)
    plot = lens.add_parser("plot", help="cross-section PNG")
    plot.add_argument("name")
    plot.add_argument("-o", "--output", required=True, help="PNG path")
    plot.add_argument("--zoom", type=_int_range(0, 1000, "--zoom"), default=0)
    plot.add_argument("--ghost", default="strongest", help="ghost path as J,I, 'strongest' or 'none'")
    lens_file_options(plot)
    convert = lens.add_parser("convert", help="convert a lens file to the jaxflare TOML format or Zemax .zmx")
    convert.add_argument("source", help="bundled lens name or lens file (.toml, .zmx, .lens, .json, .xml, .dat)")
    convert.add_argument("target", help="output .toml or .zmx")
    lens_file_options(convert)

    render = commands.add_parser("render", help="render a scene's flares to a multi-layer OpenEXR")
    render.add_argument("scene", help="scene TOML file (format: jaxflare/scenes/FORMAT.md), or 'demo'")
    render.add_argument("-o", "--output", required=True, help="output .exr path")
    render.add_argument("--quality", choices=["preview", "production"], default=None, help="default: the scene's [render] quality")
    render.add_argument("--seed", type=_int_range(0, MAX_SEED, "--seed"), default=0, help="random seed 0 .. 2^32-1 (default 0); the same seed gives the same image")
    render.add_argument("--png", action="store_true", help="also write a tone-mapped PNG preview beside the EXR")
    render.add_argument("--samples", type=_int_range(1, MAX_SAMPLES, "--samples"), default=None, help="total Monte Carlo samples, at most 2^32 (default: the quality's)")
    render.add_argument("--method", choices=["auto", "polynomial", "exact"], default=None, help="path evaluation (default: the scene's)")
    render.add_argument("--estimator", choices=["monte-carlo", "grid"], default=None, help="monte-carlo or the deterministic grid (default: the scene's)")

    fit = commands.add_parser("fit", help="fit coating colours, dirt and light gains to a plate (package fitting)")
    fit.add_argument("plate", nargs="+", help="plate image(s): EXR (any layer), 16-bit PNG or TIFF, linear; several plates of one lens are fitted together (shared coatings and dirt, light gains per plate)")
    fit.add_argument("--scene", required=True, action="append", help="scene TOML that matches the plate: once for all plates, or once per plate in their order")
    fit.add_argument("-o", "--output", required=True, help="fitted parameters .json (dirt map and renders are written beside it)")
    fit.add_argument("--params", default="coatings,dirt", help="comma-separated subset of coatings,thin-film,dirt,lights (default coatings,dirt; thin-film fits the coating layers instead of free tints)")
    fit.add_argument("--solver", default=None, help="levenberg-marquardt (default), gauss-newton or bfgs")
    fit.add_argument("--layer", default=None, help="EXR layer of the plate (default: the default layer)")
    fit.add_argument("--mask", default=None, action="append", help="mask image: 1 where the plate shows flare to fit, 0 to ignore (once for all plates, or once per plate)")
    fit.add_argument("--samples", type=_int_range(1, MAX_SAMPLES, "--samples"), default=None, help="Monte Carlo samples of the fit's model (default: the grid model, which has none; given, the model is Monte Carlo: 2^22 path images or 2^19 samples by default)")
    fit.add_argument("--seed", type=_int_range(0, MAX_SEED, "--seed"), default=0)
    fit.add_argument("--model", default="auto", help="auto (default: grid), grid (deterministic ray grid), path-images (Monte Carlo, coatings and lights only) or samples (Monte Carlo)")
    fit.add_argument("--method", default="exact", help="how the model's samples are traced: exact (default), polynomial or auto")
    fit.add_argument("--block", type=_int_range(1, 4096, "--block"), default=None, help="compare sums over BLOCK x BLOCK pixels (default 4 where 4 divides the resolution, else 2, else 1)")
    fit.add_argument("--dirt-resolution", type=_int_range(1, 1024, "--dirt-resolution"), default=16, help="dirt map cells per side (default 16)")
    fit.add_argument("--max-steps", type=_int_range(1, 100000, "--max-steps"), default=100, help="most solver steps (1 to 100000, default 100)")

    demo = commands.add_parser("demo", help="run the demo")
    demo.add_argument("--out", default="out/demo", help="output folder (default out/demo)")
    demo.add_argument("--samples", type=_int_range(1, MAX_SAMPLES, "--samples"), default=None, help="render samples (default: the demo scene's preview quality)")
    return parser


def _parse_ghost(text: str):
    if text == "strongest":
        return "strongest"
    if text == "none":
        return None
    try:
        j, i = (int(v) for v in text.split(","))
    except ValueError:
        raise ValueError(f"--ghost must be J,I (e.g. 5,2), 'strongest' or 'none', got {text!r}") from None
    return (j, i)


def _one_line(error: BaseException) -> str:
    message = error.args[0] if isinstance(error, KeyError) and error.args else str(error)
    return " ".join(str(message).split()) or type(error).__name__


def _on_terminate(signum, frame):
    raise _Terminated()


def main(argv: list[str] | None = None) -> int:
    """Run the command line; returns the exit status (see the module docstring)."""
    interrupted = []

    def on_interrupt(signum, frame):
        interrupted.append(signum)
        raise KeyboardInterrupt

    handlers = {}
    for signum, handler in ((signal.SIGTERM, _on_terminate), (signal.SIGINT, on_interrupt)):
        try:
            handlers[signum] = signal.signal(signum, handler)
        except ValueError:  # not the main thread: leave the signals alone
            pass
    try:
        status = _run(argv)
        if interrupted:  # an interrupt that something below swallowed still ends the command
            raise KeyboardInterrupt
        return status
    except KeyboardInterrupt:
        print("jaxflare: interrupted", file=sys.stderr)
        return EXIT_INTERRUPTED
    except _Terminated:
        print("jaxflare: terminated", file=sys.stderr)
        return EXIT_TERMINATED
    except BrokenPipeError:
        # the reader of our output went away: say nothing, and keep Python from complaining at exit
        try:
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, sys.stdout.fileno())
        except (OSError, ValueError):
            pass
        return EXIT_PIPE
    finally:
        for signum, handler in handlers.items():
            signal.signal(signum, handler)


def _run(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    from .optics import LensFormatError

    if args.command in {"demo", "fit", "render"}:  # compiled programs reused by later processes
        from ._compilation_cache import enable_compilation_cache

        enable_compilation_cache()
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
            print(_lens_info(args.name, args.zoom, args.top, _lens_options(args)))
        elif args.lens_command == "plot":
            from .io import save_cross_section

            print(save_cross_section(_load(args.name, args.zoom, _lens_options(args)), args.output, ghost_path=_parse_ghost(args.ghost)))
        elif args.lens_command == "convert":
            _convert(args.source, args.target, _lens_options(args))
        return 0
    except (LensFormatError, FileNotFoundError, ValueError, KeyError, OSError) as error:
        print(f"jaxflare: error: {_one_line(error)}", file=sys.stderr)
        return EXIT_ERROR
    except (KeyboardInterrupt, _Terminated, BrokenPipeError, SystemExit):
        raise
    except Exception as error:  # a bug: one line, the traceback on request
        if os.environ.get("JAXFLARE_TRACEBACK"):
            raise
        print(f"jaxflare: internal error: {type(error).__name__}: {_one_line(error)} (JAXFLARE_TRACEBACK=1 shows the traceback)", file=sys.stderr)
        return EXIT_INTERNAL


def _fit(args) -> int:
    import fitting

    from .scenes import load_scene

    if len(args.scene) not in (1, len(args.plate)):
        raise ValueError(f"--scene given {len(args.scene)} times for {len(args.plate)} plates: give it once, or once per plate")
    masks = args.mask or [None]
    if len(masks) not in (1, len(args.plate)):
        raise ValueError(f"--mask given {len(masks)} times for {len(args.plate)} plates: give it once, or once per plate")
    scenes = [load_scene(path) for path in args.scene]
    scenes = scenes * len(args.plate) if len(scenes) == 1 else scenes
    masks = masks * len(args.plate) if len(masks) == 1 else masks
    params = tuple(p.strip() for p in args.params.split(",") if p.strip())
    _check_output(args.output, ".json")
    plates = [
        fitting.load_plate(path, layer=args.layer, mask=mask, expected_size=tuple(scene.camera.resolution))
        for path, mask, scene in zip(args.plate, masks, scenes)
    ]

    def report(step, loss):
        print(f"  step {step:>4}  loss {loss:.6g}", file=sys.stderr)

    result = fitting.fit(
        scenes, plates, params=params, solver=args.solver or fitting.DEFAULT_SOLVER, model=args.model, method=args.method, samples=args.samples,
        seed=args.seed, block=args.block, dirt_resolution=args.dirt_resolution, max_steps=args.max_steps, progress=report,
    )
    path = fitting.save_fit(result, args.output)
    print(f"wrote {os.path.abspath(path)}")
    verdict = result.status if result.converged else f"{result.status} (returned the best parameters)"
    width, height = result.model_resolution or (0, 0)
    print(f"{result.solver} on {result.model} ({result.samples} {'grid sub-samples' if result.model == 'grid' else 'samples'}, {width} x {height} pixels, "
          f"block {result.block}): {verdict}, {result.steps} steps in {result.seconds:.1f} s; "
          f"loss {result.loss_history[0]:.6g} -> {min(result.loss_history):.6g}")
    if result.tint_std is not None:
        observable = result.as_dict()["observable_interfaces"]
        print(f"interfaces the plate determines (tint standard error without the prior < {fitting.OBSERVABLE_STD}): {observable or 'none'}")
    for layer in result.coating_layers or ():
        std = layer["thickness_std_nm"]
        print(
            f"  surface {layer['surface']:>3} layer {layer['layer']}: {layer['thickness_nm']:7.1f} nm (start {layer['thickness_start_nm']:.1f}"
            f"{'' if std is None else f', std {std:.2f}'}), n {layer['index']:.4f}{'' if layer['observable'] else '  (not determined by the plate)'}"
        )
    return 0 if result.converged else 1


def _convert(source: str, target: str, options: dict | None = None) -> None:
    from .io import lens_toml_text, read_prescription, write_text_atomic

    lower = target.lower()
    if not lower.endswith((".zmx", ".toml")):
        raise ValueError(f"target must end in .toml or .zmx, got {target!r}")
    prescription = read_prescription(source, **(options or {}))
    if lower.endswith(".zmx"):
        from .io import zmx_text

        write_text_atomic(target, zmx_text(prescription))
    else:
        write_text_atomic(target, lens_toml_text(prescription))
    derived = [k for k, s in enumerate(prescription.surfaces) if math.isnan(s.semi_aperture_mm)]
    if derived:
        print(f"note: the semi-apertures of surfaces {derived} are not in the file: written as 'auto', derived when the lens is loaded", file=sys.stderr)
    print(f"wrote {target}")


if __name__ == "__main__":
    raise SystemExit(main())
