"""Review N (session 47), finding M1: `simulate` (and `import`) into the current folder, empty,
wrote the dataset beside it and renamed it over it: the shell was left in a deleted folder, the
size said "0.0 MB", and `simulate fetoscopy .` then failed on ./camera.yaml (exit 2) after
writing it."""

import os

import pytest

from fusedmosaic.cli import main


@pytest.mark.parametrize("kind", ["fetoscopy", "pcle"])
@pytest.mark.parametrize("target", [".", "./", "../here"])
def test_simulate_into_the_current_folder_is_refused(tmp_path, monkeypatch, capsys, kind, target):
    here = tmp_path / "here"
    here.mkdir()
    monkeypatch.chdir(here)
    assert main(["simulate", kind, target, "--n-frames", "10"]) == 2
    named = target.rstrip("/") if target != "./" else "."  # (as Path prints it)
    assert (f"fusedmosaic: error: {named}: refusing to overwrite: it is the current folder; "
            "choose a new folder") in capsys.readouterr().err
    assert os.listdir(here) == [] and os.listdir(tmp_path) == ["here"]
    assert os.path.samefile(os.getcwd(), here)  # not replaced


def test_simulate_into_a_folder_holding_the_current_one_is_refused(tmp_path, monkeypatch,
                                                                    capsys):
    (tmp_path / "a" / "b").mkdir(parents=True)
    monkeypatch.chdir(tmp_path / "a" / "b")
    assert main(["simulate", "pcle", "..", "--n-frames", "10"]) == 2
    assert "..: refusing to overwrite: it holds the current folder" in capsys.readouterr().err
    assert os.listdir(tmp_path / "a") == ["b"]
