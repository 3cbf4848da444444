"""Review 47 (L): the run's output folder under signals, write errors and a closed stdout; the
live session's output checks; --guided-sift with ORB."""

import errno
import inspect
import json
import os
import re
import shutil
import signal
import socket
import subprocess
import sys

import numpy as np
import pytest
from _faults import file_size_limit, signal_handler
from _igtl_sender import Sender, robot_events

from fusedmosaic.cli import main
from fusedmosaic.io.output import MANIFEST, OutputWriter
from fusedmosaic.simulation import PcleOptions, simulate_pcle


def listing(folder):
    return sorted(p.relative_to(folder).as_posix() for p in folder.rglob("*"))


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    root = tmp_path_factory.mktemp("runner47") / "pcle"
    simulate_pcle(root, PcleOptions(width=128, height=112, n_frames=20, contact_loss=False,
                                    stick_slip=False))
    return root


@pytest.fixture(scope="module")
def runs(pcle, tmp_path_factory):
    """An earlier run in OUT (robot, with its report and plots) and, apart, the run that
    replaces it (ncc --no-report), as it comes out uninterrupted."""
    root = tmp_path_factory.mktemp("runs47")
    assert main(["--quiet", "run", str(pcle), "--method", "robot", "--out",
                 str(root / "robot")]) == 0
    assert main(["--quiet", "run", str(pcle), "--method", "ncc", "--out", str(root / "ncc"),
                 "--no-report"]) == 0
    return root


def _is_the_ncc_run(out, runs):
    """OUT holds the ncc run whole, its manifest naming exactly its files, and nothing of
    robot's."""
    files = ["homographies.csv", "mosaic.png", "report.json"]
    assert listing(out) == sorted([MANIFEST, *files])
    manifest = json.loads((out / MANIFEST).read_text())
    assert manifest["sets"] == {"run": {"files": files, "stale_after_run": True}}
    assert json.loads((out / "report.json").read_text())["method"] == "ncc"
    for name in ("homographies.csv", "mosaic.png"):
        assert (out / name).read_bytes() == (runs / "ncc" / name).read_bytes(), name


# -- H2: SIGTERM / SIGHUP during the commit -------------------------------------------------

# The run replacing OUT's earlier one gets `sig` once its 2nd file is moved into OUT (the
# commit's os.replace; the staging folder's renames are not counted).
_SIGNAL_IN_COMMIT = """
import os, signal, sys
from fusedmosaic.cli import main
sig, how, data, out = getattr(signal, sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
if how == "ignored":  # (nohup: SIGHUP; a scheduler's job may ignore SIGTERM)
    signal.signal(sig, signal.SIG_IGN)
else:  # (not inherited ignored: under nohup, SIGHUP is, and the command then leaves it so)
    signal.signal(sig, signal.SIG_DFL)
real, moved = os.replace, []
def replace(src, dst):
    real(src, dst)
    if os.path.dirname(os.fspath(dst)) == out and ".fusedmosaic.tmp-" not in os.fspath(dst):
        moved.append(dst)
        if len(moved) == 2:
            os.kill(os.getpid(), sig)
os.replace = replace
sys.exit(main(["--quiet", "run", data, "--method", "ncc", "--out", out, "--no-report"]))
"""


@pytest.mark.parametrize(("name", "how"), [("SIGTERM", "handled"), ("SIGHUP", "handled"),
                                           ("SIGTERM", "ignored")])
def test_sigterm_or_sighup_during_the_commit_is_held_until_the_run_is_whole(pcle, runs,
                                                                           tmp_path, name, how):
    """Only SIGINT was held during the commit: SIGTERM there raised KeyboardInterrupt after
    robot's report and plots were unlinked and 2 of ncc's files moved in, leaving robot's
    report.json beside ncc's homographies and the manifest unwritten. Now OUT holds the new
    run whole, and the command says the outputs were written. A signal the process ignores
    stays ignored (the run ends normally)."""
    out = tmp_path / "out"
    shutil.copytree(runs / "robot", out)
    done = subprocess.run([sys.executable, "-c", _SIGNAL_IN_COMMIT, name, how, str(pcle),
                           str(out)], capture_output=True, text=True, timeout=120)
    if how == "ignored":
        assert (done.returncode, done.stderr) == (0, "")
    else:
        assert done.returncode == 130, done.stderr
        assert done.stderr == f"fusedmosaic: interrupted after the outputs were written to {out}\n"
    _is_the_ncc_run(out, runs)


_WRITER_SIGTERM_DEFAULT = """
import os, signal, sys
from fusedmosaic.io.output import OutputWriter
out = sys.argv[1]
real, moved = os.replace, []
def replace(src, dst):
    real(src, dst)
    moved.append(dst)
    if len(moved) == 2:
        os.kill(os.getpid(), signal.SIGTERM)
os.replace = replace
with OutputWriter(out, record="run") as w:
    for name in ("a.txt", "b.txt", "c.txt"):
        w.write_text(name, name)
print("not reached")
"""


def test_sigterm_with_its_default_action_ends_the_process_after_the_commit(tmp_path):
    """The library without the command's handlers (SIGTERM's default: the process ends): the
    signal is held until the outputs and the manifest are in, then ends the process as it
    would have."""
    out = tmp_path / "out"
    done = subprocess.run([sys.executable, "-c", _WRITER_SIGTERM_DEFAULT, str(out)],
                          capture_output=True, text=True, timeout=60)
    assert done.returncode == -signal.SIGTERM and done.stdout == "", done.stderr
    assert listing(out) == [MANIFEST, "a.txt", "b.txt", "c.txt"]
    assert json.loads((out / MANIFEST).read_text())["sets"]["run"]["files"] == [
        "a.txt", "b.txt", "c.txt"]


# -- L6: a held Ctrl-C after a whole commit; a closed stdout ---------------------------------

def test_a_ctrl_c_held_during_the_commit_says_the_outputs_were_written(pcle, runs, tmp_path,
                                                                       monkeypatch, capsys):
    """The Ctrl-C held during the commit was delivered after it as 'interrupted', the word for
    'nothing is left behind', while OUT held the complete new run. The exit status stays 130
    (a shell script stops at the user's Ctrl-C only when the command reports it)."""
    out = tmp_path / "out"
    shutil.copytree(runs / "robot", out)
    real, moved = os.replace, []

    def replace(src, dst):
        real(src, dst)
        if os.path.dirname(os.fspath(dst)) == str(out):
            moved.append(dst)
            if len(moved) == 2:
                os.kill(os.getpid(), signal.SIGINT)

    monkeypatch.setattr(os, "replace", replace)
    with signal_handler(signal.SIGINT, signal.default_int_handler):
        code = main(["--quiet", "run", str(pcle), "--method", "ncc", "--out", str(out),
                     "--no-report"])
    assert code == 130
    assert capsys.readouterr().err == (
        f"fusedmosaic: interrupted after the outputs were written to {out}\n")
    _is_the_ncc_run(out, runs)


def test_a_closed_stdout_after_a_complete_run_is_not_an_error(pcle, runs, tmp_path):
    """`fusedmosaic run ... | true`: the summary printed into the closed pipe made it 'error:
    Broken pipe', exit 1, with every output written."""
    out = tmp_path / "out"
    read, write = os.pipe()
    os.close(read)  # the reader is gone before the command writes
    try:
        done = subprocess.run(
            [sys.executable, "-c", "import sys; from fusedmosaic._entry import main; "
             "sys.exit(main())", "run", str(pcle), "--method", "ncc", "--out", str(out),
             "--no-report"], stdout=write, stderr=subprocess.PIPE, text=True, timeout=120)
    finally:
        os.close(write)
    assert (done.returncode, done.stderr) == (0, "")
    _is_the_ncc_run(out, runs)


# -- M2: a write the file system refuses ----------------------------------------------------

WRITES = {
    "homographies.csv": lambda w: w.write_homographies(np.arange(40), np.tile(np.eye(3),
                                                                            (40, 1, 1))),
    "poses.csv": lambda w: w.write_poses(np.arange(40), np.zeros((40, 6))),
    "plane.json": lambda w: w.write_json("plane.json", {"plane": list(range(100))}),
    "report.md": lambda w: w.write_text("report.md", "x" * 1000),
    "mosaic.png": lambda w: w.write_image(
        "mosaic.png", np.random.default_rng(0).integers(0, 255, (64, 64), np.uint8)),
}


@pytest.mark.parametrize("name", list(WRITES))
def test_each_write_the_file_system_refuses_names_the_file_in_out(tmp_path, name):
    """Python's write errors carry no file name: a full disk on homographies.csv, poses.csv,
    plane.json, report.json or report.md said only 'File too large' (exit 1), while
    mosaic.png's named the file (exit 2). Each is now an OSError naming OUT/name (exit 1), and
    the partial staged file is gone."""
    out = tmp_path / "out"
    with OutputWriter(out, record="review") as w:
        with file_size_limit(200), pytest.raises(OSError) as caught:
            WRITES[name](w)
        assert w.written() == []
    assert caught.value.filename == str(out / name)
    what = "the image " if name.endswith(".png") else ""
    assert caught.value.strerror == (f"{what}could not be written (File too large: a full "
                                     f"disk, or no write permission in {out}?)")
    assert listing(out) == []  # (nothing was left to commit)


def _fail_plot(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


@pytest.mark.parametrize(("name", "limit"), [("homographies.csv", 1000),
                                             ("mosaic.png", 20_000),
                                             ("report.md", None)])
def test_run_exits_1_naming_the_output_the_file_system_refused(pcle, tmp_path, monkeypatch,
                                                               capsys, name, limit):
    """One exit status for 'the file system refused', whichever output: 1 (as a --video that
    does not read back), and the message names OUT's file."""
    import fusedmosaic.evaluation.report

    out = tmp_path / "out"
    monkeypatch.setattr(fusedmosaic.evaluation.report, "plot_trajectory", _fail_plot)
    with file_size_limit(limit or 2**40):
        code = main(["--quiet", "run", str(pcle), "--method", "robot", "--out", str(out),
                     *(["--no-report"] if limit else [])])
    err = capsys.readouterr().err
    why = "File too large" if limit else "No space left on device"
    what = {"mosaic.png": "the image ", "report.md": "the report "}.get(name, "")
    assert code == 1, err
    assert err == (f"fusedmosaic: error: {out / name}: {what}could not be written ({why}: a full "
                   f"disk, or no write permission in {out}?)\n")
    assert listing(tmp_path) == []


# -- L1: a user's plot ----------------------------------------------------------------------

def test_a_users_plot_is_refused_before_the_computation(pcle, tmp_path, monkeypatch, capsys):
    """plots/ was checked for a user's file only when the outputs were moved in, after the
    whole computation (minutes of ba)."""
    from fusedmosaic import methods

    out = tmp_path / "out"
    (out / "plots").mkdir(parents=True)
    (out / "plots" / "errors.png").write_bytes(b"mine")
    ran = []
    real = methods.get

    def get(name):
        method = real(name)
        return lambda *args, **kwargs: ran.append(name) or method(*args, **kwargs)

    monkeypatch.setattr(methods, "get", get)
    assert main(["--quiet", "run", str(pcle), "--method", "robot", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"fusedmosaic: error: {out / 'plots' / 'errors.png'}: exists and "
                          "fusedmosaic did not write it"), err
    assert ran == []
    assert listing(out) == ["plots", "plots/errors.png"]
    # without a report no plot is written: nothing to refuse
    assert main(["--quiet", "run", str(pcle), "--method", "robot", "--out", str(out),
                 "--no-report"]) == 0
    assert ran == ["robot"] and (out / "plots" / "errors.png").read_bytes() == b"mine"


def test_the_run_plots_checked_are_the_reports():
    """RUN_PLOTS (checked up front) names every plot evaluation.report.write_report draws."""
    from fusedmosaic.evaluation.report import write_report
    from fusedmosaic.runner import RUN_PLOTS

    drawn = set(re.findall(r'plots / "([\w.]+\.png)"', inspect.getsource(write_report)))
    assert drawn and drawn == set(RUN_PLOTS)


# -- M1: live checks OUT before connecting, and keeps the recording after ----------------------

def _closed_port() -> int:
    with socket.create_server(("127.0.0.1", 0)) as server:
        return server.getsockname()[1]


@pytest.mark.parametrize("name", ["report.md", "plots/errors.png"])
def test_live_refuses_a_users_file_in_out_before_connecting(pcle, tmp_path, capsys, name):
    """`run` refused a user's report.md in OUT before its computation; `live` only once its
    session was over, with its estimates (which exist nowhere else)."""
    out, record = tmp_path / "out", tmp_path / "rec"
    (out / name).parent.mkdir(parents=True, exist_ok=True)
    (out / name).write_text("my notes")
    code = main(["--quiet", "live", f"127.0.0.1:{_closed_port()}", "--camera",
                 str(pcle / "camera.yaml"), "--method", "ncc", "--record", str(record),
                 "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"fusedmosaic: error: {out / name}: exists and fusedmosaic did not "
                          "write it"), err
    assert "connect" not in err and not record.exists()


@pytest.mark.realtime
def test_live_error_once_the_session_is_over_says_the_recording_is_kept(pcle, tmp_path,
                                                                       monkeypatch, capsys):
    """A refusal when the outputs are written (here a user's report.json put in OUT during the
    session) said nothing of the recording, which is kept: it names it and how to re-run."""
    from fusedmosaic import runner
    from fusedmosaic.io import read_dataset

    out, record = tmp_path / "out", tmp_path / "rec"
    write = runner.run_dataset

    def user_file_meanwhile(*args, **kwargs):
        out.mkdir(exist_ok=True)
        (out / "report.json").write_text("{}")
        return write(*args, **kwargs)

    monkeypatch.setattr(runner, "run_dataset", user_file_meanwhile)
    sender = Sender(robot_events(read_dataset(pcle)))
    code = main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--camera",
                 str(pcle / "camera.yaml"), "--method", "robot", "--transform", "RobotToBase",
                 "--record", str(record), "--out", str(out), "--no-report"])
    sender.join()
    err = capsys.readouterr().err
    assert code == 2
    assert err.startswith(f"fusedmosaic: error: {out / 'report.json'}: exists and fusedmosaic "
                          "did not write it"), err
    assert err.endswith(f"; the live outputs are not written, the recording is kept in {record} "
                        f"(fusedmosaic run {record} --method robot --out OUT2 "
                        "--allow-untracked)\n"), err
    assert len(read_dataset(record, allow_untracked=True)) == 20


# -- L2: --guided-sift with ORB -------------------------------------------------------------

@pytest.mark.parametrize("command", ["run", "live"])
def test_guided_sift_with_orb_is_refused(pcle, tmp_path, capsys, command):
    """ORB's matching is guided already: --guided-sift was accepted and recorded in
    report.json as if used."""
    where = (["run", str(pcle), "--method", "lba-emt"] if command == "run" else
             ["live", f"127.0.0.1:{_closed_port()}", "--camera", str(pcle / "camera.yaml"),
              "--transform", "SensorToTracker", "--record", str(tmp_path / "rec")])
    assert main(["--quiet", *where, "--out", str(tmp_path / "out"), "--guided-sift",
                 "--detector", "orb"]) == 2
    assert capsys.readouterr().err == ("fusedmosaic: error: --guided-sift applies to --detector "
                                       "sift (ORB's matching is guided already)\n")
    assert listing(tmp_path) == []
