"""Kernel selections that stand in for other machines (SPEC §14).

Math libraries pick a SIMD kernel per CPU at run time; these environment variables make them pick
another one on this machine, as an older or different CPU would. oodrl's outputs must not change.
Each variable has to be set before its library loads, so the selections apply to subprocesses.

The promise covers the detectors certified machine-independent (`machine_independent`, SPEC
§17): the checks run those (`certified_only`); a library detector's outputs
(`detector_outputs`) may or may not come out identical, which `benchmarks/library_kernels.py`
reports.
"""

from __future__ import annotations

import copy
import hashlib
import json
import subprocess
import sys
from collections.abc import Mapping
from pathlib import Path
from typing import Any

#: Name → environment. "avx2" is a Haswell-class machine; "baseline" an x86-64-v2 one (SSE4.2).
_SELECTIONS: dict[str, dict[str, str]] = {
    "native": {},
    "avx2": {
        "MKL_ENABLE_INSTRUCTIONS": "AVX2",
        "ATEN_CPU_CAPABILITY": "avx2",
        "OPENBLAS_CORETYPE": "Haswell",
        "NPY_DISABLE_CPU_FEATURES": "X86_V4 AVX512_ICL AVX512_SPR",
    },
    "baseline": {
        "MKL_ENABLE_INSTRUCTIONS": "SSE4_2",
        "ATEN_CPU_CAPABILITY": "default",
        "OPENBLAS_CORETYPE": "Nehalem",
        "NPY_DISABLE_CPU_FEATURES": "X86_V3 X86_V4 AVX512_ICL AVX512_SPR",
    },
}

#: Variables some machines set for their own sake (an OpenBLAS that misbehaves on a CPU):
#: where one is set already, the selections leave it as the machine wants it.
_MACHINE_PINNED = ("OPENBLAS_CORETYPE", "OPENBLAS_L2_SIZE")


def kernel_selections() -> dict[str, dict[str, str]]:
    """The selections to compare, minus any variable this machine pins itself."""
    import os

    pinned = {name for name in _MACHINE_PINNED if name in os.environ}
    return {
        name: {k: v for k, v in selection.items() if k not in pinned}
        for name, selection in _SELECTIONS.items()
    }


def uncertified_detectors(params_data: Mapping[str, Any]) -> list[str]:
    """The detectors of `benchmark.detectors` not certified machine-independent (merged params
    data, as `oodrl.config.read_params_data` gives it)."""
    from oodrl.config import parse_params

    params = parse_params(dict(params_data), components=False)
    return [
        name
        for name in params.benchmark.detectors
        if not params.detector_class(name).machine_independent
    ]


def certified_only(params_data: Mapping[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """The params with only the certified detectors in `benchmark.detectors`, and the names
    left out: byte-identical outputs are promised for those only."""
    left_out = uncertified_detectors(params_data)
    data = copy.deepcopy(dict(params_data))
    data["benchmark"]["detectors"] = [
        name for name in data["benchmark"]["detectors"] if name not in left_out
    ]
    return data, left_out


def detector_outputs(hashes: Mapping[str, str], detector: str) -> dict[str, str]:
    """The files of `output_hashes` that one detector wrote: its model and its score stores."""
    own = (f"models/{detector}.pkl", f"scores/{detector}/")
    return {path: digest for path, digest in hashes.items() if path.startswith(own)}


#: The stages the check runs: collection (clean, and each injector at the headline and sweep
#: severities), every detector's fit, and scoring of every set.
_DRIVER = """
import json, sys
from pathlib import Path
from oodrl.config import load_params
from oodrl.stages import collect, fit, score

params = load_params(sys.argv[1])
out, policy = Path(sys.argv[2]), Path(sys.argv[3])
injectors = json.loads(sys.argv[4])
collect.collect_id(params, policy, out / "data/id.zarr")
collect.collect_eval(params, policy, out / "data/eval.zarr")
for injector in injectors:
    for kind, write in [("ood", collect.collect_ood), ("sweep", collect.collect_sweep)]:
        target = out / f"data/{kind}/{injector}.zarr"
        write(params, injector, policy, out / "data/eval.zarr", target)
for name in params.benchmark.detectors:
    model = out / f"models/{name}.pkl"
    fit.fit_detector(params, name, out / "data/id.zarr", model)
    score.score_clean_sets(name, model, out / "scores", out / "data/eval.zarr", {})
    for injector in injectors:
        ood, sweep = out / "data/ood", out / "data/sweep"
        score.score_injector_sets(name, injector, model, out / "scores", ood, sweep, None)
"""


def output_hashes(
    selection: Mapping[str, str],
    params_path: Path,
    policy_path: Path,
    out: Path,
    injectors: tuple[str, ...] = ("gaussian_state_noise", "stuck_actuator"),
) -> dict[str, str]:
    """Run the stages in a fresh process under ``selection``; SHA-256 of every file written."""
    import os

    env = {**os.environ, **selection}
    command = [sys.executable, "-c", _DRIVER, str(params_path), str(out), str(policy_path)]
    done = subprocess.run(
        [*command, json.dumps(list(injectors))], env=env, capture_output=True, text=True
    )
    if done.returncode != 0:
        raise RuntimeError(f"stages failed under {dict(selection)}:\n{done.stderr[-4000:]}")
    return {
        str(path.relative_to(out)): hashlib.sha256(path.read_bytes()).hexdigest()
        for path in sorted(out.rglob("*"))
        if path.is_file()
    }
