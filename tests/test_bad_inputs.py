"""A generated campaign of bad inputs at the public boundaries.

Every case asserts one outcome: the project's error (:class:`~jaxrefl.io.CaptureError`,
:class:`~jaxrefl.ps.PSInputError`, or a ``ValueError`` naming the argument) whose message
names the file, field or argument. Any other exception fails the case (``pytest.raises``
lets it through). Families:

* MaterialGAN text files (``camera_pos.txt``, ``light_pos.txt``, ``light_power.txt``,
  ``image_size.txt``) holding a non-finite number at every line and column;
* a :class:`~jaxrefl.io.Capture` built in Python with a non-finite or invalid field;
* generic ``capture.json`` holding booleans or non-finite numbers where numbers belong;
* ``ps.woodham`` / ``ps.robust`` / ``ps.fit_normal_brdf``: non-finite, non-unit or
  below-horizon lights, negative or non-finite intensities, negative weights, mismatched
  shapes (parametrised and property-based);
* ``fit.pixel_data`` / ``fit.ParamSpace`` / ``fit.fit_pixels``: non-finite ``scale``,
  non-unit ``wi``/``wo``, arguments that do not broadcast, non-finite ``fixed`` values;
* files a library would crash on: truncated, garbage or oversized (decompression-bomb)
  PNGs as photos and masks, non-UTF-8 ``lights.txt``, empty image lists, a resolution
  below 1, CLI counts and sizes below 1 (argparse names the option);
* Cornell (ASTM E1392) and CURET geometry files with a non-finite angle or index;
* BRDF parameters that are non-finite or outside their documented range
  (``BRDF.check_params``) and non-unit directions under ``brdf.set_validation(True)``.

Validation fails before any compilation, so the module stays fast.
"""

from __future__ import annotations

import io
import itertools
import json
import re
import shutil
import struct
import zlib
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from PIL import Image

from jaxrefl import JaxreflError, brdf, fit, ps
from jaxrefl.io import MeasuredDataError, load_capture, read_cornell, save_generic_capture
from jaxrefl.io._capture import Capture, CaptureError
from jaxrefl.io._curet import read_curet_geometry
from jaxrefl.io._photos import Photos, PNGError, read_png, write_png
from jaxrefl.scene import planar_points

BAD_NUMBERS = ("nan", "inf", "-inf", "NaN", "1e999")
NONFINITE = (np.nan, np.inf, -np.inf)
K = 2  # photos of the small captures
HYP = settings(
    max_examples=150,
    deadline=None,
    derandomize=True,
    database=None,
    suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow],
)


# ----------------------------------------------------------------------------- MaterialGAN
@pytest.fixture(scope="module")
def mg_template(tmp_path_factory):
    """A MaterialGAN folder of K 2x2 grey photos with finite geometry, one line per photo."""
    d = tmp_path_factory.mktemp("mg")
    for i in range(K):
        write_png(d / f"{i:02d}.png", np.full((2, 2, 3), 128, np.uint8))
    np.savetxt(d / "camera_pos.txt", np.tile([0.0, 0.5, 10.0], (K, 1)), delimiter=",")
    np.savetxt(d / "light_pos.txt", np.tile([1.0, 0.0, 10.0], (K, 1)), delimiter=",")
    np.savetxt(d / "light_power.txt", np.full((K, 3), 100.0), delimiter=",")
    (d / "image_size.txt").write_text("2.0\n")
    assert load_capture(d).n_photos == K
    return d


MG_CASES = [
    (f, tok, line, col)
    for f in ("camera_pos.txt", "light_pos.txt", "light_power.txt")
    for tok, line, col in itertools.product(BAD_NUMBERS, range(K), range(3))
] + [("image_size.txt", tok, 0, 0) for tok in BAD_NUMBERS]


@pytest.mark.parametrize(("fname", "token", "line", "col"), MG_CASES)
def test_materialgan_non_finite(mg_template, tmp_path, fname, token, line, col):
    d = tmp_path / "mg"
    shutil.copytree(mg_template, d)
    rows = [r.split(",") for r in (d / fname).read_text().splitlines()]
    rows[line][col] = token
    (d / fname).write_text("\n".join(",".join(r) for r in rows) + "\n")
    with pytest.raises(CaptureError, match=rf"{fname}: line {line + 1}: number {col + 1} ") as e:
        load_capture(d)
    assert e.value.path.name == fname and "finite" in e.value.problem


# ----------------------------------------------------------------------------- Capture
def _capture(light_dir=False) -> Capture:
    h = w = 2
    return Capture(
        images=np.ones((K, h, w, 3), np.float32),
        status=np.zeros((K, h, w, 3), np.uint8),
        light_pos=None if light_dir else np.tile([1.0, 0.0, 10.0], (K, 1)),
        light_dir=np.tile([0.0, 0.6, 0.8], (K, 1)) if light_dir else None,
        light_power=np.full((K, 3), 100.0),
        camera_pos=np.tile([0.0, 0.0, 10.0], (K, 1)),
        side=2.0,
        points=np.asarray(planar_points(h, w, 2.0), np.float64),
    )


def _capture_cases():
    cap = _capture()
    cases = []
    for name in ("light_pos", "light_dir", "camera_pos", "light_power", "points"):
        shape = cap.light_pos.shape if name == "light_dir" else getattr(cap, name).shape
        for idx, v in itertools.product(np.ndindex(shape), NONFINITE):
            cases.append((name, idx, v))
    cases += [("side", (), v) for v in (*NONFINITE, 0.0, -1.0)]
    cases += [("light_power", (k, c), -1.0) for k in range(K) for c in range(3)]
    return cases


@pytest.mark.parametrize(("name", "idx", "value"), _capture_cases())
def test_capture_field(name, idx, value):
    cap = _capture(light_dir=name == "light_dir")
    if name == "side":
        kw = {"side": value}
    else:
        a = np.array(getattr(cap, name), np.float64)
        a[idx] = value
        kw = {name: a}
    with pytest.raises(CaptureError) as e:
        replace(cap, **kw)
    assert e.value.field == name and name in str(e.value)


@HYP
@given(
    name=st.sampled_from(["light_pos", "camera_pos", "light_power"]),
    k=st.integers(0, K - 1),
    j=st.integers(0, 2),
    value=st.sampled_from(NONFINITE),
    base=st.floats(-50, 50),
)
def test_capture_field_property(name, k, j, value, base):
    cap = _capture()
    a = np.abs(np.array(getattr(cap, name))) + abs(base)
    a[k, j] = value
    with pytest.raises(CaptureError) as e:
        replace(cap, **{name: a})
    assert e.value.field == name


# ----------------------------------------------------------------------------- generic JSON
@pytest.fixture(scope="module")
def generic_template(tmp_path_factory):
    d = tmp_path_factory.mktemp("generic")
    save_generic_capture(
        d, np.full((K, 2, 2, 3), 0.5), side=2.0, light_pos=[0.0, 0.0, 5.0], light_power=1.0,
        camera_pos=[0.0, 0.0, 5.0], transfer="gamma2.2", file_format="png8",
    )  # fmt: skip
    return d


JSON_FIELDS = [
    ("side", ("side",)),
    ("saturation", ("saturation",)),
    *[(f"lights[{k}].position", ("lights", k, "position", j)) for k in range(K) for j in range(3)],
    *[(f"lights[{k}].power", ("lights", k, "power")) for k in range(K)],
    *[
        (f"cameras[{k}].position", ("cameras", k, "position", j))
        for k in range(K)
        for j in range(3)
    ],
]
JSON_VALUES = (True, False, float("nan"), float("inf"), float("-inf"))


@pytest.mark.parametrize("value", JSON_VALUES, ids=repr)
@pytest.mark.parametrize(("field", "path"), JSON_FIELDS, ids=[f for f, _ in JSON_FIELDS])
def test_generic_json_field(generic_template, tmp_path, field, path, value):
    d = tmp_path / "g"
    shutil.copytree(generic_template, d)
    spec = json.loads((d / "capture.json").read_text())
    node = spec
    for key in path[:-1]:
        node = node[key]
    node[path[-1]] = value
    (d / "capture.json").write_text(json.dumps(spec))  # NaN/Infinity as Python writes them
    with pytest.raises(CaptureError) as e:
        load_capture(d)
    assert e.value.field == field and e.value.path.name == "capture.json"


# ----------------------------------------------------------------------------- ps
NK, NC, NN = 4, 3, 5
LIGHTS = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [0.0, 0.6, 0.8], [-0.6, 0.0, 0.8]])


def _ps_ok():
    return np.ones((NN, NK, NC)), LIGHTS.copy(), np.ones((NK, NC)), np.ones((NN, NK, NC))


def _ps_cases():
    cases = []
    for k, j, v in itertools.product(range(NK), range(3), NONFINITE):
        cases.append(("lights", ("light", k, j, v)))
    for k, z in itertools.product(range(NK), (0.0, -0.1, -0.8, -1.0)):
        cases.append(("lights", ("below", k, z)))
    for k, f in itertools.product(range(NK), (0.0, 1e-3, 0.5, 0.99, 1.01, 2.0, -1.0)):
        cases.append(("lights", ("scale", k, f)))
    for k, c, v in itertools.product(range(NK), range(NC), (*NONFINITE, -1.0, -1e-9)):
        cases.append(("intensities", ("e", k, c, v)))
    for i, k, v in itertools.product((0, NN - 1), range(NK), (-1.0, -1e-6)):
        cases.append(("weight", ("w", i, k, v)))
    shapes = {
        "lights": [(NK - 1, 3), (NK + 1, 3), (NK, 2), (NK, 4), (3,), (NK, 3, 1)],
        "intensities": [(NK, 2), (NK + 1, NC), (NK - 1,), (1, NC), (NK, NC, 1)],
        "weight": [(NN, NK, 1), (NN + 1, NK, NC), (NN, NK), (1, NK, NC)],
        "obs": [(NN, NK), (NN * NK * NC,), (1, NN, NK, NC)],
    }
    for arg, sh in shapes.items():
        cases += [(arg, ("shape", s)) for s in sh]
    return cases


def _apply_ps(case):
    obs, lights, e, w = _ps_ok()
    kind = case[0]
    if kind == "light":
        lights[case[1], case[2]] = case[3]
    elif kind == "below":
        lights[case[1]] = [np.sqrt(max(1 - case[2] ** 2, 0.0)), 0.0, case[2]]
    elif kind == "scale":
        lights[case[1]] *= case[2]
    elif kind == "e":
        e[case[1], case[2]] = case[3]
    elif kind == "w":
        w[case[1], case[2]] = case[3]
    return obs, lights, e, w


@pytest.mark.parametrize("method", ["woodham", "robust", "fit_normal_brdf"])
@pytest.mark.parametrize(("arg", "case"), _ps_cases(), ids=str)
def test_ps_calibrated(method, arg, case):
    obs, lights, e, w = _apply_ps(case)
    if case[0] == "shape":
        names = ("obs", "lights", "intensities", "weight")
        args = dict(zip(names, (obs, lights, e, w), strict=True))
        args[arg] = np.ones(case[1])
        obs, lights, e, w = args.values()
    with pytest.raises(ps.PSInputError, match=rf"^{arg}: ") as err:
        getattr(ps, method)(obs, lights, e, w)
    assert err.value.where == arg


@HYP
@given(
    method=st.sampled_from(["woodham", "robust", "fit_normal_brdf"]),
    k=st.integers(0, NK - 1),
    what=st.sampled_from(["below", "scale", "intensity"]),
    x=st.floats(0.0, 1.0),
    f=st.one_of(st.floats(1e-6, 0.99), st.floats(1.01, 1e6)),
)
def test_ps_calibrated_property(method, k, what, x, f):
    obs, lights, e, w = _ps_ok()
    if what == "below":  # a unit direction with z in [-1, 0]
        z = -x
        lights[k] = [np.sqrt(1 - z * z), 0.0, z]
        arg = "lights"
    elif what == "scale":
        lights[k] *= f
        arg = "lights"
    else:
        e[k] = -f
        arg = "intensities"
    with pytest.raises(ps.PSInputError, match=rf"^{arg}: ") as err:
        getattr(ps, method)(obs, lights, e, w)
    assert err.value.where == arg


# ----------------------------------------------------------------------------- fit
FN, FK, FC = 3, 4, 3
WI = np.tile([0.0, 0.6, 0.8], (FN, FK, 1))


def _fit_cases():
    cases = []
    for idx, v in itertools.product([(0, 0, 0), (FN - 1, FK - 1, FC - 1), (1, 2, 0)], NONFINITE):
        cases.append(("scale", ("value", idx, v), r"scale holds a non-finite"))
    for arg, idx, f in itertools.product(
        ("wi", "wo"), [(0, 0), (FN - 1, FK - 1), (1, 2)], (0.0, 1e-3, 0.5, 0.99, 1.01, 2.0)
    ):
        cases.append((arg, ("norm", idx, f), rf"{arg} must be unit vectors"))
    bad_shapes = {
        "scale": [(FN, FK + 1, FC), (FN + 1, FK, FC), (FN, FK, 2), (2, FN, FK, FC), (FK + 1,)],
        "weight": [(FN, FK + 1, FC), (FN + 1, FK, FC), (FN, FK, 2), (2, FN, FK, FC)],
        "censored": [(FN, FK + 1, FC), (FN, FK, 2), (2, FN, FK, FC)],
        "wi": [(FN, FK + 1, 3), (FN + 1, FK, 3), (2, FN, FK, 3)],
        "wo": [(FN, FK + 1, 3), (FN + 1, FK, 3), (2, FN, FK, 3)],
    }
    for arg, shapes in bad_shapes.items():
        cases += [(arg, ("shape", s), rf"{arg} has shape {_re_shape(s)}") for s in shapes]
    return cases


def _re_shape(s):
    return str(tuple(s)).replace("(", r"\(").replace(")", r"\)")


@pytest.mark.parametrize(("arg", "case", "msg"), _fit_cases(), ids=str)
def test_pixel_data(arg, case, msg):
    kw = {"wi": WI.copy(), "wo": WI.copy(), "scale": np.ones((FN, FK, FC))}
    if case[0] == "value":
        kw[arg][case[1]] = case[2]
    elif case[0] == "norm":
        kw[arg][case[1]] *= case[2]
    else:
        bad = np.zeros(case[1]) if arg == "censored" else np.ones(case[1]) * 0.6
        if arg in ("wi", "wo"):
            bad = np.broadcast_to([0.0, 0.6, 0.8], case[1])
        kw[arg] = bad
    with pytest.raises(ValueError, match=msg):
        fit.pixel_data(np.ones((FN, FK, FC)), **kw)


@HYP
@given(
    arg=st.sampled_from(["wi", "wo"]),
    n=st.integers(0, FN - 1),
    k=st.integers(0, FK - 1),
    f=st.one_of(st.floats(1e-6, 0.995), st.floats(1.005, 1e4)),
)
def test_pixel_data_norm_property(arg, n, k, f):
    kw = {"wi": WI.copy(), "wo": WI.copy()}
    kw[arg][n, k] *= f
    with pytest.raises(ValueError, match=rf"{arg} must be unit vectors.*length"):
        fit.pixel_data(np.ones((FN, FK, FC)), **kw)


MODELS = ("lambert", "oren_nayar", "phong", "blinn_phong", "ward", "cook_torrance", "dichromatic")
FIXED_CASES = [
    (m, p, v)
    for m in MODELS
    for p in brdf.get(m).param_names
    for v in (*NONFINITE, "one")
    if brdf.get(m).param_spec(p).kind != "lobes"
]


@pytest.mark.parametrize(("model", "param", "value"), FIXED_CASES, ids=str)
def test_fixed_non_finite(model, param, value):
    m = brdf.get(model)
    if value == "one":  # one non-finite entry among finite ones (per channel)
        v = np.full(3, 0.2) if m.param_spec(param).kind == "color" else np.array(0.2)
        v = v.copy()
        v.flat[-1] = np.nan
    else:
        v = value
    with pytest.raises(ValueError, match=rf"fixed\['{param}'\].*not finite"):
        fit.ParamSpace(m, channels=3, fixed={param: v})


@pytest.mark.parametrize("value", NONFINITE)
@pytest.mark.parametrize("model", ["lambert", "cook_torrance"])
def test_fit_pixels_fixed_non_finite(model, value):
    m = brdf.get(model)
    param = m.param_names[-1]
    data = fit.pixel_data(np.ones((FN, FK, FC)), WI)
    with pytest.raises(ValueError, match=rf"fixed\['{param}'\]"):
        fit.fit_pixels(m, data, fixed={param: value})


# ----------------------------------------------------------------------------- crashes
def _png_claiming(w: int, h: int, depth: int = 8, ctype: int = 2) -> bytes:
    """A PNG whose header claims w x h pixels and whose image data is empty."""

    def chunk(kind: bytes, body: bytes) -> bytes:
        crc = zlib.crc32(kind + body) & 0xFFFFFFFF
        return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", crc)

    ihdr = struct.pack(">IIBBBBB", w, h, depth, ctype, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IEND", b"")


def _broken_pngs():
    good = io.BytesIO()
    noise = np.random.default_rng(0).integers(0, 256, (32, 32, 3), dtype=np.uint8)
    Image.fromarray(noise).save(good, format="PNG")  # incompressible: a cut loses pixels
    g = good.getvalue()
    cases = {f"cut{n}": g[:n] for n in (0, 8, 20, 33, 40, 100, len(g) // 2, len(g) - 40)}
    cases["bomb8"] = _png_claiming(100_000, 100_000)
    cases["bomb16"] = _png_claiming(100_000, 100_000, depth=16)
    cases["garbage"] = bytes(range(256))
    cases["text"] = b"not a png at all\n"
    return cases


BROKEN_PNGS = _broken_pngs()


@pytest.mark.parametrize("which", ["mask", "photo"])
@pytest.mark.parametrize("name", sorted(BROKEN_PNGS))
def test_generic_broken_png(generic_template, tmp_path, name, which):
    d = tmp_path / "g"
    shutil.copytree(generic_template, d)
    spec = json.loads((d / "capture.json").read_text())
    target = "mask.png" if which == "mask" else spec["images"][-1]
    if which == "mask":
        spec["mask"] = "mask.png"
        (d / "capture.json").write_text(json.dumps(spec))
    (d / target).write_bytes(BROKEN_PNGS[name])
    with pytest.raises(CaptureError) as e:
        load_capture(d)
    assert e.value.path.name == target


@pytest.mark.parametrize("name", sorted(BROKEN_PNGS))
def test_read_png_broken(tmp_path, name):
    p = tmp_path / f"{name}.png"
    p.write_bytes(BROKEN_PNGS[name])
    with pytest.raises(PNGError, match=re.escape(str(p))):
        read_png(p)


def _uw_folder(tmp_path, lights: bytes, listing: str | None = None):
    obj = tmp_path / "obj"
    obj.mkdir()
    for i in range(3):
        Image.fromarray(np.full((4, 4), 100, np.uint8)).save(obj / f"obj.{i}.tga")
    Image.fromarray(np.full((4, 4), 255, np.uint8)).save(obj / "obj.mask.tga")
    (obj / "lights.txt").write_bytes(lights)
    if listing is not None:
        (tmp_path / "obj.txt").write_text(listing)  # the UW listing sits beside the folder
    return obj


@pytest.mark.parametrize(
    "raw", [b"\xff\xfe3\n", b"3\n0 0 1\n\x80\x81 0 1\n", "3\n0 0 1\n".encode("utf-16")]
)
def test_uw_lights_not_utf8(tmp_path, raw):
    obj = _uw_folder(tmp_path, raw)
    with pytest.raises(ps.PSInputError, match="not a UTF-8 text file") as e:
        ps.load_uw(obj)
    assert e.value.where.endswith("lights.txt")


def test_uw_empty_image_list(tmp_path):
    obj = _uw_folder(tmp_path, b"3\n0 0 1\n0.6 0 0.8\n0 0.6 0.8\n", listing="0\n")
    with pytest.raises(ps.PSInputError, match="lists no images") as e:
        ps.load_uw(obj)
    assert e.value.where == str(obj)


def test_photos_empty_list(tmp_path):
    with pytest.raises(CaptureError, match="lists no photos") as e:
        Photos([], "linear", tmp_path / "capture.json")
    assert e.value.path.name == "capture.json"


@pytest.mark.parametrize("resolution", [0, -1, -32, 2.5, "32"])
def test_load_capture_resolution(generic_template, resolution):
    with pytest.raises(CaptureError) as e:
        load_capture(generic_template, resolution=resolution)
    assert e.value.field == "resolution"


CLI_CASES = [
    (cmd, opt, v)
    for cmd, opts in (
        ("fit", ("--resolution", "--downsample", "--tile-pixels", "--max-photos")),
        ("sample", ("--max-steps", "--walkers", "--chains", "--samples", "--downsample")),
    )
    for opt in opts
    for v in ("0", "-1", "-100", "x", "1.5")
]


@pytest.mark.parametrize(("cmd", "opt", "value"), CLI_CASES)
def test_cli_count_options(tmp_path, capsys, cmd, opt, value):
    from jaxrefl.cli import main

    assert main([cmd, str(tmp_path), "--out", str(tmp_path / "out"), opt, value]) == 2
    err = capsys.readouterr().err
    assert f"argument {opt}:" in err and (">= 1" in err)


# ----------------------------------------------------------------------------- measured files
CORNELL_ROWS = 3
CORNELL_CASES = [
    (tok, i, j)
    for tok in BAD_NUMBERS
    for i in range(CORNELL_ROWS)
    for j in range(4)
    if (i, j) != (0, 0)  # a first line starting with a letter reads as a header line
]


@pytest.mark.parametrize(("token", "row", "col"), CORNELL_CASES)
def test_cornell_non_finite_angle(tmp_path, token, row, col):
    rows = [["0.1", "0.2", "0.3", "0.4", "0.5", "0.6"] for _ in range(CORNELL_ROWS)]
    rows[row][col] = token
    p = tmp_path / "bad.astm"
    p.write_text(
        f"SAMPLE_NAME bad\nNUM_POINTS {CORNELL_ROWS}\nVARS theta_i,phi_i,theta_s,phi_s,R,G\n"
        + "".join(",".join(r) + "\n" for r in rows)
    )
    name = ("theta_i", "phi_i", "theta_s", "phi_s")[col]
    with pytest.raises(MeasuredDataError, match=rf"angle '{name}' is .*finite") as e:
        read_cornell(p)
    assert e.value.path == p and e.value.line == 4 + row


CURET_CASES = [(tok, i, j) for tok in BAD_NUMBERS for i in range(3) for j in range(5)]


@pytest.mark.parametrize(("token", "row", "col"), CURET_CASES)
def test_curet_non_finite_geometry(tmp_path, token, row, col):
    rows = [[str(k + 1), "0.1", "0.2", "0.3", "0.4"] for k in range(3)]
    rows[row][col] = token
    p = tmp_path / "table.txt"
    p.write_text("".join(" ".join(r) + "\n" for r in rows))
    angles = ("theta_v", "phi_v", "theta_i", "phi_i")
    what = "geometry index" if col == 0 else f"angle {angles[col - 1]}"
    with pytest.raises(MeasuredDataError, match=what) as e:
        read_curet_geometry(p)
    assert e.value.path == p and e.value.line == row + 1


@pytest.mark.parametrize("shape", [(NN, NK, 1), (NN, NK), (NN + 1, NK, NC)])
def test_fit_normal_brdf_saturated_shape(shape):
    obs, lights, e, w = _ps_ok()
    with pytest.raises(ps.PSInputError, match=r"^saturated: must have the shape of obs"):
        ps.fit_normal_brdf(obs, lights, e, w, np.zeros(shape, bool))


# ----------------------------------------------------------------------------- BRDF parameters
def _brdf_cases():
    cases = []
    for name in brdf.available():
        m = brdf.get(name)
        for q in m.params:
            values = [np.nan, np.inf, -np.inf]
            if q.kind != "lobes":
                if np.isfinite(q.lower):
                    values.append(q.lower - max(1e-3, 1e-3 * abs(q.lower)))
                if np.isfinite(q.upper):
                    values.append(q.upper + max(1e-3, 1e-3 * abs(q.upper)))
            cases += [(name, q.name, v) for v in values]
    return cases


@pytest.mark.parametrize(("model", "param", "value"), _brdf_cases(), ids=str)
def test_brdf_check_params(model, param, value):
    m = brdf.get(model)
    p = m.default_params(np.float64)
    bad = np.array(p[param], np.float64)
    bad.flat[-1] = value
    with pytest.raises(
        ValueError, match=rf"parameter '{param}' = .*(not finite|outside its range)"
    ):
        m.check_params({**p, param: bad})


@HYP
@given(
    arg=st.sampled_from(["wi", "wo"]),
    f=st.one_of(st.floats(1e-6, 0.995), st.floats(1.005, 1e4)),
    model=st.sampled_from(["lambert", "blinn_phong", "ward", "cook_torrance"]),
)
def test_brdf_eval_directions_property(arg, f, model):
    m = brdf.get(model)
    d = {"wi": np.array([0.0, 0.6, 0.8]), "wo": np.array([0.6, 0.0, 0.8])}
    d[arg] = d[arg] * f
    before = brdf.set_validation(True)
    try:
        with pytest.raises(ValueError, match=rf"{arg} must be unit vectors.*length"):
            m.eval(m.default_params(np.float64), d["wi"], d["wo"])
    finally:
        brdf.set_validation(before)


@pytest.mark.parametrize(
    ("kw", "name"),
    [
        ({"alpha_min": float("nan")}, "alpha_min"),
        ({"alpha_min": 0.0}, "alpha_min"),
        ({"alpha_min": 1.5}, "alpha_min"),
        ({"noise": ("gaussian", {"sigma": float("nan")})}, "sigma"),
        ({"noise": ("gaussian", {"sigma": -0.01})}, "sigma"),
        ({"noise": ("gaussian", {"sigma": 0.0})}, "sigma"),
        ({"noise": ("gaussian", {"sigma": float("inf")})}, "sigma"),
        ({"noise": ("shot", {"read": float("inf")})}, "read"),
        ({"noise": ("shot", {"read": float("nan")})}, "read"),
        ({"noise": ("shot", {"gain": -1.0})}, "gain"),
        ({"noise": ("shot", {"gain": float("inf")})}, "gain"),
        ({"loss": ("huber", {"delta": 0.0})}, "delta"),
        ({"loss": ("cauchy", {"c": float("nan")})}, "c"),
        ({"dtype": np.float16}, "dtype"),
        ({"dtype": np.int32}, "dtype"),
    ],
)
def test_fit_job_refuses_bad_numbers(kw, name):
    """FitJob and the option objects it takes refuse bad numbers, naming the field."""
    from jaxrefl import fit
    from jaxrefl.svbrdf import FitJob

    kinds = {
        "gaussian": fit.GaussianNoise,
        "shot": fit.ShotNoise,
        "huber": fit.Huber,
        "cauchy": fit.Cauchy,
    }

    def make():
        cfg = {k: v for k, v in kw.items() if k in ("noise", "loss", "dtype")}
        for k in ("noise", "loss"):
            if k in cfg:
                kind, args = cfg[k]
                cfg[k] = kinds[kind](**args)
        job = {k: v for k, v in kw.items() if k not in cfg}
        return FitJob(**job, config=fit.FitConfig(**cfg))

    with pytest.raises(JaxreflError, match=name):
        make()


def test_cli_refuses_a_nan_alpha_min(tmp_path, capsys):
    from jaxrefl.cli import main

    assert main(["fit", str(tmp_path), "--out", str(tmp_path / "o"), "--alpha-min", "nan"]) == 2
    assert "argument --alpha-min: expected a finite number" in capsys.readouterr().err


def test_every_input_error_is_a_jaxrefl_error():
    from jaxrefl import JaxreflError
    from jaxrefl.io._capture import CaptureError
    from jaxrefl.io._exr import ExrFormatError
    from jaxrefl.io._measured import MeasuredDataError
    from jaxrefl.io._photos import PNGError
    from jaxrefl.phone import PhoneCaptureError
    from jaxrefl.ps import PSInputError

    for cls in (
        CaptureError,
        ExrFormatError,
        MeasuredDataError,
        PNGError,
        PSInputError,
        PhoneCaptureError,
    ):
        assert issubclass(cls, JaxreflError) and issubclass(cls, ValueError), cls


def test_no_builtin_value_error_is_raised():
    """Every argument or input check raises a JaxreflError: `except JaxreflError` sees them all."""
    import re

    import jaxrefl

    root = Path(jaxrefl.__file__).parent
    found = [
        f"{p.relative_to(root)}:{i}"
        for p in sorted(root.rglob("*.py"))
        for i, line in enumerate(p.read_text().splitlines(), start=1)
        if re.search(r"\braise ValueError\b", line)
    ]
    assert not found, found


@pytest.mark.parametrize(
    "make",
    [
        lambda fit: fit.GaussianNoise(sigma=-1.0),
        lambda fit: fit.Huber(delta=0.0),
        lambda fit: fit.LMOptions(max_iters=0),
    ],
)
def test_option_objects_raise_jaxrefl_errors(make):
    from jaxrefl import fit

    with pytest.raises(JaxreflError):
        make(fit)


def test_fit_pixels_fixed_nan_is_a_jaxrefl_error():
    from jaxrefl import brdf, fit

    m = brdf.get("cook_torrance", distribution="ggx", fresnel="schlick", diffuse="lambert")
    wi = np.tile(np.array([0.0, 0.0, 1.0]), (2, 4, 1))
    data = fit.pixel_data(np.full((2, 4, 3), 0.1), wi, wi)
    with pytest.raises(JaxreflError, match="alpha"):
        fit.fit_pixels(m, data, fixed={"alpha": float("nan")})
