"""Policies: NoisyNet value networks, their training, and loaders for users' own policies.

Nothing heavy is imported here; use ``oodrl.policies.load`` / ``oodrl.policies.train`` directly.
"""
