"""The registry of basis kinds (``torchfmap.bases.registry``): ``get_kind``, ``kind_of``,
``register_kind``."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from torchfmap import ParameterError
from torchfmap.bases import KINDS, Basis, Column, get_kind, kind_of
from torchfmap.kinds import BasisKind


def test_register_kind_adds_a_kind_and_refuses_a_nameless_one():
    from dataclasses import replace

    from torchfmap.bases import KINDS, get_kind, register_kind

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


def test_names_of_bases_of_no_kind_are_reserved():
    """'custom' and 'diffusion_mix' name bases of no registered kind (their weights are
    W_LAP_OTHER's): a kind under either name would shadow them, so it is refused, and W_LAP
    lists every name once."""
    from torchfmap.bases.registry import RESERVED_NAMES, register_kind

    from torchfmap.errors import ParameterError
    from torchfmap.fmap.defaults import W_LAP, W_LAP_OTHER
    from torchfmap.kinds import get_kind

    assert set(RESERVED_NAMES) == set(W_LAP_OTHER)
    for name in RESERVED_NAMES:
        with pytest.raises(ParameterError, match="no registered kind"):
            register_kind(dataclasses.replace(get_kind("harmonic"), name=name))
    assert len(W_LAP) == len(set(W_LAP)) == len(list(W_LAP))
