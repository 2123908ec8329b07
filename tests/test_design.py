"""Design space: counts, canonicalisation, indexing, encodings, validation, CLI."""

from __future__ import annotations

import itertools
from collections import Counter
from math import comb

import numpy as np
import pytest

from softcrawl import cli
from softcrawl.design import (
    BASELINE_DESIGN,
    PAPER_BEST_DESIGN,
    SLOT_ANGLES_DEG,
    InvalidDesignError,
    canonical_array,
    canonical_designs,
    canonicalize,
    design_from_index,
    design_index,
    is_canonical,
    n_legs,
    one_hot,
    one_hot_batch,
    raw_designs,
    regulator_groups,
    validate_design,
)
from softcrawl.design.picture import design_ascii, plot_design


def test_slot_angles():
    assert SLOT_ANGLES_DEG == (22.5, 67.5, 112.5, 157.5, 202.5, 247.5, 292.5, 337.5)


def test_counts():
    assert len(raw_designs()) == 41_202 == sum(comb(8, k) * 3**k for k in range(3, 7))
    assert len(canonical_designs()) == 6_972
    per_legs = Counter(n_legs(d) for d in canonical_designs())
    assert per_legs == {3: 280, 4: 980, 5: 2_296, 6: 3_416}


def test_sorted_unique_and_cached():
    for designs in (raw_designs(), canonical_designs()):
        assert list(designs) == sorted(set(designs))
    assert canonical_designs() is canonical_designs()
    arr = canonical_array()
    assert arr.shape == (6_972, 8) and arr.dtype == np.int8
    assert [tuple(r) for r in arr.tolist()] == list(canonical_designs())


def test_canonical_set_is_image_of_raw():
    assert {canonicalize(d) for d in raw_designs()} == set(canonical_designs())


@pytest.mark.parametrize(
    "design, expected",
    [
        ((2, 0, 0, 1, 1, 0, 0, 2), (1, 0, 0, 2, 2, 0, 0, 1)),
        ((3, 3, 3, 0, 0, 0, 0, 0), (1, 1, 1, 0, 0, 0, 0, 0)),
        ((0, 0, 3, 1, 2, 0, 0, 0), (0, 0, 1, 2, 3, 0, 0, 0)),
        ((0, 2, 0, 3, 0, 2, 0, 1), (0, 1, 0, 2, 0, 1, 0, 3)),
        ("2,0,0,1,1,0,0,2", (1, 0, 0, 2, 2, 0, 0, 1)),
    ],
)
def test_canonicalize_examples(design, expected):
    assert canonicalize(design) == expected
    assert is_canonical(expected)


def test_canonicalize_idempotent_and_label_invariant():
    rng = np.random.default_rng(0)
    for d in (raw_designs()[i] for i in rng.choice(len(raw_designs()), 500, replace=False)):
        c = canonicalize(d)
        assert canonicalize(c) == c
        for perm in itertools.permutations((1, 2, 3)):
            relabelled = tuple(0 if v == 0 else perm[v - 1] for v in d)
            assert canonicalize(relabelled) == c
    assert not is_canonical((2, 0, 0, 1, 1, 0, 0, 2))


def test_index_round_trip_all():
    for i, d in enumerate(canonical_designs()):
        assert design_index(d) == i
        assert design_from_index(i) == d
    assert design_index((2, 0, 0, 1, 1, 0, 0, 2)) == design_index(BASELINE_DESIGN)
    with pytest.raises(IndexError):
        design_from_index(6_972)
    with pytest.raises(IndexError):
        design_from_index(-1)


def test_named_designs():
    assert is_canonical(BASELINE_DESIGN) and is_canonical(PAPER_BEST_DESIGN)
    assert regulator_groups(BASELINE_DESIGN) == {1: [0, 7], 2: [3, 4]}
    assert regulator_groups(PAPER_BEST_DESIGN) == {1: [0], 2: [3, 4]}
    assert n_legs(BASELINE_DESIGN) == 4 and n_legs(PAPER_BEST_DESIGN) == 3


def test_one_hot():
    v = one_hot(BASELINE_DESIGN)
    assert v.shape == (32,) and v.dtype == np.float32
    blocks = v.reshape(8, 4)
    assert (blocks.sum(axis=1) == 1).all()
    assert tuple(blocks.argmax(axis=1)) == BASELINE_DESIGN
    batch = one_hot_batch(canonical_designs()[:10])
    assert batch.shape == (10, 32) and batch.dtype == np.float32
    assert (batch.sum(axis=1) == 8).all()
    np.testing.assert_array_equal(one_hot_batch(canonical_array()[:10]), batch)
    assert one_hot_batch([]).shape == (0, 32)


def test_validate_accepts_forms():
    expected = (1, 0, 0, 2, 2, 0, 0, 1)
    for form in ("1,0,0,2,2,0,0,1", " [1, 0, 0, 2, 2, 0, 0, 1] ", "1 0 0 2 2 0 0 1", list(expected),
                 np.array(expected), [1.0, 0, 0, 2, 2, 0, 0, 1]):
        assert validate_design(form) == expected


@pytest.mark.parametrize(
    "design, fragment",
    [
        ("1,0,0,2,2,0,0", "8 slots, got 7"),
        ((1, 0, 0, 2, 2, 0, 0, 1, 0), "8 slots, got 9"),
        ("1,0,x,2,2,0,0,1", "slot 2"),
        ((1, 0, 0.5, 2, 2, 0, 0, 1), "not an integer"),
        ((1, 0, 0, 2, 4, 0, 0, 1), "slot 4: value 4"),
        ((1, 0, 0, -1, 2, 0, 0, 1), "slot 3: value -1"),
        ((1, 0, 0, 0, 2, 0, 0, 0), "too few legs: 2"),
        ((1, 1, 1, 2, 2, 2, 3, 0), "too many legs: 7"),
        (5, "sequence"),
    ],
)
def test_invalid_designs(design, fragment):
    with pytest.raises(InvalidDesignError, match=fragment):
        validate_design(design)
    with pytest.raises(ValueError):
        design_index(design)


def test_ascii_picture():
    pic = design_ascii(BASELINE_DESIGN)
    assert "+x" in pic
    assert pic.count("1") == 2 and pic.count("2") == 2
    lines = pic.splitlines()
    # slot 0 (22.5 deg) right of the upper line, slot 7 (337.5 deg) right of the lower line
    assert lines[2].rstrip().endswith("1") and lines[4].rstrip().endswith("1")
    assert lines[2].lstrip().startswith("2") and lines[4].lstrip().startswith("2")
    assert set(lines[0].split()) == {"."} and set(lines[-1].split()) == {"."}


def test_plot_design(tmp_path):
    path = tmp_path / "d.png"
    fig = plot_design((1, 2, 3, 0, 3, 0, 0, 2), path=path)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["regulator 1", "regulator 2", "regulator 3"]


@pytest.fixture
def designs_cli(monkeypatch):
    """``cli.main`` with only the ``designs`` subcommand (independent of other subcommands)."""
    monkeypatch.setattr(cli, "SUBCOMMANDS", ("softcrawl.cli.designs",))
    return cli.main


def test_cli_count(designs_cli, capsys):
    assert designs_cli(["designs", "count"]) == 0
    out = capsys.readouterr().out
    assert "41202" in out and "6972" in out
    for k, n in {3: 280, 4: 980, 5: 2296, 6: 3416}.items():
        assert any(line.split()[0] == str(k) and line.split()[-1] == str(n) for line in out.splitlines() if line.split())


def test_cli_list(designs_cli, capsys):
    assert designs_cli(["designs", "list", "--legs", "6", "--limit", "3"]) == 0
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) == 3
    for line in lines:
        i, d = line.split()
        assert design_from_index(int(i)) == validate_design(d) and n_legs(d) == 6


def test_cli_show(designs_cli, capsys, tmp_path):
    png = tmp_path / "b.png"
    assert designs_cli(["designs", "show", "2,0,0,1,1,0,0,2", "--png", str(png)]) == 0
    out = capsys.readouterr().out
    assert "1,0,0,2,2,0,0,1" in out
    assert f"index:      {design_index(BASELINE_DESIGN)}" in out
    assert "+x" in out and png.exists()


def test_cli_show_invalid(designs_cli, capsys):
    assert designs_cli(["designs", "show", "1,0,0,4,2,0,0,1"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "slot 3" in err
