"""Bad input through the command line (audit 4): one clear line, the right exit code, checked
before the computation, and no partial output left in OUT or beside it."""

import json
import os
import re
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest

from fusedmosaic import methods
from fusedmosaic.cli import main
from fusedmosaic.io import OutputWriter, read_homographies_csv, write_homographies_csv

SYSFS = Path("/sys")  # writing there is refused even to root (the tests may run as root)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """A tiny fetoscopy dataset (8 frames, slow motion so pairwise registers) and a pCLE one."""
    root = tmp_path_factory.mktemp("robust")
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "feto"), "--n-frames", "8",
                 "--laps", "0.1"]) == 0
    assert main(["--quiet", "simulate", "pcle", str(root / "pcle"), "--n-frames", "8",
                 "--width", "128", "--height", "112"]) == 0
    return root


@pytest.fixture
def computed(monkeypatch):
    """Records which methods actually ran (to show that a check came before the computation)."""
    calls = []
    get = methods.get

    def spy(name):
        run = get(name)

        def wrapped(*args, **kwargs):
            calls.append(name)
            return run(*args, **kwargs)

        return wrapped

    monkeypatch.setattr(methods, "get", spy)
    return calls


def run(dataset, out, method="emt", *extra):
    return main(["--quiet", "run", str(dataset), "--method", method, "--out", str(out),
                 "--no-report", *extra])


def listing(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def no_temp(folder: Path) -> bool:
    return not [p for p in folder.rglob(".*") if ".tmp" in p.name or "probe" in p.name]


# --------------------------------------------------------------------------- 4: unusable OUT


@pytest.mark.parametrize("case", ["file", "under-file", "unwritable"])
def test_unusable_out_fails_before_the_computation(data, tmp_path, computed, capsys, case):
    (tmp_path / "afile").write_text("x")
    out = {"file": tmp_path / "afile", "under-file": tmp_path / "afile" / "sub",
           "unwritable": SYSFS / "fusedmosaic_out"}[case]
    if case == "unwritable" and not SYSFS.is_dir():
        pytest.skip("needs a Linux sysfs")
    assert run(data / "feto", out) == 2
    err = capsys.readouterr().err
    expected = {"file": "exists and is not a folder",
                "under-file": f"cannot create the output folder: {tmp_path / 'afile'} is a file",
                "unwritable": "cannot write in /sys"}[case]
    assert err.startswith(f"fusedmosaic: error: {out}: ") and expected in err
    assert "Traceback" not in err and err.count("\n") == 1
    assert computed == []
    assert listing(tmp_path) == ["afile"] and (tmp_path / "afile").read_text() == "x"


def test_simulate_and_demo_check_their_folder_first(tmp_path, capsys):
    (tmp_path / "afile").write_text("x")
    assert main(["simulate", "pcle", str(tmp_path / "afile"), "--n-frames", "3"]) == 2
    assert "afile: exists and is not a folder" in capsys.readouterr().err
    assert main(["simulate", "pcle", str(tmp_path / "afile" / "d"), "--n-frames", "3"]) == 2
    assert "afile is a file" in capsys.readouterr().err
    assert main(["demo", "--out", str(tmp_path / "afile"), "--frames", "10"]) == 2
    assert "afile: exists and is not a folder" in capsys.readouterr().err
    assert listing(tmp_path) == ["afile"]


def test_simulate_into_a_non_empty_folder_names_the_cli_flag(tmp_path, capsys):
    out = tmp_path / "d"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    assert main(["simulate", "pcle", str(out), "--n-frames", "3"]) == 2
    err = capsys.readouterr().err
    assert "exists and is not empty" in err and "--overwrite" in err
    assert "overwrite=True" not in err
    assert main(["--quiet", "simulate", "pcle", str(out), "--n-frames", "3", "--width", "64",
                 "--height", "56", "--overwrite"]) == 0
    assert (out / "camera.yaml").is_file() and not (out / "notes.txt").exists()


def test_os_error_is_one_line_naming_the_path(data, tmp_path, monkeypatch, capsys):
    import fusedmosaic.runner

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / "x" / "mosaic.png"))

    monkeypatch.setattr(fusedmosaic.runner, "run_dataset", refuse)
    assert run(data / "feto", tmp_path / "x") == 1
    err = capsys.readouterr().err
    assert err == f"fusedmosaic: error: {tmp_path / 'x' / 'mosaic.png'}: Permission denied\n"


# --------------------------------------------------------------------------- 5: Ctrl-C


def test_ctrl_c_prints_interrupted_and_leaves_nothing(data, tmp_path, monkeypatch, capsys):
    import fusedmosaic.runner

    def interrupt(*args, **kwargs):  # as if Ctrl-C hit during compositing
        raise KeyboardInterrupt

    monkeypatch.setattr(fusedmosaic.runner, "compose_outputs", interrupt)
    out = tmp_path / "out"
    assert run(data / "feto", out, "emt", "--video", str(tmp_path / "v.mp4")) == 130
    err = capsys.readouterr().err
    assert err == "fusedmosaic: interrupted\n"
    assert listing(tmp_path) == []  # no OUT, no video, no temp folder


# --------------------------------------------------------------------------- 6, 7: OUT contents


def test_a_new_run_replaces_the_previous_output_set(data, tmp_path, capsys):
    out = tmp_path / "out"
    assert run(data / "feto", out, "emt", "--video", str(out / "videos" / "c.mp4")) == 0
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto"),
                 "--no-report"]) == 0
    (out / "notes.txt").write_text("mine")
    assert {"plane.json", "poses.csv", "videos/c.mp4", "evaluation.json"} <= set(listing(out))
    assert run(data / "feto", out, "pairwise") == 0
    # emt's plane, poses and video, and the evaluation of the emt run, are gone; the user's
    # file stays
    assert listing(out) == ["homographies.csv", "mosaic.png", "notes.txt", "report.json"]
    assert json.loads((out / "report.json").read_text())["method"] == "pairwise"
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto")]) == 0
    md = (out / "evaluation.md").read_text()
    assert "| pairwise |" in md and "## Plane" not in md and "## Camera poses" not in md


def test_a_folder_named_like_an_output_fails_before_anything_moves(data, tmp_path, computed,
                                                                   capsys):
    out = tmp_path / "out"
    (out / "report.json").mkdir(parents=True)
    (out / "notes.txt").write_text("mine")
    assert run(data / "feto", out) == 2
    err = capsys.readouterr().err
    assert f"{out / 'report.json'}: is a folder; the output needs a file" in err
    assert computed == []
    assert listing(out) == ["notes.txt", "report.json"] and no_temp(tmp_path)


def test_output_writer_commit_is_all_or_nothing(tmp_path):
    out = tmp_path / "out"
    out.mkdir()
    (out / "homographies.csv").write_text("old")
    with pytest.raises(ValueError, match=r"report\.json: is a folder"), OutputWriter(out) as w:
        w.write_text("homographies.csv", "new")
        w.write_text("report.json", "{}")
        (out / "report.json").mkdir()  # appears while the run computes
    assert (out / "homographies.csv").read_text() == "old"
    assert listing(out) == ["homographies.csv", "report.json"] and no_temp(tmp_path)


# --------------------------------------------------------------------------- 9, 10: evaluate


@pytest.fixture(scope="module")
def emt_out(data, tmp_path_factory):
    out = tmp_path_factory.mktemp("emt") / "out"
    assert run(data / "feto", out) == 0
    return out


@pytest.mark.parametrize(("name", "content", "message"), [
    ("plane.json", "{not json", r"plane\.json: not valid JSON \(Expecting property name"),
    ("plane.json", '{"plane": [0, 0]}', r'plane\.json: "plane" must be 3 finite numbers'),
    ("plane.json", "[1, 2, 3]", r"plane\.json: expected a JSON object"),
    ("report.json", "{bad", r"report\.json: not valid JSON"),
    ("report.json", '{"method": 5, "timings_s": "x"}', r'report\.json: "method" must be a JSON '
                                                       r"string, got int"),
    ("report.json", '{"timings_s": "x"}', r'report\.json: "timings_s" must be a JSON object'),
    ("truth_plane.json", "{", r"truth_plane\.json: not valid JSON"),
])
def test_evaluate_corrupt_json_names_the_file_and_writes_nothing(data, emt_out, tmp_path,
                                                                 capsys, name, content, message):
    out, truth = tmp_path / "out", data / "feto"
    shutil.copytree(emt_out, out)
    if name == "truth_plane.json":
        truth = tmp_path / "truth"
        shutil.copytree(data / "feto", truth)
    (truth if name == "truth_plane.json" else out).joinpath(name).write_text(content)
    before = listing(out)
    assert main(["evaluate", str(out), "--truth", str(truth)]) == 2
    captured = capsys.readouterr()
    assert re.search(message, captured.err), captured.err
    assert captured.out == ""  # no scores printed for a run that then failed
    assert listing(out) == before and no_temp(tmp_path)


def test_evaluate_json_destination(data, emt_out, tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    truth = str(data / "feto")
    # a missing folder is created, like --out and --video
    assert main(["--quiet", "evaluate", str(emt_out), "--truth", truth,
                 "--json", "new/sub/e.json"]) == 0
    assert listing(tmp_path / "new") == ["sub", "sub/e.json", "sub/e.md", "sub/e_plots"] + [
        f"sub/e_plots/{p.name}" for p in sorted((tmp_path / "new/sub/e_plots").iterdir())]
    (tmp_path / "folder").mkdir()
    assert main(["evaluate", str(emt_out), "--truth", truth, "--json", "folder"]) == 2
    err = capsys.readouterr().err
    assert "--json folder: is a folder; give a file name, e.g. folder/evaluation.json" in err
    assert main(["evaluate", str(emt_out), "--truth", truth, "--json", "e.md"]) == 2
    assert "give a .json file name" in capsys.readouterr().err
    if SYSFS.is_dir():
        assert main(["evaluate", str(emt_out), "--truth", truth, "--json",
                     str(SYSFS / "fusedmosaic" / "e.json")]) == 2
        err = capsys.readouterr().err
        assert err.startswith("fusedmosaic: error: --json /sys/fusedmosaic/e.json: ")
    assert main(["evaluate", "typo/out", "--truth", truth]) == 2  # creates no folder
    assert "homographies.csv: file not found" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["folder", "new"]  # no stray .e.json.tmp
    assert not list((tmp_path / "folder").iterdir()) and no_temp(emt_out.parent)


@pytest.mark.parametrize(("value", "message"), [
    ("-3", "--positions: the number of evenly spaced frames must be >= 1, got -3"),
    ("0", "--positions: the number of evenly spaced frames must be >= 1, got 0"),
    ("2.5", "argument --positions: invalid int value: '2.5'"),
])
def test_evaluate_positions_must_be_a_positive_integer(data, emt_out, capsys, value, message):
    argv = ["evaluate", str(emt_out), "--truth", str(data / "feto"), "--positions", value]
    if value == "2.5":  # argparse's own check
        with pytest.raises(SystemExit) as stop:
            main(argv)
        assert stop.value.code == 2
    else:
        assert main(argv) == 2
    assert message in capsys.readouterr().err
    assert not (emt_out / "evaluation.json").exists()


def test_evaluate_warns_about_another_dataset(data, emt_out, tmp_path, capsys):
    pcle = tmp_path / "p"
    assert run(data / "pcle", pcle, "robot") == 0
    report = json.loads((pcle / "report.json").read_text())
    assert report["dataset_fingerprint"]["frames"] == 8
    assert set(report["dataset_fingerprint"]["sha256"]) == {"camera.yaml", "frames.csv",
                                                            "ground_truth.csv"}
    # the fetoscopy truth also has 8 frames: scored, but with a warning
    assert main(["--quiet", "evaluate", str(pcle), "--truth", str(data / "feto"),
                 "--no-report"]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"fusedmosaic: warning: {pcle / 'report.json'} records the dataset "
                          f"{(data / 'pcle').resolve()}, but {data / 'feto'} differs from it")
    assert "camera.yaml" in err and "ground_truth.csv" in err
    # a moved copy of the right dataset is fine
    moved = tmp_path / "moved"
    shutil.copytree(data / "pcle", moved)
    assert main(["--quiet", "evaluate", str(pcle), "--truth", str(moved), "--no-report"]) == 0
    assert capsys.readouterr().err == ""
    assert "dataset_warning" not in json.loads((pcle / "evaluation.json").read_text())["results"][0]


# --------------------------------------------------------------------------- 16, 18, 20: run


@pytest.mark.parametrize("fps", ["inf", "nan", "0", "-25"])
def test_fps_must_be_finite_and_positive(data, tmp_path, computed, capsys, fps):
    assert run(data / "feto", tmp_path / "o", "emt", "--fps", fps) == 2
    assert "error: --fps: must be a finite number of frames per second > 0" in (
        capsys.readouterr().err)
    assert computed == [] and listing(tmp_path) == []


@pytest.mark.parametrize("name", ["c.txt", "c.gif", "c"])
def test_unsupported_video_extension_is_refused_up_front(data, tmp_path, computed, capsys, name):
    video = tmp_path / "o" / name
    assert run(data / "feto", tmp_path / "o", "emt", "--video", str(video)) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fusedmosaic: error: {video}: unsupported video file extension")
    assert ".mp4" in err and ".tmp" not in err
    assert computed == [] and listing(tmp_path) == []


@pytest.mark.parametrize("inside", ["frames", ".", "frames/sub"])
def test_out_inside_the_dataset_is_refused(data, computed, capsys, inside):
    dataset = data / "feto"
    before = listing(dataset)
    out = dataset / inside
    assert run(dataset, out) == 2
    err = capsys.readouterr().err
    assert "would corrupt the dataset: choose --out outside it" in err
    assert ("is the dataset folder" in err) == (inside == ".")
    assert computed == [] and listing(dataset) == before


# --------------------------------------------------------------------------- numpy warnings


def test_degenerate_rows_and_self_comparison_raise_no_numpy_warning(data, emt_out, tmp_path,
                                                                    capsys):
    out = tmp_path / "out"
    out.mkdir()
    ids, G = read_homographies_csv(emt_out / "homographies.csv")
    G[1] = 0.0  # all zero
    G[2, 2, 2] = 0.0  # h22 = 0
    write_homographies_csv(out / "homographies.csv", ids, G)
    pcle_out = tmp_path / "p"
    assert run(data / "pcle", pcle_out, "robot") == 0
    # warnings are errors under pytest: these would fail if numpy or scipy warned
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto"),
                 "--no-report"]) == 0
    result = json.loads((out / "evaluation.json").read_text())["results"][0]
    assert result["placed"] == 6 and result["e_j_px"][1] is None
    assert main(["--quiet", "evaluate", str(pcle_out), "--truth", str(data / "pcle"),
                 "--compare", str(pcle_out), "--no-report"]) == 0
    test = json.loads((pcle_out / "evaluation.json").read_text())["wilcoxon"][0]
    assert test["p_value"] == 1.0 and test["n"] == 8


def test_a_warning_is_shown_as_one_line(data, tmp_path, monkeypatch, capsys):
    import fusedmosaic.runner

    def warn(*args, **kwargs):
        np.log(np.zeros(1))  # RuntimeWarning: divide by zero encountered in log
        return "done"

    monkeypatch.setattr(fusedmosaic.runner, "run_dataset", warn)
    with warnings.catch_warnings():
        warnings.simplefilter("default")  # as outside pytest
        assert run(data / "feto", tmp_path / "o") == 0
    err = capsys.readouterr().err
    assert err == "fusedmosaic: warning: divide by zero encountered in log\n"
