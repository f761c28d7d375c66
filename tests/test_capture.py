"""Flash-capture loaders: the real bath_tile capture, the demo, three layouts, bad input.

Geometry convention and encoding: ``../shared/data/README.md`` (MaterialGAN, Guo et al.
2020): photos store (f_r E cos theta_i)^(1/2.2) clipped to [0, 1] in 8 bits, lengths in cm.
"""

from __future__ import annotations

import json
import shutil
import struct
import zlib
from dataclasses import replace

import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image

from jaxrefl import brdf
from jaxrefl.io import load_capture, save_generic_capture
from jaxrefl.io._capture import OBS_STATUS, Capture, CaptureError, ObsStatus, geometry_status
from jaxrefl.io._photos import read_png, unfilter, write_png
from jaxrefl.scene import PinholeCamera, PointLight, planar_points, render

BATH = "svbrdf_flash/bath_tile"
SIZE = 32  # demo photos


# ----------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def bath(shared_data):
    return load_capture(shared_data / BATH)


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory):
    from jaxrefl.cli import main

    out = tmp_path_factory.mktemp("demo")
    assert main(["demo", "--out", str(out), "--size", str(SIZE), "--no-fit", "--noise", "0"]) == 0
    return out


@pytest.fixture(scope="module")
def demo(demo_dir):
    return load_capture(demo_dir)


def _copy_demo(demo_dir, dst):
    shutil.copytree(demo_dir, dst)
    return dst


def _small(status, k=1, side=4.0):
    """A hand-made capture with the given (K, H, W, C) status and ramp images."""
    status = np.asarray(status, np.uint8)
    _, h, w, _ = status.shape
    return Capture(
        images=np.arange(status.size, dtype=np.float32).reshape(status.shape),
        status=status,
        light_pos=np.tile([0.0, 0.0, 10.0], (k, 1)),
        light_dir=None,
        light_power=np.ones((k, status.shape[-1])),
        camera_pos=np.tile([0.0, 0.0, 10.0], (k, 1)),
        side=side,
        points=np.asarray(planar_points(h, w, side)),
    )


# ----------------------------------------------------------------------------- real data
def test_bath_tile_loads_with_its_geometry_and_censoring(bath, shared_data):
    folder = shared_data / BATH
    params = json.loads((folder / "parameters.json").read_text())
    assert bath.shape == (9, 1024, 1024, 3) and bath.images.dtype == np.float32
    assert (bath.layout, bath.transfer, bath.bit_depth, bath.unit) == (
        "svbrdf-diff-renderer",
        "gamma2.2",
        8,
        "cm",
    )
    assert [f.name for f in bath.files] == [f"{i:02d}.png" for i in range(9)]
    np.testing.assert_array_equal(bath.light_pos, params["light_pos"])
    np.testing.assert_array_equal(bath.camera_pos, params["camera_pos"])
    np.testing.assert_array_equal(bath.light_power, np.full((9, 3), 1500.0))  # per channel
    s = params["image_size"]
    np.testing.assert_allclose(bath.points[0, 0], [-s / 2 + s / 2048, s / 2 - s / 2048, 0.0])
    np.testing.assert_allclose(bath.points[-1, -1], [s / 2 - s / 2048, -s / 2 + s / 2048, 0.0])

    # Linearisation value^2.2 and censoring, against an independent read of the PNGs.
    n_sat = n_dark = 0
    for k, f in enumerate(bath.files):
        codes = np.asarray(Image.open(f))
        n_sat += int(np.sum(codes == 255))
        n_dark += int(np.sum(codes == 0))
        if k == 3:
            np.testing.assert_allclose(bath.images[3], (codes / 255.0) ** 2.2, rtol=1e-6)
            np.testing.assert_array_equal(bath.censored_high[3], codes == 255)
    summary = bath.summary()
    assert set(summary) == set(OBS_STATUS.values())
    assert summary["saturated"] == n_sat and summary["dark"] == n_dark
    assert summary["ok"] == bath.images.size - n_sat - n_dark == int(bath.valid.sum())
    frac = summary["saturated"] / bath.images.size
    assert frac == pytest.approx(0.00529, abs=1e-5)  # 149,776 of 28.3 M observations
    assert bath.saturation_level == pytest.approx((254.5 / 255) ** 2.2)
    assert bath.dark_level == pytest.approx((0.5 / 255) ** 2.2)


def test_select_crop_downsample(bath):
    sub = bath.select([2, 0])
    np.testing.assert_array_equal(sub.images, bath.images[[2, 0]])
    np.testing.assert_array_equal(sub.light_pos, bath.light_pos[[2, 0]])
    assert [f.name for f in sub.files] == ["02.png", "00.png"]
    tile = sub.crop(100, 164, 200, 264)
    assert tile.shape == (2, 64, 64, 3)
    np.testing.assert_array_equal(tile.points, bath.points[100:164, 200:264])
    np.testing.assert_array_equal(tile.status, bath.status[[2, 0], 100:164, 200:264])
    small = tile.downsample(4)
    assert small.shape == (2, 16, 16, 3)
    blocks = tile.images.astype(np.float64).reshape(2, 16, 4, 16, 4, 3)
    np.testing.assert_allclose(small.images, blocks.mean(axis=(2, 4)), rtol=1e-6)
    # Block centres are the pixel centres of the coarser grid.
    full = np.asarray(planar_points(256, 256, bath.side))
    np.testing.assert_allclose(small.points, full[25:41, 50:66], atol=1e-12)
    with pytest.raises(ValueError, match="divide"):
        tile.downsample(5)
    with pytest.raises(ValueError, match="inside"):
        bath.crop(0, 2000, 0, 10)


def test_downsample_status_precedence():
    st = np.zeros((1, 4, 6, 1), np.uint8)
    st[0, 0, 1] = 1  # block (0, 0): one saturated -> saturated
    st[0, 1, 2] = 2  # block (0, 1): one dark -> dark
    st[0, 0, 4], st[0, 1, 5] = 1, 2  # block (0, 2): both -> censored_mixed
    st[0, 2, 0], st[0, 3, 1], st[0, 3, 0] = 5, 1, 3  # block (1, 0): nonfinite wins
    st[0, 2, 2] = 6  # block (1, 1): light below the horizon
    ds = _small(st).downsample(2)
    np.testing.assert_array_equal(ds.status[0, ..., 0], [[1, 2, 8], [3, 6, 0]])
    assert ds.images[0, 1, 2, 0] == np.mean([16, 17, 22, 23])  # rows 2-3, columns 4-5
    with pytest.raises(ValueError, match="exactly one"):
        replace(_small(st), light_dir=np.zeros((1, 3)))


# ----------------------------------------------------------------------------- demo
def test_demo_capture_matches_the_render(demo, demo_dir):
    from jaxrefl.demo import demo_scene, render_demo

    scene = demo_scene(size=SIZE)
    truth = np.asarray(render_demo(scene, encode=False), np.float64)
    assert demo.shape == (9, SIZE, SIZE, 3) and demo.transfer == "gamma2.2"
    np.testing.assert_allclose(demo.light_pos, scene.positions)
    np.testing.assert_allclose(demo.camera_pos, scene.positions)
    np.testing.assert_array_equal(demo.light_power, np.full((9, 3), 1500.0))  # one per photo
    # Clipped pixels are flagged, and only those.
    sat = demo.censored_high
    assert 0 < sat.mean() < 0.1
    assert np.all(sat[truth >= 1.0])
    assert np.all(truth[sat] >= demo.saturation_level * (1 - 1e-5))
    # Elsewhere: within 8-bit quantisation, |q^2.2 - y^2.2| <= 2.2 max(q, y)^1.2 |q - y|.
    ok = demo.valid
    enc = np.clip(truth, 0, None) ** (1 / 2.2)
    bound = 2.2 * np.minimum(enc + 0.5 / 255, 1.0) ** 1.2 * (0.5 / 255) * 1.001 + 1e-7
    err = np.abs(demo.images - truth)
    assert np.all(err[ok] <= bound[ok]), float(np.max(err[ok] - bound[ok]))
    assert np.all(truth[demo.censored_low] <= demo.dark_level * (1 + 1e-5))
    # resolution= box-downsamples the photos read.
    half = load_capture(demo_dir, resolution=SIZE // 2, max_photos=3)
    assert half.shape == (3, SIZE // 2, SIZE // 2, 3)
    np.testing.assert_allclose(half.images, demo.select([0, 1, 2]).downsample(2).images)


def test_geometry_agrees_with_render(demo):
    """f_r(wi, wo) * irradiance * cos_i == render(..., cos4=False), float64, light below too."""
    cap = demo.select([0, 3, 5]).crop(8, 16, 4, 12)
    lp = cap.light_pos.copy()
    lp[2] = [1.0, -2.0, -0.5]  # under the sample plane: prediction 0, geometry finite
    cap = replace(cap, light_pos=lp)
    geo = cap.per_pixel_geometry(np.float64)
    assert all(np.all(np.isfinite(v)) for v in geo.values())
    np.testing.assert_allclose(np.linalg.norm(geo["wi"], axis=-1), 1.0, rtol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(geo["wo"], axis=-1), 1.0, rtol=1e-14)
    assert np.all(geo["cos_i"][2] == 0)
    rng = np.random.default_rng(1)
    albedo = rng.uniform(0.1, 0.9, (8, 8, 3))
    cases = [
        (brdf.get("lambert"), {"albedo": albedo}),
        (
            brdf.get("cook_torrance", diffuse="lambert"),
            {
                "albedo": albedo,
                "specular": rng.uniform(0.02, 0.2, (8, 8, 3)),
                "alpha": rng.uniform(0.05, 0.6, (8, 8)),
            },
        ),
    ]
    lights = [PointLight(p, e) for p, e in zip(cap.light_pos, cap.light_power, strict=True)]
    cams = [PinholeCamera(p) for p in cap.camera_pos]
    for model, params in cases:
        pred = np.asarray(model.eval(params, geo["wi"], geo["wo"]))
        pred = pred * geo["irradiance"] * geo["cos_i"][..., None]
        ref = np.asarray(
            render(model, params, lights, cams, points=jnp.asarray(cap.points), cos4=False)
        )
        assert np.all(ref[2] == 0) and np.all(pred[2] == 0)
        assert np.max(ref) > 0.01
        np.testing.assert_allclose(pred, ref, rtol=1e-12, atol=1e-300)
    # The capture's own scene objects give the same images.
    again = render(model, params, cap.lights(), cap.cameras(), points=cap.points, cos4=False)
    np.testing.assert_array_equal(np.asarray(again), ref)


# ----------------------------------------------------------------------------- layouts
def test_materialgan_layout(demo, demo_dir, tmp_path):
    mg = tmp_path / "mg"
    mg.mkdir()
    for k, f in enumerate(demo.files):
        shutil.copy(f, mg / f"{k:02d}.png")
    shutil.copy(demo.files[0], mg / "rendered.png")  # not a photo: ignored
    np.savetxt(mg / "camera_pos.txt", demo.camera_pos, delimiter=",", fmt="%.6f")
    np.savetxt(mg / "light_pos.txt", demo.light_pos, delimiter=",", fmt="%.6f")
    (mg / "light_power.txt").write_text("1500.0000,1500.0000,1500.0000\n")
    (mg / "image_size.txt").write_text("11.1360\n")
    cap = load_capture(mg)
    assert cap.layout == "materialgan" and cap.transfer == "gamma2.2"
    np.testing.assert_array_equal(cap.images, demo.images)
    np.testing.assert_array_equal(cap.status, demo.status)
    np.testing.assert_allclose(cap.light_pos, demo.light_pos, atol=1e-6)
    np.testing.assert_array_equal(cap.light_power, demo.light_power)
    assert cap.side == demo.side and "light_pos" not in cap.meta
    # Without light_pos.txt the flash sits at the camera (what the MaterialGAN tools write).
    (mg / "light_pos.txt").unlink()
    cap = load_capture(mg, layout="materialgan", max_photos=2)
    assert cap.n_photos == 2 and "co-located" in cap.meta["light_pos"]
    np.testing.assert_array_equal(cap.light_pos, cap.camera_pos)
    # One line too few.
    np.savetxt(mg / "camera_pos.txt", demo.camera_pos[:8], delimiter=",")
    with pytest.raises(CaptureError, match=r"camera_pos\.txt.*8 lines.*9 photos"):
        load_capture(mg)


def _optim_layout(demo_dir, dst):
    """The demo capture rewritten in the newer svbrdf-diff-renderer layout (optim.json)."""
    params = json.loads((demo_dir / "parameters.json").read_text())
    target = dst / "target" / str(SIZE)
    shutil.copytree(demo_dir / "images/reference" / str(SIZE), target)
    optim = {
        "target_dir": f"target/{SIZE}",
        "optimize_dir": "optim/256",  # the optimiser's output folders: not read
        "rerender_dir": "optim/256",
        "im_size": params["image_size"],
        "idx": params["idx"],
        "camera_pos": params["camera_pos"],
        "light_pos": params["light_pos"],
        "light_pow": params["light_pow"],
        "gamma": params.get("gamma", 2.2),
    }
    (dst / "optim.json").write_text(json.dumps(optim))
    return dst


def test_optim_json_layout(demo, demo_dir, tmp_path):
    folder = _optim_layout(demo_dir, tmp_path / "o")
    for where in (folder, folder / "optim.json"):
        cap = load_capture(where)
        assert cap.layout == "svbrdf-diff-renderer" and cap.meta["parameters_file"] == "optim.json"
        np.testing.assert_array_equal(cap.images, demo.images)
        np.testing.assert_array_equal(cap.status, demo.status)
        np.testing.assert_array_equal(cap.light_pos, demo.light_pos)
        np.testing.assert_array_equal(cap.camera_pos, demo.camera_pos)
        np.testing.assert_array_equal(cap.light_power, demo.light_power)
        assert cap.side == demo.side
    # resolution= box-downsamples from the named folder.
    assert load_capture(folder, resolution=SIZE // 2).shape == (9, SIZE // 2, SIZE // 2, 3)


@pytest.mark.parametrize(
    ("edit", "field", "match"),
    [
        (lambda d: d.pop("im_size"), "im_size", "missing key 'im_size'"),
        (lambda d: d.pop("target_dir"), "target_dir", "missing key 'target_dir'"),
        (lambda d: d.update(target_dir="target/64"), "target_dir", "is not a folder"),
        (lambda d: d.update(target_dir=3), "target_dir", "expected a folder name"),
        (lambda d: d.pop("camera_pos"), "camera_pos", "missing key 'camera_pos'"),
        (lambda d: d.pop("light_pow"), "light_pow", "missing key 'light_pow'"),
    ],
)
def test_bad_optim_json(demo_dir, tmp_path, edit, field, match):
    folder = _optim_layout(demo_dir, tmp_path / "o")
    data = json.loads((folder / "optim.json").read_text())
    edit(data)
    (folder / "optim.json").write_text(json.dumps(data))
    with pytest.raises(CaptureError, match=match) as e:
        load_capture(folder)
    assert e.value.field == field and e.value.path.name == "optim.json"
    assert "optim.json" in str(e.value) and field in str(e.value)


def test_yellow_box_loads_from_optim_json(shared_data):
    folder = shared_data / "svbrdf_flash/yellow_box"
    optim = json.loads((folder / "optim.json").read_text())
    cap = load_capture(folder, resolution=64)
    assert cap.shape == (9, 64, 64, 3) and cap.meta["parameters_file"] == "optim.json"
    assert cap.side == optim["im_size"]
    np.testing.assert_array_equal(cap.light_pos, optim["light_pos"])
    np.testing.assert_array_equal(cap.camera_pos, optim["camera_pos"])
    full = Image.open(folder / optim["target_dir"] / "04.png")
    assert full.size == (1024, 1024)
    # Photo 4, box-downsampled 16x after linearisation, against an independent read.
    lin = (np.asarray(full, np.float64) / 255.0) ** 2.2
    ref = lin.reshape(64, 16, 64, 16, 3).mean(axis=(1, 3))
    ok = cap.valid[4]
    np.testing.assert_allclose(cap.images[4][ok], ref[ok], rtol=1e-5, atol=1e-6)


def test_generic_round_trip_exr(tmp_path):
    """Linear EXR: NaN/Inf/negative pixels, a saturation level; a light under the plane is
    refused, naming its entry."""
    rng = np.random.default_rng(0)
    k, h, w = 3, 8, 6
    img = rng.uniform(0.0, 1.5, (k, h, w, 3)).astype(np.float32)
    img[0, 1, 1, 0], img[1, 2, 2, 1], img[2, 3, 3, 2] = np.nan, np.inf, -0.25
    lp = np.array([[1.0, 2.0, 20.0], [-3.0, 0.0, 25.0], [0.0, 1.0, -1.0]])

    def save(lp):
        return save_generic_capture(
            tmp_path / "exr", img, side=5.0, light_pos=lp,
            light_power=[[100.0], [200.0], [300.0]], camera_pos=[0.0, 0.0, 30.0],
            saturation=1.25,
        )  # fmt: skip

    with pytest.raises(CaptureError, match=r"z = -1 cm, not above the sample plane") as e:
        load_capture(save(lp).parent)
    assert e.value.field == "lights[2].position" and e.value.path.name == "capture.json"
    lp[2, 2] = 40.0
    cj = save(lp)
    cap = load_capture(cj.parent)
    assert (cap.layout, cap.transfer, cap.bit_depth) == ("generic", "linear", 32)
    assert [f.suffix for f in cap.files] == [".exr"] * 3
    finite = np.isfinite(img)
    np.testing.assert_array_equal(cap.images[finite], img[finite])
    assert np.all(cap.images[~finite] == 0)
    assert cap.status[0, 1, 1, 0] == ObsStatus.NONFINITE
    assert cap.status[1, 2, 2, 1] == ObsStatus.NONFINITE
    assert cap.status[2, 3, 3, 2] == ObsStatus.NEGATIVE
    np.testing.assert_array_equal(cap.status[0] == 1, finite[0] & (img[0] >= 1.25))
    np.testing.assert_array_equal(cap.light_power, [[100.0] * 3, [200.0] * 3, [300.0] * 3])
    np.testing.assert_array_equal(cap.camera_pos, np.tile([0.0, 0.0, 30.0], (3, 1)))
    geo = cap.per_pixel_geometry()
    assert all(np.all(np.isfinite(v)) for v in geo.values())
    assert np.all(geo["cos_i"] > 0)
    r2 = np.sum((lp[1] - cap.points) ** 2, axis=-1)
    np.testing.assert_allclose(geo["irradiance"][1, ..., 0], 200.0 / r2, rtol=1e-6)


def test_generic_round_trip_png_transfers(tmp_path):
    """16-bit sRGB PNG (kept at 16 bits), 8-bit tabulated grey, directional lights, a mask."""
    rng = np.random.default_rng(2)
    img = rng.uniform(0.0, 1.0, (2, 5, 7, 3))
    img[:, 0, 0] = 1.7  # clipped in every photo and channel
    ldir = np.array([[0.0, 0.6, 0.8], [0.3, 0.0, -0.1]])  # the second one below the plane
    mask = np.ones((5, 7), bool)
    mask[4, 6] = False

    def save(ldir):
        return save_generic_capture(
            tmp_path / "p16", img, side=3.0, light_dir=ldir, light_power=2.5,
            camera_pos=[[0.0, 0.0, 9.0], [1.0, 0.0, 9.0]], transfer="srgb", mask=mask,
        )  # fmt: skip

    with pytest.raises(CaptureError, match=r"points from below the sample plane") as e:
        load_capture(save(ldir))
    assert e.value.field == "lights[1].direction"
    ldir[1, 2] = 0.9
    cj = save(ldir)
    cap = load_capture(cj)
    assert (cap.transfer, cap.bit_depth) == ("srgb", 16)
    assert read_png(cap.files[0])[0].dtype == np.uint16
    assert np.all(cap.status[0, 0, 0] == ObsStatus.SATURATED)
    assert np.all(cap.status[0, 4, 6] == ObsStatus.MASKED)
    ok = cap.valid
    assert ok.sum() == 2 * (5 * 7 * 3 - 3 - 3)  # each photo minus the clipped and masked pixel
    # d(linear)/d(encoded) <= 2.4/1.055 on [0, 1] (IEC 61966-2-1), times half a 16-bit step.
    np.testing.assert_allclose(cap.images[ok], img[ok], atol=2.4 / 1.055 * 0.5 / 65535)
    geo = cap.per_pixel_geometry(np.float64)
    np.testing.assert_allclose(geo["wi"][0], np.broadcast_to(ldir[0], (5, 7, 3)))
    assert np.all(geo["irradiance"] == 2.5) and cap.light_pos is None

    table = {"x": np.linspace(0, 1, 11).tolist(), "y": np.sqrt(np.linspace(0, 1, 11)).tolist()}
    grey = img[..., :1].copy()
    cj = save_generic_capture(
        tmp_path / "p8", grey, side=3.0, light_pos=[[0.0, 0.0, 5.0]] * 2, light_power=[1.0, 2.0],
        camera_pos=[0.0, 0.0, 9.0], transfer=table, file_format="png8",
    )  # fmt: skip
    cap = load_capture(cj)
    assert cap.shape == (2, 5, 7, 1) and cap.transfer == "tabulated" and cap.bit_depth == 8
    np.testing.assert_array_equal(cap.light_power[:, 0], [1.0, 2.0])
    # Error <= the steepest d(linear)/d(encoded) of the table (its last segment) x half a step.
    ok = cap.valid
    slope = np.max(np.diff(table["x"]) / np.diff(table["y"]))
    np.testing.assert_allclose(cap.images[ok], grey[ok], atol=slope * 0.5 / 255 * 1.0001)
    # A pixel saturated in every photo: censored, not an error, and counted.
    assert np.all(cap.censored_high[:, 0, 0]) and cap.summary()["saturated"] == 2


def test_png_full_depth_all_filters(tmp_path, shared_data):
    rng = np.random.default_rng(3)
    for c in (1, 2, 3, 4):
        a8 = rng.integers(0, 256, (9, 13, c), dtype=np.uint8)
        write_png(tmp_path / "a.png", a8)  # rows cycle through all five filters
        pil = np.asarray(Image.open(tmp_path / "a.png"))
        np.testing.assert_array_equal(pil.reshape(a8.shape), a8)  # our encoder is valid
        a16 = rng.integers(0, 65536, (9, 13, c), dtype=np.uint16)
        write_png(tmp_path / "b.png", a16)
        got, depth = read_png(tmp_path / "b.png")
        assert depth == 16 and got.dtype == np.uint16
        np.testing.assert_array_equal(got, a16)
    # The decoder on a real file matches Pillow.
    f = shared_data / BATH / "images/reference/1024/05.png"
    data = f.read_bytes()
    idat, pos = b"", 8
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos : pos + 4])
        if data[pos + 4 : pos + 8] == b"IDAT":
            idat += data[pos + 8 : pos + 8 + n]
        pos += 12 + n
    rows = np.frombuffer(zlib.decompress(idat), np.uint8).reshape(1024, -1)
    ours = unfilter(rows, 3).reshape(1024, 1024, 3)
    np.testing.assert_array_equal(ours, np.asarray(Image.open(f)))


# ----------------------------------------------------------------------------- bad input
def test_empty_or_missing_folder(tmp_path):
    with pytest.raises(CaptureError, match="no capture layout found") as e:
        load_capture(tmp_path)
    for expected in ("capture.json", "parameters.json", "camera_pos.txt", "light_power.txt"):
        assert expected in str(e.value)
    with pytest.raises(CaptureError, match="no such file or folder"):
        load_capture(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="unknown layout"):
        load_capture(tmp_path, layout="mitsuba")


def _edit(folder, fn):
    pj = folder / "parameters.json"
    data = json.loads(pj.read_text())
    fn(data)
    pj.write_text(json.dumps(data))


@pytest.mark.parametrize(
    ("edit", "field", "match"),
    [
        (lambda d: d.pop("light_pos"), "light_pos", "missing key 'light_pos'"),
        (lambda d: d.pop("image_size"), "image_size", "missing key"),
        (lambda d: d.update(light_pos=d["light_pos"][:8]), "light_pos", "8 entries.*has 9"),
        (lambda d: d.update(light_pos=[[0, 0]] * 9), "light_pos", r"\[x, y, z\]"),
        (lambda d: d.update(light_pow=[1, 2]), "light_pow", r"shape \(2,\)"),
        (lambda d: d.update(idx=list(range(10))), "idx", "0..8"),
        (lambda d: d.update(image_size=-3), "image_size", "positive"),
        (lambda d: d.update(camera_pos="north"), "camera_pos", "numbers"),
    ],
)
def test_bad_parameters_json(demo_dir, tmp_path, edit, field, match):
    folder = _copy_demo(demo_dir, tmp_path / "c")
    _edit(folder, edit)
    with pytest.raises(CaptureError, match=match) as e:
        load_capture(folder)
    assert e.value.field == field and e.value.path.name == "parameters.json"
    assert "parameters.json" in str(e.value) and field in str(e.value)


def test_bad_files(demo_dir, tmp_path):
    folder = _copy_demo(demo_dir, tmp_path / "c")
    img_dir = folder / "images/reference" / str(SIZE)
    (folder / "parameters.json").write_text('{"image_size": 11.1, "idx": [0, 1,')
    with pytest.raises(CaptureError, match=r"parameters\.json: invalid JSON"):
        load_capture(folder)
    shutil.copy(demo_dir / "parameters.json", folder / "parameters.json")
    # A photo listed in idx is missing.
    (img_dir / "05.png").rename(tmp_path / "05.png")
    with pytest.raises(CaptureError, match=r"05\.png does not exist") as e:
        load_capture(folder)
    assert e.value.field == "idx"
    # A photo of another size: named, with both sizes.
    Image.fromarray(np.zeros((16, 16, 3), np.uint8)).save(img_dir / "05.png")
    with pytest.raises(CaptureError, match=r"16x16 .* but 00\.png is 32x32") as e:
        load_capture(folder)
    assert e.value.path.name == "05.png"
    # A grey photo among colour ones.
    Image.fromarray(np.zeros((SIZE, SIZE), np.uint8)).save(img_dir / "05.png")
    with pytest.raises(CaptureError, match=r"1 channels at 8 bits but 00\.png has 3"):
        load_capture(folder)


def test_bad_generic_json(tmp_path):
    img = np.full((2, 3, 3, 3), 0.5)
    cj = save_generic_capture(
        tmp_path, img, side=2.0, light_pos=[0.0, 0.0, 0.0], light_power=1.0,
        camera_pos=[0.0, 0.0, 5.0], transfer="gamma2.2", file_format="png8",
    )  # fmt: skip
    # A point light exactly on the plane, at the sample centre, is refused at load ...
    with pytest.raises(CaptureError, match=r"the light is at z = 0 cm") as e:
        load_capture(cj)
    assert e.value.field == "lights[0].position"
    # ... and built in Python it is status 6 with finite geometry (+z on the light itself,
    # where the irradiance is 0).
    ok_json = save_generic_capture(
        tmp_path / "ok", img, side=2.0, light_pos=[0.0, 0.0, 5.0], light_power=1.0,
        camera_pos=[0.0, 0.0, 5.0], transfer="gamma2.2", file_format="png8",
    )  # fmt: skip
    ok = load_capture(ok_json)
    cap = replace(ok, light_pos=np.zeros((2, 3)))
    status = geometry_status(cap.status, cap.points, cap.light_pos, None, cap.camera_pos)
    cap = replace(cap, status=status)
    assert np.all(cap.status == ObsStatus.LIGHT_BELOW_HORIZON)
    geo = cap.per_pixel_geometry()
    assert all(np.all(np.isfinite(v)) for v in geo.values())
    np.testing.assert_array_equal(geo["wi"][:, 1, 1], [[0.0, 0.0, 1.0]] * 2)
    assert np.all(geo["irradiance"][:, 1, 1] == 0)
    geo["cos_i"][:, 1, 1] = 0.0
    assert np.all(geo["cos_i"] == 0)
    spec = json.loads(cj.read_text())

    def broken(**changes):
        d = {**spec, **changes}
        for key in [key for key, v in changes.items() if v is None]:
            d.pop(key)
        cj.write_text(json.dumps(d))
        with pytest.raises(CaptureError) as e:
            load_capture(tmp_path)
        assert "capture.json" in str(e.value)
        return e.value

    e = broken(images=["00.png", "missing.png"])
    assert e.field == "images[1]" and "missing.png" in str(e)
    e = broken(lights=[{"type": "point", "power": 1.0}])
    assert e.field == "lights[0].position"
    e = broken(lights=[{"type": "spot", "position": [0, 0, 1], "power": 1}])
    assert e.field == "lights" and "spot" in str(e)
    e = broken(transfer="log-c")
    assert e.field == "transfer" and "log-c" in str(e)
    e = broken(transfer=None)
    assert e.field == "transfer" and "missing key" in str(e)
    e = broken(cameras=[{"position": [0, 0, 5]}] * 3)
    assert e.field == "cameras" and "1 or 2" in str(e)


# ----------------------------------------------------------------------------- non-finite input
def _tiny_materialgan(dst, k=2):
    """A MaterialGAN folder of k 2x2 grey photos with finite geometry."""
    dst.mkdir()
    for i in range(k):
        write_png(dst / f"{i:02d}.png", np.full((2, 2), 128, np.uint8))
    np.savetxt(dst / "camera_pos.txt", np.tile([0.0, 0.0, 10.0], (k, 1)), delimiter=",")
    np.savetxt(dst / "light_pos.txt", np.tile([1.0, 0.0, 10.0], (k, 1)), delimiter=",")
    (dst / "light_power.txt").write_text("100\n")
    (dst / "image_size.txt").write_text("2.0\n")
    return dst


@pytest.mark.parametrize("fname", ["camera_pos.txt", "light_pos.txt", "light_power.txt"])
@pytest.mark.parametrize("bad", ["nan", "inf", "-inf"])
def test_materialgan_refuses_non_finite_numbers(tmp_path, fname, bad):
    mg = _tiny_materialgan(tmp_path / "mg")
    assert np.all(np.isfinite(load_capture(mg).light_pos))
    lines = (mg / fname).read_text().splitlines()
    lines[-1] = ",".join([bad, *lines[-1].split(",")[1:]])
    (mg / fname).write_text("\n".join(lines) + "\n")
    with pytest.raises(CaptureError, match=rf"{fname}: line {len(lines)}: .*finite") as e:
        load_capture(mg)
    assert e.value.path.name == fname


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("light_pos", [[np.nan, 0.0, 10.0]]),
        ("camera_pos", [[0.0, np.inf, 10.0]]),
        ("light_power", [[np.nan]]),
        ("side", np.nan),
        ("side", 0.0),
        ("light_power", [[-1.0]]),
    ],
)
def test_capture_refuses_non_finite_geometry(field, value):
    cap = _small(np.zeros((1, 2, 2, 1)))
    with pytest.raises(CaptureError, match=field) as e:
        replace(cap, **{field: np.asarray(value)})
    assert e.value.field == field


def test_capture_refuses_bad_light_dir():
    cap = _small(np.zeros((1, 2, 2, 1)))
    for d, msg in (([[np.nan, 0.0, 1.0]], "non-finite"), ([[0.0, 0.0, 0.0]], "zero vector")):
        with pytest.raises(CaptureError, match=msg) as e:
            replace(cap, light_pos=None, light_dir=np.asarray(d))
        assert e.value.field == "light_dir"


def test_json_booleans_are_not_numbers(tmp_path):
    img = np.full((1, 2, 2, 3), 0.5)
    cj = save_generic_capture(
        tmp_path, img, side=2.0, light_pos=[0.0, 0.0, 5.0], light_power=1.0,
        camera_pos=[0.0, 0.0, 5.0], transfer="gamma2.2", file_format="png8",
    )  # fmt: skip
    spec = json.loads(cj.read_text())
    for key, value in (("side", True), ("saturation", False)):
        cj.write_text(json.dumps({**spec, key: value}))
        with pytest.raises(CaptureError, match="boolean") as e:
            load_capture(cj)
        assert e.value.field == key
    spec["lights"][0]["position"] = [0.0, True, 5.0]
    cj.write_text(json.dumps(spec))
    with pytest.raises(CaptureError, match="boolean") as e:
        load_capture(cj)
    assert e.value.field == "lights[0].position"
