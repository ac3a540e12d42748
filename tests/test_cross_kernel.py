"""The same outputs whatever SIMD kernels the math libraries pick (SPEC §14).

Collection, fitting and scoring run in fresh processes under kernel selections that stand in for
other machines (oodrl.testing.kernels); every file they write must be byte-identical. The promise
covers the detectors certified machine-independent (SPEC §17): the check runs those only.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from oodrl.config import read_params_data
from oodrl.testing.kernels import certified_only, kernel_selections, output_hashes

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_outputs_are_byte_identical_under_every_kernel_selection(tmp_path: Path):
    params, _ = certified_only(read_params_data(ROOT / "ci" / "params.yaml"))
    params["env"]["T"] = 40
    params["data"].update(n_id=4, n_ood=2)
    params_path = tmp_path / "params.yaml"
    params_path.write_text(yaml.safe_dump(params))
    hashes = {
        name: output_hashes(selection, params_path, ROOT / "models" / "policy.pt", tmp_path / name)
        for name, selection in kernel_selections().items()
    }
    reference = hashes.pop("native")
    assert any(path.startswith("scores/") for path in reference)
    assert len(reference) > 20
    for name, other in hashes.items():
        differing = sorted(
            p for p in reference.keys() | other.keys() if reference.get(p) != other.get(p)
        )
        assert not differing, f"{name}: {differing}"
