"""Run the main job on the embedded demo.

    jaxrefl demo [--out DIR] [--size N] [--seed S] [--noise X] [--no-fit]

Builds the procedural SVBRDF tile of :mod:`jaxrefl.demo`, renders its nine phone-flash
photographs with sensor noise (1% relative plus 0.2% of full scale, Gaussian, seeded), writes
them in the svbrdf-diff-renderer layout (``parameters.json`` +
``images/reference/<size>/NN.png``, 8-bit gamma 2.2) with the ground-truth maps, reads the
capture back like a real one, fits it (``jaxrefl fit`` with the default GGX + Lambert model,
photo 0 held out), writes ``fit/maps.exr``, ``fit/report.json`` and previews, and prints how
close the recovered maps are to the truth.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from ._main import check_out_dir, non_negative_float, non_negative_int

HELP = "render, fit and check the embedded demo capture"

# Sensor noise of the demo photos (linear units, before encoding).
_NOISE_REL = 0.01
_NOISE_ABS = 0.002


def _size(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number, not {text!r}") from None
    if value < 8 or value % 4:
        raise argparse.ArgumentTypeError(f"must be a multiple of 4 and at least 8, got {value}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("jaxrefl-demo"), help="output folder")
    p.add_argument(
        "--size", type=_size, default=128, help="image side in pixels, a multiple of 4, >= 8"
    )
    p.add_argument(
        "--seed", type=non_negative_int, default=0, help="seed of the procedural sample (>= 0)"
    )
    p.add_argument("--no-fit", action="store_true", help="only render and write the capture")
    p.add_argument(
        "--noise",
        type=non_negative_float,
        default=1.0,
        help="sensor noise, as a multiple of 1%% relative + 0.2%% of full scale (0: none)",
    )


def _write_png(path: Path, img) -> None:
    import numpy as np
    from PIL import Image

    arr = np.clip(np.rint(np.asarray(img) * 255.0), 0, 255).astype(np.uint8)
    Image.fromarray(arr).save(path)


def run(args: argparse.Namespace) -> int:
    import jax
    import numpy as np

    from jaxrefl import __version__
    from jaxrefl.brdf import alpha_to_roughness
    from jaxrefl.demo import demo_scene, render_demo

    check_out_dir(args.out)
    scene = demo_scene(size=args.size, seed=args.seed)
    render_fn = jax.jit(lambda p: render_demo(_with(scene, p), encode=False))

    t0 = time.perf_counter()
    compiled = render_fn.lower(scene.params).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    linear = np.asarray(jax.block_until_ready(compiled(scene.params)), np.float64)
    t_run = time.perf_counter() - t0
    rng = np.random.default_rng(args.seed + 1)
    noisy = linear * (1 + args.noise * _NOISE_REL * rng.standard_normal(linear.shape))
    noisy = noisy + args.noise * _NOISE_ABS * rng.standard_normal(linear.shape)
    images = np.clip(noisy, 0.0, 1.0) ** (1.0 / scene.gamma)

    out: Path = args.out
    img_dir = out / "images" / "reference" / str(args.size)
    img_dir.mkdir(parents=True, exist_ok=True)
    (out / "truth").mkdir(exist_ok=True)
    k = images.shape[0]
    print(f"jaxrefl {__version__} demo: {args.size}x{args.size} SVBRDF tile, {k} flash photos")
    print(f"model: {type(scene.model).__name__} {scene.model.param_names}")
    print(f"{'photo':>5}  {'flash position (cm)':>24}  {'mean':>6}  {'clipped':>7}")
    for i in range(k):
        _write_png(img_dir / f"{i:02d}.png", images[i])
        pos = ", ".join(f"{v:5.1f}" for v in scene.positions[i])
        clipped = float(np.mean(images[i] >= 1.0))
        print(f"{i:>5}  ({pos:>20})  {images[i].mean():6.3f}  {clipped:7.2%}")
    params = {
        "_comment": "jaxrefl demo capture; in cm; svbrdf-diff-renderer layout",
        "images_dir": "images",
        "image_size": scene.side_cm,
        "idx": list(range(k)),
        "camera_pos": scene.positions.tolist(),
        "light_pos": scene.positions.tolist(),
        "light_pow": [scene.light_power] * k,
        "gamma": scene.gamma,
        "model": "cook_torrance(ggx, smith_height_correlated, schlick) + lambert",
    }
    (out / "parameters.json").write_text(json.dumps(params, indent=2))
    truth = {name: np.asarray(v) for name, v in scene.params.items()}
    truth["roughness"] = np.asarray(alpha_to_roughness(scene.params["alpha"]))
    # numpy >= 2 stubs: a ** dict might bind allow_pickle (bool); these keys are array names.
    np.savez_compressed(out / "truth" / "params.npz", **truth)  # type: ignore[arg-type]
    _write_png(out / "truth" / "albedo.png", truth["albedo"] ** (1 / 2.2))
    _write_png(out / "truth" / "roughness.png", truth["roughness"])
    print(
        f"render: compile {t_compile:.2f} s, run {t_run * 1e3:.1f} ms ({jax.devices()[0].platform})"
    )
    print(f"wrote {k} photos, parameters.json and truth maps to {out}/")
    if not args.no_fit:
        _fit_and_check(out, truth)
    return 0


def _fit_and_check(out: Path, truth: dict) -> None:
    import numpy as np

    from jaxrefl.cli._fit import print_summary, remove_tiles
    from jaxrefl.fit import has_estimate
    from jaxrefl.io import load_capture
    from jaxrefl.svbrdf import FitJob, fit_capture, write_outputs

    capture = load_capture(out)
    job = FitJob(model="ggx", holdout=(0,))
    print(f"fitting {capture} (photo 0 held out)")
    result = fit_capture(capture, job, out / "fit", restart=True)
    write_outputs(result, capture, out / "fit")
    remove_tiles(out / "fit")
    print_summary(result.report)
    m = result.maps
    ok = has_estimate(m["status"])
    alb = np.stack([m["albedo.R"], m["albedo.G"], m["albedo.B"]], -1)
    err_alb = np.abs(alb - truth["albedo"])[ok]
    err_spec = np.abs(m["specular"] - truth["specular"][..., 0])[ok]
    rel_rough = np.abs(m["roughness"] / truth["roughness"] - 1.0)[ok]
    z = ((m["roughness"] - truth["roughness"]) / m["roughness_std"])[ok & (m["laplace_flag"] == 0)]
    print("recovered maps against the truth (pixels with an estimate):")
    print(f"  diffuse albedo  median |error| {np.median(err_alb):.4f}")
    print(f"  specular F0     median |error| {np.median(err_spec):.4f}")
    print(f"  roughness       median relative error {np.median(rel_rough):.2%}")
    if z.size:
        cover = float(np.mean(np.abs(z) <= 2.0))
        print(f"  roughness truth within 2 Laplace std on {cover:.1%} of reliable pixels")
    print(f"wrote the fit to {out / 'fit'}/ (maps.exr, report.json, previews)")


def _with(scene, params):
    from dataclasses import replace

    return replace(scene, params=params)
