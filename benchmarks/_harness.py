"""What the benchmarks in this folder share; each ``bench_*.py`` keeps only what it measures.

- the command line: :func:`make_parser` (``--quick``), :func:`add_out_option`, :func:`add_stem_option`,
  :func:`output_folder`, :func:`quick_stem`;
- the machine header: :func:`machine_info`, :func:`machine_string`, :func:`load_average`,
  :func:`announce`, and :func:`run_meta` (the first keys of every results JSON);
- JSON helpers: :func:`_json_default`, :func:`_finite_or_null`, :func:`json_text` (strict JSON,
  NaN and infinities as null);
- timing: :func:`timed` (median of repeated calls), :func:`blocked`;
- atomic output: :class:`Outputs` (CSV, JSON and PNG files in one folder, each written to a temporary
  file and renamed over the target with :mod:`jaxflare.io`'s writers), :func:`csv_text`;
- charts (matplotlib, Agg): :func:`pyplot`, :func:`save_figure`, :func:`cpu_label`;
- running: :data:`log`, :class:`GuardedSteps` (one failed part does not lose the others),
  :func:`temporary_env`, :func:`shown_paths`, :func:`fmt`;
- render measurements (``bench_render.py``, ``bench_sampling.py``): :func:`render_once`,
  :func:`with_resolution`, :func:`seed_noise`, :func:`sq_norm`, :func:`relative`, :func:`median`.

A sibling module, not a package: a script run as ``python benchmarks/bench_x.py`` (or through
``run_all.py``) has this folder first on ``sys.path``, so ``from _harness import ...`` needs no path
edits. Only the public API of jaxflare is used.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import functools
import io
import json
import math
import os
import platform
import statistics
import tempfile
import time
import traceback
import warnings
from collections.abc import Callable, Iterable
from pathlib import Path

import numpy as np

from jaxflare.io import atomic_output_path, write_text_atomic

HERE = Path(__file__).resolve().parent
REPO = HERE.parent
DEFAULT_OUT = HERE / "results"

log = functools.partial(print, flush=True)
"""``print`` that flushes: the benchmarks' progress lines."""


# --------------------------------------------------------------------------- command line


def make_parser(doc: str, quick_help: str) -> argparse.ArgumentParser:
    """A benchmark's parser: its docstring's first line as the description, and ``--quick``."""
    parser = argparse.ArgumentParser(description=doc.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help=quick_help)
    return parser


def add_out_option(parser: argparse.ArgumentParser, *, quick_folder: bool) -> None:
    """``--out DIR``. ``quick_folder``: without ``--out``, ``--quick`` writes into a new temporary
    folder (see :func:`output_folder`); else the default is ``benchmarks/results`` in both modes."""
    if quick_folder:
        text = "output folder (default benchmarks/results; --quick: a new temporary folder)"
        parser.add_argument("--out", type=Path, help=text)
    else:
        parser.add_argument("--out", type=Path, default=DEFAULT_OUT, help="output folder (default benchmarks/results)")


def add_stem_option(parser: argparse.ArgumentParser, help_text: str) -> None:
    parser.add_argument("--stem", help=help_text)


def output_folder(args: argparse.Namespace, name: str) -> Path:
    """``--out``, else a new temporary folder with ``--quick`` (never ``benchmarks/results``), else
    ``benchmarks/results``; created."""
    out_dir = args.out or (Path(tempfile.mkdtemp(prefix=f"jaxflare_bench_{name}_quick_")) if args.quick else DEFAULT_OUT)
    out_dir.mkdir(parents=True, exist_ok=True)
    return out_dir


def quick_stem(args: argparse.Namespace, stem: str) -> str:
    """``--stem``, else ``stem`` (``stem_quick`` with ``--quick``: a smoke test does not overwrite the full results)."""
    return args.stem or (stem + "_quick" if args.quick else stem)


# --------------------------------------------------------------------------- the machine


def machine_info() -> dict:
    import jax

    info = {
        "platform": platform.platform(),
        "machine": platform.machine(),
        "processor": platform.processor() or "n/a",
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "jax": jax.__version__,
        "jax_backend": jax.default_backend(),
        "jax_devices": [str(d) for d in jax.devices()],
        "jax_x64": bool(jax.config.jax_enable_x64),
        "numpy": np.__version__,
    }
    try:
        import jaxlib

        info["jaxlib"] = jaxlib.__version__
    except Exception:  # pragma: no cover
        pass
    try:
        sched = os.sched_getaffinity(0)
        info["usable_cpus"] = len(sched)
    except AttributeError:  # pragma: no cover
        pass
    try:
        with open("/proc/cpuinfo") as handle:
            for line in handle:
                if line.startswith("model name"):
                    info["cpu_model"] = line.split(":", 1)[1].strip()
                    break
    except OSError:
        pass
    return info


def load_average() -> float | None:
    try:
        return round(os.getloadavg()[0], 2)
    except (AttributeError, OSError):
        return None


def machine_string(info: dict) -> str:
    return (
        f"{info.get('cpu_model', info['processor'])}; {info['cpu_count']} CPUs; {info['platform']}; "
        f"python {info['python']}; jax {info['jax']} ({info['jax_backend']})"
    )


def usable_cpus(info: dict) -> int:
    return info.get("usable_cpus") or info["cpu_count"] or 1


def announce(name: str, quick: bool, log=log) -> tuple[dict, str]:
    """Print a benchmark's header (machine, devices, a warning when the CPUs are already busy)
    and return the machine description (dict, with ``load_average_start``, and one line)."""
    info = machine_info()
    machine = machine_string(info)
    info["load_average_start"] = load_average()
    log(f"{name} ({'quick' if quick else 'full'}): {machine}")
    log(f"  devices: {', '.join(info['jax_devices'])}")
    cpus = usable_cpus(info)
    if info["load_average_start"] is not None and info["load_average_start"] > 0.25 * cpus:
        log(f"  WARNING: 1-minute load average {info['load_average_start']:.2f} on {cpus} CPUs: "
            "timings will be pessimistic and noisy")
    return info, machine


def run_meta(benchmark: str | None, quick: bool, cfg: dict, info: dict, machine: str, *, after_config: dict | None = None,
             **extra) -> dict:
    """The head of a results JSON: benchmark (unless None), mode, creation time, configuration
    (then ``after_config``), machine (``info``, given ``load_average_end`` now), jaxflare version,
    then ``extra`` in order."""
    import jaxflare

    info["load_average_end"] = load_average()
    meta = {} if benchmark is None else {"benchmark": benchmark}
    meta.update({"mode": "quick" if quick else "full", "created_unix": time.time(),
                 "created": time.strftime("%Y-%m-%d %H:%M:%S %Z"), "config": cfg})
    meta.update(after_config or {})
    meta.update({"machine": info, "machine_string": machine, "jaxflare_version": getattr(jaxflare, "__version__", "unknown")})
    meta.update(extra)
    return meta


# --------------------------------------------------------------------------- JSON


def _finite_or_null(value):
    """Strict JSON: NaN and infinities become null."""
    if isinstance(value, dict):
        return {k: _finite_or_null(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_null(v) for v in value]
    if isinstance(value, (float, np.floating)) and not math.isfinite(float(value)):
        return None
    return value


def _json_default(value):
    if isinstance(value, (np.floating, np.integer)):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    return str(value)


def json_text(payload) -> str:
    """``payload`` as strict, indented JSON (NumPy values as numbers and lists, paths and other
    objects as strings, NaN and infinities as null, also inside arrays), with a final newline."""
    plain = json.loads(json.dumps(payload, default=_json_default))
    return json.dumps(_finite_or_null(plain), indent=1, allow_nan=False) + "\n"


# --------------------------------------------------------------------------- timing


def timed(fn: Callable, repeats: int):
    """(median seconds, all times, last result) of ``repeats`` calls of ``fn`` (which blocks)."""
    times, result = [], None
    for _ in range(max(repeats, 1)):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times), times, result


def blocked(fn: Callable) -> Callable:
    """``fn`` that waits for its result (``jax.block_until_ready``): for :func:`timed`."""
    import jax

    return lambda: jax.block_until_ready(fn())


# --------------------------------------------------------------------------- output files


def csv_text(rows: Iterable[dict], fields: list[str], *, float_format: str | None = None, blank_nonfinite: bool = False) -> str:
    """CSV of ``fields`` (missing keys empty). ``float_format`` (e.g. ``".6g"``): how Python floats
    are written (else ``str``); ``blank_nonfinite``: NaN and infinities as empty cells."""
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for r in rows:
        out = {}
        for k in fields:
            value = r.get(k)
            if float_format is not None and isinstance(value, float):
                value = "" if blank_nonfinite and not math.isfinite(value) else format(value, float_format)
            out[k] = value
        writer.writerow(out)
    return buffer.getvalue()


class Outputs:
    """A benchmark's result files in one folder, each written atomically (a temporary file beside
    the target renamed over it: a reader never sees half a file); ``written`` lists them in order."""

    def __init__(self, folder: Path, log=log):
        self.folder = Path(folder)
        self.log = log
        self.written: list[Path] = []

    def text(self, name: str, text: str) -> Path:
        path = self.folder / name
        write_text_atomic(path, text)
        self.written.append(path)
        return path

    def csv(self, name: str, rows: Iterable[dict], fields: list[str], **options) -> Path:
        """See :func:`csv_text` for the options."""
        return self.text(name, csv_text(rows, fields, **options))

    def json(self, name: str, payload) -> Path:
        return self.text(name, json_text(payload))

    def chart(self, name: str, draw: Callable, *args, dpi: int = 110) -> Path | None:
        """``draw(*args)`` returns a matplotlib figure, saved as PNG. A failure is logged, not
        raised: a chart must not lose the numbers."""
        path = self.folder / name
        try:
            save_figure(draw(*args), path, dpi=dpi)
        except Exception as error:
            self.log(f"chart {name} not written: {type(error).__name__}: {error}")
            traceback.print_exc()
            return None
        self.written.append(path)
        return path


def shown_paths(paths: Iterable[Path]) -> str:
    """The paths, relative to the repository where they lie in it, comma-separated."""
    return ", ".join(str(p.relative_to(REPO)) if p.is_relative_to(REPO) else str(p) for p in paths)


# --------------------------------------------------------------------------- charts


def pyplot():
    """``matplotlib.pyplot`` on the Agg backend (no display)."""
    import matplotlib

    matplotlib.use("Agg", force=True)
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: Path, dpi: int = 110) -> None:
    """Save ``fig`` as PNG atomically, then close it."""
    import matplotlib.pyplot as plt

    try:
        with atomic_output_path(path) as temporary:
            fig.savefig(temporary, format="png", dpi=dpi)
    finally:
        plt.close(fig)


def cpu_label(machine: dict) -> str:
    """``"<CPU model>, <n> CPUs"`` of a :func:`machine_info` dict, for chart titles."""
    return f"{machine.get('cpu_model', machine.get('processor'))}, {machine.get('cpu_count')} CPUs"


# --------------------------------------------------------------------------- running


class GuardedSteps:
    """Mixin: :meth:`step` runs one part of a benchmark; a failure is logged and noted in
    ``self.skipped`` (the subclass sets ``skipped`` and ``log``), and the other parts still run."""

    skipped: list[str]

    def step(self, name: str, fn: Callable, *args) -> None:
        try:
            fn(*args)
        except Exception as error:  # noqa: BLE001  (one failed part must not lose the others)
            self.skipped.append(f"{name} failed: {type(error).__name__}: {error}")
            self.log(f"\nnote: {self.skipped[-1]}")
            traceback.print_exc()


@contextlib.contextmanager
def temporary_env(name: str, value: str):
    """Set environment variable ``name`` inside the block, then restore it (or remove it)."""
    previous = os.environ.get(name)
    os.environ[name] = value
    try:
        yield
    finally:
        if previous is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = previous


def fmt(value, spec: str, missing: str = "-") -> str:
    """``format(value, spec)`` for a finite number, else ``missing`` right-aligned to the width."""
    if isinstance(value, (int, float)) and math.isfinite(value):
        return format(value, spec)
    width = "".join(ch for ch in spec.split(".")[0] if ch.isdigit())
    return missing.rjust(int(width) if width else 0)


# --------------------------------------------------------------------------- render measurements

STAT_KEYS = ("render_seconds", "compile_seconds", "setup_seconds", "total_seconds", "samples", "sensor_hit_rate",
             "exact_paths", "polynomial_paths", "paths_rendered", "batches", "unevaluated_fraction")
"""The render statistics every :func:`render_once` record keeps."""


def step_traces() -> int:
    """How often the render step has been traced (compiled) in this process."""
    import equinox as eqx

    from jaxflare.rendering import render_step

    return eqx.debug.get_num_traces(render_step)


def with_resolution(scene, resolution):
    return dataclasses.replace(scene, camera=dataclasses.replace(scene.camera, resolution=tuple(resolution)))


def render_once(scene, log, label: str, **kwargs):
    """One timed ``jaxflare.render``: (record, flare RGB float32 (H, W, 3), result)."""
    import jaxflare

    traces = step_traces()
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        t0 = time.perf_counter()
        result = jaxflare.render(scene, **kwargs)
        wall = time.perf_counter() - t0
    stats = result.statistics
    record = {"label": label, "wall_seconds": wall, **{k: stats.get(k) for k in STAT_KEYS},
              "step_traces": step_traces() - traces, "seed": kwargs.get("seed", 0),
              "resolution": "x".join(map(str, stats["resolution"])), "warnings": [str(w.message) for w in caught]}
    flare = np.array(result.image[..., :3], np.float32)
    log(f"  {label:34s} {record['samples']:>10d} samples  wall {wall:8.2f} s  (render {record['render_seconds']:7.2f}, "
        f"compile/first batch {record['compile_seconds']:6.2f}, set-up {record['setup_seconds']:6.2f})  hit rate "
        f"{record['sensor_hit_rate']:.4f}" + (f"  traced step x{record['step_traces']}" if record["step_traces"] else ""))
    for message in record["warnings"]:
        log(f"    warning: {message}")
    return record, flare, result


def sq_norm(x) -> float:
    return float(np.sum(np.square(np.asarray(x, np.float64))))


def relative(sigma2: float, mu2: float) -> float:
    return math.sqrt(sigma2 / mu2) if mu2 > 0 and sigma2 >= 0 else float("nan")


def seed_noise(images: list[np.ndarray]) -> dict:
    """Per-render noise variance (whole-image squared norm), noise-free squared norm and relative
    RMSE from k >= 2 independent renders of the same configuration."""
    k = len(images)
    mean = np.mean([np.asarray(a, np.float64) for a in images], axis=0)
    sigma2 = sum(sq_norm(np.asarray(a, np.float64) - mean) for a in images) / (k - 1)
    mu2 = sq_norm(mean) - sigma2 / k
    return {"renders": k, "sigma2": sigma2, "mu2": mu2, "relative_rmse": relative(sigma2, mu2)}


def median(records: list[dict], key: str) -> float:
    values = [r[key] for r in records if r.get(key) is not None]
    return statistics.median(values) if values else float("nan")
