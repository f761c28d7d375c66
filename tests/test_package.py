"""The package's shape: what ``import jaxrefl`` gives, and who may import whose internals."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
PACKAGE = ROOT / "jaxrefl"

SUBPACKAGES = sorted(
    p.name for p in PACKAGE.iterdir() if p.is_dir() and (p / "__init__.py").exists()
)
PUBLIC_MODULES = sorted(p.stem for p in PACKAGE.glob("*.py") if not p.stem.startswith("_"))


def _python(code: str) -> str:
    r = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=300
    )
    assert r.returncode == 0, r.stdout + r.stderr
    return r.stdout


def test_bare_import_gives_every_subpackage():
    """``jaxrefl.svbrdf.fit_capture`` (as the README writes it) after a bare ``import jaxrefl``;
    the heavy subpackages are loaded on first use, not by the import itself."""
    assert {"brdf", "fit", "io", "measured", "posterior", "ps", "scene", "svbrdf"} <= set(
        SUBPACKAGES
    )
    names = SUBPACKAGES + PUBLIC_MODULES
    out = _python(
        "import sys, types, jaxrefl\n"
        "heavy = sorted(m for m in ('jaxrefl.posterior', 'jaxrefl.svbrdf', 'blackjax', 'emcee')"
        " if m in sys.modules)\n"
        "print('loaded:', heavy)\n"
        f"for name in {names!r}:\n"
        "    assert isinstance(getattr(jaxrefl, name), types.ModuleType), name\n"
        "    assert name in dir(jaxrefl), name\n"
        "assert callable(jaxrefl.svbrdf.fit_capture)\n"
        "assert callable(jaxrefl.posterior.sample_pixels)\n"
        "try:\n"
        "    jaxrefl.no_such_thing\n"
        "except AttributeError:\n"
        "    print('ok')\n"
    )
    assert out.splitlines() == ["loaded: []", "ok"]
