"""Review 51 (dataset path): frame files numbered in steps with a file missing, the summary of a
mosaic skipped for want of frames, and an AVI that lost a frame inside it."""

from __future__ import annotations

import re
import warnings

import cv2
import numpy as np
import pytest

from fusedmosaic.io import Camera, read_dataset, write_camera_yaml, write_dataset
from fusedmosaic.io.video import FrameSource

W, H = 32, 24


def _stepped(root, n=12, *, step=2, first=0, missing=(), frames_csv=None):
    """n frames (frame i: every pixel 10 + i) in files numbered first + step * i, the files of
    frames ``missing`` removed; frames.csv with the ids ``frames_csv`` (one per file left)."""
    write_dataset(root, camera=Camera(W, H),
                  frames=[np.full((H, W), 10 + i, np.uint8) for i in range(n)], timestamps=None)
    folder = root / "frames"
    for i in reversed(range(n)):  # (renamed from the last: 000000.png.. -> step * i)
        (folder / f"{i:06d}.png").rename(folder / f"{first + step * i:06d}.png")
    for i in missing:
        (folder / f"{first + step * i:06d}.png").unlink()
    (root / "frames.csv").unlink(missing_ok=True)
    if frames_csv is not None:
        ids = np.asarray(frames_csv)
        (root / "frames.csv").write_text("frame,timestamp\n" + "".join(
            f"{k},{k / 25.0}\n" for k in ids))
    return root


def _read(root, **kw):
    with warnings.catch_warnings(record=True) as heard:
        warnings.simplefilter("always")
        ds = read_dataset(root, **kw)
    return ds, [str(w.message) for w in heard]


def test_files_in_steps_of_2_unchanged(tmp_path):
    ds, said = _read(_stepped(tmp_path / "d"))
    np.testing.assert_array_equal(ds.frame_ids, np.arange(12))
    np.testing.assert_allclose(ds.timestamps, np.arange(12) / 25.0)
    assert ds.frame_times == "frame / 25 fps (the default: PNG frames; no frames.csv)"
    assert len(said) == 1 and re.fullmatch(
        r"\S*frames: the frame files are numbered in steps of 2 \(000000\.png, 000002\.png, "
        r"\.\.\.\): no frames\.csv, so they are taken as consecutive frames, timed frame / 25 "
        r"fps \(the default: PNG frames; no frames\.csv\); if the numbers are the video's frame "
        r"numbers \(every 2nd frame kept\), give frames\.csv with their times, or --fps 12\.5",
        said[0])


def test_files_in_steps_of_2_with_one_missing_warned_and_timed_across_the_gap(tmp_path):
    """000010.png gone (a step of 4 once): read before at frame / 25 fps as consecutive frames
    without a word, every frame after the gap taking the previous frame's time (and tracker
    sample). Now the step of 2 is one frame interval, as without the gap, and the frames after
    the gap keep their own times, as for files numbered frame by frame."""
    ds, said = _read(_stepped(tmp_path / "d", missing=[5]))
    kept = np.r_[0:5, 6:12]  # the frames present (frame i: file 2i, pixel 10 + i)
    np.testing.assert_array_equal(ds.frame_ids, kept)
    np.testing.assert_allclose(ds.timestamps, kept / 25.0, atol=1e-12)  # as with no file gone
    assert [int(ds.frames[k][0, 0]) - 10 for k in range(len(ds))] == kept.tolist()
    assert ds.frame_times == ("frame / 25 fps (the default: PNG frames; no frames.csv; frame = "
                              "file number / 2, 1 missing)")
    assert len(said) == 1 and re.fullmatch(
        r"\S*frames: the frame files are numbered in steps of 2 \(000000\.png, 000002\.png, "
        r"\.\.\.\): no frames\.csv, so a step of 2 is taken as one frame interval and the frames "
        r"are timed by their numbers, frame / 25 fps .*: 000010\.png missing between "
        r"000008\.png and 000012\.png: the frames after a gap keep their own times, and the "
        r"missing frames are left out; if the numbers are the video's frame numbers \(every 2nd "
        r"frame kept\), give frames\.csv with their times, or --fps 12\.5", said[0])


def test_files_in_steps_from_an_offset_with_gaps(tmp_path):
    ds, said = _read(_stepped(tmp_path / "d", step=3, first=7, missing=[2, 3, 8]), fps=10)
    kept = np.r_[0:2, 4:8, 9:12]
    np.testing.assert_array_equal(ds.frame_ids, kept)
    np.testing.assert_allclose(ds.timestamps, kept / 10.0, atol=1e-12)
    assert "frame = file (number - 7) / 3, 3 missing" in ds.frame_times
    assert len(said) == 1
    assert ("000013.png-000016.png (2 files) missing between 000010.png and 000019.png; "
            "000031.png missing between 000028.png and 000034.png" in said[0])
    assert said[0].endswith("every 3rd frame kept), give frames.csv with their times, or --fps "
                            "the kept frames' rate (the video's / 3; the 10 given is taken as "
                            "such)")


def test_files_numbered_frame_by_frame_with_a_gap_unchanged(tmp_path):
    ds, said = _read(_stepped(tmp_path / "d", step=1, missing=[5]))
    np.testing.assert_array_equal(ds.frame_ids, np.r_[0:5, 6:12])
    np.testing.assert_allclose(ds.timestamps, np.r_[0:5, 6:12] / 25.0)
    assert ds.frame_times == ("frame / 25 fps (the default: PNG frames; no frames.csv; frame = "
                              "file number, 1 missing)")
    assert len(said) == 1 and "steps of" not in said[0]
    assert said[0].endswith("frames: 000005.png missing between 000004.png and 000006.png: no "
                            "frames.csv, so the frames are numbered and timed by their file "
                            "numbers (frame id = file number, timestamp = id / 25 fps): the "
                            "frames after a gap keep their own times, and the missing frames are "
                            "left out; give frames.csv if the file numbers are not frame numbers")


def test_irregular_numbers_not_taken_as_steps(tmp_path):
    """Steps of 2 and 3 (gcd 1, median 2): neither frame numbers nor a step: ids by position,
    as before."""
    root = _stepped(tmp_path / "d", n=5)
    (root / "frames" / "000008.png").rename(root / "frames" / "000009.png")
    ds, said = _read(root)
    np.testing.assert_array_equal(ds.frame_ids, np.arange(5))
    assert said == []


@pytest.mark.parametrize("ids", [[0, 2, 4, 6, 8, 12, 14], [0, 1, 2, 3, 4, 6, 7],
                                 [100, 101, 102, 103, 104, 106, 107]])
def test_frames_csv_skipping_what_stepped_files_skip_is_silent(tmp_path, ids):
    """frames.csv's ids may be the video's frame numbers (steps of 2) or the frames' (1)."""
    ds, said = _read(_stepped(tmp_path / "d", n=8, missing=[5], frames_csv=ids))
    np.testing.assert_array_equal(ds.frame_ids, ids)
    assert said == []


def test_frames_csv_not_skipping_what_stepped_files_skip_warned(tmp_path):
    with pytest.warns(UserWarning, match=r"frames\.csv: row 7: frame 5 goes with \S*frames/"
                                         r"000012\.png .* that file's number would make it "
                                         r"frame 6: .*000010\.png missing between 000008\.png "
                                         r"and 000012\.png\)"):
        read_dataset(_stepped(tmp_path / "d", n=8, missing=[5], frames_csv=np.arange(7)))


def test_summary_names_why_the_mosaic_was_not_written(tmp_path, capsys):
    """Every frame black: the mosaic is skipped for want of a frame to compose, which the
    summary called 'above the canvas budget' (pointing at --max-canvas-pixels)."""
    from fusedmosaic.cli import main
    from fusedmosaic.simulation import PcleOptions, simulate_pcle

    root = simulate_pcle(tmp_path / "d", PcleOptions(n_frames=6, width=96, height=96))
    for path in (root / "frames").glob("*.png"):
        image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), np.zeros_like(image))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(["run", str(root), "--method", "robot", "--out", str(tmp_path / "out"),
                     "--no-report"])
    assert code == 0
    out = capsys.readouterr().out
    assert ("  mosaic  not written: no frame to compose a mosaic from: the 6 placed frame(s) are "
            "all left out (report.json mosaic.skipped_frames says why)\n") in out
    assert "canvas budget" not in out


# ---- an AVI that lost a frame inside it (review 51's repro_avi_damage.py) ----

def _avi(root, n=12):
    """A dataset with a 12-frame MJPG video.avi of distinct frames, no frames.csv; its bytes
    and the offsets of its frames' chunks."""
    rng = np.random.default_rng(0)
    images = [cv2.resize(rng.integers(0, 256, (6, 8, 3), dtype=np.uint8), (64, 48),
                         interpolation=cv2.INTER_NEAREST) for _ in range(n)]
    root.mkdir()
    writer = cv2.VideoWriter(str(root / "video.avi"), cv2.VideoWriter_fourcc(*"MJPG"), 25.0,
                             (64, 48))
    for image in images:
        writer.write(image)
    writer.release()
    write_camera_yaml(root / "camera.yaml", Camera(64, 48))
    data = bytearray((root / "video.avi").read_bytes())
    movi = data.index(b"movi")
    chunks = [i for i in range(movi, data.index(b"idx1")) if data[i:i + 4] == b"00dc"]
    assert len(chunks) == n
    return root, data, chunks, images


def _shown(ds, images):
    return [int(np.argmin([np.abs(ds.frames[k].astype(float) - o).mean() for o in images]))
            for k in range(len(ds))]


@pytest.mark.parametrize("damage", ["cut", "renamed"])
def test_avi_that_lost_a_frame_inside_refused(tmp_path, damage):
    """Frame 5's chunk cut out (or its id damaged): the offsets after it shift, the seek to the
    header's last frame fails, and 11 frames decode; read before with the truncated file's
    warning, frames 5-10 under frames 6-11's numbers, times and tracker samples."""
    root, data, chunks, _ = _avi(tmp_path / "d")
    if damage == "cut":
        data = data[:chunks[5]] + data[chunks[6]:]
    else:
        data[chunks[5]:chunks[5] + 4] = b"xxxx"
    (root / "video.avi").write_bytes(bytes(data))
    with pytest.raises(ValueError, match=r"video\.avi: its header counts 12 frames but decoding "
                                         r"it gives 11, and the file is whole at its end: its "
                                         r"index \(idx1\) lists 12 frames, and frame 5's chunk "
                                         r"is not where it says .*: bytes lost or damaged inside "
                                         r"the file at frame 5; the decoder passes the loss "
                                         r"without an error, so every frame after it would be "
                                         r"read under another frame's number .*; repair the "
                                         r"file, or give the frames that decode as frames/\*\.png "
                                         r"with frames\.csv \(each one's frame number and time\)$"):
        read_dataset(root)


def test_avi_cut_short_still_read_with_a_warning(tmp_path):
    """Cut short at frame 9's chunk (its index gone with its end): the 9 frames that decode are
    the first 9, read with the warning."""
    root, data, chunks, images = _avi(tmp_path / "d")
    (root / "video.avi").write_bytes(bytes(data[:chunks[9]]))
    with pytest.warns(UserWarning, match=r"video\.avi: its header counts 12 frames but 9 decode "
                                         r"\(a truncated file, or frames damaged in the middle"):
        ds = read_dataset(root)
    assert _shown(ds, images) == list(range(9))
    np.testing.assert_allclose(ds.timestamps, np.arange(9) / 25.0)


def test_avi_whole_and_with_an_undecodable_frame_unchanged(tmp_path):
    root, data, chunks, images = _avi(tmp_path / "d")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _shown(read_dataset(root), images) == list(range(12))
    s = chunks[5] + 8 + 200  # frame 5's data overwritten: flagged, the others keep their number
    data[s:s + 300] = np.random.default_rng(1).integers(0, 256, 300, np.uint8).tobytes()
    (root / "video.avi").write_bytes(bytes(data))
    frames = FrameSource(video=root / "video.avi", blank_unreadable=True)
    assert len(frames) == 12
