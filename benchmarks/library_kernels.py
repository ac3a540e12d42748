"""Which library detectors happen to give byte-identical outputs under the three kernel
selections (SPEC §14, §17), though none is certified to.

    python benchmarks/library_kernels.py [--blocks src/oodrl/library_detectors.yaml] [names...]

Runs the stages of `oodrl.testing.kernels` (collection, fit, scoring of the clean set and of two
injectors at the headline and sweep severities) on tiny params (ci/params.yaml, T = 40, 4 ID and
2 OOD trajectories) under each kernel selection, with the library detectors and one certified
control (mahalanobis_distance), and prints per detector whether its model and score files are
identical under every selection. "identical" here is about this machine's libraries under
these selections only: a library that compiles for the host CPU (HBOS through numba) is not
exercised by them at all.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

import yaml

from oodrl.config import read_params_data
from oodrl.testing.kernels import (
    detector_outputs,
    kernel_selections,
    output_hashes,
    uncertified_detectors,
)

ROOT = Path(__file__).resolve().parents[1]
CONTROL = "mahalanobis_distance"


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("names", nargs="*")
    parser.add_argument("--blocks", type=Path, default=ROOT / "src/oodrl/library_detectors.yaml")
    args = parser.parse_args()
    blocks = yaml.safe_load(args.blocks.read_text())
    names = args.names or list(blocks)
    params = read_params_data(ROOT / "ci" / "params.yaml")
    params["env"]["T"] = 40
    params["data"].update(n_id=4, n_ood=2)
    params["detectors"].update({name: blocks[name] for name in names})
    params["benchmark"]["detectors"] = [CONTROL, *names]
    uncertified = set(uncertified_detectors(params))
    with tempfile.TemporaryDirectory(prefix="oodrl-library-kernels-") as scratch:
        params_path = Path(scratch) / "params.yaml"
        params_path.write_text(yaml.safe_dump(params))
        policy = ROOT / "models" / "policy.pt"
        hashes = {
            selection: output_hashes(env, params_path, policy, Path(scratch) / selection)
            for selection, env in kernel_selections().items()
        }
    reference_name, reference = next(iter(hashes.items()))
    print(f"Outputs per detector under kernel selections {', '.join(hashes)}:")
    control_identical = True
    for name in params["benchmark"]["detectors"]:
        own = detector_outputs(reference, name)
        differing = sorted(
            {
                path
                for other in hashes.values()
                for path, digest in detector_outputs(other, name).items()
                if own.get(path) != digest
            }
        )
        status = "identical" if not differing else f"differ in {len(differing)} of {len(own)}"
        certified = "uncertified" if name in uncertified else "certified"
        print(f"  {name:24} {certified:12} {status} ({len(own)} files vs {reference_name})")
        if differing:
            print(f"    e.g. {', '.join(differing[:3])}")
            control_identical &= name in uncertified
    return 0 if control_identical else 1


if __name__ == "__main__":
    sys.exit(main())
