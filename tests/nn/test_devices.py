"""Device names of the learned path (``torchfmap.nn.devices``): 'auto' takes CUDA only where it
exists, names are checked, and CUDA asked for without CUDA is a clear error with the fix."""

from __future__ import annotations

import pytest
import torch

from torchfmap.errors import ParameterError
from torchfmap.nn import resolve_device


def test_auto_is_cuda_where_there_is_one_else_the_cpu(monkeypatch):
    for available, expected in ((False, "cpu"), (True, "cuda")):
        monkeypatch.setattr(torch.cuda, "is_available", lambda a=available: a)
        assert resolve_device("auto") == resolve_device(None) == torch.device(expected)


def test_names_and_devices_pass_and_bad_ones_name_the_fix(monkeypatch):
    assert resolve_device("cpu") == resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("meta").type == "meta"
    with pytest.raises(ParameterError, match="unknown device 'gpu'. Fix: 'cpu', 'cuda'"):
        resolve_device("gpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for name in ("cuda", "cuda:1", torch.device("cuda")):
        with pytest.raises(ParameterError, match="no CUDA device here. Fix: device 'cpu'"):
            resolve_device(name)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
