"""Folders a killed run leaves behind are removed by the next run, never a live run's
(`oodrl.suite.scratch`)."""

from __future__ import annotations

import os
import subprocess

from oodrl.suite.run import DEAD_TASK_FOLDER, DVC_CONFIG_FOLDER, TASK_FOLDER
from oodrl.suite.scratch import remove_dead


def test_a_dead_process_folder_goes_and_a_live_one_stays(tmp_path):
    dead = subprocess.Popen(["true"])
    dead.wait()  # its pid now names no process
    live = os.getppid()  # pytest's parent: alive while the test runs
    gone = [
        tmp_path / f"{TASK_FOLDER}{dead.pid}-a1b2c3",
        tmp_path / f"{DVC_CONFIG_FOLDER}{dead.pid}-x_9",
    ]
    kept = [
        tmp_path / f"{TASK_FOLDER}{live}-d4e5f6",
        tmp_path / f"{TASK_FOLDER}older-{dead.pid}",  # not a name the pattern knows
        tmp_path / f"other-{dead.pid}-a1",
    ]
    for folder in gone + kept:
        folder.mkdir()
        (folder / "clone").write_text("left by a task")
    (tmp_path / f"{TASK_FOLDER}{dead.pid}-file").write_text("a file, not a folder")
    remove_dead(tmp_path, DEAD_TASK_FOLDER)
    assert [f for f in gone if f.exists()] == []
    assert all((f / "clone").is_file() for f in kept)
    assert (tmp_path / f"{TASK_FOLDER}{dead.pid}-file").is_file()
