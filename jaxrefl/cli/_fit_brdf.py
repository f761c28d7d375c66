"""Fit analytic BRDF models to one measured material and report error, parameters and time.

    jaxrefl fit-brdf FILE [--models NAME ...] --out OUT_DIR

FILE is a Cornell ASTM E1392 file (``.astm``; spectral, converted to linear sRGB under
``--illuminant`` with the CIE 1931 2-degree colour-matching functions, or fitted band by
band with ``--spectral bands``), a CURET value file (``abrdf.dat``; ``--sample N`` picks one
of the 61 samples, ``--curet-table`` the geometry table, default ``table.txt`` beside it) or
a MERL binary file (``.binary``; ``--merl-samples`` random cells). Default models: lambert,
blinn_phong, ward, beckmann, ggx, lafortune_1..3 (``jaxrefl models NAME`` describes one;
the older names ``cook_torrance_ggx`` and ``cook_torrance_beckmann`` are accepted).

Writes OUT_DIR/report.json (per model: parameters, the cosine-weighted L2 of Ngan et al.
2005, log-space and relative L2, fit wall time without compilation, compilation time, number
of parameters, solver status, float64 retry) and OUT_DIR/lobes.png (polar plots of measured
against fitted f_r cos(theta_o) in the plane of incidence at several incidence angles).
"""

from __future__ import annotations

import argparse
from pathlib import Path

from jaxrefl._errors import JaxreflError
from jaxrefl._names import ILLUMINANTS, MEASURED_MODELS, SPECTRAL_CHOICES, canonical

from ._main import check_out_dir, finite_float, non_negative_int, positive_int
from ._options import BACKENDS, DTYPES, fit_config

HELP = "fit analytic models to a measured BRDF (Cornell, CURET, MERL)"


def _curet_sample(text: str) -> int:
    value = positive_int(text)
    if value > 61:
        raise argparse.ArgumentTypeError(f"CURET has samples 1..61, got {value}")
    return value


def _angle(text: str) -> float:
    """An argparse type: an angle in degrees below 90 (finite)."""
    value = finite_float(text)
    if not value < 90.0:
        raise argparse.ArgumentTypeError(f"must be below 90 degrees, got {value:g}")
    return value


def _incidence(text: str) -> float:
    value = _angle(text)
    if value < 0:
        raise argparse.ArgumentTypeError(f"must be in [0, 90) degrees, got {value:g}")
    return value


def add_arguments(p: argparse.ArgumentParser) -> None:
    default = [n for n in MEASURED_MODELS if not n.endswith("_dielectric")]
    p.add_argument("path", metavar="FILE", help="measured BRDF file (.astm, .dat, .binary)")
    p.add_argument(
        "--models",
        nargs="+",
        default=None,
        metavar="NAME",
        help=f"models to fit, by name or comma-separated (default: all of {', '.join(default)})",
    )
    p.add_argument("--out", required=True, type=Path, help="output folder (created)")
    p.add_argument(
        "--spectral",
        choices=SPECTRAL_CHOICES,
        default=SPECTRAL_CHOICES[0],
        help="spectral data: convert to RGB or fit every band separately",
    )
    p.add_argument(
        "--illuminant",
        choices=ILLUMINANTS,
        default=ILLUMINANTS[0],
        help="illuminant of the spectral-to-RGB conversion (CIE D65 daylight, or equal energy)",
    )
    p.add_argument(
        "--sample",
        type=_curet_sample,
        default=None,
        help="CURET sample number, 1..61 (no default: required for a CURET file)",
    )
    p.add_argument(
        "--curet-table",
        type=Path,
        default=None,
        help="CURET geometry table (default: table.txt beside FILE)",
    )
    p.add_argument(
        "--merl-samples",
        type=non_negative_int,
        default=20_000,
        help="MERL cells drawn at random (0: all)",
    )
    p.add_argument(
        "--max-theta",
        type=_angle,
        default=80.0,
        help="leave out directions beyond this angle from the normal, degrees, below 90 (as "
        "Ngan et al. 2005; a negative value keeps all)",
    )
    p.add_argument("--no-cosine", action="store_true", help="fit f_r, not f_r cos(theta_i)")
    p.add_argument(
        "--backend",
        choices=BACKENDS,
        default="lean",
        help="least-squares solver: lean (jaxrefl's own), optimistix or jaxopt "
        "(pip install 'jaxrefl[backends]')",
    )
    p.add_argument(
        "--dtype", choices=DTYPES, default="float32", help="floating-point type of the fit"
    )
    p.add_argument("--no-retry", action="store_true", help="no automatic float64 retry")
    p.add_argument(
        "--max-iters",
        type=positive_int,
        default=None,
        help="solver iteration budget (default: the solver's own)",
    )
    p.add_argument(
        "--thetas",
        type=_incidence,
        nargs="+",
        default=None,
        help="incidence angles of the lobe plots, degrees (default: spread over the data)",
    )
    p.add_argument("--no-plot", action="store_true", help="skip lobes.png")
    p.add_argument(
        "--fresnel",
        choices=("schlick", "dielectric", "both"),
        default="schlick",
        help="Fresnel term of the Cook-Torrance models: Schlick's F0 (default), the exact "
        "dielectric one with a fitted eta, or both (the report says which fits better)",
    )
    p.add_argument(
        "--starts",
        type=int,
        default=24,
        help="quasi-random starts per model, solved together with the data-driven ones "
        "(default 24)",
    )
    p.add_argument(
        "--single-start", action="store_true", help="one automatic start per model, no certificate"
    )


def _model_names(raw: list[str] | None) -> list[str] | None:
    """Canonical names of ``--models`` (aliases resolved, duplicates dropped)."""
    if raw is None:
        return None
    names = [canonical(n) for item in raw for n in item.split(",") if n.strip()]
    unknown = [n for n in names if n not in MEASURED_MODELS]
    if unknown:
        raise JaxreflError(
            f"--models: unknown model(s) {', '.join(unknown)}; choose from "
            f"{', '.join(MEASURED_MODELS)}"
        )
    return list(dict.fromkeys(names))


def _with_fresnel(names: list[str] | None, fresnel: str) -> list[str]:
    """The model names with the Fresnel choice applied (``both``: each Cook-Torrance model
    with Schlick, then with the dielectric term)."""
    from jaxrefl.measured import DEFAULT_MODELS, fresnel_variant

    out: list[str] = []
    for n in DEFAULT_MODELS if names is None else names:
        kinds = ("schlick", "dielectric") if fresnel == "both" else (fresnel,)
        for v in (fresnel_variant(n, k) for k in kinds):
            if v not in out:
                out.append(v)
    return out


def run(args: argparse.Namespace) -> int:
    from jaxrefl import measured as jm
    from jaxrefl._jsonsafe import report_json

    names = _with_fresnel(_model_names(args.models), args.fresnel)
    check_out_dir(args.out)
    if args.starts < 0:
        raise JaxreflError(f"--starts must be >= 0, got {args.starts}")
    starts = None if args.single_start else jm.MultiStart(n_random=args.starts)
    m = jm.load_measured(
        args.path,
        curet_table=args.curet_table,
        curet_sample=args.sample,
        merl_samples=None if args.merl_samples == 0 else args.merl_samples,
    )
    max_theta = None if args.max_theta < 0 else args.max_theta
    print(f"{m.name}: {len(m)} samples, {m.n_channels} channels from {args.path}")
    report = jm.fit_brdf(
        m,
        names,
        options=jm.MeasuredOptions(
            max_theta_deg=max_theta,
            cosine=not args.no_cosine,
            retry_float64=not args.no_retry,
            spectral=args.spectral,
            illuminant=args.illuminant,
        ),
        config=fit_config(args.backend, args.dtype, max_iters=args.max_iters),
        progress=lambda name: print(f"  fitting {name} ...", flush=True),
        starts=starts,
    )
    args.out.mkdir(parents=True, exist_ok=True)
    report_path = args.out / "report.json"
    report_path.write_text(report_json(report.to_dict()))
    print(report.table())
    print(f"best (cosine-weighted L2): {report.best()}")
    print(f"wrote {report_path}")
    if not args.no_plot:
        import matplotlib

        matplotlib.use("Agg")  # files only: no window, whatever MPLBACKEND says
        import matplotlib.pyplot as plt

        fig = jm.plot_fit_lobes(report, thetas_deg=args.thetas)
        fig.savefig(args.out / "lobes.png", dpi=100)
        plt.close(fig)
        print(f"wrote {args.out / 'lobes.png'}")
    return 0
