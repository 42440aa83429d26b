"""`wtbench eval` on folders: pairing, CSV + JSON record, 16-bit/RGBA input, and one-line errors."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pandas as pd
import pytest
from skimage.metrics import peak_signal_noise_ratio as sk_psnr
from skimage.metrics import structural_similarity as sk_ssim

import worldtree
from benchmarks import cli
from benchmarks.commands import method_options
from benchmarks.evaluation.evaluate import evaluate_folder, pair_files
from worldtree.imageio import write_image
from worldtree.infra.errors import UserError
from worldtree.infra.hashing import sha256_files

H, W = 30, 40


@pytest.fixture(autouse=True)
def no_weights(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv("WTBENCH_LPIPS_WEIGHTS", raising=False)


def make_dirs(root, n=3, seed=0):
    rng = np.random.default_rng(seed)
    data = []
    for d in ("pred", "gt", "mask"):
        (root / d).mkdir(parents=True, exist_ok=True)
    for i in range(n):
        gt = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
        pred = np.clip(gt.astype(int) + rng.integers(-20, 21, gt.shape), 0, 255).astype(np.uint8)
        mask = rng.random((H, W)) > 0.5
        name = f"v000_t{i:03d}"
        write_image(root / "gt" / f"{name}.png", gt)
        write_image(root / "pred" / f"{name}.png", pred)
        write_image(root / "mask" / f"{name}.png", mask)
        data.append((name, pred, gt, mask))
    return data


def wtbench(args, monkeypatch, capsys):
    """Run the console entry point in-process; returns (exit code, stdout, stderr)."""
    monkeypatch.setattr(sys, "argv", ["wtbench", *map(str, args)])
    # For a command other than run, main() turns `wtbench run`'s method options off for the rest of the process
    # (the app's run command then caches its signature without them): kept on, so that a later test in this
    # worker that runs `wtbench run` in-process still has --ablate, --depth...
    monkeypatch.setattr(method_options, "skip_generation", lambda: None)
    code = 0
    try:
        cli.main()
    except SystemExit as e:
        code = e.code or 0
    out = capsys.readouterr()
    return code, out.out, out.err


def test_eval_writes_csv_and_record(tmp_path, monkeypatch, capsys):
    data = make_dirs(tmp_path)
    code, out, err = wtbench(
        ["eval", tmp_path / "pred", "--gt", tmp_path / "gt", "--masks", tmp_path / "mask"],
        monkeypatch,
        capsys,
    )
    assert code == 0, err
    csv = tmp_path / "metrics.csv"  # default: beside PRED_DIR
    assert f"wrote {csv}" in out and "mean" in out
    assert err.count("warning:") == 1 and "wtbench weights install --from DIR" in err
    text = csv.read_text().splitlines()
    assert text[0] == "frame,psnr,ssim,lpips,avge,mpsnr,mssim,mlpips,mavge"
    assert text[-1].startswith("mean,")
    assert ",,," in text[1]  # LPIPS and AVGE cells empty without weights
    t = pd.read_csv(csv, dtype={"frame": str})
    for i, (name, pred, gt, mask) in enumerate(data):
        assert t.loc[i, "frame"] == name
        assert t.loc[i, "psnr"] == pytest.approx(sk_psnr(gt, pred), abs=1e-7)
        assert t.loc[i, "ssim"] == pytest.approx(sk_ssim(gt, pred, channel_axis=-1), abs=1e-6)
        assert t.loc[i, "mpsnr"] == pytest.approx(sk_psnr(gt[mask], pred[mask]), abs=1e-7)
    rec = json.loads((tmp_path / "metrics.json").read_text())
    assert rec["protocol"]["name"] == "worldtree" and rec["protocol"]["version"] == "1"
    assert rec["lpips"]["available"] is False and rec["lpips"]["net"] == "alex"
    assert rec["frame_count"] == 3 and rec["tool_version"] == worldtree.__version__
    assert rec["inputs"]["pred_sha256"] == sha256_files(sorted((tmp_path / "pred").iterdir()))
    assert rec["inputs"]["gt_sha256"] == sha256_files(sorted((tmp_path / "gt").iterdir()))
    assert rec["inputs"]["mask_sha256"] == sha256_files(sorted((tmp_path / "mask").iterdir()))
    assert rec["csv"] == "metrics.csv" and "eval" in rec["command"] and rec["timestamp"]
    assert rec["mean"]["psnr"] == pytest.approx(t["psnr"].iloc[:-1].mean())


def test_eval_dycheck_without_masks_to_named_out(tmp_path, monkeypatch, capsys):
    make_dirs(tmp_path)
    out_csv = tmp_path / "res" / "d.csv"
    code, _, err = wtbench(
        ["eval", tmp_path / "pred", "--gt", tmp_path / "gt", "--protocol", "dycheck", "--out", out_csv],
        monkeypatch,
        capsys,
    )
    assert code == 0, err
    t = pd.read_csv(out_csv)
    assert t[["mpsnr", "mssim", "mlpips", "mavge"]].isna().all().all()
    assert json.loads((tmp_path / "res" / "d.json").read_text())["protocol"]["name"] == "dycheck"


def test_16bit_rgba_and_other_suffix_inputs(tmp_path):
    rng = np.random.default_rng(1)
    (tmp_path / "pred").mkdir()
    (tmp_path / "gt").mkdir()
    gt = rng.integers(0, 256, (H, W, 3), dtype=np.uint8)
    pred = np.clip(gt.astype(int) + rng.integers(-20, 21, gt.shape), 0, 255).astype(np.uint8)
    # Ground truth as 16-bit RGB (v * 257 reads back as v); prediction as 8-bit RGBA with an alpha to drop.
    cv2.imwrite(str(tmp_path / "gt" / "f0.png"), cv2.cvtColor(gt, cv2.COLOR_RGB2BGR).astype(np.uint16) * 257)
    rgba = np.dstack([cv2.cvtColor(pred, cv2.COLOR_RGB2BGR), rng.integers(0, 256, (H, W), dtype=np.uint8)])
    cv2.imwrite(str(tmp_path / "pred" / "f0.png"), rgba)
    write_image(tmp_path / "gt" / "f1.jpg", gt)  # same stem, different suffix: pairs with pred/f1.png
    write_image(tmp_path / "pred" / "f1.png", pred)
    res = evaluate_folder(tmp_path / "pred", tmp_path / "gt", lpips_weights=False)
    assert res.table.loc[0, "psnr"] == pytest.approx(sk_psnr(gt, pred), abs=1e-9)
    assert res.table.loc[0, "ssim"] == pytest.approx(sk_ssim(gt, pred, channel_axis=-1), abs=1e-6)
    assert list(res.table["frame"]) == ["f0", "f1", "mean"]


def test_pairing_errors_list_the_files(tmp_path):
    make_dirs(tmp_path, n=3)
    (tmp_path / "pred" / "v000_t001.png").unlink()
    write_image(tmp_path / "pred" / "extra.png", np.zeros((H, W, 3), np.uint8))
    (tmp_path / "mask" / "v000_t002.png").unlink()
    with pytest.raises(UserError) as e:
        pair_files(tmp_path / "pred", tmp_path / "gt", tmp_path / "mask")
    msg = str(e.value)
    assert "no prediction for 1 ground-truth frame(s): v000_t001" in msg
    assert "no ground truth for 1 prediction(s): extra" in msg
    assert "no mask for 1 frame(s): v000_t002" in msg
    write_image(tmp_path / "gt" / "v000_t000.jpg", np.zeros((H, W, 3), np.uint8))
    with pytest.raises(UserError, match="share the frame name"):
        pair_files(tmp_path / "pred", tmp_path / "gt")


def test_size_mismatch_and_unreadable_name_the_files(tmp_path):
    make_dirs(tmp_path, n=2)
    write_image(tmp_path / "pred" / "v000_t001.png", np.zeros((H, W + 2, 3), np.uint8))
    with pytest.raises(UserError) as e:
        evaluate_folder(tmp_path / "pred", tmp_path / "gt", lpips_weights=False)
    assert "pred/v000_t001.png" in str(e.value) and "gt/v000_t001.png" in str(e.value)
    write_image(tmp_path / "pred" / "v000_t001.png", np.zeros((H, W, 3), np.uint8))
    write_image(tmp_path / "mask" / "v000_t000.png", np.zeros((H - 1, W), bool))
    with pytest.raises(UserError, match="mask/v000_t000.png"):
        evaluate_folder(tmp_path / "pred", tmp_path / "gt", tmp_path / "mask", lpips_weights=False)
    (tmp_path / "gt" / "v000_t000.png").write_bytes(b"\x89PNG garbage")
    with pytest.raises(UserError, match="gt/v000_t000.png"):
        evaluate_folder(tmp_path / "pred", tmp_path / "gt", lpips_weights=False)


def test_cli_errors_are_one_line_without_traceback(tmp_path, monkeypatch, capsys):
    make_dirs(tmp_path, n=2)
    (tmp_path / "gt" / "v000_t001.png").unlink()
    code, _, err = wtbench(["eval", tmp_path / "pred", "--gt", tmp_path / "gt"], monkeypatch, capsys)
    assert code == 2 and err.startswith("error: ") and err.count("\n") == 1 and "v000_t001" in err
    code, _, err = wtbench(["eval", tmp_path / "pred", "--gt", tmp_path / "nowhere"], monkeypatch, capsys)
    assert code == 2 and "--gt" in err and "Traceback" not in err
    code, _, err = wtbench(
        ["eval", tmp_path / "pred", "--gt", tmp_path / "gt", "--out", tmp_path / "x.txt"], monkeypatch, capsys
    )
    assert code == 2 and "--out" in err


def test_console_script_error_exit_code(tmp_path):
    # The real entry point, as a user runs it: exit status 2 and no traceback.
    p = subprocess.run(
        [
            sys.executable,
            "-m",
            "benchmarks.cli",
            "eval",
            str(tmp_path),
            "--gt",
            str(tmp_path),
            "--protocol",
            "nope",
        ],
        capture_output=True,
        text=True,
    )
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert p.stderr.strip() == "error: --protocol 'nope' is unknown; use one of: worldtree, dycheck"
