"""Locating, checking, installing and (offline) downloading LPIPS weights; `wtbench weights`."""

from __future__ import annotations

import hashlib
import urllib.error
import urllib.request

import pytest
import torch
from typer.testing import CliRunner

from benchmarks.cli import app
from benchmarks.evaluation import lpips_weights as lw
from benchmarks.evaluation.lpips import LPIPS, random_state_dicts
from worldtree.infra.errors import UserError


@pytest.fixture
def weights_src(tmp_path, monkeypatch):
    """A folder with random weights; the expected AlexNet file name/prefix follow its real sha256, as
    torchvision names its files, so the checksum check runs for real."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    monkeypatch.delenv(lw.ENV_VAR, raising=False)
    alex, lin = random_state_dicts(seed=2)
    src = tmp_path / "src"
    src.mkdir()
    torch.save(alex, src / "tmp.pth")
    prefix = hashlib.sha256((src / "tmp.pth").read_bytes()).hexdigest()[:8]
    monkeypatch.setattr(lw, "ALEXNET_FILE", f"alexnet-owt-{prefix}.pth")
    monkeypatch.setattr(lw, "ALEXNET_SHA256_PREFIX", prefix)
    (src / "tmp.pth").rename(src / lw.ALEXNET_FILE)
    torch.save(lin, src / lw.LIN_FILE)
    return src, alex, lin


def test_default_folder_follows_xdg(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert lw.default_folder() == tmp_path / "worldtree-bench" / "lpips"


def test_search_order_and_missing(tmp_path, monkeypatch, weights_src):
    src, _, _ = weights_src
    with pytest.raises(lw.WeightsNotFound, match="wtbench weights install --from DIR"):
        lw.locate()
    monkeypatch.setenv(lw.ENV_VAR, str(tmp_path / "nowhere"))
    with pytest.raises(UserError, match=lw.ENV_VAR) as e:
        lw.locate()
    assert not isinstance(e.value, lw.WeightsNotFound)  # a named folder must hold the files
    monkeypatch.setenv(lw.ENV_VAR, str(src))
    assert lw.locate().path == src
    origins = [f.origin for f in lw.search_folders(tmp_path)]
    assert origins == ["--lpips-weights", f"${lw.ENV_VAR}", "user cache"]
    with pytest.raises(UserError, match="--lpips-weights"):
        lw.locate(tmp_path)


def test_load_from_folder_records_checksums(weights_src):
    src, alex, lin = weights_src
    model, info = lw.load_lpips(src)
    assert info.alexnet_sha256 == hashlib.sha256((src / lw.ALEXNET_FILE).read_bytes()).hexdigest()
    assert info.lin_sha256 == hashlib.sha256((src / lw.LIN_FILE).read_bytes()).hexdigest()
    x = torch.rand(1, 3, 64, 64) * 2 - 1
    ref = LPIPS.from_state_dicts(alex, lin)
    assert model.distance(x, -x).item() == pytest.approx(ref.distance(x, -x).item(), rel=1e-6)


def test_install_copies_checked_files_into_cache(weights_src):
    src, _, _ = weights_src
    installed = lw.install_from(src)
    cache = lw.default_folder()
    assert set(installed) == {lw.ALEXNET_FILE, lw.LIN_FILE}
    assert (cache / lw.LIN_FILE).read_bytes() == (src / lw.LIN_FILE).read_bytes()
    assert lw.locate().path == cache


def test_corrupt_or_foreign_files_are_refused(weights_src):
    src, alex, lin = weights_src
    data = bytearray((src / lw.ALEXNET_FILE).read_bytes())
    data[-20] ^= 0xFF
    (src / lw.ALEXNET_FILE).write_bytes(bytes(data))
    with pytest.raises(UserError, match="sha256"):
        lw.install_from(src)
    assert not (lw.default_folder() / lw.ALEXNET_FILE).exists()
    torch.save({**lin, "lin5.model.1.weight": torch.zeros(1, 3, 1, 1)}, src / lw.LIN_FILE)
    with pytest.raises(UserError, match="alex.pth"):
        lw.check_lin(src / lw.LIN_FILE)
    (src / lw.LIN_FILE).write_bytes(b"not a pickle")
    with pytest.raises(UserError, match="cannot read"):
        lw.check_lin(src / lw.LIN_FILE)


def test_download_offline_gives_one_line_error(tmp_path, monkeypatch):
    def offline(*a, **k):
        raise urllib.error.URLError("Name or service not known")

    monkeypatch.setattr(urllib.request, "urlopen", offline)
    with pytest.raises(UserError) as e:
        lw.download(tmp_path / "dest")
    assert "\n" not in str(e.value) and "install --from" in str(e.value)
    assert list((tmp_path / "dest").iterdir()) == []  # no partial file left behind


def test_weights_cli_show_and_install(weights_src):
    src, _, _ = weights_src
    runner = CliRunner()
    res = runner.invoke(app, ["weights", "show"])
    assert res.exit_code == 0 and "missing" in res.output and "eval uses: no LPIPS" in res.output
    res = runner.invoke(app, ["weights", "install", "--from", str(src)])
    assert res.exit_code == 0, res.output
    assert "installed" in res.output
    res = runner.invoke(app, ["weights", "show"])
    assert res.output.count(" ok  sha256 ") == 2 and "eval uses: " + str(lw.default_folder()) in res.output
