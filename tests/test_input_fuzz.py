"""Issue 17: a seeded fuzzer over the three kinds of input people hand us (lens TOML, Zemax .zmx,
scene TOML). Each mutant of a valid file (a number swapped for an extreme or a wrong type, a line
dropped, doubled or swapped, the file cut short, stray bytes) either loads into something finite
and physical, or is refused with a one-line ``ValueError`` (LensFormatError, SceneError) that
names the file; never another exception (a traceback on the command line), never a hang (an
alarm bounds each input). The specific cases the issue lists are pinned by the tests of each
reader (tests/scenes/test_scene.py, tests/cli/test_cli_errors.py) and by
test_listed_lens_defects_are_refused below."""

from __future__ import annotations

import math
import re
import signal
import warnings
from pathlib import Path

import numpy as np
import pytest

import jaxflare
from jaxflare.scenes import camera_lens
from tests.helpers import DATA

ROOT = Path(__file__).resolve().parents[1]
SECONDS_PER_INPUT = 20  # far above any real load (< 1 s); only a hang reaches it
NUMBER = re.compile(rb"(?<![A-Za-z_])-?\d+(?:\.\d+)?(?:[eE][-+]?\d+)?")
TOML_VALUES = [b"1e30", b"-1e30", b"nan", b"inf", b"-inf", b"0", b"-0.5", b"1e-30", str(2**70).encode(), b'"text"', b"[1, 2]", b"{}", b"true", b"[]"]
JSON_VALUES = [b"1e30", b"-1e30", b"0", b"-0.5", b"1e-30", b"1e400", str(2**70).encode(), b'"text"', b"[1, 2]", b"{}", b"true", b"null", b"[]"]
ZMX_VALUES = [b"1e30", b"-1e30", b"nan", b"inf", b"0", b"-1", b"1e400", b"x", b"", str(2**70).encode(), b"0.5"]


def mutants(data: bytes, values: list[bytes], count: int, seed: int) -> list[tuple[str, bytes]]:
    """``count`` deterministic mutants of ``data``: (what was done, bytes)."""
    rng = np.random.default_rng(seed)
    numbers = list(NUMBER.finditer(data))
    out = []
    for k in range(count):
        lines = data.split(b"\n")
        kind = k % 6
        if kind in (0, 1):  # the most common mistake: a wrong value
            match = numbers[rng.integers(len(numbers))]
            value = values[rng.integers(len(values))]
            out.append((f"value {match.group().decode()} at byte {match.start()} -> {value.decode()}", data[: match.start()] + value + data[match.end() :]))
        elif kind == 2:
            i = int(rng.integers(len(lines)))
            out.append((f"line {i + 1} dropped", b"\n".join(lines[:i] + lines[i + 1 :])))
        elif kind == 3:
            i = int(rng.integers(len(lines)))
            out.append((f"line {i + 1} doubled", b"\n".join(lines[: i + 1] + lines[i:])))
        elif kind == 4:
            cut = int(rng.integers(1, len(data)))
            out.append((f"cut at byte {cut}", data[:cut]))
        else:
            at = int(rng.integers(len(data)))
            noise = bytes(rng.choice([0x00, 0xFF, 0xE9, 0x80, 0x22, 0x5B, 0x0A], size=int(rng.integers(1, 4))))
            out.append((f"bytes {noise!r} at {at}", data[:at] + noise + data[at:]))
    return out


class Hang(Exception):
    pass


def bounded(function, *args):
    def alarm(signum, frame):
        raise Hang

    previous = signal.signal(signal.SIGALRM, alarm)
    signal.alarm(SECONDS_PER_INPUT)
    try:
        return function(*args)
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, previous)


def check_outcome(load, path: Path, what: str):
    """``load(path)``; a refusal must be a one-line ValueError naming the file."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return bounded(load, path)
    except Hang:
        pytest.fail(f"{what}: no answer within {SECONDS_PER_INPUT} s")
    except ValueError as error:
        message = str(error)
        assert "\n" not in message and path.name in message, f"{what}: {message!r}"
        return None
    except Exception as error:  # noqa: BLE001 - anything else is a traceback on the command line
        pytest.fail(f"{what}: {type(error).__name__}: {error}")


def check_lens(lens, what: str):
    """A lens that loaded is physical: finite focal length, finite positive apertures."""
    efl = float(lens.focal_length())
    assert math.isfinite(efl) and efl != 0, what
    semi = np.asarray(lens.semi_aperture_mm, np.float64)
    assert np.all(np.isfinite(semi)) and np.all(semi > 0), what
    assert lens.num_interfaces >= 1


@pytest.mark.parametrize(
    "source, values, count",
    [(ROOT / "lenses" / "zeiss_biotar.toml", TOML_VALUES, 48), (DATA / "zmx" / "double_gauss_50mm.zmx", ZMX_VALUES, 48),
        (DATA / "lens" / "Zeiss_100mm_F4.5_Tessar.lens", ZMX_VALUES, 24),
        (DATA / "realflare" / "kodak_100mm.json", JSON_VALUES, 24),
        (DATA / "openlensflare" / "heliar-tronnier.xml", ZMX_VALUES, 24),
        (DATA / "pbrt" / "tronnier_double_gauss.50mm.dat", ZMX_VALUES, 24),
    ],
    ids=["lens-toml", "zmx", "flaresim-lens", "realflare-json", "openlensflare-xml", "pbrt-dat"],
)
def test_lens_mutants_load_or_are_refused_cleanly(tmp_path, source, values, count):
    loaded = refused = 0
    for n, (what, data) in enumerate(mutants(source.read_bytes(), values, count, seed=17)):
        path = tmp_path / f"mutant{n}{source.suffix}"
        path.write_bytes(data)
        lens = check_outcome(jaxflare.load_lens, path, what)
        if lens is None:
            refused += 1
        else:
            loaded += 1
            check_lens(lens, what)
    assert refused > 0 and loaded > 0  # the fuzzer reaches both outcomes


def test_scene_mutants_load_or_are_refused_cleanly(tmp_path):
    source = ROOT / "jaxflare" / "scenes" / "demo.toml"
    loaded = refused = 0
    for n, (what, data) in enumerate(mutants(source.read_bytes(), TOML_VALUES, 60, seed=23)):
        path = tmp_path / f"scene{n}.toml"
        path.write_bytes(data)
        scene = check_outcome(jaxflare.load_scene, path, what)
        if scene is None:
            refused += 1
            continue
        try:
            lens = bounded(camera_lens, scene.camera)
        except ValueError as error:  # refused once the lens is known (focus, f-number): names the key
            assert "\n" not in str(error) and re.match(r"camera\.\w+", str(error)), f"{what}: {error}"
            refused += 1
            continue
        loaded += 1
        check_lens(lens, what)
        last_vertex = float(np.sum(np.asarray(lens.thickness_mm)[:-1]))
        assert float(lens.sensor_z_mm) > last_vertex - 1e-6, f"{what}: the sensor is in front of the lens"
    assert refused > 0 and loaded > 0


ONE_ELEMENT = """name = "fuzz"
f_number = 4.0
surfaces = [
  { radius = 50.0, thickness = 5.0, n_d = 1.5, v_d = 60.0, semi_aperture = 10.0 },
  { radius = "flat", thickness = 2.0, semi_aperture = 8.0, stop = true },
  { radius = -50.0, thickness = 45.0, semi_aperture = 10.0 },
]
"""


@pytest.mark.parametrize(
    "change, message",
    [
        (("thickness = 45.0", "thickness = 1e30"), r"lens\.toml:6: surface 2: 'thickness' must be <= 100000"),
        (("semi_aperture = 10.0 },\n  { radius = \"flat\"", "semi_aperture = 10.0, conic = 1e30 },\n  { radius = \"flat\""), r"lens\.toml:4: surface 0: 'conic' must be <= 10000"),
        (("f_number = 4.0", "f_number = 0.1"), r"lens\.toml.*f_number"),
        ((", n_d = 1.5, v_d = 60.0", ""), r"lens\.toml: the lens has no refracting interface"),
        (("semi_aperture = 10.0 },", "semi_aperture = 10.0, aspheric = 3 },"), r"lens\.toml:4: surface 0: 'aspheric' must be a list"),
    ],
)
def test_listed_lens_defects_are_refused(tmp_path, change, message):
    """The lens cases of the issue that loaded silently or crashed."""
    path = tmp_path / "lens.toml"
    path.write_text(ONE_ELEMENT.replace(*change, 1))
    with pytest.raises(jaxflare.LensFormatError, match=message):
        jaxflare.load_lens(path)
