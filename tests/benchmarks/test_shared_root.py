"""`--root-from`'s checks and linking (benchmarks.runner.shared_root, methods.shared_root) on hand-made run
folders. The runs themselves (a tree grown on a lent root renders as the tree trained alone) are in
tests/methods/test_worldtree_run.py."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from benchmarks.runner.shared_root import check_root_from
from methods.registry import get_method
from methods.shared_root import ROOT_FROM_FILE, lend_root, root_from_record
from worldtree.infra.errors import UserError

WT = get_method("worldtree")
BASE = get_method("base")


def _config(**change) -> dict:
    cfg = {"seed": 0, "steps": 600, "downscale": 1, "ablate": [], "photometric": {"steps": 600, "lr": 1e-3},
           "depth": 2, "auto_split": {"max_depth": 6}, "chain_length": None}  # fmt: skip
    cfg.update(change)
    return cfg


def _record(scene: Path, **change) -> dict:
    return {"method": "worldtree", "scene": str(scene), "imported_priors": {}, "device": "cpu",
            "config": _config(**change)}  # fmt: skip


def _lender(root: Path, scene: Path, method="worldtree", items=("ba.pt", "sw", "photometric"), ledger=None,
            **config) -> Path:  # fmt: skip
    """A run folder with config.json, the given checkpoints (a folder holds ckpt_0000001.pt and a hidden
    temporary file) and a stage ledger."""
    root.mkdir(parents=True)
    rec = _record(scene, **config)
    rec["method"] = method
    if method == "base":
        for k in ("depth", "auto_split", "chain_length"):
            rec["config"].pop(k)
    (root / "config.json").write_text(json.dumps(rec))
    ck = root / "checkpoints"
    ck.mkdir()
    for name in items:
        if name.endswith(".pt"):
            (ck / name).write_bytes(name.encode())
        else:
            (ck / name).mkdir()
            (ck / name / "ckpt_0000001.pt").write_bytes(b"weights")
            (ck / name / ".ckpt_0000002.pt.123.tmp").write_bytes(b"half")
    ledger = ledger or {"stages_s": {"priors": 5.0, "sw": 2.0, "photometric": 7.0, "tree": 9.0},
                        "stages_cpu_s": {"sw": 3.0, "photometric": 11.0}}  # fmt: skip
    (ck / "stage_timing.json").write_text(json.dumps(ledger))
    return root


def test_a_tree_may_take_the_root_of_another_depth_or_of_base(tmp_path):
    scene = tmp_path / "scene"
    src = _lender(tmp_path / "d0", scene, depth=0, ablate=["tpt"])
    lent = check_root_from(src, tmp_path / "d2", WT, _record(scene, depth=2), "cpu")
    assert lent.items == ("ba.pt", "sw", "photometric") and lent.method == "worldtree"
    # Only the lent stages' seconds, not the priors (this run computes its own) nor the lender's tree.
    assert lent.stages_s == {"sw": 2.0, "photometric": 7.0} and lent.stages_cpu_s == {"sw": 3.0, "photometric": 11.0}
    base = _lender(tmp_path / "base", scene, method="base")
    assert check_root_from(base, tmp_path / "d1", WT, _record(scene, depth=1), "cpu").method == "base"
    # Base takes a tree run's root too; the tree's own settings are not Base's and are not compared.
    rec = _record(scene)
    for k in ("depth", "auto_split", "chain_length"):
        rec["config"].pop(k)
    assert check_root_from(src, tmp_path / "b", BASE, rec, "cpu").items


@pytest.mark.parametrize(
    ("change", "words"),
    [
        ({"config": {"steps": 900}}, "differs in steps"),
        ({"config": {"photometric": {"steps": 600, "lr": 2e-3}}}, "differs in photometric"),
        ({"config": {"ablate": ["ba"]}}, "ablates"),
        ({"scene": "elsewhere"}, "trained on"),
        ({"imported_priors": {"masks": "/m"}}, "imported other priors"),
    ],
)
def test_a_root_trained_otherwise_is_refused_naming_the_difference(tmp_path, change, words):
    scene = tmp_path / "scene"
    src = _lender(tmp_path / "src", scene)
    rec = _record(scene, **change.pop("config", {}))
    rec.update(change)
    with pytest.raises(UserError, match=words) as e:
        check_root_from(src, tmp_path / "dst", WT, rec, "cpu")
    assert "\n" not in str(e.value) and str(src) in str(e.value)


def test_what_is_not_a_lender_is_refused(tmp_path):
    scene = tmp_path / "scene"
    rec = _record(scene)
    with pytest.raises(UserError, match="not a run folder"):
        check_root_from(tmp_path / "nothing", tmp_path / "dst", WT, rec, "cpu")
    src = _lender(tmp_path / "src", scene)
    with pytest.raises(UserError, match="own folder"):
        check_root_from(src, src, WT, rec, "cpu")
    with pytest.raises(UserError, match="trains every stage itself"):
        check_root_from(src, tmp_path / "dst", get_method("static"), rec, "cpu")
    other = _lender(tmp_path / "static", scene, method="static")
    with pytest.raises(UserError, match="takes a root from base, worldtree"):
        check_root_from(other, tmp_path / "dst", WT, rec, "cpu")
    empty = _lender(tmp_path / "empty", scene, items=())
    with pytest.raises(UserError, match="holds none of"):
        check_root_from(empty, tmp_path / "dst", WT, rec, "cpu")
    (src / "timing.json").write_text(json.dumps({"device": "cuda:0"}))
    with pytest.raises(UserError, match="trained on cuda"):
        check_root_from(src, tmp_path / "dst", WT, rec, "cpu")


def test_lending_links_whole_items_once_and_refuses_a_run_with_its_own_root(tmp_path):
    scene = tmp_path / "scene"
    src = _lender(tmp_path / "src", scene)
    dst = tmp_path / "dst" / "checkpoints"
    lent = check_root_from(src, dst.parent, WT, _record(scene), "cpu")
    # An interrupted earlier attempt left a temporary copy: it is replaced, never taken for the item.
    dst.mkdir(parents=True)
    (dst / ".sw.lent.tmp").mkdir()
    (dst / ".sw.lent.tmp" / "junk").write_bytes(b"x")
    assert lend_root(lent, dst, WT.shared_root.checkpoints) == ["ba.pt", "sw", "photometric"]
    assert sorted(p.name for p in dst.iterdir()) == sorted(["ba.pt", "sw", "photometric", ROOT_FROM_FILE])
    assert sorted(p.name for p in (dst / "sw").iterdir()) == ["ckpt_0000001.pt"]  # the hidden temporary left out
    assert (dst / "photometric" / "ckpt_0000001.pt").read_bytes() == b"weights"
    assert root_from_record(dst)["run"] == str(src.resolve())
    # The next session with the same lender links only what is missing, and keeps what the run trained.
    (dst / "photometric" / "ckpt_0000001.pt").unlink()
    (dst / "photometric" / "ckpt_0000009.pt").write_bytes(b"own")
    (dst / "ba.pt").unlink()
    assert lend_root(lent, dst, WT.shared_root.checkpoints) == ["ba.pt"]
    assert sorted(p.name for p in (dst / "photometric").iterdir()) == ["ckpt_0000009.pt"]
    # The lender's file is untouched by the borrower's writes (a checkpoint is replaced, not rewritten).
    assert (src / "checkpoints" / "photometric" / "ckpt_0000001.pt").read_bytes() == b"weights"
    other = _lender(tmp_path / "other", scene)
    with pytest.raises(UserError, match="was grown on"):
        lend_root(check_root_from(other, dst.parent, WT, _record(scene), "cpu"), dst, WT.shared_root.checkpoints)
    own = tmp_path / "own" / "checkpoints"
    (own / "sw").mkdir(parents=True)
    with pytest.raises(UserError, match="already trained sw itself"):
        lend_root(lent, own, WT.shared_root.checkpoints)
    assert not (own / ROOT_FROM_FILE).exists() and not (own / "photometric").exists()


def test_a_lenders_own_lent_seconds_carry_over(tmp_path):
    scene = tmp_path / "scene"
    src = _lender(tmp_path / "src", scene, ledger={"stages_s": {"photometric": 1.0}})
    (src / "checkpoints" / ROOT_FROM_FILE).write_text(
        json.dumps({"run": "/first", "stages_s": {"photometric": 40.0, "sw": 5.0}, "stages_cpu_s": {"sw": 6.0}})
    )
    lent = check_root_from(src, tmp_path / "dst", WT, _record(scene), "cpu")
    assert lent.stages_s == {"photometric": 41.0, "sw": 5.0} and lent.stages_cpu_s == {"sw": 6.0}
