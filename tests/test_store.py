"""Zarr stores: round trip, byte-identical rewrites, atomic writes, clear errors."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from oodrl.errors import StoreError
from oodrl.io.store import (
    read_scores,
    read_sweep,
    read_trajectories,
    write_scores,
    write_sweep,
    write_trajectories,
)


def rewrite_entries(path: Path, edit) -> None:
    """Rewrite the store's ZIP with `edit(name, data)` -> new data, or None to drop the entry."""
    with zipfile.ZipFile(path) as archive:
        entries = [(info, archive.read(info)) for info in archive.infolist()]
    with zipfile.ZipFile(path, "w") as archive:
        for info, data in entries:
            data = edit(info.filename, data)
            if data is not None:
                archive.writestr(info, data)


def test_round_trip_and_byte_identical(tmp_path, heuristic_clean):
    tset = heuristic_clean
    write_trajectories(tmp_path / "a.zarr", tset)
    write_trajectories(tmp_path / "b.zarr", tset)
    assert (tmp_path / "a.zarr").read_bytes() == (tmp_path / "b.zarr").read_bytes()
    back = read_trajectories(tmp_path / "a.zarr")
    for name in ("states", "actions", "rewards", "next_states", "dones", "seeds"):
        np.testing.assert_array_equal(getattr(back, name), getattr(tset, name))
    assert (tmp_path / "a.zarr").is_file(), "one file per store: one DVC file-state lookup"
    with zipfile.ZipFile(tmp_path / "a.zarr") as archive:
        entries = archive.infolist()
    assert len(entries) <= 20, "sharded: a handful of entries, not one per episode"
    assert {e.date_time for e in entries} == {(1980, 1, 1, 0, 0, 0)}, "no write time inside"
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
    with zipfile.ZipFile(tmp_path / "s.zarr") as archive:
        text = archive.read("zarr.json").decode()
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
    rewrite_entries(path, lambda name, data: None if name.startswith("states/c") else data)
    with pytest.raises(StoreError, match=r"'/?states' is truncated or corrupt.*dvc repro -s -f x"):
        read_trajectories(path, stage="x")


def test_corrupt_bytes_are_detected(tmp_path, heuristic_clean):
    path = tmp_path / "t.zarr"
    write_trajectories(path, heuristic_clean)

    def flip_a_byte(name, data):
        if not name.startswith("rewards/c"):
            return data
        data = bytearray(data)
        data[len(data) // 2] ^= 0xFF
        return bytes(data)

    rewrite_entries(path, flip_a_byte)
    with pytest.raises(StoreError, match="rewards"):
        read_trajectories(path, stage="x")


def test_foreign_store_is_refused(tmp_path, heuristic_clean):
    write_sweep(tmp_path / "sw.zarr", {0.1: heuristic_clean}, {})
    with pytest.raises(StoreError, match="not an oodrl-trajectories store"):
        read_trajectories(tmp_path / "sw.zarr")
    (tmp_path / "junk.zarr").write_text("{not a zip")
    with pytest.raises(StoreError, match="junk.zarr: unreadable store"):
        read_trajectories(tmp_path / "junk.zarr")


def test_truncated_file_and_old_directory_stores_are_refused(tmp_path, heuristic_clean):
    path = tmp_path / "t.zarr"
    write_trajectories(path, heuristic_clean)
    path.write_bytes(path.read_bytes()[: path.stat().st_size // 2])
    with pytest.raises(StoreError, match=r"t.zarr: unreadable store.*dvc repro -s -f x"):
        read_trajectories(path, stage="x")
    (tmp_path / "old.zarr").mkdir()
    (tmp_path / "old.zarr" / "zarr.json").write_text("{}")
    with pytest.raises(StoreError, match=r"old.zarr: a directory store from an older oodrl"):
        read_trajectories(tmp_path / "old.zarr", stage="x")


def test_rewrite_replaces_an_old_directory_store(tmp_path, heuristic_clean):
    path = tmp_path / "t.zarr"
    (path / "states").mkdir(parents=True)
    write_trajectories(path, heuristic_clean)
    assert path.is_file()
    np.testing.assert_array_equal(read_trajectories(path).states, heuristic_clean.states)
