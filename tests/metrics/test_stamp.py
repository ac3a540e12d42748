"""The protocol stamp of results files and the one-version rule of the leaderboard."""

from __future__ import annotations

import pytest

from oodrl.config import parse_params
from oodrl.errors import StoreError
from oodrl.metrics.stamp import (
    PROTOCOL_VERSION,
    UNSTAMPED_VERSION,
    one_protocol_version,
    params_hash,
    protocol_stamp,
)

PARAMS = {
    "seed": 0,
    "benchmark": {"detectors": ["cusum"], "injectors": ["gradual_drift"]},
    "detectors": {"cusum": {}},
    "anomaly": {"injectors": {"gradual_drift": {}}},
}


def test_params_hash_follows_resolved_params_not_the_executor():
    base = parse_params(PARAMS, "params", components=False)
    assert params_hash(base) == params_hash(parse_params(dict(PARAMS), "p", components=False))
    explicit = parse_params(PARAMS | {"metrics": {"n_boot": 1000}}, "p", components=False)
    assert params_hash(explicit) == params_hash(base)  # a default written out is the same
    workers = parse_params(PARAMS | {"executor": {"workers": 3}}, "p", components=False)
    assert params_hash(workers) == params_hash(base)
    other = parse_params(PARAMS | {"seed": 1}, "p", components=False)
    assert params_hash(other) != params_hash(base)
    stamp = protocol_stamp(base)
    assert stamp["protocol_version"] == PROTOCOL_VERSION == 5 and stamp["params_hash"].startswith(
        "sha256:"
    )


def test_one_protocol_version_refuses_a_mix_in_one_line():
    assert one_protocol_version({"a.yaml": {}, "b.yaml": {}}) == UNSTAMPED_VERSION
    assert one_protocol_version({"a.yaml": {"protocol_version": 2}}) == 2
    with pytest.raises(StoreError) as error:
        one_protocol_version({"a.yaml": {}, "b.yaml": {"protocol_version": 2}, "c.yaml": {}})
    message = str(error.value)
    assert "\n" not in message
    assert "version 1: a.yaml, c.yaml; version 2: b.yaml" in message
    with pytest.raises(StoreError, match="x.yaml: protocol_version must be an integer"):
        one_protocol_version({"x.yaml": {"protocol_version": "2"}})
