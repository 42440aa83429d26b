"""The checks a scene's cameras and imported priors must pass, shared by the commands that write them
(`nvls import`, `nvls build --poses`) and `nvls verify`, which re-checks them: a scene is never written that
verify would reject, and verify rejects what import would have refused.

Each function returns why its input is unusable (a phrase for a one-line message), or None when it is fine.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

#: Largest ``|R R^T - I|`` entry of a rotation (the files store about 7 significant digits or more).
ROTATION_TOL = 1e-4
#: Focal length range in units of the image's larger side: from a field of view of about 169 degrees
#: (0.05) to a 1000 x telephoto; outside it a pinhole camera sees nothing usable (1e300 is a broken file).
FOCAL_RANGE = (0.05, 1000.0)
#: Largest flow vector, in units of the flow map's larger side: a pixel that moves ten image widths is not a
#: correspondence (3e38 is a broken export).
FLOW_MAX_SIDES = 10.0
#: Smallest share of positive values in a depth or disparity map: both are positive where they are defined;
#: a map mostly <= 0 has the wrong sign or is not a depth map.
DEPTH_MIN_POSITIVE = 0.5


def dtype_problem(a: np.ndarray) -> str | None:
    """Numbers must be real: not text, complex, boolean or objects (their conversion to float drops or
    invents information)."""
    if a.dtype.kind not in "fiu":
        return f"holds {a.dtype} values, not real numbers (save float or int)"
    return None


def pose_rows_problem(pb: np.ndarray) -> str | None:
    """An LLFF ``poses_bounds.npy`` array: real numbers, shape ``(N, 17)`` with N >= 1, all finite."""
    why = dtype_problem(pb)
    if why is not None:
        return why
    if pb.ndim != 2 or pb.shape[1] != 17 or pb.shape[0] == 0:
        return f"shape {tuple(pb.shape)}; expected (N, 17) LLFF rows, N >= 1"
    if not np.isfinite(pb).all():
        return "holds NaN or Inf"
    return None


def rotation_problem(R: np.ndarray, tol: float = ROTATION_TOL) -> str | None:
    """A 3x3 rotation: finite, orthonormal within ``tol``, determinant +1 (not a reflection)."""
    R = np.asarray(R)
    if R.shape != (3, 3) or R.dtype.kind not in "fiu" or not np.isfinite(R).all():
        return "rotation is not a finite 3x3 matrix"
    R = R.astype(np.float64)
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > tol:
        return f"rotation not orthonormal (|R R^T - I| = {err:.2g}, at most {tol:g})"
    if np.linalg.det(R) < 0:
        return "rotation is a reflection (det < 0)"
    return None


def intrinsics_problem(K: np.ndarray, width: float, height: float) -> str | None:
    """A pinhole ``K`` for a ``width x height`` image: finite real 3x3, focal lengths within
    :data:`FOCAL_RANGE` of the larger side."""
    K = np.asarray(K)
    if K.shape != (3, 3) or K.dtype.kind not in "fiu" or not np.isfinite(K).all():
        return "bad intrinsics K (not a finite 3x3 matrix)"
    side = float(max(width, height))
    lo, hi = FOCAL_RANGE[0] * side, FOCAL_RANGE[1] * side
    for name, f in (("fx", float(K[0, 0])), ("fy", float(K[1, 1]))):
        if not lo <= f <= hi:
            return (
                f"bad intrinsics K: {name} = {f:.6g} px outside {lo:.6g}..{hi:.6g} "
                f"({FOCAL_RANGE[0]:g} to {FOCAL_RANGE[1]:g} x the larger image side {side:g})"
            )
    return None


def camera_problem(K: np.ndarray, w2c: np.ndarray, width: float, height: float) -> str | None:
    """One camera: :func:`intrinsics_problem` and a finite real 4x4 ``w2c`` whose rotation passes
    :func:`rotation_problem`."""
    why = intrinsics_problem(K, width, height)
    if why is not None:
        return why
    w2c = np.asarray(w2c)
    if w2c.shape != (4, 4) or w2c.dtype.kind not in "fiu" or not np.isfinite(w2c).all():
        return "w2c is not a finite 4x4 matrix"
    return rotation_problem(w2c[:3, :3])


def depth_map_problem(a: np.ndarray, kind: str) -> str | None:
    """A depth or disparity map (``kind``): real, 2-D, finite, mostly positive."""
    why = dtype_problem(a)
    if why is not None:
        return why
    if a.ndim != 2 or a.size == 0:
        return f"map of shape {tuple(a.shape)}; expected [H, W]"
    if not np.isfinite(a).all():
        return "map holds NaN or Inf"
    positive = float((a > 0).mean())
    if positive < DEPTH_MIN_POSITIVE:
        return (
            f"{kind} map is positive at only {100 * positive:.0f}% of its pixels (at least "
            f"{100 * DEPTH_MIN_POSITIVE:.0f}% expected); wrong sign, or not a {kind} map"
        )
    return None


def flow_problem(f: np.ndarray) -> str | None:
    """An optical flow ``[H, W, 2]`` in pixels: real, finite, no vector longer than :data:`FLOW_MAX_SIDES`
    times the map's larger side."""
    why = dtype_problem(f)
    if why is not None:
        return why
    if f.ndim != 3 or f.shape[-1] != 2 or f.shape[0] == 0 or f.shape[1] == 0:
        return f"flow of shape {tuple(f.shape)}; expected [H, W, 2]"
    if not np.isfinite(f).all():
        return "flow holds NaN or Inf"
    limit = FLOW_MAX_SIDES * max(f.shape[0], f.shape[1])
    longest = float(np.abs(f.astype(np.float64)).max())
    if longest > limit:
        return (
            f"flow of {longest:.3g} px, over {limit:g} px ({FLOW_MAX_SIDES:g} x the map's larger side); "
            "not a flow in pixels"
        )
    return None


def read_pose_rows(path: Path, option: str = "", rows: int | None = None) -> np.ndarray:
    """An LLFF ``poses_bounds.npy`` read whole and checked (:func:`nvidia_ls.scene_checks.pose_rows_problem`):
    an empty, damaged or non-numeric file is a one-line :class:`UserError` naming it (and ``option``).
    ``rows``: the number of rows required (one per rig camera)."""
    from worldtree.infra.errors import UserError

    path = Path(path)
    shown = f"{option} {path}" if option else str(path)
    if path.is_file() and path.stat().st_size == 0:
        raise UserError(f"{shown}: empty file; give an LLFF poses_bounds.npy")
    try:
        pb = np.load(path, allow_pickle=False)
        if isinstance(pb, np.lib.npyio.NpzFile):
            pb.close()
            raise ValueError("an .npz archive of several arrays, not one array")
    except (ValueError, OSError, EOFError) as e:  # EOFError: a file cut short
        raise UserError(f"{shown}: not a readable .npy array ({e}); give an LLFF poses_bounds.npy") from None
    if rows is not None and dtype_problem(pb) is None and pb.shape != (rows, 17):
        raise UserError(f"{shown}: shape {tuple(pb.shape)}, expected ({rows}, 17) for the {rows} rig cameras")
    why = pose_rows_problem(pb)
    if why is not None:
        raise UserError(f"{shown}: {why}; give an LLFF poses_bounds.npy")
    return pb
