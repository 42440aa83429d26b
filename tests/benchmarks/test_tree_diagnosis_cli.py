"""`python -m benchmarks.speed.tree_diagnosis` on folders that are not WorldTree runs: one error line, exit 2."""

from __future__ import annotations

import pytest


def test_a_run_without_tree_nodes_is_one_error_line(tmp_path, capsys):
    from benchmarks.speed import tree_diagnosis

    tree, root = tmp_path / "tree", tmp_path / "root"
    tree.mkdir()
    root.mkdir()
    with pytest.raises(SystemExit) as e:
        tree_diagnosis.main([str(tree), str(root), "--scene", str(tmp_path)])
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: ") and "node" in err[0], err
