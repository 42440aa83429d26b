"""save_torch / load_torch: round trip, one-line errors for missing and damaged files, no partial writes."""

from __future__ import annotations

import pytest
import torch

from worldtree.infra.errors import UserError
from worldtree.infra.torchfile import load_torch, save_torch

MSG = {"missing": "no such thing; make it", "unreadable": "damaged thing ({error}); delete it"}


def test_round_trip_keeps_tensors_and_plain_data(tmp_path):
    obj = {"a": torch.arange(6.0).reshape(2, 3), "n": 3, "names": ["x", "y"]}
    save_torch(tmp_path / "sub" / "f.pt", obj)
    got = load_torch(tmp_path / "sub" / "f.pt", "cpu", **MSG)
    assert torch.equal(got["a"], obj["a"]) and got["n"] == 3 and got["names"] == ["x", "y"]
    assert [p.name for p in (tmp_path / "sub").iterdir()] == ["f.pt"]  # no temporary file left behind


def test_missing_and_damaged_files_give_the_callers_messages(tmp_path):
    with pytest.raises(UserError, match=r"f\.pt: no such thing; make it$"):
        load_torch(tmp_path / "f.pt", "cpu", **MSG)
    (tmp_path / "f.pt").write_bytes(b"not a torch file")
    with pytest.raises(UserError, match=r"f\.pt: damaged thing \(\w+\); delete it$"):
        load_torch(tmp_path / "f.pt", "cpu", **MSG)
