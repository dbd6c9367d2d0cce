"""Ground truth of a folder (discover_pairs, eval --gt): never a silent identity for meshes
that do not share vertex order."""

from __future__ import annotations

import numpy as np
import pytest

from torchfmap import ParameterError, save_mesh
from torchfmap.cli import main
from torchfmap.eval import discover_pairs

from .conftest import bend, bumpy_blob


@pytest.fixture
def shuffled_folder(tmp_path):
    """Two meshes of equal vertex count whose vertex orders differ (the second is shuffled)."""
    x = bumpy_blob(2)
    perm = np.random.default_rng(0).permutation(x.n_vertices)
    save_mesh(x, tmp_path / "a.off")
    save_mesh(x.copy(bend(x.vertices, 0.2)).permuted(perm), tmp_path / "b.off")
    return tmp_path


def test_identity_only_for_one_template_unless_asked(shuffled_folder, tmp_path, capsys):
    with pytest.raises(ParameterError, match="face lists differ.*--gt identity"):
        list(discover_pairs(shuffled_folder))
    ((_, _, _, _, gt),) = list(discover_pairs(shuffled_folder, identity=True))
    np.testing.assert_array_equal(gt.idx_x, gt.idx_y)
    assert main(["eval", str(shuffled_folder), "--k", "8", "--quiet"]) == 2
    assert "--gt identity" in capsys.readouterr().err
    # the same template (same faces): identity is the convention, and --gt files refuses it
    same = tmp_path / "same"
    same.mkdir()
    x = bumpy_blob(2)
    for i, s in enumerate((0.1, 0.3)):
        save_mesh(x.copy(bend(x.vertices, s)), same / f"m{i}.off")
    assert len(list(discover_pairs(same))) == 1
    with pytest.raises(ParameterError, match="no ground truth"):
        list(discover_pairs(same, identity=False))
    assert main(["eval", str(same), "--k", "8", "--quiet", "--gt", "files"]) == 2


def test_gt_from_vts_names_paths_given_for_arrays(tmp_path):
    from torchfmap.eval import gt_from_vts

    with pytest.raises(ParameterError, match=r"not their paths.*read_vts"):
        gt_from_vts(str(tmp_path / "a.vts"), tmp_path / "b.vts")
