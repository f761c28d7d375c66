"""OpenEXR reading and writing (jaxrefl.io._exr) on the OpenEXR sample images in
``shared/data/exr`` (from the openexr-images collection) and on files written here."""

from __future__ import annotations

import json

import numpy as np
import OpenEXR
import pytest

from jaxrefl.io import _atomic, _exr
from jaxrefl.io._exr import ExrFormatError, ExrImage, read_exr, write_exr, write_exr_rgb

# name -> (size (H, W), channels, tiled, number of parts, pixel type of every channel)
SAMPLES = {
    "AllHalfValues.exr": ((256, 256), ["B", "G", "R"], False, 1, "HALF"),
    "BrightRingsNanInf.exr": ((800, 800), ["B", "G", "R"], False, 1, "HALF"),
    "Desk.exr": ((874, 644), ["A", "B", "G", "R"], False, 1, "HALF"),
    "GoldenGate.exr": ((860, 1262), ["B", "G", "R"], True, 1, "HALF"),
    "WideFloatRange.exr": ((500, 500), ["G"], False, 1, "FLOAT"),
    "stripes.exr": ((50, 100), ["A", "B", "G", "R"], False, 1, "HALF"),
    "multipart.0001.exr": ((876, 877), ["A", "B", "G", "R"], False, 10, "HALF"),
    "singlepart.0001.exr": ((876, 911), None, False, 1, "HALF"),
}


@pytest.fixture(scope="module")
def exr_dir(shared_data):
    return shared_data / "exr"


@pytest.mark.parametrize("name", sorted(SAMPLES))
def test_sample_layout(exr_dir, name):
    size, names, tiled, nparts, ptype = SAMPLES[name]
    im = read_exr(exr_dir / name)
    assert isinstance(im, ExrImage)
    assert im.size == size and im.tiled is tiled and len(im.parts) == nparts
    if names is not None:
        assert sorted(im.channels) == names
    assert set(im.pixel_types.values()) == {ptype}
    for arr in im.channels.values():
        assert arr.shape == size and arr.dtype == np.float32
    (x0, y0), (x1, y1) = im.header["dataWindow"]
    assert (y1 - y0 + 1, x1 - x0 + 1) == size
    assert im.header["channels"] == im.pixel_types
    assert "not supported" not in im.report()


def test_all_half_values(exr_dir):
    """Every one of the 65536 half bit patterns appears once per channel."""
    im = read_exr(exr_dir / "AllHalfValues.exr")
    for name, arr in im.channels.items():
        bits = arr.astype(np.float16).view(np.uint16)  # float32 -> half is exact here
        assert np.unique(bits).size == 65536
        finite = arr[np.isfinite(arr)]
        assert finite.max() == 65504.0 and finite.min() == -65504.0
        assert np.min(np.abs(finite[finite != 0])) == 2.0**-24  # smallest subnormal
        assert np.isposinf(arr).sum() == 1 and np.isneginf(arr).sum() == 1
        assert np.isnan(arr).sum() == 2046  # 2 signs x (2**10 - 1) mantissas
        assert im.nonfinite[name] == 2048
    assert "B: 2046 NaN, 2 Inf" in im.report()
    assert (~im.valid_mask()).sum() == 2048


def test_nan_inf_reported_and_masked(exr_dir):
    im = read_exr(exr_dir / "BrightRingsNanInf.exr")
    assert im.nonfinite == {"B": 6, "G": 6, "R": 6}
    rgb = im.rgb()
    assert rgb.shape == (800, 800, 3) and rgb.dtype == np.float32
    assert np.isnan(rgb[320, 320]).all() and np.isinf(rgb[360, 360]).all()
    mask = im.valid_mask()
    assert mask.shape == (800, 800) and mask.dtype == bool
    assert (~mask).sum() == 12  # the NaN/Inf pixels of B, G, R are at different places
    assert np.isfinite(rgb[mask]).all() and not np.isfinite(rgb[~mask]).all(axis=-1).any()
    assert (~im.valid_mask(["G"])).sum() == 6
    report = im.report()
    assert "12 of 640000 pixels" in report
    for c in "BGR":
        assert f"{c}: 2 NaN, 4 Inf" in report
    assert "all values finite" in read_exr(exr_dir / "stripes.exr").report()


def test_float_channel_and_attributes(exr_dir):
    g = read_exr(exr_dir / "WideFloatRange.exr").channels["G"]
    assert g.max() == np.float32(2.0**127) and g.min() == -np.float32(2.0**127)
    gg = read_exr(exr_dir / "GoldenGate.exr")
    h = gg.header
    assert h["owner"] == "Copyright 2004 Industrial Light & Magic"
    assert h["expTime"] == 8.0 and h["compression"] == "PIZ_COMPRESSION"
    assert h["tiles"]["xSize"] == 128 and h["type"] == "tiledimage"
    desk = read_exr(exr_dir / "Desk.exr")
    np.testing.assert_array_equal(desk.rgba()[..., 3], 1.0)
    np.testing.assert_array_equal(desk.rgba()[..., :3], desk.rgb())


def test_multipart_selection_and_windows(exr_dir):
    path = exr_dir / "multipart.0001.exr"
    first = read_exr(path)
    assert first.parts[:3] == ["rgba_right", "depth_left", "forward_left"]
    assert first.part_name == "rgba_right" and first.part_index == 0
    z = read_exr(path, part="depth_left")
    assert list(z.channels) == ["Z"] and z.part_index == 1 and z.header["view"] == "left"
    mask = read_exr(path, part=3, channels=["whitebarmask.mask"])
    assert mask.part_name == "whitebarmask_left" and mask.size == (769, 385)
    assert mask.data_window == ((1106, 245), (1490, 1013))
    assert mask.display_window == ((0, 0), (2047, 1555))
    shown = mask.display()
    assert shown.shape == (1556, 2048, 1)
    np.testing.assert_array_equal(shown[245:1014, 1106:1491, 0], mask.channels["whitebarmask.mask"])
    assert np.isnan(shown[:245]).all() and np.isnan(shown[:, 1491:]).all()
    with pytest.raises(ExrFormatError, match=r"no part 'nope'.*10 part\(s\): rgba_right"):
        read_exr(path, part="nope")
    with pytest.raises(ExrFormatError, match=r"multipart\.0001\.exr"):
        read_exr(path, part=10)
    with pytest.raises(ExrFormatError, match=r"no channel\(s\) \['Q'\]"):
        read_exr(path, part=1, channels=["Q"])


def test_layers_and_multipart_agree(exr_dir):
    """singlepart.0001.exr holds the views of multipart.0001.exr as layers (``left.R`` ...)."""
    single = read_exr(exr_dir / "singlepart.0001.exr")
    assert single.part_name == "rgba" and "left" in single.layers
    left = single.rgba(layer="left")
    np.testing.assert_array_equal(left[..., 0], single.channels["left.R"])
    left_part = read_exr(exr_dir / "multipart.0001.exr", part="rgba_left")
    a, b = (
        left_part.display(["R", "G", "B", "A"]),
        single.display(["left.R", "left.G", "left.B", "left.A"]),
    )
    inside = np.isfinite(a)
    assert inside.sum() == 876 * 877 * 4
    np.testing.assert_array_equal(a[inside], b[inside])
    with pytest.raises(
        ExrFormatError, match=r"no channel\(s\) right\.R.*layers with an R channel: \(none\), left"
    ):
        single.rgb(layer="right")


def test_unsupported_layouts_are_refused(exr_dir, tmp_path):
    yc = exr_dir / "Rec709_YC.exr"
    with pytest.raises(ExrFormatError) as err:
        read_exr(yc)
    assert str(yc) in str(err.value)
    assert "luminance/chroma (Y, RY, BY) EXR is not supported; convert to RGB first" in str(
        err.value
    )
    # Same file with the chroma channels renamed BY -> BX, RY -> RX (same length, still
    # sorted): a plain image with 2x2-subsampled channels.
    raw = yc.read_bytes()
    start = raw.index(b"channels\0chlist\0")
    head = raw[start : start + 200].replace(b"BY\0", b"BX\0", 1).replace(b"RY\0", b"RX\0", 1)
    sub = tmp_path / "subsampled.exr"
    sub.write_bytes(raw[:start] + head + raw[start + 200 :])
    with pytest.raises(
        ExrFormatError, match=r"subsampled\.exr: subsampled channels .*BX \(2x2\), RX \(2x2\)"
    ):
        read_exr(sub)
    # A deep scanline file, written with the bindings (each pixel an array of samples).
    z = np.empty((2, 3), dtype=object)
    for i in np.ndindex(z.shape):
        z[i] = np.arange(sum(i), dtype=np.float32)
    deep = tmp_path / "deep.exr"
    OpenEXR.File(
        {"compression": OpenEXR.ZIPS_COMPRESSION, "type": OpenEXR.deepscanline}, {"Z": z}
    ).write(str(deep))
    with pytest.raises(
        ExrFormatError, match=r"deep\.exr: deep EXR \(deepscanline\) is not supported"
    ):
        read_exr(deep)


def test_missing_and_corrupt_files(exr_dir, tmp_path):
    missing = tmp_path / "nowhere.exr"
    with pytest.raises(FileNotFoundError, match=r"nowhere\.exr"):
        read_exr(missing)
    raw = (exr_dir / "BrightRingsNanInf.exr").read_bytes()
    truncated = tmp_path / "truncated.exr"
    truncated.write_bytes(raw[: len(raw) // 2])  # header intact, pixel data cut
    with pytest.raises(ExrFormatError, match=r"truncated\.exr: corrupt or truncated"):
        read_exr(truncated)
    # last chunk of a 10-part file cut: the bindings silently return fewer parts
    raw_mp = (exr_dir / "multipart.0001.exr").read_bytes()
    (tmp_path / "mp.exr").write_bytes(raw_mp[:-100])
    with pytest.raises(ExrFormatError, match=r"mp\.exr: corrupt or truncated.*only 8 of 10 parts"):
        read_exr(tmp_path / "mp.exr", part=0)
    stub = tmp_path / "stub.exr"
    stub.write_bytes(raw[:200])  # header cut
    with pytest.raises(ExrFormatError, match=r"stub\.exr: not a readable OpenEXR file"):
        read_exr(stub)
    text = tmp_path / "text.exr"
    text.write_text("not an image")
    with pytest.raises(ExrFormatError, match=r"text\.exr"):
        read_exr(text)


def _outputs(rng, h=5, w=7):
    albedo = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    rough = rng.uniform(1e-4, 1, (h, w)).astype(np.float32)
    rough[0, 0] = np.nan  # a pixel that failed
    return {
        "albedo.R": albedo[..., 0],
        "albedo.G": albedo[..., 1],
        "albedo.B": albedo[..., 2],
        "roughness": rough,
        "roughness.std": rng.uniform(0, 0.1, (h, w)),  # float64 -> stored as float32
        "status": rng.integers(0, 5, (h, w)).astype(np.int32),
    }


def test_round_trip_channels_and_metadata(tmp_path):
    chans = _outputs(np.random.default_rng(0))
    meta = {
        "model": "ward",
        "units": "1/sr",
        "version": "0.1.0",
        "n_iter": 40,
        "alpha_bounds": [1e-4, 1.0],
        "fit": {"loss": "l2", "ok": True},
    }
    path = write_exr(tmp_path / "fit.exr", chans, metadata=meta, half={"roughness.std"})
    im = read_exr(path)
    assert im.pixel_types == {
        "albedo.B": "FLOAT",
        "albedo.G": "FLOAT",
        "albedo.R": "FLOAT",
        "roughness": "FLOAT",
        "roughness.std": "HALF",
        "status": "UINT",
    }
    for c in "RGB":
        np.testing.assert_array_equal(im.channels[f"albedo.{c}"], chans[f"albedo.{c}"])
    np.testing.assert_array_equal(im.channels["roughness"], chans["roughness"])  # NaN too
    std = im.channels["roughness.std"]
    np.testing.assert_array_equal(std, chans["roughness.std"].astype(np.float16).astype(np.float32))
    assert np.max(np.abs(std - chans["roughness.std"])) <= 2.0**-11 * 0.1
    assert im.channels["status"].dtype == np.uint32
    np.testing.assert_array_equal(im.channels["status"], chans["status"])
    assert im.nonfinite["roughness"] == 1 and sum(im.nonfinite.values()) == 1
    assert im.metadata == meta
    assert im.header["jaxrefl/model"] == "ward" and json.loads(im.header["jaxrefl/n_iter"]) == 40
    assert im.header["compression"] == "ZIP_COMPRESSION" and im.header["type"] == "scanlineimage"
    assert im.header["software"].startswith("jaxrefl") and len(im.header["capDate"]) == 19
    assert isinstance(im.header["utcOffset"], float)
    np.testing.assert_array_equal(
        im.stack(["albedo.R", "albedo.G", "albedo.B"]), im.rgb(layer="albedo")
    )
    # all-half, other compression; integer channels stay UINT under half=True
    im2 = read_exr(write_exr(tmp_path / "h.exr", chans, half=True, compression="piz"))
    assert im2.pixel_types["status"] == "UINT" and im2.pixel_types["albedo.R"] == "HALF"
    assert im2.header["compression"] == "PIZ_COMPRESSION"


def test_write_rgb(tmp_path):
    img = np.random.default_rng(1).uniform(0, 2, (4, 6, 4)).astype(np.float32)
    im = read_exr(write_exr_rgb(tmp_path / "rgba.exr", img, metadata={"scene": "test"}))
    np.testing.assert_array_equal(im.rgba(), img)
    im = read_exr(write_exr_rgb(tmp_path / "lay.exr", img[..., :3], layer="render", half=True))
    assert sorted(im.channels) == ["render.B", "render.G", "render.R"]
    np.testing.assert_array_equal(
        im.rgb("render"), img[..., :3].astype(np.float16).astype(np.float32)
    )
    with pytest.raises(ExrFormatError, match=r"bad\.exr: image must have shape"):
        write_exr_rgb(tmp_path / "bad.exr", img[..., :2])


@pytest.mark.parametrize(
    ("chans", "kwargs", "match"),
    [
        ({}, {}, "nothing to write"),
        ({"": np.zeros((2, 2))}, {}, "non-empty strings"),
        (
            {"a": np.zeros((2, 2)), "b": np.zeros((2, 3))},
            {},
            r"'b' has shape \(2, 3\), but 'a' has \(2, 2\)",
        ),
        ({"a": np.zeros(4)}, {}, r"\(H, W\) array"),
        ({"a": np.full((2, 2), 1e5)}, {"half": True}, r"overflow half \(max 65504\)"),
        ({"a": np.full((2, 2), 1e300)}, {}, "overflow float32"),
        ({"s": -np.ones((2, 2), dtype=int)}, {}, r"outside 0..2\*\*32-1"),
        ({"s": np.ones((2, 2), dtype=int)}, {"half": {"s"}}, "cannot be written as half"),
        ({"a": np.zeros((2, 2))}, {"half": {"b"}}, r"unknown channels \['b'\]"),
        ({"a": np.zeros((2, 2))}, {"compression": "gzip"}, "unknown compression 'gzip'"),
        ({"a": np.zeros((2, 2))}, {"metadata": {"f": object()}}, "not JSON-serialisable"),
    ],
)
def test_write_validation(tmp_path, chans, kwargs, match):
    with pytest.raises(ExrFormatError, match=match) as err:
        write_exr(tmp_path / "out.exr", chans, **kwargs)
    assert str(tmp_path / "out.exr") in str(err.value)
    assert list(tmp_path.iterdir()) == []  # nothing written, no temporary file left


def test_atomic_write(tmp_path, monkeypatch):
    path = tmp_path / "result.exr"
    write_exr(path, {"a": np.ones((3, 4), np.float32)}, metadata={"run": 1})
    before = path.read_bytes()
    # 1. invalid input: refused before any file is created
    with pytest.raises(ExrFormatError):
        write_exr(path, {"a": np.ones((3, 4)), "b": np.ones((4, 3))})
    assert path.read_bytes() == before and sorted(tmp_path.iterdir()) == [path]

    # 2. the writer dies half way through the temporary file
    written = []

    def dying_writer(exr_file, tmp):
        assert tmp.parent == path.parent and tmp != path
        tmp.write_bytes(b"v/1\x01 partial")
        written.append(tmp)
        raise OSError("disk full")

    monkeypatch.setattr(_exr, "_write_file", dying_writer)
    with pytest.raises(OSError, match="disk full"):
        write_exr(path, {"a": np.zeros((3, 4), np.float32)}, metadata={"run": 2})
    assert written and not written[0].exists()
    assert path.read_bytes() == before and sorted(tmp_path.iterdir()) == [path]
    assert read_exr(path).metadata == {"run": 1}

    # 3. a successful write replaces the file completely
    monkeypatch.undo()
    path.chmod(0o640)
    write_exr(path, {"b": np.zeros((2, 2), np.float32)}, metadata={"run": 3})
    im = read_exr(path)
    assert list(im.channels) == ["b"] and im.metadata == {"run": 3}
    assert sorted(tmp_path.iterdir()) == [path] and (path.stat().st_mode & 0o777) == 0o640


def test_unwritable_folder_names_the_target(tmp_path, monkeypatch):
    def refuse(path, *args, **kwargs):
        raise PermissionError(13, "Permission denied", str(path))

    monkeypatch.setattr(_atomic.os, "open", refuse)  # a read-only folder (root ignores modes)
    target = tmp_path / "out.exr"
    with pytest.raises(PermissionError, match=r"cannot write out\.exr in .*Permission denied") as e:
        write_exr(target, {"Y": np.zeros((2, 2), np.float32)})
    assert e.value.filename == str(target) and ".tmp" not in str(e.value)
