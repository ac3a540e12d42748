"""Prove the pipeline reproduces on other machines: from-scratch runs under different math
kernels give identical outputs (SPEC §14).

    python benchmarks/reproduce.py --params ci/params.yaml

For each kernel selection of `oodrl.testing.kernels` (this CPU's own kernels, an AVX2 machine's,
an SSE4.2 machine's), a fresh copy of the project (own git + DVC repo, no data) runs
`dvc repro` with the libraries' kernels forced; then every output hash in the dvc.lock files must
be identical, `dvc status -q` must exit 0, and a further `dvc repro` must run no stage.
Exit code 1 on any difference. Detectors not certified machine-independent (library ones, SPEC
§17) are left out of the copied params and named; benchmarks/library_kernels.py reports on them.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

from oodrl.config import read_params_data
from oodrl.testing.kernels import certified_only, kernel_selections
from oodrl.testing.pipeline import copy_project, lock_hashes, repro, run

ROOT = Path(__file__).resolve().parents[1]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--params", type=Path, default=ROOT / "ci" / "params.yaml")
    args = parser.parse_args()
    # Merged: the copy has no base file beside it. Only certified detectors are promised.
    params, left_out = certified_only(read_params_data(args.params))
    if left_out:
        print(f"Left out, not certified machine-independent: {', '.join(left_out)}")
    runs = {}
    with tempfile.TemporaryDirectory(prefix="oodrl-reproduce-") as scratch:
        for name, selection in kernel_selections().items():
            repo = copy_project(ROOT, Path(scratch) / name, params)
            start = time.perf_counter()
            ran = repro(repo, env=selection)
            seconds = time.perf_counter() - start
            print(f"{name} kernels: dvc repro ran {len(ran)} stages in {seconds:.1f} s", flush=True)
            status = run(
                repo, "dvc", "status", "-q", "--with-deps", "dvc.yaml", check=False, env=selection
            )
            if status.returncode != 0:
                print(f"FAIL: {name}: `dvc status -q` exit {status.returncode}")
                return 1
            again = repro(repo, env=selection)
            if again:
                print(f"FAIL: {name}: a second dvc repro re-ran {again}")
                return 1
            runs[name] = lock_hashes(repo)
    reference_name, reference = next(iter(runs.items()))
    for name, hashes in runs.items():
        differing = sorted(
            p for p in reference.keys() | hashes.keys() if reference.get(p) != hashes.get(p)
        )
        if differing:
            print(
                f"FAIL: {len(differing)} outputs differ between the {reference_name} and "
                f"{name} runs: {differing}"
            )
            return 1
    print(
        f"OK: {len(reference)} outputs byte-identical across {len(runs)} from-scratch runs under "
        f"kernel selections {', '.join(runs)}; dvc status clean; a second repro ran nothing"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
