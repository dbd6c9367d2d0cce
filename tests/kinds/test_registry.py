"""The registry of basis kinds (``torchfmap.kinds.registry``): ``get_kind``, ``learned_kind``,
``kind_of``, ``register_kind``."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from torchfmap import ParameterError
from torchfmap.bases import Basis, Column
from torchfmap.kinds import KINDS, BasisKind, get_kind, kind_of, learned_kind, register_kind


def test_register_kind_adds_a_kind_and_refuses_a_nameless_one():
    copy = replace(KINDS["harmonic"], name="harmonic_copy")
    try:
        assert register_kind(copy) is copy and get_kind("harmonic_copy") is copy
    finally:
        KINDS.pop("harmonic_copy", None)
    with pytest.raises(ParameterError, match="non-empty string name"):
        register_kind(object())


def test_unknown_kind_is_refused_with_the_choices():
    with pytest.raises(ParameterError, match="unknown basis kind 'eigen'.*laplacian, hybrid, diffusion"):
        get_kind("eigen")
    assert get_kind(KINDS["stack"]) is KINDS["stack"]
    assert all(isinstance(kind, BasisKind) and KINDS[kind.name] is kind for kind in KINDS.values())
    assert kind_of(Basis(np.ones((4, 1)), np.ones(4), [Column("custom")])) is None


def test_learned_kind_refuses_the_classical_only_kinds():
    assert learned_kind("laplacian") is KINDS["laplacian"]
    with pytest.raises(ParameterError, match="the hybrid basis is solved block-wise.*Fix: one of laplacian"):
        learned_kind("hybrid")
