"""Each package's public surface is what docs/architecture.md documents: its ``__all__`` is
the list the document gives under the package's marker (``<!-- fit-all -->``), every name there
is importable, and whatever else the package exposes is a listed helper that is not public."""

from __future__ import annotations

import importlib
import re
import types
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
ARCHITECTURE = ROOT / "docs" / "architecture.md"

# Helpers reachable as package attributes though not public (out of ``__all__``): those the
# other packages of jaxrefl share (a package uses another through its ``__init__`` only,
# tests/test_package.py), and those benchmarks and tests import from the package.
REACHABLE = {
    "fit": {
        "check_number",
        "cho_solve_unrolled",
        "cholesky_unrolled",
        "device_count",
        "equilibrated_condition",
        "fingerprint_hash",
        "flag_counts",
        "keep_lower",
        "process_barrier",
        "process_gather",
        "process_share",
        "refuse_other_work",
        "replace_params",
        "same_residual",
        "sample_arrays",
        "solve_lower_t_unrolled",
        "solve_lower_unrolled",
        "undefined_correlations",
    },
    "measured": {"fresnel_variant"},
    "svbrdf": {
        "fit_theta",
        "gain_prior",
        "laplace_dof",
        "laplace_interval",
        "laplace_theta_std",
        "light_problem",
        "map_posterior",
        "photo_information",
    },
    "brdf": {
        "DIELECTRIC_F0_DEFAULT",
        "MERL_SCALE",
        "MERL_SHAPE",
        "ZooEntry",
        "check_directions",
        "hemisphere_grid",
        "model_zoo",
        "random_directions",
        "random_params",
        "safe_normalize",
        "spherical_direction",
    },
    "io": {
        "atomic_path",
        "atomic_write",
        "exr_channels",
        "merl_to_measured",
        "read_merl_table",
        "save_npz_atomic",
        "write_text_atomic",
    },
    "phone": {"corner_pixels", "refine_corners", "tag_cells"},
    "ps": {"NormalBRDFResidual", "check_lights"},
    "scene": {"orthonormal_basis", "shading_frame", "to_local", "to_world"},
    "posterior": {
        "HEARTBEAT_S",
        "MCMC_METHODS",
        "NonFinite",
        "log_likelihood_draws",
        "sample_truncated",
        "thin",
        "uncertainty_channels",
    },
}


def documented(package: str) -> set[str]:
    """The names docs/architecture.md lists after ``<!-- {package}-all -->``, up to the
    paragraph's end."""
    text = ARCHITECTURE.read_text()
    marker = f"<!-- {package}-all -->"
    assert text.count(marker) == 1, f"docs/architecture.md needs one {marker}"
    seg = text[text.index(marker) + len(marker) :]
    return set(re.findall(r"`(\w+)`", seg[: seg.index("\n\n")]))


@pytest.mark.parametrize("package", sorted(REACHABLE))
def test_all_is_what_the_architecture_documents(package):
    mod = importlib.import_module(f"jaxrefl.{package}")
    listed = documented(package)
    assert set(mod.__all__) == listed, (
        f"only in __all__: {sorted(set(mod.__all__) - listed)}; "
        f"only in the document: {sorted(listed - set(mod.__all__))}"
    )
    assert len(mod.__all__) == len(set(mod.__all__))
    missing = [n for n in mod.__all__ if not hasattr(mod, n)]
    assert not missing, missing


@pytest.mark.parametrize("package", sorted(REACHABLE))
def test_whatever_else_a_package_exposes_is_a_listed_helper(package):
    """Every other name without a leading underscore is a submodule or one of the helpers
    :data:`REACHABLE` lists (so a new name is either documented or kept in its module)."""
    mod = importlib.import_module(f"jaxrefl.{package}")
    extra = {
        n
        for n, v in vars(mod).items()
        if not n.startswith("_") and n not in mod.__all__ and not isinstance(v, types.ModuleType)
    }
    assert extra == REACHABLE[package]


# The packages whose modules docs/architecture.md tables, each after its line here.
ROOMS = {
    "fit": "The rooms of `fit`:",
    "svbrdf": "Inside `svbrdf`, each module",
    "posterior": "The rooms of `posterior`:",
}


def rooms_table(text: str, intro: str) -> str:
    """The Markdown table that first follows the line ``intro`` in ``text``."""
    assert text.count(intro) == 1, f"docs/architecture.md needs one {intro!r}"
    lines = text[text.index(intro) :].splitlines()
    start = next(i for i, ln in enumerate(lines) if ln.startswith("|"))
    end = next((i for i in range(start, len(lines)) if not lines[i].startswith("|")), len(lines))
    return "\n".join(lines[start:end])


def test_rooms_table_reads_the_table_after_its_line():
    text = "The rooms of `p`:\n\n| module | what |\n|---|---|\n| `_a.py` | a |\n\n| `_b.py` |\n"
    table = rooms_table(text, "The rooms of `p`:")
    assert "`_a.py`" in table and "`_b.py`" not in table


@pytest.mark.parametrize("package", sorted(ROOMS))
def test_the_architecture_tables_every_module_of_the_package(package):
    """Each module of the package is named in its rooms table, and the table names no module
    that is not there (the document describes what is there)."""
    table = rooms_table(ARCHITECTURE.read_text(), ROOMS[package])
    here = {p.name for p in (ROOT / "jaxrefl" / package).glob("_*.py")} - {"__init__.py"}
    named = set(re.findall(r"`(_\w+\.py)`", table))
    assert here - named == set(), f"modules of {package} the table leaves out"
    assert named - here == set(), f"modules the {package} table names that are not there"
