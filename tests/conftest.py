"""Shared fixtures: every registered system and scheme (plugins included) is tested."""

from __future__ import annotations

import pytest

import lieflow as lf

REGISTRY = lf.default_registry()
SYSTEMS = sorted(REGISTRY.systems)
SCHEMES = sorted(REGISTRY.schemes)


def make_system(name: str) -> lf.IsospectralSystem:
    """The registered system ``name`` with its default parameters (the plugin contract)."""
    return lf.systems.get(name)


@pytest.fixture(params=SYSTEMS)
def system(request: pytest.FixtureRequest) -> lf.IsospectralSystem:
    return make_system(request.param)


@pytest.fixture(params=SCHEMES)
def scheme(request: pytest.FixtureRequest) -> lf.Scheme:
    return lf.schemes.get(request.param)
