"""List the BRDF models, their options and their parameters with ranges and units."""

from __future__ import annotations

import argparse

HELP = "list the BRDF models and their parameters"


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("name", nargs="?", help="show one model only")


def run(args: argparse.Namespace) -> int:
    from jaxrefl import brdf

    names = [args.name] if args.name else list(brdf.available())
    for name in names:
        m = brdf.get(name)
        flags = []
        flags.append("reciprocal" if m.reciprocal else "not reciprocal")
        if m.energy_conserving:
            flags.append("energy conserving")
        print(f"{name}  ({type(m).__name__}; {', '.join(flags)})")
        for q in m.params:
            print(
                f"    {q.name:<10} {q.kind:<6} [{q.lower:g}, {q.upper:g}]  default {q.default}"
                f"  {q.units}: {q.doc}"
            )
    return 0
