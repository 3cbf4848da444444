"""Audit 19: small datasets, comparisons that cannot be made, out-of-range options, one-frame
videos, users' files in OUT, huge frame ids, evaluation JSON inside the truth and times
around 1000 s. Each test fails on the code before the fix."""

import json

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.evaluation import drift_ratio
from fusedmosaic.evaluation.metrics import drift_note
from fusedmosaic.io import FrameSource, read_dataset, read_homographies_csv, write_homographies_csv
from fusedmosaic.io.tracking import no_overlap_message


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Six fetoscopy frames (a quarter is one frame) and eight pCLE frames, run once each."""
    root = tmp_path_factory.mktemp("audit19")
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "f6"), "--n-frames", "6",
                 "--width", "320", "--height", "320", "--laps", "0.16"]) == 0
    assert main(["--quiet", "simulate", "pcle", str(root / "pcle"), "--n-frames", "8",
                 "--width", "128", "--height", "112"]) == 0
    assert main(["--quiet", "run", str(root / "f6"), "--method", "ba-emt", "--out",
                 str(root / "ba"), "--no-report"]) == 0
    assert main(["--quiet", "run", str(root / "pcle"), "--method", "robot", "--out",
                 str(root / "robot"), "--no-report"]) == 0
    return root


def test_a_reference_written_as_the_identity_up_to_rounding_has_no_drift_ratio(data, capsys):
    """Frame 0 is the reference: a method writes it as the identity up to rounding (e_j ~1e-14
    px), which gave drift ratios of 1e13 for sequences under 8 frames."""
    assert np.isnan(drift_ratio(np.array([3e-14, 0.2, 0.4])))
    assert drift_note(np.array([3e-14, 0.2, 0.4])).startswith(
        "the first quarter (frame 0) holds only the reference frame")
    assert drift_ratio(np.array([1e-3, 0.2, 0.4])) == pytest.approx(400.0)  # a real error
    assert main(["evaluate", str(data / "ba"), "--truth", str(data / "f6"), "--no-report"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines() if line.startswith("ba"))
    assert row.split()[1] == "6/6" and row.split()[-1] == "n/a"
    assert json.loads((data / "ba" / "evaluation.json").read_text())["results"][0][
        "drift_ratio"] is None


def test_compare_with_an_output_placing_under_two_frames_keeps_the_other_pairs(data, tmp_path,
                                                                              capsys):
    ids, G = read_homographies_csv(data / "robot" / "homographies.csv")
    lone = tmp_path / "lone"
    lone.mkdir()
    G[1:] = np.nan  # frame 0 only: no Wilcoxon test against it
    write_homographies_csv(lone / "homographies.csv", ids, G)
    assert main(["evaluate", str(data / "robot"), "--truth", str(data / "pcle"), "--compare",
                 str(lone), str(data / "robot"), "--no-report", "--json",
                 str(tmp_path / "e.json")]) == 0
    printed = capsys.readouterr().out
    assert ("Wilcoxon signed-rank robot vs lone: n/a: 1 frame placed by both (the test needs "
            "at least 2)") in printed
    assert ("Wilcoxon signed-rank robot vs robot: p = 1 (n = 8, 0 ranked): no paired difference "
            "above 1e-06: nothing to rank") in printed
    lone_pair, same = json.loads((tmp_path / "e.json").read_text())["wilcoxon"]
    assert lone_pair["n"] == 1 and lone_pair["p_value"] is None
    assert lone_pair["note"].startswith("n/a: 1 frame placed by both")
    assert same["n"] == 8 and same["n_ranked"] == 0 and same["p_value"] == 1.0


@pytest.mark.parametrize("gap, bad", [(["5", "50"], 50), (["-3", "2"], -3)])
def test_tracker_gap_outside_the_frames_is_refused_before_writing(tmp_path, capsys, gap, bad):
    out = tmp_path / "g"
    assert main(["simulate", "fetoscopy", str(out), "--n-frames", "10", "--laps", "0.27",
                 "--tracker-gap", *gap]) == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: --tracker-gap: frame {bad} outside 0..9\n")
    assert not out.exists()


def test_tracker_gap_reaching_the_first_frame_simulates(tmp_path, capsys):
    """A gap from frame 0 is a dataset whose tracker starts late: written, no error (its
    overlap warning reads the ground truth alone)."""
    out = tmp_path / "late"
    assert main(["simulate", "fetoscopy", str(out), "--n-frames", "10", "--laps", "0.27",
                 "--tracker-gap", "0", "4"]) == 0
    assert "error" not in capsys.readouterr().err
    assert (out / "tracking.csv").is_file()


@pytest.mark.parametrize("fourcc, ext", [("MJPG", "avi"), ("mp4v", "mp4")])
def test_a_one_frame_video_reads_again_and_again(tmp_path, fourcc, ext):
    """FFmpeg does not seek back to frame 0 from the end of a one-frame video (the end was
    probed, then frame 0 read): "none of its 1 frames can be read" before."""
    path = tmp_path / f"video.{ext}"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 25, (64, 48))
    writer.write(np.full((48, 64, 3), 120, np.uint8))
    writer.release()
    frames = FrameSource.open(tmp_path)
    assert len(frames) == 1
    for _ in range(3):
        assert frames[0].shape == (48, 64, 3)
        assert abs(float(frames[0].mean()) - 120) < 5


def test_a_frame_id_beyond_64_bits_is_a_row_error(data, tmp_path):
    import shutil

    root = tmp_path / "big"
    shutil.copytree(data / "f6", root)
    lines = (root / "frames.csv").read_text().splitlines()
    lines[3] = "9" * 25 + "," + lines[3].split(",")[1]
    (root / "frames.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(ValueError) as info:
        read_dataset(root)
    assert str(info.value) == (
        f"{root / 'frames.csv'}: row 4, column 'frame': '{'9' * 25}' is out of range (a 64-bit "
        "integer: -9223372036854775808..9223372036854775807)")


def test_evaluation_json_inside_the_truth_dataset_is_refused(data, capsys):
    before = sorted(p.name for p in (data / "f6").iterdir())
    for where in (data / "f6" / "video.json", data / "f6" / "frames" / "e.json"):
        assert main(["evaluate", str(data / "ba"), "--truth", str(data / "f6"), "--json",
                     str(where)]) == 2
        assert capsys.readouterr().err == (
            f"fusedmosaic: error: --json {where}: would be written inside the truth dataset "
            f"folder {data / 'f6'}, which it would corrupt; choose a path outside it\n")
    assert sorted(p.name for p in (data / "f6").iterdir()) == before
    read_dataset(data / "f6")  # still one recording


def test_times_around_1000_s_keep_their_milliseconds():
    text = no_overlap_message("tracking.csv", "tracker", np.array([1000.215, 1000.255]),
                              999.882, 1000.2)
    assert "[999.882, 1000.200] s (the frames span [1000.215, 1000.255] s)" in text


def test_sidecar_files_named_video_are_not_videos(tmp_path):
    """A subtitle or metadata file beside the recording (video.srt, video.json) is not a
    second video: the recording is read; alone, there is no video."""
    path = tmp_path / "video.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 25, (64, 48))
    for k in range(3):
        writer.write(np.full((48, 64, 3), 60 * k, np.uint8))
    writer.release()
    (tmp_path / "video.srt").write_text("1\n00:00:00,000 --> 00:00:01,000\nprobe at 3 mm\n")
    (tmp_path / "video.json").write_text("{}")
    frames = FrameSource.open(tmp_path)
    assert frames.video == path and len(frames) == 3
    path.unlink()
    with pytest.raises(ValueError, match=r"no frames \(neither frames/\*\.png nor a video\.\* "
                                         r"file\)"):
        FrameSource.open(tmp_path)
    (tmp_path / "frames").mkdir()
    cv2.imwrite(str(tmp_path / "frames" / "0.png"), np.zeros((48, 64), np.uint8))
    assert len(FrameSource.open(tmp_path)) == 1  # frames/ beside a sidecar: not two recordings


# ------------------------------------------------------------------ audit 20 (CLI options)


@pytest.mark.parametrize("command", [
    ["simulate", "fetoscopy", "{out}", "--n-frames", "8", "--laps", "0.1", "--seed", "-1"],
    ["simulate", "pcle", "{out}", "--n-frames", "8", "--width", "128", "--height", "112",
     "--seed", "-1"],
    ["simulate", "checkerboard", "{out}", "--seed", "-1"],
    ["bench", "--seed", "-1"],
])
def test_a_negative_seed_is_named(tmp_path, capsys, command):
    out = tmp_path / "s"
    assert main([c.replace("{out}", str(out)) for c in command]) == 2
    assert capsys.readouterr().err == (
        "fusedmosaic: error: --seed: must be an integer >= 0, got -1\n")
    assert not out.exists()


def test_demo_needs_two_frames_and_stays_out_of_a_dataset(data, tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "d"), "--frames", "1"]) == 2
    assert capsys.readouterr().err == "fusedmosaic: error: --frames must be >= 2, got 1\n"
    assert not (tmp_path / "d").exists()
    before = sorted(p.name for p in (data / "f6").iterdir())
    assert main(["demo", "--out", str(data / "f6"), "--frames", "5"]) == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: {data / 'f6'}: is a dataset folder; writing the demo there would "
        "corrupt it: choose --out outside it\n")
    assert sorted(p.name for p in (data / "f6").iterdir()) == before


def test_a_folder_given_for_a_file_is_named_a_folder(data, tmp_path, capsys):
    from fusedmosaic.io import read_camera_yaml

    assert main(["import", str(data / "f6"), str(tmp_path / "im")]) == 2
    assert capsys.readouterr().err == (
        f"fusedmosaic: error: {data / 'f6'}: is a folder; expected a file\n")
    with pytest.raises(ValueError, match=r"f6: is a folder; expected a file$"):
        read_camera_yaml(data / "f6")


@pytest.mark.parametrize("option, message", [
    (["--laps", "1e9"], "the path is 3.14e+12 µm long (--radius-um x --laps); at "
                        "most 1e+07 µm"),
    (["--speed-um-per-frame", "1e12"], "the frames span up to 7e+12 µm "
                                       "(--radius-um x --laps, and --n-frames x "
                                       "--speed-um-per-frame beyond the path): a texture of"),
    (["--cell-size-um", "1e-9"], "--cell-size-um: must be at least a pixel (1.0 µm), got 1e-09"),
    (["--fibre-spacing-px", "1e-6"], "--fibre-spacing-px: must be >= 1, got 1e-06"),
    (["--noise-floor", "2"], "--noise-floor: must be in 0..1, got 2.0"),
    (["--fibre-contrast", "5"], "--fibre-contrast: must be in 0..1, got 5.0"),
])
def test_pcle_sizes_and_fractions_refused_before_allocating(tmp_path, capsys, option, message):
    """Before, these allocated the path or the texture first (a MemoryError traceback at
    tens of GiB) or simulated clipped frames without a word."""
    out = tmp_path / "p"
    assert main(["simulate", "pcle", str(out), "--n-frames", "8", "--width", "128", "--height",
                 "112", *option]) == 2
    assert capsys.readouterr().err.startswith(f"fusedmosaic: error: {message}")
    assert not out.exists()
