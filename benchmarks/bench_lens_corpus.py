"""Load rate of real lens files: how many of a folder's lens files jaxflare reads and builds.

Run:  python benchmarks/bench_lens_corpus.py [--quick] [--corpus DIR ...] [--out DIR] [--stem NAME]

Every ``.zmx``, ``.toml``, ``.lens``, ``.json``, ``.xml`` and ``.dat`` file under the corpus folders
(default, and with ``--quick``: ``tests/data``; point ``--corpus`` at a larger local collection, e.g.
the lens folders of flaresim, realflare, lentil, OpenLensFlare, pbrt-v4-scenes and public ``.zmx``
files) is loaded with :func:`jaxflare.load_lens`, first with the file's own semi-apertures
(``semi_aperture="file"``) and, where that fails, with ``semi_aperture="auto"``. A lentil database
(a JSON of lenses by id) counts every lens in it (``lenses.json#ID``). Each attempt ends as

- ``loaded``: the lens built; its paraxial EFL is compared with the focal length the file states;
- ``refused``: a :class:`jaxflare.LensFormatError` / ``FileNotFoundError`` / ``ValueError`` with a
  one-line message (what the file holds that jaxflare cannot model, or bad data);
- ``crashed``: any other exception (a bug: it should have been a clear error).

The same script runs against an older checkout (put it first on ``PYTHONPATH``): an API without
``semi_aperture`` is called without it, so before/after load rates come from one script.
Outputs (atomic): ``lens_corpus.{json,csv}`` in ``benchmarks/results`` (``--quick``: a temporary
folder), with the machine header; per file: format, outcome per mode, message, EFL and stated EFL.
"""

from __future__ import annotations

import json
import math
import time
import warnings
from collections import Counter
from pathlib import Path

from _harness import (
    REPO,
    Outputs,
    add_out_option,
    add_stem_option,
    announce,
    log,
    make_parser,
    output_folder,
    quick_stem,
    run_meta,
    shown_paths,
)

import jaxflare

STEM = "lens_corpus"
EXTENSIONS = (".zmx", ".toml", ".lens", ".json", ".xml", ".dat")


def corpus_entries(folders: list[Path]) -> list[tuple[str, str]]:
    """(format, source) for every lens file under ``folders``; one entry per lens of a lentil database."""
    entries = []
    for folder in folders:
        for path in sorted(p for p in Path(folder).rglob("*") if p.is_file() and p.suffix.lower() in EXTENSIONS):
            suffix = path.suffix.lower()
            if suffix == ".json":
                try:
                    data = json.loads(path.read_text(encoding="utf-8"))
                except (OSError, ValueError, UnicodeDecodeError):
                    data = None
                if isinstance(data, dict) and "lens_elements" not in data and all(isinstance(v, dict) for v in data.values()) and data:
                    entries.extend(("lentil .json", f"{path}#{key}") for key in sorted(data))
                    continue
                entries.append(("realflare .json" if isinstance(data, dict) and "lens_elements" in data else ".json", str(path)))
            else:
                entries.append((suffix, str(path)))
    return entries


def attempt(source: str, mode: str) -> dict:
    started = time.perf_counter()
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            try:
                lens = jaxflare.load_lens(source, semi_aperture=mode)
            except TypeError as error:
                if "semi_aperture" not in str(error):
                    raise
                if mode != "file":
                    return {"outcome": "n/a", "message": "this version has no semi_aperture option"}
                lens = jaxflare.load_lens(source)
        efl = float(lens.focal_length(plane=getattr(lens.prescription, "stated_focal_length_plane", "y")))
        stated = lens.prescription.stated_focal_length_mm
        return {
            "outcome": "loaded", "efl_mm": efl, "stated_efl_mm": stated,
            "efl_error": abs(abs(efl) - stated) / stated if stated else None, "seconds": time.perf_counter() - started,
        }
    except (jaxflare.LensFormatError, FileNotFoundError, ValueError) as error:
        message = str(error)
        return {"outcome": "refused" if "\n" not in message else "refused (multi-line)", "message": message.split("\n")[0][:300]}
    except Exception as error:  # noqa: BLE001 - a crash: should have been a clear error
        return {"outcome": "crashed", "message": f"{type(error).__name__}: {error}"[:300]}


def main(argv: list[str] | None = None) -> int:
    parser = make_parser(__doc__, "tests/data only (a few seconds per file)")
    parser.add_argument("--corpus", type=Path, nargs="+", default=None, help="folders of lens files (default tests/data)")
    add_out_option(parser, quick_folder=True)
    add_stem_option(parser, "output file stem (default lens_corpus)")
    args = parser.parse_args(argv)
    info, machine = announce("lens corpus load rate", args.quick)
    folders = args.corpus or [REPO / "tests" / "data"]
    entries = corpus_entries(folders)
    log(f"  {len(entries)} lens entries under {', '.join(str(f) for f in folders)}")
    rows = []
    for k, (kind, source) in enumerate(entries):
        first = attempt(source, "file")
        second = attempt(source, "auto") if first["outcome"] != "loaded" else first
        rows.append({"format": kind, "source": source, "file": first, "auto": second})
        if (k + 1) % 100 == 0:
            log(f"  {k + 1} / {len(entries)}")
    by_format: dict[str, dict] = {}
    for row in rows:
        summary = by_format.setdefault(row["format"], {"files": 0, "loaded_file": 0, "loaded_auto": 0, "refused": 0, "crashed": 0, "efl_within_1pct": 0, "efl_stated": 0})
        summary["files"] += 1
        summary["loaded_file"] += row["file"]["outcome"] == "loaded"
        final = row["auto"] if row["auto"]["outcome"] == "loaded" else row["file"]
        summary["loaded_auto"] += final["outcome"] == "loaded"
        summary["refused"] += final["outcome"].startswith("refused")
        summary["crashed"] += "crashed" in (row["file"]["outcome"], row["auto"]["outcome"])
        if final["outcome"] == "loaded" and final.get("efl_error") is not None:
            summary["efl_stated"] += 1
            summary["efl_within_1pct"] += final["efl_error"] <= 0.01
    for kind, summary in sorted(by_format.items()):
        log(
            f"  {kind:>16}: {summary['files']:>5} files, loaded {summary['loaded_file']:>5} as given, {summary['loaded_auto']:>5} with "
            f"semi_aperture='auto' where needed; refused {summary['refused']}, crashed {summary['crashed']}; EFL within 1 % of the stated "
            f"value: {summary['efl_within_1pct']} of {summary['efl_stated']}"
        )
    reasons = Counter(
        (row["auto"] if row["auto"]["outcome"] != "n/a" else row["file"]).get("message", "").split(": ")[-1][:90]
        for row in rows if "loaded" not in (row["file"]["outcome"], row["auto"]["outcome"])
    )
    for message, count in reasons.most_common(12):
        log(f"    {count:>4} x {message}")
    out = Outputs(output_folder(args, STEM))
    stem = quick_stem(args, STEM)
    cfg = {"corpus": [str(f) for f in folders], "modes": ["file", "auto"]}
    out.json(f"{stem}.json", {**run_meta("lens_corpus", args.quick, cfg, info, machine), "summary": by_format, "files": rows})
    flat = [
        {"format": r["format"], "source": r["source"], "file": r["file"]["outcome"], "auto": r["auto"]["outcome"],
         "efl_mm": (r["auto"] if r["auto"]["outcome"] == "loaded" else r["file"]).get("efl_mm", math.nan),
         "stated_efl_mm": (r["auto"] if r["auto"]["outcome"] == "loaded" else r["file"]).get("stated_efl_mm") or math.nan,
         "message": (r["auto"] if r["auto"]["outcome"] != "loaded" else r["file"]).get("message", "")}
        for r in rows
    ]
    out.csv(f"{stem}.csv", flat, ["format", "source", "file", "auto", "efl_mm", "stated_efl_mm", "message"], float_format=".4f", blank_nonfinite=True)
    log(f"wrote {shown_paths(out.written)}")
    crashed = sum(s["crashed"] for s in by_format.values())
    return 1 if crashed else 0


if __name__ == "__main__":
    raise SystemExit(main())
