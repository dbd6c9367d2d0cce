"""The one reading of a device name (``torchfmap.nn.devices.resolve_device``)."""

from __future__ import annotations

import pytest
import torch

from torchfmap.errors import ParameterError
from torchfmap.nn import resolve_device


def test_names_resolve_to_devices_and_auto_follows_cuda(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu") == resolve_device(torch.device("cpu"))
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == resolve_device(None) == resolve_device() == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 1)
    assert resolve_device("auto") == torch.device("cuda") == resolve_device("cuda")
    with pytest.raises(ParameterError, match="sees 1 CUDA device.*Fix: cuda:0"):
        resolve_device("cuda:3")


def test_unknown_names_and_cuda_without_cuda_are_refused_with_the_fix(monkeypatch):
    with pytest.raises(ParameterError, match="unknown device 'gpu'.*Fix: one of auto, cpu, cuda"):
        resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ParameterError, match="no CUDA device.*Fix: --device cpu"):
        resolve_device("cuda")
