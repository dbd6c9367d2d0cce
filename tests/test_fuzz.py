"""Fuzz suite of every reader (``bench/fuzz.py``): mutated meshes (OFF, NOFF, COFF, PLY, OBJ,
STL, gzip), point files, ``.vts``, landmark, map and test-pairs files, saved bases, checkpoints
and cache entries either load as the mutation allows or raise a torchfmap error naming the file;
never another exception, a hang or a silently changed result.

A bounded, derandomised number of examples per reader runs here; ``python -m bench robustness
--case fuzz`` runs many more and tabulates the outcomes."""

from __future__ import annotations

import pytest

from bench import fuzz

#: Examples per reader in the suite: enough to reach every mutation kind of a reader.
EXAMPLES = 80


@pytest.mark.parametrize("reader", sorted(fuzz.readers()))
def test_reader_loads_what_the_mutation_allows_or_names_the_file(reader):
    tally = fuzz.check(reader, EXAMPLES)
    assert tally["examples"] == EXAMPLES
    assert any(key.startswith("refused") for key in tally)  # the mutations reached the checks


def test_the_oracle_fails_a_reader_that_changes_rows_silently(tmp_path):
    """The property can fail: a reader that drops a row, or raises a foreign exception, is caught."""
    reader = fuzz.readers()["landmarks"]
    path = tmp_path / "l.txt"
    path.write_bytes(reader.make())
    expected = reader.read(path)
    same = fuzz.Mutant(reader.make(), "same", "unchanged")
    dropping = fuzz.Reader("dropping", ".txt", reader.make, lambda p: reader.read(p)[1:], "table")
    with pytest.raises(AssertionError, match="different result"):
        fuzz.judge(dropping, path, same, expected)
    raising = fuzz.Reader("raising", ".txt", reader.make, lambda p: {}["x"], "table")
    with pytest.raises(AssertionError, match="KeyError instead of a torchfmap error"):
        fuzz.judge(raising, path, same, expected)
    refused = fuzz.Mutant(b"", "refuse", "empty")
    with pytest.raises(AssertionError, match="loaded instead of refused"):
        lenient = fuzz.Reader("lenient", ".txt", reader.make, lambda p: expected, "table")
        fuzz.judge(lenient, path, refused, expected)


def test_a_hang_is_reported_within_the_time_limit(tmp_path, monkeypatch):
    import time

    monkeypatch.setattr(fuzz, "TIME_LIMIT", 0.2)
    path = tmp_path / "l.txt"
    path.write_text("1\n")
    hanging = fuzz.Reader("hanging", ".txt", lambda: b"1\n", lambda p: time.sleep(5), "table")
    start = time.monotonic()
    with pytest.raises(AssertionError, match="no answer within 0.2 s"):
        fuzz.judge(hanging, path, fuzz.Mutant(b"1\n", "same", "x"), None)
    assert time.monotonic() - start < 4
