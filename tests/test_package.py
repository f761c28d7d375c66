"""The package's shape: what ``import jaxrefl`` gives, and who may import whose internals."""

from __future__ import annotations

import ast
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


def _private(part: str) -> bool:
    return part.startswith("_") and not part.startswith("__")


def private_imports(source: str, module: str) -> list[str]:
    """Imports in ``source`` (the code of the dotted ``module``) of a private module or
    name of another subpackage of ``jaxrefl``: ``jaxrefl.<other>._x`` or ``from
    jaxrefl.<other> import _x``. The root's own private modules (``jaxrefl._errors``) are
    shared by every subpackage and allowed; so is anything within one subpackage."""
    parts = module.split(".")
    is_package = parts[-1] == "__init__"
    if is_package:
        parts = parts[:-1]
    package = parts if is_package else parts[:-1]
    own = package[1] if len(package) > 1 else None
    found = []
    for node in ast.walk(ast.parse(source)):
        targets: list[list[str]] = []
        if isinstance(node, ast.Import):
            targets = [a.name.split(".") for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
            else:
                base = []
            target = base + (node.module.split(".") if node.module else [])
            targets = [target] + [[*target, a.name] for a in node.names]
        for target in targets:
            if len(target) < 3 or target[0] != "jaxrefl" or target[1] == own:
                continue
            if any(_private(p) for p in target[2:]):
                found.append(f"{module}:{node.lineno}: {'.'.join(target)}")
    return found


def test_private_import_checker_sees_violations():
    src = (
        "from ..brdf._frame import safe_normalize\n"
        "from jaxrefl.fit import _replaced\n"
        "import jaxrefl.fit._lm as lm\n"
        "def f():\n"
        "    from jaxrefl.posterior._adaptive import _restarts\n"
        "from ._camera import x\n"  # same subpackage: fine
        "from .._errors import JaxreflError\n"  # the root's shared internals: fine
        "from jaxrefl.brdf import BRDF\n"
    )
    found = private_imports(src, "jaxrefl.scene._lights")
    assert [f.split(": ")[1] for f in found] == [
        "jaxrefl.brdf._frame",
        "jaxrefl.brdf._frame.safe_normalize",
        "jaxrefl.fit._replaced",
        "jaxrefl.fit._lm",
        "jaxrefl.posterior._adaptive",
        "jaxrefl.posterior._adaptive._restarts",
    ]
    # Within one subpackage, from its __init__ or a module: fine.
    assert private_imports("from ._frame import safe_normalize\n", "jaxrefl.brdf.__init__") == []
    assert private_imports("from ..brdf._frame import reflect\n", "jaxrefl.brdf._base") == []
    assert private_imports("from .brdf._base import Params\n", "jaxrefl.plot") == [
        "jaxrefl.plot:1: jaxrefl.brdf._base",
        "jaxrefl.plot:1: jaxrefl.brdf._base.Params",
    ]


def test_no_cross_package_private_imports():
    """A subpackage uses another one through its public ``__init__`` only."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        module = ".".join(path.relative_to(ROOT).with_suffix("").parts)
        found += private_imports(path.read_text(encoding="utf-8"), module)
    assert not found, "imports of another subpackage's private names:\n" + "\n".join(found)
