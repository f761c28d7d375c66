"""Run the main job on the embedded demo.

Builds the procedural SVBRDF tile of :mod:`jaxrefl.demo`, renders its nine phone-flash
photographs, prints what it did (per photo: flash position, mean and clipped fraction of the
encoded image; compile and run times apart) and writes the capture in the
svbrdf-diff-renderer layout (``parameters.json`` + ``images/reference/<size>/NN.png``)
together with the ground-truth maps, so that the capture can be read back like a real one.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

HELP = "render (and, as the project grows, fit) the embedded demo capture"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", type=Path, default=Path("jaxrefl-demo"), help="output folder")
    p.add_argument("--size", type=int, default=128, help="image side in pixels (default 128)")
    p.add_argument("--seed", type=int, default=0, help="seed of the procedural sample")


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

    if args.size < 8 or args.size % 4:
        raise ValueError(f"--size must be a multiple of 4 and at least 8, got {args.size}")
    scene = demo_scene(size=args.size, seed=args.seed)
    render_fn = jax.jit(lambda p: render_demo(_with(scene, p)))

    t0 = time.perf_counter()
    compiled = render_fn.lower(scene.params).compile()
    t_compile = time.perf_counter() - t0
    t0 = time.perf_counter()
    images = np.asarray(jax.block_until_ready(compiled(scene.params)))
    t_run = time.perf_counter() - t0

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
    np.savez_compressed(out / "truth" / "params.npz", **truth)
    _write_png(out / "truth" / "albedo.png", truth["albedo"] ** (1 / 2.2))
    _write_png(out / "truth" / "roughness.png", truth["roughness"])
    print(
        f"render: compile {t_compile:.2f} s, run {t_run * 1e3:.1f} ms ({jax.devices()[0].platform})"
    )
    print(f"wrote {k} photos, parameters.json and truth maps to {out}/")
    return 0


def _with(scene, params):
    from dataclasses import replace

    return replace(scene, params=params)
