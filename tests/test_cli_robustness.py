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
from _faults import signal_handler

from fusedmosaic import methods
from fusedmosaic.cli import main
from fusedmosaic.io import OutputWriter, read_homographies_csv, write_homographies_csv
from fusedmosaic.io.output import MANIFEST
from fusedmosaic.runner import run_dataset

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


def test_demo_simulates_again_when_asked_for_another_sequence(tmp_path, capsys):
    """A demo folder keeps its simulated sequence for the next demo only when --frames and
    --motion ask for the same one; a dataset folder the demo did not write is refused."""
    out = tmp_path / "demo"

    def frames_in_dataset() -> int:
        return len((out / "dataset" / "frames.csv").read_text().splitlines()) - 1

    assert main(["demo", "--out", str(out), "--frames", "12"]) == 0
    assert "[demo] simulated a syn fetoscopy sequence (12 frames" in capsys.readouterr().out
    assert main(["demo", "--out", str(out), "--frames", "12"]) == 0
    said = capsys.readouterr().out
    assert f"[demo] reusing the simulated sequence in {out / 'dataset'}" in said
    assert "12/12 frames placed" in said
    assert main(["demo", "--out", str(out), "--frames", "14"]) == 0
    said = capsys.readouterr().out
    assert (f"[demo] {out / 'dataset'} holds a syn sequence of 12 frames; simulating the one "
            "asked for") in said
    assert "14/14 frames placed" in said and frames_in_dataset() == 14
    other = tmp_path / "other"
    (other / "dataset").mkdir(parents=True)
    (other / "dataset" / "notes.txt").write_text("mine")
    assert main(["demo", "--out", str(other), "--frames", "12"]) == 2
    assert (f"{other / 'dataset'}: exists and is not a sequence a fusedmosaic demo simulated "
            "(no simulation.json or camera.yaml); choose another --out, or move it"
            ) in capsys.readouterr().err
    assert listing(other) == ["dataset", "dataset/notes.txt"]


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
    small = ["--n-frames", "3", "--width", "64", "--height", "56", "--overwrite"]
    # --overwrite replaces only a dataset, never a folder of the user's files
    assert main(["--quiet", "simulate", "pcle", str(out), *small]) == 2
    err = capsys.readouterr().err
    assert err == (f"fusedmosaic: error: {out}: refusing to overwrite: it does not look like a "
                   "dataset (no camera.yaml or simulation.json), and overwriting would delete "
                   "everything in it; choose a new folder, or empty it yourself\n")
    assert listing(tmp_path) == ["d", "d/notes.txt"]
    (out / "notes.txt").unlink()
    assert main(["--quiet", "simulate", "pcle", str(out), *small]) == 0  # empty: no overwrite
    (out / "extra.txt").write_text("old run's file")
    assert main(["--quiet", "simulate", "pcle", str(out), *small]) == 0  # a dataset: replaced
    assert (out / "camera.yaml").is_file() and not (out / "extra.txt").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d"]  # no .d.old-* or .d.tmp-*


@pytest.mark.parametrize("where", [".", "..", "../d"])
def test_simulate_overwrite_refuses_the_current_folder_and_its_parents(tmp_path, monkeypatch,
                                                                      capsys, where):
    """`simulate pcle . --overwrite` used to fail with EBUSY and leave a `..old-*` folder."""
    cwd = tmp_path / "proj" / "d"
    cwd.mkdir(parents=True)
    (cwd / "camera.yaml").write_text("looks like a dataset")  # even then: it is the cwd
    (cwd / "thesis.tex").write_text("mine")
    monkeypatch.chdir(cwd)
    before = listing(tmp_path)
    assert main(["--quiet", "simulate", "pcle", where, "--n-frames", "3", "--width", "64",
                 "--height", "56", "--overwrite"]) == 2
    err = capsys.readouterr().err
    what = "is the current folder" if where != ".." else f"holds the current folder {cwd}"
    assert err == (f"fusedmosaic: error: {where}: refusing to overwrite: it {what}; choose a "
                   "new folder\n")
    assert listing(tmp_path) == before
    # the library refuses too
    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    with pytest.raises(ValueError, match=r"refusing to overwrite: it is the current folder"):
        simulate_pcle(".", PcleOptions(n_frames=3, width=64, height=56), overwrite=True)
    assert listing(tmp_path) == before


def test_os_error_is_one_line_naming_the_path(data, tmp_path, monkeypatch, capsys):
    import fusedmosaic.runner

    def refuse(*args, **kwargs):
        raise PermissionError(13, "Permission denied", str(tmp_path / "x" / "mosaic.png"))

    monkeypatch.setattr(fusedmosaic.runner, "run_dataset", refuse)
    assert run(data / "feto", tmp_path / "x") == 1
    err = capsys.readouterr().err
    assert err == f"fusedmosaic: error: {tmp_path / 'x' / 'mosaic.png'}: Permission denied\n"


def test_a_video_that_does_not_read_back_is_an_error(data, tmp_path, monkeypatch, capsys):
    """OpenCV's VideoWriter reports no write error: on a full disk --video left a file without
    its index (unplayable) and the run exited 0. The video is read back on close; here the
    disk 'fills' as the writer finishes (the file cut in half)."""
    import cv2

    real = cv2.VideoWriter

    class FullDisk:
        def __init__(self, path, *args):
            self.path, self.writer = path, real(path, *args)

        def __getattr__(self, name):
            return getattr(self.writer, name)

        def release(self):
            self.writer.release()
            os.truncate(self.path, os.path.getsize(self.path) // 2)

    monkeypatch.setattr(cv2, "VideoWriter", FullDisk)
    video = tmp_path / "v.mp4"
    assert run(data / "feto", tmp_path / "out", "emt", "--video", str(video)) == 1
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: {video}: the video does not read back (0 of 8 frames; a full "
        "disk?): no video written\n")
    assert listing(tmp_path) == []  # no video, no OUT, no temp file
    # one frame (a pairwise chain broken at frame 1 places only the reference): refused too
    from fusedmosaic.compositing.video import MosaicVideoWriter

    writer = MosaicVideoWriter(tmp_path / "one.mp4", (0, 0, 64, 48), 64, 48)
    writer.add(np.full((48, 64, 3), 128, np.uint8), np.eye(3))
    with pytest.raises(OSError, match=r"the video does not read back \(0 of 1 frames"):
        writer.close()
    assert listing(tmp_path) == []
    # ... nor the folders made for a video in a new folder (they were left empty)
    video = tmp_path / "new" / "sub" / "v.mp4"
    assert run(data / "feto", tmp_path / "out", "emt", "--video", str(video)) == 1
    assert listing(tmp_path) == []
    monkeypatch.setattr(cv2, "VideoWriter", real)
    # a video skipped (canvas over the budget) creates no folder either
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the skipped mosaic's warning (test_report's)
        assert run(data / "feto", tmp_path / "out", "emt", "--video", str(video),
                   "--max-canvas-pixels", "1000") == 0
    assert not (tmp_path / "new").exists()
    shutil.rmtree(tmp_path / "out")


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


@pytest.mark.parametrize("name", ["SIGTERM", "SIGHUP"])
def test_sigterm_and_sighup_end_a_run_as_ctrl_c_does(data, tmp_path, monkeypatch, capsys, name):
    """A scheduler's stop, `timeout` or a closed terminal: before, the process died at once and
    left its staging folder and video behind (only `live` handled them)."""
    import signal

    import fusedmosaic.runner

    sig = getattr(signal, name)

    def stopped(*args, **kwargs):  # the signal arrives during compositing
        signal.raise_signal(sig)
        raise AssertionError(f"{name} did not interrupt the run")

    monkeypatch.setattr(fusedmosaic.runner, "compose_outputs", stopped)
    with signal_handler(sig, signal.SIG_DFL):
        out = tmp_path / "out"
        assert run(data / "feto", out, "emt", "--video", str(tmp_path / "v.mp4")) == 130
        assert signal.getsignal(sig) is signal.SIG_DFL  # restored once main returns
    assert capsys.readouterr().err == "fusedmosaic: interrupted\n"
    assert listing(tmp_path) == []  # no OUT, no video, no temp folder


def test_ctrl_c_during_the_demo_simulation_leaves_no_empty_folder(tmp_path, monkeypatch,
                                                                   capsys):
    """Before: the simulation's staging removed itself, but the demo folder it was staged in
    stayed, empty. A folder that existed before is kept."""
    import fusedmosaic.io.dataset

    def interrupt(*args, **kwargs):  # as if Ctrl-C hit once the dataset's staging exists
        raise KeyboardInterrupt

    monkeypatch.setattr(fusedmosaic.io.dataset, "write_camera_yaml", interrupt)
    assert main(["demo", "--out", str(tmp_path / "demo"), "--frames", "4"]) == 130
    assert capsys.readouterr().err == "fusedmosaic: interrupted\n"
    assert listing(tmp_path) == []
    (tmp_path / "mine").mkdir()
    assert main(["demo", "--out", str(tmp_path / "mine"), "--frames", "4"]) == 130
    assert listing(tmp_path) == ["mine"]


@pytest.mark.parametrize("how", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_an_interrupt_while_the_command_line_loads_is_not_a_traceback(monkeypatch, capsys, how):
    """The first second of every command is importing NumPy, OpenCV and the core; a Ctrl-C
    there printed a KeyboardInterrupt traceback (the console script imported fusedmosaic.cli,
    and the package its mosaickers, before any handler), and SIGTERM / SIGHUP killed it
    outright (exit 143 / 129)."""
    import signal
    import sys

    from fusedmosaic import _entry

    class Interrupted:  # a meta path finder: the signal arrives while fusedmosaic.cli imports
        def find_spec(self, name, path=None, target=None):
            if name == "fusedmosaic.cli":
                signal.raise_signal(getattr(signal, how))
                raise AssertionError(f"{how} did not interrupt the import")
            return None

    monkeypatch.delitem(sys.modules, "fusedmosaic.cli")
    monkeypatch.setattr(sys, "meta_path", [Interrupted(), *sys.meta_path])
    with signal_handler(signal.SIGINT, signal.default_int_handler), \
            signal_handler(signal.SIGTERM, signal.SIG_DFL), \
            signal_handler(signal.SIGHUP, signal.SIG_DFL):
        assert _entry.main() == 130
        assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL  # restored
    assert capsys.readouterr().err == "fusedmosaic: interrupted\n"


def test_the_console_entry_loads_nothing_heavy():
    """What runs before the guard above (the package's __init__ and fusedmosaic._entry) must
    stay light, or an interrupt there is a traceback again."""
    import subprocess
    import sys

    code = ("import sys, fusedmosaic._entry; print(sorted({'numpy', 'cv2', 'scipy', "
            "'fusedmosaic._core', 'fusedmosaic.cli'} & set(sys.modules)))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out == "[]\n"


def test_sigterm_during_simulate_leaves_nothing(tmp_path):
    import signal
    import subprocess
    import sys
    import time

    out = tmp_path / "sim"
    proc = subprocess.Popen([sys.executable, "-m", "fusedmosaic.cli", "simulate", "fetoscopy",
                             str(out), "--n-frames", "3000"], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while not any(tmp_path.iterdir()) and time.monotonic() < deadline:  # staging started
            time.sleep(0.05)
        assert any(tmp_path.iterdir()), "simulate wrote nothing within 60 s"
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 130, err
    assert err.endswith("fusedmosaic: interrupted\n")
    assert listing(tmp_path) == []  # the staged dataset (.sim.tmp-*) removed


@pytest.mark.parametrize(("argv", "name"), [
    (["run", "DATA", "--method", "emt", "--out", ""], "OUT"),
    (["simulate", "pcle", " ", "--n-frames", "3"], "OUT"),
    (["evaluate", "", "--truth", "DATA"], "OUT"),
    (["evaluate", "OUT", "--truth", ""], "--truth"),
    (["run", "", "--method", "emt", "--out", "OUT"], "DATASET"),
])
def test_an_empty_path_is_refused_not_read_as_the_current_folder(data, tmp_path, monkeypatch,
                                                                  capsys, argv, name):
    monkeypatch.chdir(tmp_path)
    argv = [str(data / "feto") if a == "DATA" else str(tmp_path / "o") if a == "OUT" else a
            for a in argv]
    assert main(["--quiet", *argv]) == 2
    assert capsys.readouterr().err == (f"fusedmosaic: error: {name} is an empty path (an unset "
                                       "shell variable?)\n")
    assert listing(tmp_path) == []


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
    assert listing(out) == [MANIFEST, "homographies.csv", "mosaic.png", "notes.txt",
                            "report.json"]
    assert json.loads((out / "report.json").read_text())["method"] == "pairwise"
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto")]) == 0
    md = (out / "evaluation.md").read_text()
    assert "| pairwise |" in md and "## Plane" not in md and "## Camera poses" not in md


def test_a_run_never_deletes_the_users_files(data, tmp_path, capsys):
    """Review 4 #1: only what a fusedmosaic run recorded is replaced; a user's plots/, report.md
    and evaluation.md in OUT survive a --no-report run (with no record, and with one)."""
    out = tmp_path / "myproj"
    (out / "plots").mkdir(parents=True)
    mine = {"plots/fig.png": "mine", "report.md": "notes", "evaluation.md": "notes",
            "evaluation_plots": "a file named like a folder we might write", "other.txt": "k"}
    for name, text in mine.items():
        (out / name).write_text(text)
    for _ in range(2):  # the second run finds the first run's record
        assert run(data / "feto", out, "emt") == 0
        assert {n: (out / n).read_text() for n in mine} == mine
    assert json.loads((out / MANIFEST).read_text())["sets"]["run"]["files"] == [
        "homographies.csv", "mosaic.png", "plane.json", "poses.csv", "report.json"]
    # a run with a report would write report.md: the user's is refused, not replaced (audit
    # 19); moved away, the run's report goes in and its plots beside the user's figure in
    # plots/; a later --no-report run removes only those
    capsys.readouterr()
    assert main(["--quiet", "run", str(data / "feto"), "--method", "emt", "--out",
                 str(out)]) == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: {out / 'report.md'}: exists and fusedmosaic did not write it (not "
        f"listed in {out / MANIFEST}); it is not replaced: choose another output folder, or "
        "move the file away\n")
    assert {n: (out / n).read_text() for n in mine} == mine and no_temp(tmp_path)
    (out / "report.md").unlink()
    assert main(["--quiet", "run", str(data / "feto"), "--method", "emt", "--out",
                 str(out)]) == 0
    ours = sorted(p.name for p in (out / "plots").iterdir() if p.name != "fig.png")
    assert ours and (out / "report.md").read_text() != "notes"
    assert run(data / "feto", out, "pairwise") == 0
    assert listing(out / "plots") == ["fig.png"] and not (out / "report.md").exists()
    assert (out / "evaluation.md").read_text() == "notes" and no_temp(tmp_path)


def test_a_foreign_report_json_deletes_nothing(data, tmp_path, capsys):
    out = tmp_path / "foreign"
    (out / "mydata").mkdir(parents=True)
    (out / "mydata" / "a.csv").write_text("precious")
    (out / "summary.csv").write_text("precious")
    (out / "plane.json").write_text("{}")
    foreign = [{"tool": "other", "outputs": ["mydata/", "summary.csv", "plane.json"]},
               {"method": "emt", "outputs": ["mydata/", "summary.csv"]},  # no fingerprint
               {"method": "not-ours", "dataset_fingerprint": {}, "outputs": ["mydata/"]}]
    for report in foreign:
        (out / "report.json").write_text(json.dumps(report))
        (out / MANIFEST).unlink(missing_ok=True)
        ours = report.get("method") == "emt"  # an older fusedmosaic run's: replaced
        capsys.readouterr()
        assert run(data / "feto", out, "pairwise") == (0 if ours else 2)
        if not ours:  # anyone else's report.json is refused, not replaced (audit 19)
            err = capsys.readouterr().err  # (or the homographies.csv the emt run left)
            assert err.startswith(f"fusedmosaic: error: {out}{os.sep}")
            assert ": exists and fusedmosaic did not write it" in err
            assert json.loads((out / "report.json").read_text()) == report
        assert (out / "mydata" / "a.csv").read_text() == "precious"
        assert (out / "summary.csv").read_text() == "precious"
        assert (out / "plane.json").exists() == (not ours)
        (out / "plane.json").write_text("{}")


def test_an_older_fusedmosaic_run_is_replaced_by_its_report(data, tmp_path, capsys):
    """Without a manifest (outputs of an older version), a recognisably fusedmosaic
    report.json still tells what to replace: audit 4 #6, stale plane.json / poses.csv."""
    out = tmp_path / "out"
    assert main(["--quiet", "run", str(data / "feto"), "--method", "emt", "--out",
                 str(out)]) == 0
    (out / MANIFEST).unlink()
    (out / "plots" / "mine.png").write_text("x")
    report = json.loads((out / "report.json").read_text())
    assert "plots/" not in report["outputs"] and "plane.json" in report["outputs"]
    report["outputs"] = sorted({*report["outputs"], "plots/"})  # as the previous version wrote
    (out / "report.json").write_text(json.dumps(report))
    assert run(data / "feto", out, "pairwise") == 0  # listed (fingerprint present): all gone
    assert listing(out) == [MANIFEST, "homographies.csv", "mosaic.png", "report.json"]
    # the oldest reports: no fingerprint and no "outputs": plane.json and poses.csv only
    assert run(data / "feto", out, "emt") == 0
    (out / MANIFEST).unlink()
    report = json.loads((out / "report.json").read_text())
    del report["dataset_fingerprint"], report["outputs"]
    (out / "report.json").write_text(json.dumps(report))
    assert run(data / "feto", out, "pairwise") == 0
    assert listing(out) == [MANIFEST, "homographies.csv", "mosaic.png", "report.json"]
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto")]) == 0
    assert "## Plane" not in (out / "evaluation.md").read_text()


def test_an_evaluation_of_other_outputs_survives_a_run(data, emt_out, tmp_path, capsys):
    """An evaluation written into OUT that scores other folders is not OUT's run's: kept."""
    out = tmp_path / "out"
    assert run(data / "feto", out, "pairwise") == 0
    assert main(["--quiet", "evaluate", str(emt_out), "--truth", str(data / "feto"),
                 "--json", str(out / "emt_eval.json")]) == 0
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto")]) == 0
    assert run(data / "feto", out, "emt") == 0
    names = listing(out)
    assert "emt_eval.json" in names and "emt_eval.md" in names and "emt_eval_plots" in names
    assert "evaluation.json" not in names and "evaluation_plots" not in names
    sets = json.loads((out / MANIFEST).read_text())["sets"]
    assert sorted(sets) == ["evaluation:emt_eval.json", "run"]


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


def test_a_failed_calibrate_or_writer_leaves_no_folder_it_created(data, tmp_path, capsys):
    """Review A #4: calibrate's up-front check created --out's parents and a calibration that
    then failed left them (np2/sub after `calibrate ... --out np2/sub/scope`); OutputWriter
    left the parents it made for OUT when the block failed. Folders that existed before stay."""
    assert main(["--quiet", "calibrate", str(data / "feto"), "--board", "9x6", "--square-mm",
                 "2", "--out", str(tmp_path / "np2" / "sub" / "scope")]) == 2
    assert "the 9x6 board" in capsys.readouterr().err
    assert listing(tmp_path) == []
    (tmp_path / "pre").mkdir()
    with pytest.raises(KeyboardInterrupt), OutputWriter(tmp_path / "pre" / "a" / "b" / "out",
                                                        record="run") as w:
        w.write_text("report.json", "{}")
        raise KeyboardInterrupt
    assert listing(tmp_path) == ["pre"]
    # (a folder someone else filled meanwhile is kept, with its parents)
    with pytest.raises(ValueError, match="failed"), OutputWriter(tmp_path / "pre" / "a" / "out"):
        (tmp_path / "pre" / "a" / "theirs.txt").write_text("x")
        raise ValueError("failed")
    assert listing(tmp_path) == ["pre", "pre/a", "pre/a/theirs.txt"]


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
    assert listing(tmp_path / "new") == ["sub", f"sub/{MANIFEST}", "sub/e.json", "sub/e.md",
                                         "sub/e_plots"] + [
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
    # a file of that name that no evaluation wrote is the user's: refused, left as it was
    (tmp_path / "folder" / "mine.json").write_text('{"my": "numbers"}')
    assert main(["evaluate", str(emt_out), "--truth", truth, "--json",
                 "folder/mine.json"]) == 2
    assert capsys.readouterr().err == (
        "fusedmosaic: error: --json folder/mine.json: exists and is not an evaluation "
        "fusedmosaic wrote; choose another --json name, or move that file\n")
    assert (tmp_path / "folder" / "mine.json").read_text() == '{"my": "numbers"}'
    (tmp_path / "folder" / "mine.json").unlink()
    assert main(["evaluate", "typo/out", "--truth", truth]) == 2  # creates no folder
    assert "homographies.csv: file not found" in capsys.readouterr().err
    assert sorted(os.listdir(tmp_path)) == ["folder", "new"]  # no stray .e.json.tmp
    assert not list((tmp_path / "folder").iterdir()) and no_temp(emt_out.parent)


def test_evaluate_json_keeps_the_users_md_and_plots(data, emt_out, tmp_path, capsys):
    """Review 4 #2: `evaluate --json DIR/NAME.json` replaces NAME.md and NAME_plots/ only when
    a fusedmosaic evaluation wrote them."""
    res = tmp_path / "res"
    (res / "summary_plots").mkdir(parents=True)
    (res / "summary.md").write_text("my own summary")
    (res / "summary_plots" / "a.png").write_text("x")
    truth = str(data / "feto")
    argv = ["--quiet", "evaluate", str(emt_out), "--truth", truth, "--json",
            str(res / "summary.json")]
    assert main([*argv, "--no-report"]) == 0  # the user's report and plots stay
    assert listing(res) == [MANIFEST, "summary.json", "summary.md", "summary_plots",
                            "summary_plots/a.png"]
    assert (res / "summary.md").read_text() == "my own summary"
    # a report would overwrite them: refused before anything is computed or written
    before = {p: p.read_bytes() for p in res.rglob("*") if p.is_file()}
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == (f"fusedmosaic: error: --json {res / 'summary.json'}: the report would replace "
                   f"{res / 'summary.md'}, which no fusedmosaic evaluation wrote; choose another "
                   "--json name, move that file, or pass --no-report\n")
    (res / "summary.md").unlink()
    assert main(argv) == 2
    assert f"the report's plots would go into {res / 'summary_plots'}, a folder no " in (
        capsys.readouterr().err)
    (res / "summary.md").write_text("my own summary")
    assert {p: p.read_bytes() for p in res.rglob("*") if p.is_file()} == before
    # once a fusedmosaic evaluation wrote them, the next one replaces them, and --no-report
    # removes them again
    (res / "summary.md").unlink()
    shutil.rmtree(res / "summary_plots")
    assert main(argv) == 0 and main(argv) == 0
    assert (res / "summary.md").read_text().startswith("# fusedmosaic evaluation")
    assert main([*argv, "--no-report"]) == 0
    assert listing(res) == [MANIFEST, "summary.json"] and no_temp(tmp_path)


def _older_evaluation(data, emt_out, res: Path) -> None:
    """res/e.json, e.md and e_plots/ as an older version left them (no manifest)."""
    assert main(["--quiet", "evaluate", str(emt_out), "--truth", str(data / "feto"), "--json",
                 str(res / "e.json"), "--no-report"]) == 0
    (res / MANIFEST).unlink()
    (res / "e.md").write_text("# fusedmosaic evaluation\n\nold report\n")
    (res / "e_plots").mkdir()
    (res / "e_plots" / "old.png").write_text("x")


def test_evaluate_json_of_an_older_version_counts_as_ours(data, emt_out, tmp_path, capsys):
    res = tmp_path / "res"
    _older_evaluation(data, emt_out, res)
    assert main(["--quiet", "evaluate", str(emt_out), "--truth", str(data / "feto"), "--json",
                 str(res / "e.json")]) == 0
    assert "old report" not in (res / "e.md").read_text()
    assert not (res / "e_plots/old.png").exists()


@pytest.mark.parametrize("mine", [
    {"results": []}, {"results": [{"output": "a", "e_M_px": 1.0}]}, {"results": ["x"]}])
def test_evaluate_json_with_a_results_list_of_the_users_is_kept(data, emt_out, tmp_path, capsys,
                                                                mine):
    """Review A #2: any NAME.json with a "results" list was taken for an older version's
    evaluation, and NAME.json, NAME.md and NAME_plots/ were replaced. Only results entries
    carrying evaluate_output's keys are ours, and NAME.md only if it starts with the report's
    title line."""
    res = tmp_path / "res"
    res.mkdir()
    (res / "e.json").write_text(json.dumps(mine))
    (res / "e.md").write_text("mine")
    argv = ["--quiet", "evaluate", str(emt_out), "--truth", str(data / "feto"), "--json",
            str(res / "e.json")]
    for extra in ([], ["--no-report"]):
        assert main([*argv, *extra]) == 2
        assert capsys.readouterr().err == (
            f"fusedmosaic: error: --json {res / 'e.json'}: exists and is not an evaluation "
            "fusedmosaic wrote; choose another --json name, or move that file\n")
    assert json.loads((res / "e.json").read_text()) == mine
    assert listing(res) == ["e.json", "e.md"] and (res / "e.md").read_text() == "mine"


def test_evaluate_json_of_an_older_version_keeps_a_users_md_and_plots(data, emt_out, tmp_path,
                                                                      capsys):
    """Review A #2: beside an older version's NAME.json, a NAME.md that does not start with
    the report's title line, or a NAME_plots/ holding other than PNG files, is the user's."""
    res = tmp_path / "res"
    _older_evaluation(data, emt_out, res)
    (res / "e.md").write_text("my notes on the evaluation\n")
    (res / "e_plots" / "notes.txt").write_text("mine")
    argv = ["--quiet", "evaluate", str(emt_out), "--truth", str(data / "feto"), "--json",
            str(res / "e.json")]
    assert main(argv) == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: --json {res / 'e.json'}: the report would replace {res / 'e.md'}, "
        "which no fusedmosaic evaluation wrote; choose another --json name, move that file, or "
        "pass --no-report\n")
    (res / "e.md").unlink()
    assert main(argv) == 2
    assert f"the report's plots would go into {res / 'e_plots'}, a folder no " in (
        capsys.readouterr().err)
    (res / "e.md").write_text("my notes on the evaluation\n")
    assert main([*argv, "--no-report"]) == 0  # the JSON is replaced, the user's files stay
    assert (res / "e.md").read_text() == "my notes on the evaluation\n"
    assert sorted(p.name for p in (res / "e_plots").iterdir()) == ["notes.txt", "old.png"]


def test_outputs_are_staged_inside_an_existing_folder(data, emt_out, tmp_path, monkeypatch,
                                                      capsys):
    """Review 4 #3: `--json ~/e.json` must work when ~'s parent is not writable: an existing
    folder is staged inside (only it needs write access); a new one beside it."""
    import tempfile

    import fusedmosaic.io.output as output

    home = tmp_path / "ro" / "home"
    home.mkdir(parents=True)
    refused = []

    def not_in_ro(make):  # as if tmp_path/ro were read-only (the tests may run as root)
        def guarded(*args, dir=None, **kwargs):
            if Path(dir).resolve() == (tmp_path / "ro").resolve():
                refused.append(dir)
                raise PermissionError(13, "Permission denied", str(dir))
            return make(*args, dir=dir, **kwargs)
        return guarded

    monkeypatch.setattr(output.tempfile, "mkdtemp", not_in_ro(tempfile.mkdtemp))
    monkeypatch.setattr(output.tempfile, "mkstemp", not_in_ro(tempfile.mkstemp))
    assert main(["--quiet", "evaluate", str(emt_out), "--truth", str(data / "feto"), "--json",
                 str(home / "e.json")]) == 0
    assert (home / "e.json").is_file() and refused == [] and no_temp(tmp_path)
    assert run(data / "feto", home, "pairwise") == 0
    assert (home / "mosaic.png").is_file() and refused == [] and no_temp(tmp_path)
    # a folder that must be created needs its parent
    assert run(data / "feto", tmp_path / "ro" / "new", "pairwise") == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: {tmp_path / 'ro' / 'new'}: cannot write in {tmp_path / 'ro'} (the "
        "output folder is created there): Permission denied\n")


def test_stale_staging_folders_of_a_killed_run_are_removed(data, tmp_path, capsys):
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"],
                          capture_output=True, text=True, check=True)
    dead = int(done.stdout)  # a process that has exited
    out = tmp_path / "out"
    out.mkdir()
    stale = [out / f".fusedmosaic.tmp-{dead}-abc", tmp_path / f".new.fusedmosaic.tmp-{dead}-x"]
    alive = out / f".fusedmosaic.tmp-{os.getpid()}-running"  # another writer, still running
    for folder in (*stale, alive):
        folder.mkdir()
        (folder / "creation.mp4").write_text("partial")
    (out / ".fusedmosaic.tmp-notes").mkdir()  # no pid: not a staging folder of ours
    assert run(data / "feto", out, "pairwise") == 0
    assert run(data / "feto", tmp_path / "new", "pairwise") == 0
    assert not any(p.exists() for p in stale)
    assert alive.is_dir() and (out / ".fusedmosaic.tmp-notes").is_dir()


def test_ctrl_c_during_the_commit_is_deferred_until_it_is_complete(tmp_path, monkeypatch):
    import signal

    import fusedmosaic.io.output as output

    replace = os.replace
    moved = []

    def interrupted_replace(src, dst):
        if not moved:
            signal.raise_signal(signal.SIGINT)  # Ctrl-C right after the first file
        moved.append(dst)
        return replace(src, dst)

    monkeypatch.setattr(output.os, "replace", interrupted_replace)
    # Ctrl-C as in a terminal: Python's handler (where SIGINT is ignored, Ctrl-C does nothing
    # and nothing is deferred)
    with signal_handler(signal.SIGINT, signal.default_int_handler):
        out = tmp_path / "out"
        with pytest.raises(KeyboardInterrupt), OutputWriter(out, record="run") as w:
            for name in ("a.csv", "b.png", "c/d.json"):
                w.write_text(name, name)
        assert listing(out) == [MANIFEST, "a.csv", "b.png", "c", "c/d.json"]  # all, not one
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        assert no_temp(tmp_path)


@pytest.mark.parametrize(("value", "message"), [
    ("-3", "--positions: the number of evenly spaced frames must be an integer >= 1, got -3"),
    ("0", "--positions: the number of evenly spaced frames must be an integer >= 1, got 0"),
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


def test_evaluate_refuses_or_warns_about_another_dataset(data, emt_out, tmp_path, capsys):
    pcle = tmp_path / "p"
    assert run(data / "pcle", pcle, "robot") == 0
    report = json.loads((pcle / "report.json").read_text())
    assert report["dataset_fingerprint"]["frames"] == 8
    assert set(report["dataset_fingerprint"]["sha256"]) == {
        "camera.yaml", "frames.csv", "ground_truth.csv",
        "pixels of the first, middle and last frame"}
    # the fetoscopy truth also has 8 frames, but of another size: refused (e_j's grid of points
    # is the truth's frame), nothing written
    assert main(["--quiet", "evaluate", str(pcle), "--truth", str(data / "feto"),
                 "--no-report"]) == 2
    assert (f"{pcle / 'report.json'}: the output was computed on 128x112 frames, the truth "
            f"dataset {data / 'feto'} has 400x400 frames" in capsys.readouterr().err)
    assert not (pcle / "evaluation.json").exists()
    # another pCLE recording of the same size: refused (its frames differ), nothing written;
    # with --allow-other-dataset scored, but with a warning
    other = tmp_path / "other"
    assert main(["--quiet", "simulate", "pcle", str(other), "--n-frames", "8", "--width", "128",
                 "--height", "112", "--trajectory", "spiral"]) == 0
    assert main(["--quiet", "evaluate", str(pcle), "--truth", str(other), "--no-report"]) == 2
    assert capsys.readouterr().err.startswith(
        f"fusedmosaic: error: {pcle / 'report.json'} records the dataset "
        f"{(data / 'pcle').resolve()}, but {other} differs from it")
    assert not (pcle / "evaluation.json").exists()
    assert main(["--quiet", "evaluate", str(pcle), "--truth", str(other), "--no-report",
                 "--allow-other-dataset"]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"fusedmosaic: warning: {pcle / 'report.json'} records the dataset "
                          f"{(data / 'pcle').resolve()}, but {other} differs from it")
    # (its truth differs too: a note of its own, not a reason for the warning)
    assert "ground_truth.csv" not in err.splitlines()[0]
    assert "fusedmosaic: note: " in err and "the truth changed since the run" in err
    # a moved copy of the right dataset is fine
    moved = tmp_path / "moved"
    shutil.copytree(data / "pcle", moved)
    assert main(["--quiet", "evaluate", str(pcle), "--truth", str(moved), "--no-report"]) == 0
    assert capsys.readouterr().err == ""
    assert "dataset_warning" not in json.loads((pcle / "evaluation.json").read_text())["results"][0]


def test_evaluate_positions_tests_the_sampled_frames_and_refuses_more_than_there_are(
        data, tmp_path, capsys):
    """Review A #5: with --positions N the Wilcoxon test ran on all frames while the statistics
    were over the N evenly spaced ones (seed 004 tests those); an N above the frame count was
    reduced to the frame count without a word."""
    from fusedmosaic.evaluation.metrics import compare_position_errors, evenly_spaced

    truth = data / "pcle"
    ids, G = read_homographies_csv(truth / "ground_truth.csv")
    exact, shifted = tmp_path / "exact", tmp_path / "shifted"
    exact.mkdir()
    shifted.mkdir()
    write_homographies_csv(exact / "homographies.csv", ids, G)
    moved = G.copy()
    moved[:, 0, 2] += np.arange(len(ids)) + 1.0  # frame k off by k + 1 px
    write_homographies_csv(shifted / "homographies.csv", ids, moved)
    argv = ["evaluate", str(exact), "--truth", str(truth), "--compare", str(shifted),
            "--no-report"]
    assert main([*argv, "--positions", "3"]) == 0
    out = capsys.readouterr().out
    report = json.loads((exact / "evaluation.json").read_text())
    test = report["wilcoxon"][0]
    assert test["n"] == 3 and test["frames"] == "positions" and test["positions"] == 3
    sampled = evenly_spaced(8, 3)
    assert sampled.tolist() == [0, 4, 7]
    a, b = (np.array(r["position_errors_um"], float)[sampled] for r in report["results"])
    assert test["p_value"] == compare_position_errors(a, b)["p_value"]
    assert report["results"][1]["position_sampled_frames"] == ids[sampled].tolist()
    assert "Wilcoxon signed-rank exact vs shifted at the 3 evenly spaced frames: p = " in out
    assert "(n = 3)" in out
    assert main(argv) == 0  # without --positions: every frame
    test = json.loads((exact / "evaluation.json").read_text())["wilcoxon"][0]
    assert test["n"] == 8 and test["frames"] == "all" and "positions" not in test
    # more positions than frames: refused (statistics over 8 frames would pass for 13)
    (exact / "evaluation.json").unlink()
    capsys.readouterr()  # (the notes that exact and shifted have no report.json)
    assert main([*argv, "--positions", "13"]) == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: {truth}: 8 frames, fewer than the 13 evenly spaced frames asked "
        "for (positions_n, --positions); give at most 8\n")
    assert not (exact / "evaluation.json").exists()
    assert main([*argv, "--positions", "8"]) == 0
    with pytest.raises(ValueError, match=r"^9 evenly spaced frames of a sequence of 8: at most "
                                         r"8$"):
        evenly_spaced(8, 9)


def test_a_run_without_ground_truth_matches_its_dataset(data, tmp_path, capsys):
    """Review 4 #12: a run on a copy with the ground truth held out is the same dataset."""
    nogt = tmp_path / "nogt"
    shutil.copytree(data / "feto", nogt)
    (nogt / "ground_truth.csv").unlink()
    assert run(nogt, tmp_path / "o", "emt") == 0
    assert main(["--quiet", "evaluate", str(tmp_path / "o"), "--truth", str(data / "feto"),
                 "--no-report"]) == 0
    assert capsys.readouterr().err == ""
    (nogt / "camera.yaml").write_text((nogt / "camera.yaml").read_text() + "\n# edited\n")
    assert run(nogt, tmp_path / "o", "emt") == 0
    # another camera.yaml: another dataset, refused unless --allow-other-dataset (a warning)
    assert main(["--quiet", "evaluate", str(tmp_path / "o"), "--truth", str(data / "feto"),
                 "--no-report"]) == 2
    assert "differs from it (camera.yaml): it is another dataset" in capsys.readouterr().err
    assert main(["--quiet", "evaluate", str(tmp_path / "o"), "--truth", str(data / "feto"),
                 "--no-report", "--allow-other-dataset"]) == 0
    err = capsys.readouterr().err
    assert err.startswith("fusedmosaic: warning: ") and "differs from it (camera.yaml)" in err


def test_evaluate_warns_about_other_frames_behind_the_same_files(data, tmp_path, capsys):
    """Review A #3: a run on a dataset without ground_truth.csv (an imported recording), scored
    against another recording with the same camera.yaml and frame times, was not warned about:
    only the files were compared, never the frames. The warning is in evaluation.md too."""
    held_out = tmp_path / "held_out"
    shutil.copytree(data / "pcle", held_out)
    (held_out / "ground_truth.csv").unlink()
    out = tmp_path / "o"
    assert run(held_out, out, "robot") == 0
    other = tmp_path / "other"
    assert main(["--quiet", "simulate", "pcle", str(other), "--n-frames", "8", "--width", "128",
                 "--height", "112", "--trajectory", "spiral"]) == 0
    for name in ("camera.yaml", "frames.csv"):  # the files alone cannot tell them apart
        assert (other / name).read_bytes() == (held_out / name).read_bytes()
    res = tmp_path / "res"
    # refused (decision of review C #5), scored with a warning when allowed
    assert main(["--quiet", "evaluate", str(out), "--truth", str(other), "--json",
                 str(res / "e.json")]) == 2
    assert ("differs from it (pixels of the first, middle and last frame): it is another "
            "dataset" in capsys.readouterr().err)
    assert not (res / "e.json").exists()
    assert main(["--quiet", "evaluate", str(out), "--truth", str(other), "--json",
                 str(res / "e.json"), "--allow-other-dataset"]) == 0
    warning = (f"{out / 'report.json'} records the dataset {held_out.resolve()}, but {other} "
               "differs from it (pixels of the first, middle and last frame): the scores may "
               "compare the output with another dataset's ground truth")
    assert capsys.readouterr().err == f"fusedmosaic: warning: {warning}\n"
    assert json.loads((res / "e.json").read_text())["results"][0]["dataset_warning"] == warning
    assert f"**Warning:** {warning}" in (res / "e.md").read_text().split("## ")[0]
    # the right dataset (frames read the same way as by the run) and an older version's
    # fingerprint, which has no frame pixels: no warning
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "pcle"), "--json",
                 str(res / "e.json")]) == 0
    assert capsys.readouterr().err == "" and "Warning" not in (res / "e.md").read_text()
    report = json.loads((out / "report.json").read_text())
    del report["dataset_fingerprint"]["sha256"]["pixels of the first, middle and last frame"]
    (out / "report.json").write_text(json.dumps(report))
    assert main(["--quiet", "evaluate", str(out), "--truth", str(other), "--no-report"]) == 0
    assert capsys.readouterr().err == ""


# --------------------------------------------------------------------------- 16, 18, 20: run


@pytest.mark.parametrize("fps", ["inf", "nan", "0", "-25"])
def test_fps_must_be_finite_and_positive(data, tmp_path, computed, capsys, fps):
    assert run(data / "feto", tmp_path / "o", "emt", "--fps", fps) == 2
    assert capsys.readouterr().err == (f"fusedmosaic: error: --fps must be positive and finite, "
                                       f"got {float(fps)}\n")
    assert computed == [] and listing(tmp_path) == []
    # the library says the same, naming its own argument (one check: io.dataset.check_fps)
    with pytest.raises(ValueError, match=r"^fps must be positive and finite, got inf$"):
        run_dataset(data / "feto", "emt", tmp_path / "o", fps=float("inf"))
    with pytest.raises(ValueError, match=r"^fps must be positive and finite, got True$"):
        run_dataset(data / "feto", "emt", tmp_path / "o", fps=True)
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


@pytest.mark.parametrize("out", ["linked/frames", "shared/frames", "shared/frames/sub"])
def test_out_in_a_symlinked_frames_folder_is_refused(data, tmp_path, computed, capsys, out):
    """A dataset whose frames/ links to a shared folder: --out DATA/frames resolved outside
    the dataset and wrote mosaic.png, report.json, ... among the shared frames (audit)."""
    import shutil

    shutil.copytree(data / "feto" / "frames", tmp_path / "shared" / "frames")
    linked = tmp_path / "linked"
    shutil.copytree(data / "feto", linked, ignore=shutil.ignore_patterns("frames"))
    (linked / "frames").symlink_to(tmp_path / "shared" / "frames")
    before = listing(tmp_path / "shared")
    assert run(linked, tmp_path / out) == 2
    err = capsys.readouterr().err
    assert "would corrupt the dataset: choose --out outside it" in err
    assert computed == [] and listing(tmp_path / "shared") == before


def test_a_video_inside_a_recording_yet_to_be_made_is_refused(tmp_path):
    """live --record REC --video REC/creation.mp4: REC does not exist when it is checked (a
    first version of the symlinked-frames check skipped missing dataset folders; review)."""
    from fusedmosaic.runner import check_video_destination

    with pytest.raises(ValueError, match="the video would be written inside the dataset: its "
                       "path is inside the dataset folder"):
        check_video_destination(tmp_path / "REC" / "creation.mp4", tmp_path / "OUT",
                                tmp_path / "REC")


# --------------------------------------------------------------------------- numpy warnings


def test_degenerate_rows_and_self_comparison_raise_no_numpy_warning(data, emt_out, tmp_path,
                                                                    capsys):
    """An all-zero row is refused (singular); h22 = 0 sends the frame's corner (0, 0) to
    infinity: placed, with e_j inf, so e_M is inf (not left out); evaluation.json is strict
    JSON: null there, the frame named in placed_at_infinity."""
    out = tmp_path / "out"
    out.mkdir()
    ids, G = read_homographies_csv(emt_out / "homographies.csv")
    G[1] = 0.0  # all zero
    write_homographies_csv(out / "homographies.csv", ids, G)
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto"),
                 "--no-report"]) == 2
    assert "row 3 (frame 1): singular homography" in capsys.readouterr().err
    ids, G = read_homographies_csv(emt_out / "homographies.csv")
    G[2, 2, 2] = 0.0  # h22 = 0
    write_homographies_csv(out / "homographies.csv", ids, G)
    pcle_out = tmp_path / "p"
    assert run(data / "pcle", pcle_out, "robot") == 0
    # warnings are errors under pytest: these would fail if numpy or scipy warned
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto"),
                 "--no-report"]) == 0
    text = (out / "evaluation.json").read_text()
    assert "Infinity" not in text and "NaN" not in text  # strict JSON: null, the frames named
    result = json.loads(text)["results"][0]
    assert result["placed"] == 8 and result["e_j_px"][2] is None
    assert result["placed_at_infinity"] == [2] and result["e_M_px"] is None
    # evaluation.md says inf, not "–" (no score)
    assert main(["--quiet", "evaluate", str(out), "--truth", str(data / "feto")]) == 0
    row = next(line for line in (out / "evaluation.md").read_text().splitlines()
               if line.startswith("| out |"))
    assert row.split(" | ")[3:5] == ["inf", "inf"], row
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


def test_evaluate_refuses_a_singular_homography_and_counts_placed_frames(data, emt_out,
                                                                         tmp_path, capsys):
    """A singular homography in the output is refused, naming the row and frame; a frame the
    truth does not place is still counted as placed (listed apart), not as unplaced."""
    ids, G = read_homographies_csv(emt_out / "homographies.csv")
    bad = tmp_path / "bad"
    bad.mkdir()
    G_bad = G.copy()
    G_bad[2] = [[1.0, 1.0, 0], [0, 0, 0], [0, 0, 1.0]]
    write_homographies_csv(bad / "homographies.csv", ids, G_bad)
    assert main(["--quiet", "evaluate", str(bad), "--truth", str(data / "feto"),
                 "--no-report"]) == 2
    assert (f"{bad / 'homographies.csv'}: row 4 (frame 2): singular homography"
            in capsys.readouterr().err)
    assert not (bad / "evaluation.json").exists()
    truth = tmp_path / "truth"
    shutil.copytree(data / "feto", truth)
    t_ids, T = read_homographies_csv(truth / "ground_truth.csv")
    T[5] = np.nan
    write_homographies_csv(truth / "ground_truth.csv", t_ids, T)
    good = tmp_path / "good"
    shutil.copytree(emt_out, good)
    assert main(["--quiet", "evaluate", str(good), "--truth", str(truth), "--no-report"]) == 0
    result = json.loads((good / "evaluation.json").read_text())["results"][0]
    assert result["placed"] == np.isfinite(G).all(axis=(1, 2)).sum()
    assert result["placed_without_truth"] == [5] and result["e_j_px"][5] is None


# ------------------------------------------------------------------ unreadable frames


@pytest.mark.parametrize("kind, method, status", [
    ("feto", "ba-emt", "prior-only"), ("pcle", "kalman-robot", "prior-only"),
    ("pcle", "robot", "prior-only"), ("pcle", "ncc", "unplaced: its image cannot be read")])
def test_unreadable_frame_is_a_frame_without_visual_content(data, tmp_path, capsys, kind,
                                                            method, status):
    """A damaged frame does not stop the run: it is placed from the priors (the tracker, the
    robot) or left unplaced saying why, named in report.json and in a warning, and left out of
    the mosaic; --stop-on-unreadable makes it an error naming the file, leaving no output."""
    root = tmp_path / kind
    shutil.copytree(data / kind, root)
    damaged = sorted((root / "frames").glob("*.png"))[4]
    damaged.write_bytes(damaged.read_bytes()[:100])  # cut short
    out = tmp_path / "out"
    assert run(root, out, method) == 0
    err = capsys.readouterr().err
    assert (f"fusedmosaic: warning: 1 of 8 frames could not be read (frames 4; first: {damaged}:"
            f" cannot read image): taken as frames without visual content, "
            f"{int(status == 'prior-only')} placed from the priors, left out of the mosaic "
            "(report.json unreadable_frames)") in err
    report = json.loads((out / "report.json").read_text())
    assert report["unreadable_frames"] == {"4": f"{damaged}: cannot read image"}
    assert report["frame_status"][4] == status
    assert report["mosaic"]["skipped_frames"]["4"] == "image unreadable: not composed"
    assert report["mosaic"]["frames_shown"] == report["placed"] - (status == "prior-only")

    strict = tmp_path / "strict"
    assert run(root, strict, method, "--stop-on-unreadable") == 2  # bad input
    assert capsys.readouterr().err == f"fusedmosaic: error: {damaged}: cannot read image\n"
    assert not strict.exists()


def test_pairwise_starts_its_chain_after_an_unreadable_frame0(data, tmp_path, capsys):
    """pairwise with frame 0 damaged: the chain from frame 0 broke at once, every frame was
    unplaced and the run failed with "no placed frame to compose a mosaic from", naming neither
    the file nor the cause (review). Now the chain starts at frame 1, the reference, frame 0
    unplaced; warnings name the damaged file and the new start."""
    root = tmp_path / "feto"
    shutil.copytree(data / "feto", root)
    damaged = sorted((root / "frames").glob("*.png"))[0]
    damaged.write_bytes(b"")
    out = tmp_path / "out"
    assert run(root, out, "pairwise") == 0
    err = capsys.readouterr().err
    assert f"1 of 8 frames could not be read (frames 0; first: {damaged}: cannot read" in err
    assert ("warning: the pairwise chain starts at frame 1, the first frame registered to the "
            "next one: the 1 frame(s) before it are unplaced (frame 0: its image cannot be "
            "read)") in err
    report = json.loads((out / "report.json").read_text())
    assert report["frame_status"][0] == "unplaced: its image cannot be read"
    assert report["frame_status"][1:] == ["placed"] * 7, report["frame_status"]
    assert report["reference_frame"] == 1 and report["mosaic"]["frames_shown"] == 7


def test_live_outputs_survive_one_ctrl_c():
    """Once a live session's loop is over, a first SIGINT is told and ignored, a second
    interrupts (one Ctrl-C lost the whole live result; audit); the handler is restored, and
    a SIGINT the process ignores stays ignored."""
    import signal

    from fusedmosaic.runner import _EndingGuard

    # (Ctrl-C's usual handling: a test run started as a background job inherits SIGINT
    # ignored, which the guard rightly leaves alone; checked below)
    before, told = signal.signal(signal.SIGINT, signal.default_int_handler), []
    try:
        guard = _EndingGuard(lambda: told.append("told"))
        guard.start()
        try:
            signal.raise_signal(signal.SIGINT)
            assert told == ["told"]
            with pytest.raises(KeyboardInterrupt):
                signal.raise_signal(signal.SIGINT)
                pytest.fail("the second SIGINT did not interrupt")
        finally:
            guard.stop()
        assert told == ["told"]
        assert signal.getsignal(signal.SIGINT) is signal.default_int_handler
        signal.signal(signal.SIGINT, signal.SIG_IGN)
        guard = _EndingGuard(lambda: told.append("told"))
        guard.start()
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
        guard.stop()
    finally:
        signal.signal(signal.SIGINT, before)
