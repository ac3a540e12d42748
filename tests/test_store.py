"""Zarr stores: round trip, byte-identical rewrites, atomic writes, clear errors."""

from __future__ import annotations

import hashlib
import shutil
from pathlib import Path

import numpy as np
import pytest

from oodrl.errors import StoreError
from oodrl.store import (
    read_scores,
    read_sweep,
    read_trajectories,
    write_scores,
    write_sweep,
    write_trajectories,
)


def tree_digest(root: Path) -> str:
    digest = hashlib.sha256()
    for path in sorted(p for p in root.rglob("*") if p.is_file()):
        digest.update(str(path.relative_to(root)).encode())
        digest.update(path.read_bytes())
    return digest.hexdigest()


def test_round_trip_and_byte_identical(tmp_path, heuristic_clean):
    tset = heuristic_clean
    write_trajectories(tmp_path / "a.zarr", tset)
    write_trajectories(tmp_path / "b.zarr", tset)
    assert tree_digest(tmp_path / "a.zarr") == tree_digest(tmp_path / "b.zarr")
    back = read_trajectories(tmp_path / "a.zarr")
    for name in ("states", "actions", "rewards", "next_states", "dones", "seeds"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tset, name))
    files = [p for p in (tmp_path / "a.zarr").rglob("*") if p.is_file()]
    assert len(files) <= 20, "sharded: a handful of files, not one per episode"
    assert not list(tmp_path.glob(".*tmp*")), "no temporary path left behind"


def test_attributes_are_sorted_and_host_free(tmp_path, heuristic_clean):
    tset = type(heuristic_clean)(
        **{
            k: getattr(heuristic_clean, k)
            for k in (
                "states",
                "actions",
                "rewards",
                "next_states",
                "dones",
                "executed_actions",
                "episode_index",
                "seeds",
            )
        },
        attrs={"zeta": 1, "alpha": {"b": 2, "a": 1}},
    )
    write_trajectories(tmp_path / "s.zarr", tset)
    text = (tmp_path / "s.zarr" / "zarr.json").read_text()
    assert text.index('"alpha"') < text.index('"zeta"')
    assert str(tmp_path) not in text


def test_sweep_and_scores_round_trip(tmp_path, heuristic_clean):
    write_sweep(tmp_path / "sw.zarr", {0.2: heuristic_clean, 0.1: heuristic_clean}, {"x": 1})
    sweep = read_sweep(tmp_path / "sw.zarr")
    assert list(sweep) == [0.1, 0.2]
    scores = np.random.default_rng(0).normal(size=(3, 7))
    write_scores(tmp_path / "sc.zarr", {"clean": {"scores": scores}}, {"threshold": 1.5})
    groups, attrs = read_scores(tmp_path / "sc.zarr")
    np.testing.assert_array_equal(groups["clean"]["scores"], scores)
    assert attrs["threshold"] == 1.5


def test_missing_store_names_the_stage(tmp_path):
    with pytest.raises(StoreError, match=r"missing.*dvc repro -s -f collect_eval"):
        read_trajectories(tmp_path / "eval.zarr", stage="collect_eval")


def test_truncated_store_is_detected(tmp_path, heuristic_clean):
    path = tmp_path / "t.zarr"
    write_trajectories(path, heuristic_clean)
    shutil.rmtree(path / "states" / "c")
    with pytest.raises(StoreError, match=r"'/?states' is truncated or corrupt.*dvc repro -s -f x"):
        read_trajectories(path, stage="x")


def test_corrupt_bytes_are_detected(tmp_path, heuristic_clean):
    path = tmp_path / "t.zarr"
    write_trajectories(path, heuristic_clean)
    shard = next(p for p in (path / "rewards" / "c").rglob("*") if p.is_file())
    data = bytearray(shard.read_bytes())
    data[len(data) // 2] ^= 0xFF
    shard.write_bytes(bytes(data))
    with pytest.raises(StoreError, match="rewards"):
        read_trajectories(path, stage="x")


def test_foreign_store_is_refused(tmp_path, heuristic_clean):
    write_sweep(tmp_path / "sw.zarr", {0.1: heuristic_clean}, {})
    with pytest.raises(StoreError, match="not an oodrl-trajectories store"):
        read_trajectories(tmp_path / "sw.zarr")
    (tmp_path / "junk.zarr").mkdir()
    (tmp_path / "junk.zarr" / "zarr.json").write_text("{not json")
    with pytest.raises(StoreError, match="junk.zarr"):
        read_trajectories(tmp_path / "junk.zarr")
