"""Short labels of long configuration names (benchmarks/reporting/names.py): codes, short texts, the key."""

from __future__ import annotations

import pytest

from benchmarks.reporting.names import ELLIPSIS, MAX_CHARS, abbreviate, cut, letter_code, name_key, shorten

#: Configuration names as runs with imported priors get them (describe_configuration), 150+ characters.
PRIORS = (
    "priors.depth_import.fit_scale_shift=true priors.depth_import.kind=disparity "
    "priors.depth_import.merge=fill depth_maps=balloon1_dav2 flow=balloon1_raft"
)
LONG = [
    f"base quick {PRIORS} train.tv_weight=0.1",
    f"worldtree quick depth=2 split=binary {PRIORS} train.tv_weight=0.1",
    f"worldtree quick -sac depth=2 split=binary {PRIORS} train.tv_weight=0.2",
    f"worldtree quick depth=2 split=binary {PRIORS} train.tv_weight=0.2 masks=balloon1_sam2",
]


def test_letter_codes_run_like_spreadsheet_columns():
    assert [letter_code(i) for i in (0, 1, 25, 26, 27, 51, 52, 701, 702)] == [
        "A", "B", "Z", "AA", "AB", "AZ", "BA", "ZZ", "AAA",
    ]  # fmt: skip
    assert len({letter_code(i) for i in range(2000)}) == 2000
    with pytest.raises(ValueError):
        letter_code(-1)


def test_abbreviate_and_cut():
    assert abbreviate("priors.depth_import.kind=disparity") == "kind=disparity"
    assert abbreviate("masks=/data/priors/balloon1_masks/") == "masks=balloon1_masks"
    assert abbreviate("-sac") == "-sac" and abbreviate("depth=2") == "depth=2"
    assert cut("short", 10) == "short"
    assert cut("one two three four", 10) == "one two" + ELLIPSIS
    assert cut("x" * 30, 10) == "x" * 9 + ELLIPSIS
    assert all(len(cut(n, 40)) <= 40 for n in LONG)


def test_key_distinct_stable_and_complete():
    assert min(len(n) for n in LONG) >= 150
    names = [LONG[2], LONG[0], LONG[2], LONG[3], LONG[1]]  # a repeat, out of order
    key = name_key(names)
    assert key.shortened
    # Stable order: codes follow first appearance; the repeat keeps its code.
    assert key.names == (LONG[2], LONG[0], LONG[3], LONG[1])
    assert key.codes == ("A", "B", "C", "D")
    assert key.code(LONG[2]) == "A" and key.code(LONG[1]) == "D"
    # Distinct names, distinct labels; every label is short.
    labels = [key.label(n) for n in key.names]
    assert len(set(labels)) == len(labels) and all(len(lab) <= MAX_CHARS + 3 for lab in labels)
    # Short texts keep what tells the names apart (the words every name shares are dropped).
    assert key.short(LONG[2]).startswith("worldtree -sac") and "tv_weight=0.2" in key.short(LONG[2])
    assert "fit_scale_shift" not in key.short(LONG[2])
    # Cut to length, the words most names share go first: the one name with masks keeps them.
    assert key.short(LONG[3]).startswith("worldtree") and "masks=balloon1_sam2" in key.short(LONG[3])
    assert all(len(s) <= MAX_CHARS for s in key.shorts)
    # The key lists every full name once, with its code and short text.
    entries = key.entries()
    assert [e["full"] for e in entries] == list(key.names)
    assert [e["code"] for e in entries] == list(key.codes)
    assert [e["full"] for e in key.entries([LONG[1], LONG[0]])] == [LONG[0], LONG[1]]
    # The same names in the same order give the same key (a report rebuilt says the same).
    assert name_key(names) == key


def test_short_names_are_shown_as_they_are():
    names = ["static quick", "worldtree quick", "worldtree quick -sac"]
    key = name_key(names)
    assert not key.shortened
    assert [key.label(n) for n in names] == names
    assert shorten(names) == names
    assert shorten([]) == [] and name_key([]).names == ()
    # One long name among short ones: only it is shortened, and it keeps its own words.
    mixed = shorten(["quick", LONG[0]])
    assert mixed[0] == "quick" and len(mixed[1]) <= MAX_CHARS and mixed[1].startswith("base")
