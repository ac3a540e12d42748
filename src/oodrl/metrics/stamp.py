"""The protocol stamp every results file carries (SPEC §15): the protocol version its numbers
follow and a hash of the resolved params that produced them. The leaderboard refuses to rank
results of two versions together; a file without a stamp is read as `UNSTAMPED_VERSION`, the
protocol before stamps.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from oodrl.config import Params


#: The protocol a results file follows: 2 = SPEC §15/§16 (impact tiers, operating points,
#: policy seeds, trivial-signal baselines); 3 = SPEC §19 (tiers searched and verified, the
#: benign tier, 100-stream cells, the training-conditional threshold, the audit set); 4 = SPEC
#: §23/§24 (per-detector cells merged, tiers searched with common random numbers and planned
#: verification, the time-aware per-stream rule beside the constant one, cusum_tv and
#: action_consistency); 5 = a tier verified only once its interval reaches the target width
#: (SPEC §23), tier results stored as JSON. Bump it whenever results stop being comparable with
#: the previous version's.
PROTOCOL_VERSION = 5
#: What a results file without a stamp is read as: the protocol before stamps, SPEC §3-§12.
UNSTAMPED_VERSION = 1


def params_hash(params: Params) -> str:
    """sha256 of the resolved params (defaults filled in, `extends` merged) as canonical JSON.

    The executor block is left out: results are identical for any worker count.
    """
    resolved = params.model_dump(mode="json", exclude={"executor"})
    text = json.dumps(resolved, sort_keys=True, separators=(",", ":"), ensure_ascii=True)
    return "sha256:" + hashlib.sha256(text.encode()).hexdigest()


def protocol_stamp(params: Params) -> dict[str, Any]:
    """The keys every results file carries: its protocol version and its params' hash."""
    return {"protocol_version": PROTOCOL_VERSION, "params_hash": params_hash(params)}


def protocol_version(document: Mapping[str, Any]) -> int:
    """The protocol version of a results document; unstamped files are `UNSTAMPED_VERSION`."""
    version = document.get("protocol_version", UNSTAMPED_VERSION)
    if isinstance(version, bool) or not isinstance(version, int):
        raise ValueError(f"protocol_version must be an integer; got {version!r}")
    return version


def one_protocol_version(documents: Mapping[str, Mapping[str, Any]]) -> int:
    """The one protocol version of every document (name → document), or a one-line error."""
    from oodrl.errors import StoreError

    versions: dict[int, list[str]] = {}
    for name, document in documents.items():
        try:
            versions.setdefault(protocol_version(document), []).append(str(name))
        except ValueError as error:
            raise StoreError(f"{name}: {error}.") from None
    if len(versions) > 1:
        parts = "; ".join(
            f"version {v}: {', '.join(sorted(names))}" for v, names in sorted(versions.items())
        )
        raise StoreError(
            f"Results of different protocol versions cannot be ranked together ({parts}); "
            f"re-run the metrics stage of the older pipelines."
        )
    return next(iter(versions), PROTOCOL_VERSION)
