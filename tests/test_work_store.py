"""The resumable work store (:class:`jaxrefl.fit.WorkStore`): a folder of one job's pieces,
refused to another job with one wording, cleared by restart, written atomically, and seen
by every store open on the same folder."""

from __future__ import annotations

import json

import numpy as np
import pytest

from jaxrefl import JaxreflError
from jaxrefl.fit import WorkStore
from jaxrefl.fit._work_store import fingerprint_hash

JOB = {"model": "ggx", "tile": 16, "bounds": (0.0, 1.0)}


def test_fingerprint_hash_is_canonical():
    assert fingerprint_hash(JOB) == fingerprint_hash(dict(reversed(list(JOB.items()))))
    assert fingerprint_hash(JOB) == fingerprint_hash({**JOB, "bounds": [0.0, 1.0]})
    assert fingerprint_hash(JOB) != fingerprint_hash({**JOB, "tile": 32})


def test_another_job_is_refused_with_the_way_out_and_restart_clears(tmp_path):
    store = WorkStore.open(tmp_path, JOB, record={"note": 1})
    store.save("a", {"x": np.arange(3)})
    manifest = json.loads((tmp_path / "manifest.json").read_text())
    assert manifest["model"] == "ggx" and manifest["note"] == 1
    assert manifest["fingerprint"] == fingerprint_hash(JOB)
    # The same job (another record) resumes: the piece is there.
    again = WorkStore.open(tmp_path, JOB, record={"note": 2})
    assert again.done(["a", "b"]) == ["a"]
    np.testing.assert_array_equal(again.load("a")["x"], np.arange(3))
    other = {**JOB, "tile": 32}
    with pytest.raises(
        JaxreflError, match=r"belongs to a different job \(it differs in: tile\); use --restart"
    ) as e:
        WorkStore.open(tmp_path, other)
    assert "another --out folder" in str(e.value)
    assert (tmp_path / "a.npz").exists()  # a refusal touches nothing
    # An unreadable manifest: the same way out.
    (tmp_path / "manifest.json").write_text('{"model": ')
    with pytest.raises(JaxreflError, match=r"unreadable resume manifest.*use --restart"):
        WorkStore.open(tmp_path, JOB)
    # A manifest without the hash (a folder written before it had one) is another job.
    (tmp_path / "manifest.json").write_text(json.dumps(JOB))
    with pytest.raises(JaxreflError, match="different job; use --restart"):
        WorkStore.open(tmp_path, JOB)
    fresh = WorkStore.open(tmp_path, other, restart=True)
    assert fresh.done(["a"]) == [] and fresh.load("a") is None
    assert WorkStore.open(tmp_path, other).digest == fingerprint_hash(other)


def test_pieces_without_a_manifest_are_cleared(tmp_path):
    (tmp_path / "a.npz").write_bytes(b"stray")
    store = WorkStore.open(tmp_path, JOB)
    assert store.done(["a"]) == []


def test_save_is_atomic_and_a_bad_file_reads_as_not_done(tmp_path):
    store = WorkStore.open(tmp_path, JOB)
    store.save("a", {"x": np.ones(4)})

    class Unsavable:
        def __array__(self, dtype=None, copy=None):
            raise RuntimeError("interrupted")

    with pytest.raises(RuntimeError, match="interrupted"):
        store.save("a", {"x": np.zeros(4), "y": Unsavable()})
    np.testing.assert_array_equal(store.load("a")["x"], np.ones(4))  # the old piece, whole
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a.npz", "manifest.json"]
    with pytest.raises(RuntimeError, match="interrupted"):
        store.save("b", {"y": Unsavable()})
    assert store.load("b") is None and store.done(["b"]) == []
    assert store.load("a", check=lambda a: a["x"].shape == (5,)) is None  # another size
    (tmp_path / "c.npz").write_bytes(b"truncated")
    assert store.load("c") is None
    with pytest.raises(RuntimeError, match=r"c\.npz: missing or unreadable.*one folder shared"):
        store.require("c")


def test_two_stores_on_one_folder_see_each_others_pieces(tmp_path):
    first = WorkStore.open(tmp_path, JOB)
    second = WorkStore.open(tmp_path, JOB)
    first.save("p0", {"x": np.zeros(2)})
    second.save("p1", {"x": np.ones(2)})
    keys = ["p0", "p1", "p2"]
    assert first.done(keys) == second.done(keys) == ["p0", "p1"]
    np.testing.assert_array_equal(first.require("p1")["x"], np.ones(2))
    np.testing.assert_array_equal(second.require("p0")["x"], np.zeros(2))
