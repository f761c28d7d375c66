"""List the models by name, or describe one: what it is, where it is used, its parameters.

    jaxrefl models [NAME]

One naming scheme (:mod:`jaxrefl._names`) serves every command: BRDF families
(``jaxrefl.brdf.get``), the capture models of ``fit --model`` and ``sample --model``, and the
measured-BRDF models of ``fit-brdf --models`` and ``sample --brdf-model``. A name that is in
several tables (``ggx``, ``lambert``) is one physical model in each. Older spellings
(``cook_torrance_ggx``) are accepted and shown with their canonical name. Parameters are
listed with their kind, valid range, default, units and meaning.
"""

from __future__ import annotations

import argparse

from jaxrefl._errors import JaxreflError
from jaxrefl._names import (
    ALIASES,
    CAPTURE_MODELS,
    FAMILIES,
    MEASURED_MODELS,
    all_names,
    canonical,
    describe,
)

HELP = "list the model names of every command, or describe one model"
COMPILES = False


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "name",
        nargs="?",
        help="a model name or alias: describe it and list its parameters (default: list all)",
    )


def _model(name: str):
    """A built model for the parameter table of ``name`` (canonical)."""
    if name in MEASURED_MODELS:
        from jaxrefl.measured import build_model

        return build_model(name)
    if name in CAPTURE_MODELS:
        from jaxrefl.svbrdf import capture_model

        return capture_model(name, alpha=0.1)[0]
    from jaxrefl import brdf

    return brdf.get(name)


def _params(name: str) -> None:
    m = _model(name)
    flags = ["reciprocal" if m.reciprocal else "not reciprocal"]
    if m.energy_conserving:
        flags.append("energy conserving")
    print(f"  parameters ({type(m).__name__}; {', '.join(flags)}):")
    for q in m.params:
        print(
            f"    {q.name:<10} {q.kind:<6} [{q.lower:g}, {q.upper:g}]  default {q.default}"
            f"  {q.units}: {q.doc}"
        )


def run(args: argparse.Namespace) -> int:
    if args.name is None:
        for title, table, used in (
            ("BRDF families", FAMILIES, "jaxrefl.brdf.get(NAME, **options)"),
            ("capture models", CAPTURE_MODELS, "fit --model, sample --model"),
            ("measured-BRDF models", MEASURED_MODELS, "fit-brdf --models, sample --brdf-model"),
        ):
            print(f"{title} ({used}):")
            for name, text in table.items():
                print(f"  {name:<14} {text}")
        aliases = ", ".join(f"{a} = {c}" for a, c in ALIASES.items())
        print(f"aliases: {aliases}")
        print("jaxrefl models NAME lists a model's parameters.")
        return 0
    name = canonical(args.name)
    lines = describe(name)
    if not lines:
        raise JaxreflError(f"unknown model {args.name!r}; choose from {', '.join(all_names())}")
    shown = name if name == args.name else f"{name} (given as {args.name})"
    print(shown)
    for line in lines:
        print(f"  {line}")
    _params(name)
    return 0
