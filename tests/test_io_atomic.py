"""Atomic writes (jaxrefl/io/_atomic.py): an interrupted write, by an exception or by the
process dying, leaves the old file whole under its name; a finished one replaces it."""

from __future__ import annotations

import subprocess
import sys
import threading

import numpy as np
import pytest

from jaxrefl import io


def _only(folder):
    return sorted(p.name for p in folder.iterdir())


def test_write_replaces_the_file_and_leaves_no_temporary(tmp_path):
    path = tmp_path / "report.json"
    assert io.write_text_atomic(path, '{"run": 1}') == path
    path.chmod(0o640)
    io.write_text_atomic(path, '{"run": 2}')
    assert path.read_text() == '{"run": 2}' and _only(tmp_path) == ["report.json"]
    assert path.stat().st_mode & 0o777 == 0o640  # the target's permissions are kept
    with io.atomic_write(tmp_path / "raw.bin") as fh:
        fh.write(b"\x00\x01")
    assert (tmp_path / "raw.bin").read_bytes() == b"\x00\x01"


def test_an_exception_mid_write_leaves_the_old_file_whole(tmp_path):
    path = tmp_path / "manifest.json"
    io.write_text_atomic(path, "old contents")
    with pytest.raises(RuntimeError, match="interrupted"), io.atomic_write(path, "w") as fh:
        fh.write("new, half")
        fh.flush()
        raise RuntimeError("interrupted")
    assert path.read_text() == "old contents" and _only(tmp_path) == ["manifest.json"]


def test_an_interrupted_archive_leaves_the_old_archive_loadable(tmp_path, monkeypatch):
    path = tmp_path / "tile_0000.npz"
    io.save_npz_atomic(path, theta=np.arange(4.0))

    def dying_savez(fh, **arrays):
        fh.write(b"PK\x03\x04 truncated")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez", dying_savez)
    with pytest.raises(OSError, match="disk full"):
        io.save_npz_atomic(path, theta=np.zeros(4))
    monkeypatch.undo()
    with np.load(path) as z:
        np.testing.assert_array_equal(z["theta"], np.arange(4.0))
    assert _only(tmp_path) == ["tile_0000.npz"]


def test_a_process_killed_mid_write_leaves_the_old_file_whole(tmp_path):
    path = tmp_path / "maps.bin"
    path.write_bytes(b"old" * 1000)
    code = (
        "import os, sys\n"
        "from jaxrefl.io import atomic_write\n"
        "with atomic_write(sys.argv[1]) as fh:\n"
        "    fh.write(b'new' * 500)\n"
        "    fh.flush()\n"
        "    os._exit(3)\n"  # no cleanup, no rename: as a kill would leave it
    )
    r = subprocess.run([sys.executable, "-c", code, str(path)], capture_output=True, timeout=120)
    assert r.returncode == 3, r.stderr
    assert path.read_bytes() == b"old" * 1000
    # At most a hidden temporary file beside it, never under the final name.
    assert all(
        n == "maps.bin" or (n.startswith(".maps.bin.") and n.endswith(".tmp"))
        for n in _only(tmp_path)
    )


def test_concurrent_writers_each_leave_a_whole_file(tmp_path):
    path = tmp_path / "shared.txt"
    texts = [str(i) * 100_000 for i in range(8)]
    threads = [threading.Thread(target=io.write_text_atomic, args=(path, t)) for t in texts]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert path.read_text() in texts and _only(tmp_path) == ["shared.txt"]


def test_a_missing_folder_names_the_target(tmp_path):
    target = tmp_path / "nowhere" / "out.json"
    with pytest.raises(FileNotFoundError, match="no directory") as e:
        io.write_text_atomic(target, "x")
    assert e.value.filename == str(target)
