"""Export for renderers: channel names, textures, Mitsuba 3 and glTF 2.0.

The render check: a 32 x 32 flat sample facing a pinhole camera with a point light at the
camera (a flash), rendered by Mitsuba 3 (``scalar_rgb``, ``direct`` integrator) from the
exported scene and by :func:`jaxrefl.scene.render` from the same maps. With the light at
the camera the half vector is the view direction, so Schlick's factor is F0 exactly, and
within the 19.5 degrees of this view Burley's retro-reflection ((1 - cos)^5 < 1e-6), the
dielectric-versus-Schlick Fresnel (evaluated at cos = 1) and separable-versus-correlated
Smith G (relative difference about Lambda^2 < 1e-4) are negligible: the two agree up to
Mitsuba's pixel integration (the box filter averages each pixel's footprint, jaxrefl takes
its centre), measured at 0.05% median and 0.5% max over the pixels with nearest-texel
lookups and 256 samples a pixel. The tolerances are 0.3% median and 1.5% max.
"""

from __future__ import annotations

import json
from pathlib import Path

import jax.numpy as jnp
import numpy as np
import pytest

from jaxrefl import brdf, svbrdf
from jaxrefl.cli import main
from jaxrefl.io import corr_name, exr_channel, map_key, map_name, read_png, write_exr
from jaxrefl.scene import PinholeCamera, PointLight, planar_points, render
from jaxrefl.svbrdf._export import F0_DIELECTRIC, FlashView, mitsuba_scene, renderer_maps

mi = pytest.importorskip("mitsuba")

N = 32
SIDE, DIST, POWER = 2.0, 4.0, 10.0


def test_channel_names_follow_one_scheme():
    assert map_name("albedo.R") == "albedo.R" and map_name("alpha") == "alpha"
    assert map_name("albedo.R", "_std") == "albedo_std.R"
    assert map_name("alpha", "_q05") == "alpha_q05"
    assert corr_name("albedo.R", "alpha") == "corr_albedo_R_alpha"
    assert exr_channel("alpha_std") == "alpha_std.Y" and exr_channel("albedo.G") == "albedo.G"
    for name in ("alpha", "albedo_std.B", "normal.Y", "normal.X", "corr_tilt_x_tilt_y"):
        assert map_key(exr_channel(name)) == name
    with pytest.raises(ValueError, match="starts with '_'"):
        map_name("alpha", ".std")


def _maps(normals: bool) -> dict[str, np.ndarray]:
    """Smooth metallic-roughness maps (so that the metallic view is exact) as a fit's maps:
    albedo = b (1 - m), F0 = 0.04 (1 - m) + b m (Mitsuba principled's reading)."""
    u = np.linspace(0.0, 1.0, N)
    uu, vv = np.meshgrid(u, u)
    base = np.stack([0.2 + 0.6 * uu, 0.3 + 0.4 * vv, 0.5 - 0.3 * uu * vv], -1)
    metal = 0.6 * uu * vv
    alb, f0 = brdf.metallic_to_specular(jnp.asarray(base), jnp.asarray(metal))
    alb = np.asarray(alb) / (1.0 - F0_DIELECTRIC)
    maps = {f"albedo.{c}": alb[..., i] for i, c in enumerate("RGB")}
    maps |= {f"specular.{c}": np.asarray(f0)[..., i] for i, c in enumerate("RGB")}
    maps["alpha"] = (0.3 + 0.4 * vv) ** 2
    if normals:
        n = np.stack([0.15 * np.sin(2 * np.pi * uu), 0.1 * np.cos(2 * np.pi * vv), 1 + 0 * uu], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        maps |= {f"normal.{a}": n[..., i] for i, a in enumerate("XYZ")}
    maps["status"] = np.zeros((N, N), np.uint32)
    return {
        k: np.asarray(v, v.dtype if v.dtype == np.uint32 else np.float32) for k, v in maps.items()
    }


def _jaxrefl_render(maps):
    model, _ = svbrdf.capture_model("ggx_rgb")
    params = {
        "albedo": np.stack([maps[f"albedo.{c}"] for c in "RGB"], -1),
        "specular": np.stack([maps[f"specular.{c}"] for c in "RGB"], -1),
        "alpha": maps["alpha"],
    }
    normals = None
    if "normal.X" in maps:
        normals = np.stack([maps[f"normal.{a}"] for a in "XYZ"], -1)
    eye = np.array([0.0, 0.0, DIST])
    img = render(
        model,
        params,
        PointLight(eye, jnp.full((3,), POWER)),
        PinholeCamera(eye, look_at=(0.0, 0.0, 0.0)),
        points=planar_points(N, N, SIDE),
        normals=normals,
        cos4=False,  # Mitsuba's film records radiance: no vignetting
    )
    return np.asarray(img)[0]


def _nearest(d):
    if isinstance(d, dict):
        if d.get("type") == "bitmap":
            d["filter_type"] = "nearest"
        for v in d.values():
            _nearest(v)


@pytest.mark.parametrize("normals", [False, True], ids=["flat", "normal_map"])
def test_mitsuba_render_of_the_export_matches_jaxrefl(tmp_path, normals):
    mi.set_variant("scalar_rgb")
    maps = _maps(normals)
    paths = svbrdf.write_mitsuba(maps, tmp_path)
    assert (tmp_path / "scene.xml") in paths and all(p.exists() for p in paths)
    tex = svbrdf.write_textures(maps, tmp_path)
    assert ("normal_exr" in tex.files) == normals
    view = FlashView(side=SIDE, distance=DIST, intensity=POWER, width=N, height=N)
    scene = mitsuba_scene(tex, view)
    _nearest(scene)  # texel = pixel: no bilinear blur between neighbours
    img = np.array(mi.render(mi.load_dict(scene), seed=0, spp=256))
    ref = _jaxrefl_render(maps)
    rel = np.abs(img / ref - 1.0)
    assert np.median(rel) < 3e-3 and rel.max() < 1.5e-2, (np.median(rel), rel.max())
    # the XML file is the same scene (default view, bilinear textures) as the dict
    xml = np.array(mi.render(mi.load_file(str(tmp_path / "scene.xml")), seed=1, spp=4))
    same = np.array(mi.render(mi.load_dict(mitsuba_scene(tex)), seed=1, spp=4))
    np.testing.assert_allclose(xml, same, rtol=1e-5, atol=1e-7)


def test_maps_exr_loads_and_splits_in_mitsuba(tmp_path):
    """maps.exr's channels (value, std, correlation, codes) split into RGB and Y layers."""
    mi.set_variant("scalar_rgb")
    maps = _maps(normals=True)
    maps["alpha_std"] = 0.1 * maps["alpha"]
    maps[map_name("albedo.G", "_std")] = maps["albedo.G"]
    maps[corr_name("albedo.R", "alpha")] = maps["alpha"]
    write_exr(tmp_path / "maps.exr", {exr_channel(k): v for k, v in maps.items()})
    layers = dict(mi.Bitmap(str(tmp_path / "maps.exr")).split())
    pf = mi.Bitmap.PixelFormat
    assert layers["albedo"].pixel_format() == pf.RGB
    assert layers["specular"].pixel_format() == pf.RGB
    assert layers["normal"].pixel_format() == pf.XYZ
    for name in ("alpha", "alpha_std", "status", "corr_albedo_R_alpha"):
        assert layers[name].pixel_format() == pf.Y, name
    np.testing.assert_array_equal(np.array(layers["alpha"]).reshape(N, N), maps["alpha"])
    # a single-layer texture of the export loads in the bitmap plugin
    tex = svbrdf.write_textures(tmp_path, tmp_path / "tex")
    mi.load_dict({"type": "bitmap", "filename": str(tex.path("roughness_exr"))})


def test_metallic_view_and_principled_specular():
    """Grey dielectric F0 <= 0.04: metallic 0, the base colour the albedo (principled) or
    albedo / 0.96 (glTF); principled's specular is F0 / 0.08, clipped at 1."""
    h, w = 2, 3
    rgb = zip("RGB", (0.5, 0.3, 0.2), strict=True)
    maps = {f"albedo.{c}": np.full((h, w), v, np.float32) for c, v in rgb}
    maps["specular"] = np.array([[0.02, 0.04, 0.06], [0.2, 0.1, 0.03]], np.float32)
    maps["alpha"] = np.full((h, w), 0.25, np.float32)
    maps["albedo.R"][1, 2] = np.nan  # no estimate: black, rough (alpha 1), dielectric
    rm = renderer_maps(maps)
    assert rm.missing.sum() == 1 and rm.missing[1, 2]
    assert rm.roughness[1, 2] == 1 and np.all(rm.base_color[1, 2] == 0)
    np.testing.assert_allclose(rm.roughness[~rm.missing], 0.5)
    assert rm.metallic[0, 0] == 0 and rm.metallic_principled[0, 0] == 0
    np.testing.assert_allclose(rm.base_color_principled[0, 0], [0.5, 0.3, 0.2], rtol=1e-6)
    np.testing.assert_allclose(rm.base_color[0, 0], np.array([0.5, 0.3, 0.2]) / 0.96, rtol=1e-6)
    np.testing.assert_allclose(rm.specular[0], [0.25, 0.5, 0.75], rtol=1e-6)
    assert rm.specular[1, 0] == 1.0  # F0 0.2 > 0.08: clipped
    assert 0 < rm.metallic[0, 2] < 1  # a dielectric F0 above 0.04: partly metallic
    with pytest.raises(ValueError, match="8 or 16"):
        svbrdf.write_textures(maps, "unused", bits=12)


def assert_valid_gltf(path: Path) -> dict:
    """The glTF 2.0 spec's required fields and index ranges (sections 5.x 'Properties')."""
    doc = json.loads(path.read_text())
    assert doc["asset"]["version"] == "2.0"
    for key in ("bufferViews", "accessors", "images", "textures", "samplers", "materials"):
        assert isinstance(doc.get(key, []), list)

    def in_range(i, key):
        assert isinstance(i, int) and 0 <= i < len(doc[key]), (key, i)

    for b in doc["buffers"]:
        assert b["byteLength"] >= 1
    for v in doc["bufferViews"]:
        in_range(v["buffer"], "buffers")
        assert v.get("byteOffset", 0) + v["byteLength"] <= doc["buffers"][v["buffer"]]["byteLength"]
    for a in doc["accessors"]:
        in_range(a["bufferView"], "bufferViews")
        assert a["componentType"] in (5120, 5121, 5122, 5123, 5125, 5126) and a["count"] >= 1
        assert a["type"] in ("SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT3", "MAT4")
    for m in doc["meshes"]:
        for p in m["primitives"]:
            assert "POSITION" in p["attributes"]
            for i in (*p["attributes"].values(), p.get("indices", 0)):
                in_range(i, "accessors")
            in_range(p["material"], "materials")
    pos = doc["accessors"][doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"]]
    assert "min" in pos and "max" in pos  # required for POSITION
    for t in doc["textures"]:
        in_range(t["source"], "images")
        in_range(t["sampler"], "samplers")
    for im in doc["images"]:
        assert (path.parent / im["uri"]).exists()
    for mat in doc["materials"]:
        pbr = mat["pbrMetallicRoughness"]
        for key in ("baseColorTexture", "metallicRoughnessTexture"):
            in_range(pbr[key]["index"], "textures")
        if "normalTexture" in mat:
            in_range(mat["normalTexture"]["index"], "textures")
    in_range(doc["scene"], "scenes")
    for node in doc["nodes"]:
        in_range(node["mesh"], "meshes")
    return doc


@pytest.mark.parametrize("bits", [8, 16])
def test_gltf_material_is_valid_and_textures_follow_its_conventions(tmp_path, bits):
    maps = _maps(normals=True)
    svbrdf.write_gltf(maps, tmp_path, bits=bits)
    doc = assert_valid_gltf(tmp_path / "material.gltf")
    assert "normalTexture" in doc["materials"][0]
    rm = renderer_maps(maps)
    top = (1 << bits) - 1
    mr, _ = read_png(tmp_path / "metallic_roughness.png")
    assert mr.dtype == (np.uint8 if bits == 8 else np.uint16)
    np.testing.assert_allclose(mr[..., 1] / top, rm.roughness, atol=0.5 / top + 1e-6)
    np.testing.assert_allclose(mr[..., 2] / top, rm.metallic, atol=0.5 / top + 1e-6)
    srgb = read_png(tmp_path / "base_color.png")[0] / top
    lin = np.where(srgb <= 0.04045, srgb / 12.92, ((srgb + 0.055) / 1.055) ** 2.4)
    np.testing.assert_allclose(lin, rm.base_color, atol=2e-2 if bits == 8 else 1e-4)
    nrm = read_png(tmp_path / "normal.png")[0] / top * 2 - 1
    np.testing.assert_allclose(nrm[0, 8], [maps[f"normal.{a}"][0, 8] for a in "XYZ"], atol=5e-3)


def test_cli_export_of_a_fit_folder(tmp_path, capsys):
    fit_dir = tmp_path / "fit"
    fit_dir.mkdir()
    maps = _maps(normals=False)
    write_exr(fit_dir / "maps.exr", {exr_channel(k): v for k, v in maps.items()})
    for fmt, made in (("textures", "base_color.png"), ("mitsuba", "scene.xml")):
        assert main(["export", str(fit_dir), "--format", fmt]) == 0
        assert (fit_dir / f"export_{fmt}" / made).exists()
    assert main(["export", str(fit_dir), "--format", "gltf", "--out", str(tmp_path / "g")]) == 0
    assert_valid_gltf(tmp_path / "g" / "material.gltf")
    assert "material.gltf" in capsys.readouterr().out
    assert main(["export", str(tmp_path / "nothing"), "--format", "gltf"]) == 1
    assert "no maps.exr" in capsys.readouterr().err
