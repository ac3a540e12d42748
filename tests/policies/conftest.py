"""The policy tests' shared network."""

from __future__ import annotations

import pytest
import torch

from oodrl.policies.networks import NoisyQNetwork


@pytest.fixture
def noisy_network() -> NoisyQNetwork:
    """A small noisy Q-network, the same weights each time."""
    torch.manual_seed(0)
    return NoisyQNetwork(8, 4, (32, 32), sigma0=0.5)
