"""Run every benchmark in this folder: each ``bench_*.py`` module's ``main(argv)``.

Usage:  python benchmarks/run_all.py [--quick] [--only NAME ...] [--list] [-- extra args for every benchmark]

Benchmarks (``--only`` takes the name with or without ``bench_``): ``compile`` (what a cold render
spends compiling: render call, XLA compile seconds and kernels of the render step), ``fitting`` (plate-fitting solvers:
recovered coatings and dirt against wall time on synthetic plates), ``plate_fits`` (the table of
grid-model fits on a Zemax double Gauss the tests do not fit: coatings, thin film, coatings + dirt
from three plates), ``polynomial`` (path-system error
against throughput), ``render`` (demo-scene render times and noise against the paper's budgets),
``sampling`` (noise against time per sampling mode; time saved and error of each modelling
shortcut), ``trace`` (exact-trace throughput against optiland).

Convention for a benchmark module ``benchmarks/bench_<name>.py``:

- it defines ``main(argv: list[str] | None = None) -> int | None`` that parses its own arguments with
  argparse and accepts at least ``--quick`` (a smoke-test run well under a minute);
- importing it does no work (heavy imports may happen at import time, measurements must not);
- it writes its results under ``benchmarks/results/`` atomically (temporary file + ``os.replace``); with
  ``--quick`` it must not overwrite the full results (``bench_trace``/``bench_polynomial`` write ``*_quick.*``,
  ``bench_render``, ``bench_sampling`` and ``bench_fitting`` write into a new temporary folder and print where);
- it returns 0 (or None) on success and a non-zero code on failure;
- what it shares with the others (command-line pieces, machine header, JSON/CSV/PNG writers, chart and
  timing helpers, render measurements) it imports from the sibling module ``_harness``, never from
  another benchmark, and it uses only jaxflare's public API. This folder is first on ``sys.path`` when
  a script in it is run (``python benchmarks/run_all.py`` or ``python benchmarks/bench_x.py``), so
  ``from _harness import ...`` needs no path edits.

Benchmarks run in this process one after another, in file-name order; a failure (non-zero return or an
exception) is reported and the remaining benchmarks still run. The exit code is non-zero if any failed.
"""

from __future__ import annotations

import argparse
import importlib.util
import sys
import time
import traceback
from pathlib import Path

HERE = Path(__file__).resolve().parent


def discover() -> list[Path]:
    return sorted(p for p in HERE.glob("bench_*.py") if p.is_file())


def load(path: Path):
    name = f"benchmarks_{path.stem}"
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    passthrough: list[str] = []
    if "--" in argv:
        cut = argv.index("--")
        argv, passthrough = argv[:cut], argv[cut + 1 :]
    parser = argparse.ArgumentParser(description="Run every benchmarks/bench_*.py module's main().")
    parser.add_argument("--quick", action="store_true", help="pass --quick to every benchmark (smoke test)")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run only these benchmarks (e.g. trace or bench_trace)")
    parser.add_argument("--list", action="store_true", help="list the benchmarks and exit")
    args = parser.parse_args(argv)

    benches = discover()
    if args.only:
        wanted = {name if name.startswith("bench_") else f"bench_{name}" for name in args.only}
        wanted = {name[:-3] if name.endswith(".py") else name for name in wanted}
        unknown = wanted - {p.stem for p in benches}
        if unknown:
            print(f"run_all: unknown benchmark(s) {', '.join(sorted(unknown))}; have {', '.join(p.stem for p in benches)}")
            return 2
        benches = [p for p in benches if p.stem in wanted]
    if args.list:
        for path in benches:
            print(path.stem)
        return 0
    if not benches:
        print("run_all: no benchmarks/bench_*.py found")
        return 1

    bench_argv = (["--quick"] if args.quick else []) + passthrough
    outcomes: list[tuple[str, str, float]] = []
    for path in benches:
        print(f"\n{'=' * 20} {path.stem} {' '.join(bench_argv)} {'=' * 20}", flush=True)
        started = time.perf_counter()
        try:
            module = load(path)
            entry = getattr(module, "main", None)
            if not callable(entry):
                raise AttributeError(f"{path.name} has no main(argv) function")
            code = entry(list(bench_argv))
            status = "ok" if code in (0, None) else f"failed (exit code {code})"
        except SystemExit as exit_:  # argparse errors and explicit sys.exit inside main
            status = "ok" if exit_.code in (0, None) else f"failed (SystemExit {exit_.code})"
        except Exception:
            traceback.print_exc()
            status = "failed (exception)"
        outcomes.append((path.stem, status, time.perf_counter() - started))

    print("\nbenchmark summary:")
    for name, status, seconds in outcomes:
        print(f"  {name:24s} {status:28s} {seconds:8.1f} s")
    return 0 if all(status == "ok" for _, status, _ in outcomes) else 1


if __name__ == "__main__":
    sys.exit(main())
