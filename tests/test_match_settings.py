"""Settings that would change nothing are refused, in the API and the CLI (no silent no-op)."""

from __future__ import annotations

import pytest

from torchfmap import ParameterError, save_mesh
from torchfmap.cli import main
from torchfmap.eval import landmarks_from_gt
from torchfmap.pipeline import match


def test_unused_settings_are_refused(bent_pair, tmp_path, capsys):
    x, y, gt = bent_pair
    lm = landmarks_from_gt(x, gt, 6)
    with pytest.raises(ParameterError, match="k_final=40 is the size ZoomOut grows"):
        match(x, y, k=20, k_final=40)
    with pytest.raises(ParameterError, match="k_final=40 is the size ZoomOut grows"):
        match(x, y, k=20, k_final=40, landmarks=lm, refine="icp")
    with pytest.raises(ParameterError, match="the laplacian basis has none"):
        match(x, y, k=20, times=[0.01], landmarks=lm, basis="laplacian")
    with pytest.raises(ParameterError, match="the laplacian basis has none"):
        match(x, y, k=20, times=[0.01])
    # the default with landmarks passes times to its feature-aware candidate only
    assert match(x, y, k=20, times=[0.01], landmarks=lm).candidates
    save_mesh(x, tmp_path / "x.off")
    save_mesh(y, tmp_path / "y.off")
    args = ["match", str(tmp_path / "x.off"), str(tmp_path / "y.off"), "--out", str(tmp_path / "m.txt")]
    assert main([*args, "--k", "20", "--k-final", "40"]) == 2
    err = capsys.readouterr().err
    assert "--k-final 40 is the size ZoomOut grows" in err and "--refine zoomout" in err
    assert main([*args, "--k", "20", "--times", "0.01"]) == 2
    assert "--times are the heat times" in capsys.readouterr().err
