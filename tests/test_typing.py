"""mypy over the package (settings in ``pyproject.toml``) is part of the test suite, so CI,
which runs only pytest, fails on a type error. The cache lives in ``.pytest_cache/mypy``: a
warm run takes about a second, a cold one some tens of seconds."""

from __future__ import annotations

from pathlib import Path

from mypy import api

ROOT = Path(__file__).resolve().parents[1]


def test_mypy_clean(monkeypatch):
    monkeypatch.chdir(ROOT)  # the config names the package relative to the repository root
    out, err, status = api.run(
        [
            "--config-file",
            str(ROOT / "pyproject.toml"),
            "--cache-dir",
            str(ROOT / ".pytest_cache" / "mypy"),
        ]
    )
    assert status == 0, f"mypy reports errors:\n{out}{err}"
