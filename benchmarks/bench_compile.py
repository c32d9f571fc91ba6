"""Cold render: what a fresh process spends compiling before its first Monte Carlo batch.

Usage:  python benchmarks/bench_compile.py [--quick] [--repeats N] [--out DIR]

Each configuration is rendered in a fresh Python process with the persistent compilation cache
off (what a first render, or a test, waits for): a small Biotar scene (128 x 96, one directional
light, 2^14 samples, exact tracing) with and without its core (the light's own image, a second
path set), and the demo scene at 720p (2^19 samples). Recorded per run: the render call's own
seconds and its first batch including compilation (``RenderStatistics``), the process's XLA
backend-compile seconds for the render step and for everything (``jax.monitoring``), and the
number of fused kernels in the compiled render step (each costs compiler time on a CPU). Medians
over ``--repeats`` processes; ``results/compile_times.{csv,json}``.
"""

from __future__ import annotations

import json
import os
import statistics
import subprocess
import sys

from _harness import Outputs, add_out_option, announce, log, make_parser, output_folder, run_meta, shown_paths

CHILD = r"""
import json, sys, time
import jax
import jax.monitoring

compile_seconds = {}
def listener(event, duration, **fields):
    if event.endswith("backend_compile_duration"):
        name = fields.get("fun_name", "?")
        compile_seconds[name] = compile_seconds.get(name, 0.0) + duration
jax.monitoring.register_event_duration_secs_listener(listener)

import dataclasses
import equinox as eqx
import jaxflare as jf
from jaxflare.rendering import empty_accumulators, plan_render, render_step

config = json.loads(sys.argv[1])
if config["scene"] == "demo":
    scene = jf.load_scene("demo")
else:
    scene = jf.Scene(
        camera=jf.Camera(lens="zeiss_biotar", f_number=8.0, resolution=(128, 96), look_at_m=(0.0, 0.0, -10.0)),
        lights=(jf.Light(kind="directional", direction=(0.05, 0.0, -1.0)),),
        render=jf.RenderSettings(core=config["core"]),
    )
started = time.perf_counter()
result = jf.render(scene, samples=config["samples"], method="exact", estimator="monte-carlo", seed=1)
call_seconds = time.perf_counter() - started
during_render = dict(compile_seconds)
plan = plan_render(scene, samples=config["samples"], method="exact", seed=1)
compiled = eqx.filter_jit(render_step).lower(plan.setup, empty_accumulators(plan.setup, plan.layers.count), plan.batch_key(0)).compile()
executable = compiled.compiled  # equinox's Compiled holds jax's
stats = result.statistics
print(json.dumps({
    "render_call_seconds": call_seconds,
    "first_batch_seconds": stats["compile_seconds"],
    "setup_seconds": stats["setup_seconds"],
    "step_compile_seconds": during_render.get("jit(render_step)", 0.0),
    "all_compile_seconds": sum(during_render.values()),
    "step_kernels": executable.as_text().count(" fusion("),
    "path_sets": len(plan.setup.path_sets),
}))
"""

CONFIGS = (
    {"label": "biotar 128x96, flares + core", "scene": "biotar", "core": True, "samples": 2**14},
    {"label": "biotar 128x96, flares only", "scene": "biotar", "core": False, "samples": 2**14},
    {"label": "demo 1280x720, flares + core", "scene": "demo", "core": True, "samples": 2**19},
)
FIELDS = ["label", "runs", "render_call_seconds", "first_batch_seconds", "setup_seconds", "step_compile_seconds", "all_compile_seconds", "step_kernels", "path_sets"]


def run_child(config: dict) -> dict:
    env = dict(os.environ, JAXFLARE_COMPILATION_CACHE="0")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    done = subprocess.run([sys.executable, "-c", CHILD, json.dumps(config)], capture_output=True, text=True, env=env, timeout=1800)
    if done.returncode != 0:
        raise RuntimeError(f"{config['label']}: the child process failed:\n{done.stderr[-3000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "the small scenes once each, into a temporary folder")
    parser.add_argument("--repeats", type=int, default=3, help="fresh processes per configuration (median; default 3)")
    add_out_option(parser, quick_folder=True)
    args = parser.parse_args(argv)
    info, machine = announce("bench_compile", args.quick)
    configs = CONFIGS[:2] if args.quick else CONFIGS
    repeats = 1 if args.quick else max(1, args.repeats)
    rows = []
    for config in configs:
        runs = [run_child(config) for _ in range(repeats)]
        row = {"label": config["label"], "runs": repeats}
        for key in FIELDS[2:]:
            row[key] = statistics.median(run[key] for run in runs)
        rows.append(row)
        log(f"  {row['label']:32s} render call {row['render_call_seconds']:6.2f} s  first batch {row['first_batch_seconds']:6.2f} s  "
            f"step compile {row['step_compile_seconds']:6.2f} s  all compiles {row['all_compile_seconds']:6.2f} s  "
            f"{row['step_kernels']} kernels  ({row['path_sets']} path sets)")
    out = Outputs(output_folder(args, "compile"))
    stem = "compile_times"  # --quick writes into a new temporary folder
    out.csv(f"{stem}.csv", rows, FIELDS, float_format=".3f")
    out.json(f"{stem}.json", {**run_meta("compile", args.quick, {"repeats": repeats, "configs": list(configs)}, info, machine), "rows": rows})
    log(f"wrote {shown_paths(out.written)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
