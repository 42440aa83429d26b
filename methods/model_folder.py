"""Reading a run's ``model/`` folder back (``Method.load_model``): its ``model.json`` checked first, so that a
missing, damaged or foreign folder is one line naming the file and the fix."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from worldtree.infra.errors import UserError


def read_model_json(folder: str | Path, method: str) -> dict[str, Any]:
    """``folder/model.json`` (written by ``save_model``) when it names ``method``; a :class:`UserError`
    otherwise."""
    path = Path(folder) / "model.json"
    if not path.is_file():
        raise UserError(f"{path}: missing; the run has no saved model: finish it with `wtbench run` first")
    try:
        info = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
        raise UserError(f"{path}: unreadable ({type(e).__name__}); re-run with `wtbench run --force`") from e
    if not isinstance(info, dict) or info.get("method") != method:
        got = info.get("method") if isinstance(info, dict) else None
        raise UserError(f"{path}: a model of method {got!r}, not {method!r}; load it with its own method")
    return info
