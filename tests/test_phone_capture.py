"""Phone photos to a capture (``jaxrefl.phone``, ``jaxrefl frame``, ``jaxrefl capture``).

A set of photos is rendered (``jaxrefl.phone.render_photo``): a pinhole camera with radial
distortion (k1, k2) and an off-centre principal point, held by hand at six positions 25-29 cm
above the printed frame (side 17 cm) with a textured, flash-lit GGX sample 1 mm below the
marker plane; 640 x 480 JPEGs (quality 95, 4:4:4) with EXIF exposure tags. The set goes
through ``jaxrefl capture`` and back through ``jaxrefl.io.load_capture``, and is compared
with the truth: camera positions, reprojection error, and the rectified photos against the
sample rendered directly at their pixel centres from the true camera positions.
"""

from __future__ import annotations

import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from jaxrefl import JaxreflError  # noqa: E402
from jaxrefl.cli import main  # noqa: E402
from jaxrefl.io import load_capture  # noqa: E402
from jaxrefl.phone import (  # noqa: E402
    CaptureOptions,
    DetectorOptions,
    FrameLayout,
    PhoneCamera,
    PhoneCaptureError,
    Refinement,
    corner_pixels,
    default_sample,
    detect_markers,
    photos_to_capture,
    read_photo_meta,
    render_photo,
    render_sample,
    tag_cells,
    write_jpeg,
)

SIDE, DEPTH, SIZE = 17.0, 0.1, 128
LENS = {"f": 520.0, "cx": 323.1, "cy": 238.4, "k1": -0.12, "k2": 0.05}
# exposure 1/60 s, ISO 100, f/1.8, orientation 1, make
EXIF = {0x829A: (1, 60), 0x8827: 100, 0x829D: (18, 10), 0x0112: 1, 0x010F: "jaxrefl test"}


@dataclass
class PhotoSet:
    raw: Path
    files: list[Path]
    cameras: list[PhoneCamera]


def _cameras(n: int, seed: int = 0) -> list[PhoneCamera]:
    """Hand-held views: the phone 25-29 cm up, up to 7 cm off centre, aimed near the centre,
    turned by a few degrees."""
    rng = np.random.default_rng(seed)
    offsets = [(0, 0), (6, 0), (-6, 1), (1, 6), (0, -6), (5, 5), (-5, -5), (4, -5)][:n]
    return [
        PhoneCamera(
            position=(ox + rng.normal(0, 0.5), oy + rng.normal(0, 0.5), 27 + rng.normal(0, 1)),
            look_at=(rng.normal(0, 0.8), rng.normal(0, 0.8), 0.0),
            roll=rng.normal(0, 8),
            **LENS,
        )
        for ox, oy in offsets
    ]


@pytest.fixture(scope="module")
def photos(tmp_path_factory) -> PhotoSet:
    raw = tmp_path_factory.mktemp("raw")
    layout, sample = FrameLayout(SIDE), default_sample()
    cams = _cameras(6)
    files = []
    for k, cam in enumerate(cams):
        img = render_photo(cam, layout, sample, depth=DEPTH, supersample=2)
        files.append(write_jpeg(raw / f"IMG_{k:04d}.jpg", img, EXIF))
    return PhotoSet(raw, files, cams)


def _folder(tmp_path: Path, files: list[Path], name: str = "raw") -> Path:
    d = tmp_path / name
    d.mkdir()
    for f in files:
        shutil.copy(f, d / f.name)
    return d


def _nothing_written(tmp_path: Path, out: Path) -> None:
    assert not out.exists()
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(f".{out.name}.")]


# ------------------------------------------------------------------------------- the frame
def test_tag_patterns_are_opencvs_apriltag_dictionary():
    """The frame's tags, drawn without OpenCV, are OpenCV's DICT_APRILTAG_36h11 markers 0-15
    up to a turn (OpenCV versions differ in which turn: jaxrefl.phone._tags)."""
    d = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_APRILTAG_36h11)
    for i in range(16):
        theirs = d.generateImageMarker(i, 8) > 0
        assert any(np.array_equal(np.rot90(theirs, k), tag_cells(i)) for k in range(4)), i


def test_frame_command_writes_a_true_scale_sheet(tmp_path, capsys):
    png, pdf = tmp_path / "frame.png", tmp_path / "frame.pdf"
    assert main(["frame", "--side", "17", "--out", str(png), "--dpi", "120"]) == 0
    assert main(["frame", "--side", "17", "--out", str(pdf)]) == 0
    assert "tag36h11 ids 0-15, side 17 cm" in capsys.readouterr().out
    assert pdf.read_bytes()[:5] == b"%PDF-"
    gray = cv2.imread(str(png), cv2.IMREAD_GRAYSCALE)
    det = detect_markers(gray)
    assert det.ids.tolist() == list(range(16))
    # tag 0 to tag 4 (top row) are 16 layout units = 16/18 of the side apart, at 120 dpi
    px_per_cm = 120 / 2.54
    span = np.linalg.norm(det.corners[4].mean(0) - det.corners[0].mean(0)) / px_per_cm
    assert span == pytest.approx(SIDE * 16 / 18, abs=0.05)  # half a pixel at 120 dpi
    # corners as printed: tag 0's top-left is up and to the left of its bottom-right
    tl, br = det.corners[0][0], det.corners[0][2]
    assert tl[0] < br[0] and tl[1] < br[1]


def test_edge_refinement_beats_opencvs_corners(photos):
    """The default refinement (the ring's edges in linear intensity) against OpenCV's own
    corners on a rendered JPEG; benchmarks/marker_detection.py measures all of them on
    finer renders."""
    layout, cam = FrameLayout(SIDE), photos.cameras[1]
    gray = cv2.cvtColor(cv2.imread(str(photos.files[1])), cv2.COLOR_BGR2GRAY)
    truth = corner_pixels(cam, layout)

    def rms(refinement: Refinement) -> float:
        det = detect_markers(gray, DetectorOptions(refinement=refinement))
        assert det.count == 16
        return float(np.sqrt(np.mean(np.sum((det.corners - truth[det.ids]) ** 2, -1))))

    ours = rms(Refinement.EDGES)
    theirs = min(rms(r) for r in Refinement if r is not Refinement.EDGES)
    # 2 x 2 samples per pixel draw edges to ~0.2 px; OpenCV's corners sit >= 0.5 px inside
    assert ours < 0.3 and ours < theirs / 2


# ------------------------------------------------------------------------------- the capture
def test_capture_recovers_cameras_and_sample(photos, tmp_path, capsys):
    out = tmp_path / "cap"
    argv = ["capture", str(photos.raw), "--side", str(SIDE), "--out", str(out)]
    assert main([*argv, "--depth", str(DEPTH), "--size", str(SIZE)]) == 0
    assert "wrote 6 rectified photos" in capsys.readouterr().out
    cap = load_capture(out)
    rec = json.loads((out / "calibration.json").read_text())
    truth = np.array([c.position for c in photos.cameras]) + np.array([0.0, 0.0, DEPTH])
    assert cap.images.shape == (6, SIZE, SIZE, 3)
    assert cap.side == pytest.approx(SIDE * 0.64)
    # the target: camera positions within 2 mm (capture coordinates, cm)
    assert np.max(np.linalg.norm(cap.camera_pos - truth, axis=1)) < 0.2
    np.testing.assert_allclose(cap.light_pos, cap.camera_pos)  # flash at the lens
    errors = [p["reprojection_error_px"] for p in rec["photos"]]
    assert max(errors) < 0.5  # the target: reprojection error under 0.5 pixel
    k = np.array(rec["intrinsics"]["camera_matrix"])
    assert k[0, 0] == pytest.approx(LENS["f"], rel=0.01)  # 1%: a 2.7 mm range error at 27 cm
    for p, cam in zip(rec["photos"], photos.cameras, strict=True):
        axis = np.array(p["camera_orientation"])[:, 2]  # the camera's forward axis
        want = cam.rotation()[2]
        assert np.degrees(np.arccos(np.clip(axis @ want, -1, 1))) < 0.5  # well under a degree
        assert p["metadata"]["exposure_time"] == pytest.approx(1 / 60)
        assert p["metadata"]["iso"] == 100 and p["metadata"]["f_number"] == pytest.approx(1.8)
        assert p["metadata"]["relative_exposure"] == pytest.approx(1.0)
    # Rectified photos against the sample rendered directly at their pixel centres from the
    # true positions, linear values: RMS difference over the square / mean reference value.
    layout, sample = FrameLayout(SIDE), default_sample()
    for i, cam in enumerate(photos.cameras):
        ref = render_sample(np.array(cam.position), layout, sample, SIZE, depth=DEPTH)
        rmse = np.sqrt(np.mean((np.asarray(cap.images[i], np.float64) - ref) ** 2))
        assert rmse / ref.mean() < 0.01, i  # the target: within 1% RMSE
    assert sorted(p.name for p in (out / "preview").iterdir()) == cap.meta.get(
        "images", [f"{i:02d}.png" for i in range(6)]
    )


def test_given_intrinsics_place_the_cameras(photos, tmp_path):
    """--intrinsics: the calibration.json of a first capture places a second set's cameras."""
    first = photos_to_capture(
        photos.raw, tmp_path / "a", CaptureOptions(side=SIDE, depth=DEPTH, size=32)
    )
    raw = _folder(tmp_path, photos.files[:3])
    out = tmp_path / "b"
    argv = ["capture", str(raw), "--side", str(SIDE), "--out", str(out), "--size", "32"]
    assert (
        main([*argv, "--depth", str(DEPTH), "--intrinsics", str(first.out / "calibration.json")])
        == 0
    )
    rec = json.loads((out / "calibration.json").read_text())
    assert rec["intrinsics"]["source"] == "given"
    got = np.array([p["camera_position"] for p in rec["photos"]])
    np.testing.assert_allclose(got, first.positions[:3], atol=1e-6)  # same camera, same poses


# ------------------------------------------------------------------------------- bad input
def test_photo_without_frame_is_left_out_and_named(photos, tmp_path, capsys):
    from PIL import Image

    raw = _folder(tmp_path, photos.files[:3])
    rng = np.random.default_rng(1)
    Image.fromarray(rng.integers(90, 160, (480, 640, 3), dtype=np.uint8)).save(raw / "table.jpg")
    out = tmp_path / "cap"
    assert main(["capture", str(raw), "--side", str(SIDE), "--out", str(out), "--size", "32"]) == 0
    text = capsys.readouterr().out
    assert "left out table.jpg: 0 of 16 tags (ids none)" in text
    assert len(load_capture(out).files) == 3


def test_too_few_usable_photos_writes_nothing(photos, tmp_path, capsys):
    from PIL import Image, ImageFilter

    raw = _folder(tmp_path, photos.files[:2])
    with Image.open(photos.files[2]) as img:
        img.filter(ImageFilter.GaussianBlur(4)).save(raw / "blurred.jpg", quality=95)
    out = tmp_path / "cap"
    assert main(["capture", str(raw), "--side", str(SIDE), "--out", str(out), "--size", "32"]) == 1
    err = capsys.readouterr().err
    assert "2 usable photos; a capture needs 3" in err
    assert "blurred.jpg:" in err and "of 16 tags" in err
    _nothing_written(tmp_path, out)


def test_photos_of_different_sizes_are_refused(photos, tmp_path):
    from PIL import Image

    raw = _folder(tmp_path, photos.files[:3])
    with Image.open(photos.files[3]) as img:
        img.resize((320, 240)).save(raw / "small.jpg")
    out = tmp_path / "cap"
    with pytest.raises(
        PhoneCaptureError, match=r"different sizes: IMG_0000.jpg is 640x480, small.jpg is 320x240"
    ):
        photos_to_capture(raw, out, CaptureOptions(side=SIDE, size=32))
    _nothing_written(tmp_path, out)


@dataclass(frozen=True)
class _StretchedView(PhoneCamera):
    """A camera looking at a frame printed ``stretch`` times longer down the page than
    across: the same rays traced in the frame's coordinates with y divided by ``stretch``
    (an affine map of space keeps rays straight and their hits on z = 0)."""

    stretch: float = 1.0

    def rays(self, u, v):
        d = super().rays(u, v) * np.array([1.0, 1.0 / self.stretch, 1.0])
        return d / np.linalg.norm(d, axis=-1, keepdims=True)


def test_frame_that_disagrees_with_the_layout_is_refused(tmp_path):
    """A print 8% short down the page: no camera puts the tags where a frame of this side
    does; the reprojection error says so, and nothing is written."""
    layout, sample = FrameLayout(SIDE), default_sample()
    raw = tmp_path / "raw"
    raw.mkdir()
    for k, cam in enumerate(_cameras(3, seed=2)):
        x, y, z = cam.position
        view = _StretchedView(
            position=(x, y / 0.92, z), look_at=cam.look_at, roll=cam.roll, **LENS, stretch=0.92
        )
        write_jpeg(raw / f"{k}.jpg", render_photo(view, layout, sample, supersample=1), EXIF)
    out = tmp_path / "cap"
    with pytest.raises(
        PhoneCaptureError,
        match=r"reprojection errors .* exceed 1 px: the tags are not where a 17 cm frame",
    ):
        photos_to_capture(raw, out, CaptureOptions(side=SIDE, size=32))
    _nothing_written(tmp_path, out)


def test_output_folder_in_the_way(photos, tmp_path):
    out = tmp_path / "cap"
    out.mkdir()
    (out / "keep.txt").write_text("mine")
    with pytest.raises(JaxreflError, match="exists and is not an empty folder"):
        photos_to_capture(photos.raw, out, CaptureOptions(side=SIDE, size=32))
    assert (out / "keep.txt").read_text() == "mine"


def test_missing_opencv_says_how_to_install(monkeypatch):
    import importlib

    from jaxrefl.phone._errors import require_cv2

    real = importlib.import_module

    def no_cv2(name, *a):
        if name == "cv2":
            raise ImportError("No module named 'cv2'")
        return real(name, *a)

    monkeypatch.setattr(importlib, "import_module", no_cv2)
    with pytest.raises(PhoneCaptureError, match=r"pip install 'jaxrefl\[capture\]'"):
        require_cv2()


# ------------------------------------------------------------------------------- metadata
def test_exif_exposure_tags_are_read(tmp_path):
    img = np.full((8, 8, 3), 0.2)
    tags = {0x829A: (1, 125), 0x8827: 400, 0x829D: (28, 10), 0x0112: 6, 0x920A: (47, 10)}
    meta = read_photo_meta(write_jpeg(tmp_path / "a.jpg", img, {**tags, 0x0110: "Phone 9"}))
    assert meta.exposure_time == pytest.approx(1 / 125)
    assert meta.iso == 400 and meta.f_number == pytest.approx(2.8)
    assert meta.orientation == 6 and meta.focal_length == pytest.approx(4.7)
    assert meta.model == "Phone 9"
    assert meta.exposure == pytest.approx((1 / 125) * 400 / 2.8**2)  # H = t S / N^2
    assert meta.transfer == "srgb"


def test_missing_exif_is_none_and_srgb(tmp_path):
    from PIL import Image

    Image.fromarray(np.full((8, 8, 3), 100, np.uint8)).save(tmp_path / "plain.jpg")
    meta = read_photo_meta(tmp_path / "plain.jpg")
    assert meta.exposure_time is None and meta.iso is None and meta.f_number is None
    assert meta.exposure is None and meta.orientation == 1
    assert (meta.transfer, meta.transfer_source) == ("srgb", "assumed: no colour metadata")


def test_transfer_follows_the_colour_metadata():
    """ColorSpace uncalibrated + interoperability index R03 is Adobe RGB (Pillow cannot
    write the interoperability IFD, so the rule is checked on the parsed tags)."""
    from types import SimpleNamespace

    from jaxrefl.phone._exif import _transfer

    plain = SimpleNamespace(info={})
    assert _transfer(plain, {0xA001: 0xFFFF}, {0x0001: "R03"})[0] == f"gamma{563 / 256!r}"
    assert _transfer(plain, {0xA001: 1}, {})[0] == "srgb"
    assert _transfer(plain, {0xA001: 0xFFFF}, {})[0] == "srgb"  # uncalibrated, no index
