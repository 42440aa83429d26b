"""``manifest.json`` of a built scene: provenance plus the sha256 of every file, and its verification."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from nvidia_ls import llff
from nvidia_ls.sampling import pingpong
from nvidia_ls.scene_checks import (
    ROTATION_TOL,
    camera_problem,
    depth_map_problem,
    flow_problem,
    pose_rows_problem,
    rotation_problem,
)
from worldtree.infra.atomic import atomic_write_json
from worldtree.infra.hashing import sha256_file

MANIFEST = "manifest.json"
MANIFEST_SCHEMA = 1


DERIVED_FOLDERS = ("priors", "gt_priors")
"""Top-level scene folders written after the build (the priors cache of `wtbench prep`/`run`, and
`nvls gt-priors`): not part of the scene's record, so `nvls verify` ignores them."""


def scene_files(scene: Path) -> list[str]:
    """Relative paths (POSIX) of every file in the scene except the manifest and :data:`DERIVED_FOLDERS`,
    sorted."""
    rels = (p.relative_to(scene) for p in scene.rglob("*") if p.is_file() and p.name != MANIFEST)
    return sorted(r.as_posix() for r in rels if r.parts[0] not in DERIVED_FOLDERS)


def hash_files(scene: str | Path) -> dict[str, str]:
    """``{relative path: sha256}`` of every file of the scene except the manifest."""
    scene = Path(scene)
    return {rel: sha256_file(scene / rel) for rel in scene_files(scene)}


def write_manifest(scene: str | Path, record: dict, files: dict[str, str] | None = None) -> dict:
    """Add ``files`` (relative path -> sha256; computed when not given) to ``record``; write ``manifest.json``."""
    scene = Path(scene)
    record = dict(record)
    record["schema"] = MANIFEST_SCHEMA
    record["files"] = hash_files(scene) if files is None else files
    atomic_write_json(scene / MANIFEST, record)
    return record


def _rotation_problem(R: np.ndarray, tol: float = ROTATION_TOL) -> str | None:
    """:func:`nvidia_ls.scene_checks.rotation_problem` (kept under its old name)."""
    return rotation_problem(R, tol)


def verify_scene(scene: str | Path, check_hashes: bool = True) -> list[str]:
    """Re-check a built scene; returns a list of problems (empty when all is well).

    Checks: manifest readable; every listed file present with its sha256; no unlisted files; cameras.json
    counts against the manifest and the folders; training frames never use the test camera and follow
    the ping-pong order (classic protocol: the manifest's order, frame 0 the test camera); rotations
    orthonormal; intrinsics positive; near < far; poses_bounds.npy agrees with cameras.json.
    """
    from worldtree.scene_schema import read_cameras, read_manifest

    scene = Path(scene)
    problems: list[str] = []
    mpath = scene / MANIFEST
    if not mpath.is_file():
        return [f"{mpath}: missing (not a scene built by `nvls build`?)"]
    # The manifest's shape and its paths (each inside the scene) are checked before any listed file is
    # opened: a manifest naming ../ or /etc/... stops here with one line.
    man = read_manifest(scene)
    files = man.get("files", {})
    for rel, digest in files.items():
        p = scene / rel
        if not p.is_file():
            problems.append(f"{rel}: missing")
        elif check_hashes and sha256_file(p) != digest:
            problems.append(f"{rel}: checksum differs from the manifest (file changed)")
    for rel in scene_files(scene):
        if rel not in files:
            problems.append(f"{rel}: not listed in the manifest")

    cpath = scene / "cameras.json"
    try:
        cams = json.loads(cpath.read_text())
    except (OSError, json.JSONDecodeError, UnicodeDecodeError) as e:
        problems.append(f"cameras.json: unreadable ({e})")
        return problems
    # The document's shape, and every file/mask it names lying inside the scene, are checked first: any
    # problem there is one line naming the key or entry (worldtree.scene_schema).
    read_cameras(scene)
    problems += _count_problems(scene, man, cams)
    cam_problems, by_id = _camera_problems(cams)
    problems += cam_problems + _poses_bounds_problems(scene, by_id) + _imported_problems(scene)
    return problems


def _imported_problems(scene: Path) -> list[str]:
    """The priors `nvls import` wrote under ``imported/`` (depth or disparity maps, flow), with the checks
    import applied to them (:mod:`nvidia_ls.scene_checks`)."""
    problems: list[str] = []
    for sub, kind in (("disp", "disparity"), ("depth", "depth"), ("flow", "flow")):
        folder = scene / "imported" / sub
        for p in sorted(folder.glob("*.npy")) if folder.is_dir() else []:
            try:
                a = np.load(p, allow_pickle=False)
            except (ValueError, OSError, EOFError) as e:
                problems.append(f"{p.relative_to(scene).as_posix()}: unreadable ({e})")
                continue
            why = flow_problem(a) if kind == "flow" else depth_map_problem(a, kind)
            if why is not None:
                problems.append(f"{p.relative_to(scene).as_posix()}: {why}")
    return problems


def _count_problems(scene: Path, man: dict, cams: dict) -> list[str]:
    """Frame, test-view and mask counts of the manifest, cameras.json and the folders; the training frames'
    cameras (never the test camera, ping-pong order; under the classic protocol the manifest's order from the
    test camera)."""
    problems: list[str] = []
    counts = man.get("counts", {})
    frames, tests = cams.get("frames", []), cams.get("test_frames", [])
    n_img = len(list((scene / "images").glob("*.png")))
    n_gt = len(list((scene / "gt_images").glob("*.png")))
    n_mask = len(list((scene / "masks").glob("*.png")))
    if counts.get("frames") != len(frames) or n_img != len(frames):
        problems.append(
            f"frame count mismatch: manifest {counts.get('frames')}, cameras.json {len(frames)}, images/ {n_img}"
        )
    if counts.get("test_frames") != len(tests) or n_gt != len(tests):
        problems.append(
            f"test frame count mismatch: manifest {counts.get('test_frames')}, cameras.json {len(tests)}, "
            f"gt_images/ {n_gt}"
        )
    n_mask_expected = sum(1 for f in tests if f.get("mask"))
    if n_mask != n_mask_expected:
        problems.append(f"mask count mismatch: cameras.json lists {n_mask_expected}, masks/ holds {n_mask}")
    test_cam = cams.get("test_camera")
    used = [f.get("camera") for f in frames]
    train = man.get("train_cameras")
    if man.get("protocol", "nvidia-ls") == "classic":
        # Frame t is the t-th camera of the manifest's order, which starts at the test camera.
        if train and (used != train[: len(used)] or train[0] != test_cam):
            problems.append("training frame cameras do not follow the classic order of the manifest (frame t "
                            "from its t-th camera, frame 0 the test camera)")  # fmt: skip
        return problems
    if test_cam in used:
        problems.append(f"training frames use the test camera {test_cam}")
    if train and used != pingpong(train, len(used)):
        problems.append("training frame cameras do not follow the ping-pong order of the manifest")
    return problems


def _camera_problems(cams: dict) -> tuple[list[str], dict]:
    """Every camera's intrinsics and rotation, the frames' cameras listed, near < far. Returns the problems
    and the cameras by id."""
    problems: list[str] = []
    frames, tests = cams.get("frames", []), cams.get("test_frames", [])
    by_id: dict = {}
    width, height = cams.get("width"), cams.get("height")
    if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in (width, height)):
        problems.append(f"cameras.json: width/height must be positive integers (got {width}, {height})")
        width = height = 1
    for c in cams.get("cameras", []):
        cid = c.get("id")
        by_id[cid] = c
        try:
            K = np.asarray(c.get("K"), float)
            w2c = np.asarray(c.get("w2c"), float)
        except (TypeError, ValueError):
            problems.append(f"camera {cid}: K or w2c is not a matrix of numbers")
            continue
        # The same check `nvls import` and `nvls build` apply before writing (nvidia_ls.scene_checks).
        msg = camera_problem(K, w2c, width, height)
        if msg:
            problems.append(f"camera {cid}: {msg}")
    for f in frames + tests:
        if f.get("camera") not in by_id:
            problems.append(f"{f.get('file')}: camera {f.get('camera')} is not listed in cameras.json")
    near, far = cams.get("near"), cams.get("far")
    if not (isinstance(near, (int, float)) and isinstance(far, (int, float)) and 0 < near < far):
        problems.append(f"cameras.json: near/far must satisfy 0 < near < far (got {near}, {far})")
    return problems, by_id


def _poses_bounds_problems(scene: Path, by_id: dict) -> list[str]:
    """``poses_bounds.npy`` (when present) against cameras.json's poses."""
    problems: list[str] = []
    pb_path = scene / "poses_bounds.npy"
    if pb_path.is_file():
        try:
            pb = np.load(pb_path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            problems.append(f"poses_bounds.npy: unreadable ({e})")
        else:
            ids = sorted(by_id)
            why = pose_rows_problem(pb) if isinstance(pb, np.ndarray) else "not one array"
            if why is not None:
                problems.append(f"poses_bounds.npy: {why}")
            elif pb.shape != (len(ids), 17):
                problems.append(f"poses_bounds.npy: shape {pb.shape}, expected ({len(ids)}, 17)")
            elif ids:
                _, w2cs, _ = llff.llff_to_opencv(pb)
                ref = np.stack([np.asarray(by_id[i]["w2c"], float) for i in ids])
                if not np.allclose(w2cs, ref, atol=1e-5):
                    problems.append("poses_bounds.npy: poses disagree with cameras.json")
    return problems
