"""Datasets with frames missing (gaps in the frame files' numbers), ground truth for frames not
in the dataset, and camera.yaml that is not YAML or has misspelt keys."""

from __future__ import annotations

import warnings

import cv2
import numpy as np
import pytest

from fusedmosaic.io import Camera, read_camera_yaml, read_dataset, write_dataset

W, H = 32, 24


def _dataset(root, n=20, *, frames_csv=True, truth=False):
    images = [np.full((H, W), 10 + i, np.uint8) for i in range(n)]
    G = np.repeat(np.eye(3)[None], n, axis=0)
    G[:, 0, 2] = np.arange(n)
    write_dataset(root, camera=Camera(W, H), frames=images,
                  timestamps=np.arange(n) / 25.0 if frames_csv else None,
                  ground_truth=G if truth else None)
    return root


def _drop_row(path, frame):
    lines = path.read_text().splitlines(keepends=True)
    path.write_text("".join(line for line in lines if not line.startswith(f"{frame},")))


def test_gap_without_frames_csv_is_timed_by_the_file_numbers(tmp_path):
    root = _dataset(tmp_path / "d", frames_csv=False)
    (root / "frames" / "000010.png").unlink()
    with pytest.warns(UserWarning, match=r"frames: 000010\.png missing between 000009\.png and "
                                         r"000011\.png: no frames\.csv, so the frames are "
                                         r"numbered and timed by their file numbers \(frame id = "
                                         r"file number, timestamp = id / 25 fps\)"):
        ds = read_dataset(root)
    expected = np.r_[0:10, 11:20]
    np.testing.assert_array_equal(ds.frame_ids, expected)
    np.testing.assert_allclose(ds.timestamps, expected / 25.0)
    assert ds.frames[10][0, 0] == 21  # 000011.png, frame 11
    assert ds.frame_times == ("frame / 25 fps (the default: PNG frames; no frames.csv; frame = "
                              "file number, 1 missing)")


def test_several_gaps_named(tmp_path):
    root = _dataset(tmp_path / "d", frames_csv=False)
    for k in (3, 4, 5, 12):
        (root / "frames" / f"{k:06d}.png").unlink()
    with pytest.warns(UserWarning, match=r"000003\.png-000005\.png \(3 files\) missing between "
                                         r"000002\.png and 000006\.png; 000012\.png missing "
                                         r"between 000011\.png and 000013\.png: no frames\.csv"):
        ds = read_dataset(root, fps=10)
    np.testing.assert_allclose(ds.timestamps, np.r_[0:3, 6:12, 13:20] / 10.0)


def test_numbered_files_without_gaps_unchanged(tmp_path):
    """Files numbered from 1 (ffmpeg's default) or not numbered at all keep ids 0..N-1."""
    root = _dataset(tmp_path / "d", n=5, frames_csv=False)
    frames = root / "frames"
    for k in reversed(range(5)):  # 000000..000004 -> frame_1..frame_5
        (frames / f"{k:06d}.png").rename(frames / f"frame_{k + 1}.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, np.arange(5))
    assert ds.frames[0][0, 0] == 10
    for k, name in enumerate("abcde"):
        (frames / f"frame_{k + 1}.png").rename(frames / f"img_{name}.png")
    (frames / "img_c.png").unlink()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, np.arange(4))
    np.testing.assert_allclose(ds.timestamps, np.arange(4) / 25.0)


def test_gap_from_the_first_file_number(tmp_path):
    root = _dataset(tmp_path / "d", n=6, frames_csv=False)
    frames = root / "frames"
    for k in reversed(range(6)):
        (frames / f"{k:06d}.png").rename(frames / f"f{k + 1}.png")
    (frames / "f3.png").unlink()
    with pytest.warns(UserWarning, match=r"f3\.png missing between f2\.png and f4\.png: .*"
                                         r"\(frame id = file number - 1, "):
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, [0, 1, 3, 4, 5])


def test_files_numbered_in_steps_taken_as_consecutive_with_a_warning(tmp_path):
    """Files numbered 0, 5, 10, ... (every 5th frame, named by its number): consecutive
    frames at the frame rate, as before, but no longer without a word (the tracker would be
    paired with frames 5x too close in time)."""
    root = _dataset(tmp_path / "d", n=4, frames_csv=False)
    frames = root / "frames"
    for k in reversed(range(4)):
        (frames / f"{k:06d}.png").rename(frames / f"frame_{5 * k:06d}.png")
    with pytest.warns(UserWarning, match=r"frames: the frame files are numbered in steps of 5 "
                                         r"\(frame_000000\.png, frame_000005\.png, \.\.\.\): "
                                         r"no frames\.csv, so they are taken as consecutive "
                                         r"frames, timed frame / 25 fps .*or --fps 5$"):
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, np.arange(4))
    np.testing.assert_allclose(ds.timestamps, np.arange(4) / 25.0)
    write_dataset(tmp_path / "e", camera=Camera(W, H), frames=[ds.frames[k] for k in range(4)],
                  timestamps=np.arange(4) / 5.0)  # with frames.csv: its times, no warning
    for k in reversed(range(4)):
        (tmp_path / "e" / "frames" / f"{k:06d}.png").rename(
            tmp_path / "e" / "frames" / f"{5 * k:06d}.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_allclose(read_dataset(tmp_path / "e").timestamps, np.arange(4) / 5.0)


def test_timestamp_named_files_are_not_frame_numbers(tmp_path):
    root = _dataset(tmp_path / "d", n=4, frames_csv=False)
    frames = root / "frames"
    for k, stamp in reversed(list(enumerate((1637000000000, 1637000000033, 1637000000067,
                                             1637000000100)))):
        (frames / f"{k:06d}.png").rename(frames / f"{stamp}.png")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, np.arange(4))


def test_frames_csv_missing_its_last_row_and_a_file_warned(tmp_path):
    """Rows pair with the files by position: 000011.png is read as frame 10, which the file
    numbers contradict: warned, naming the row and the files (a warning, not a refusal: ids
    renumbered or a counter of their own are valid; review)."""
    root = _dataset(tmp_path / "d")
    (root / "frames" / "000010.png").unlink()
    _drop_row(root / "frames.csv", 19)
    with pytest.warns(UserWarning, match=r"frames\.csv: row 12: frame 10 goes with \S*frames/"
                                         r"000011\.png \(the rows go with the frame files in name "
                                         r"order\), but after frame 9 \(000009\.png\) that file's "
                                         r"number would make it frame 11: .*000010\.png missing "
                                         r"between 000009\.png and 000011\.png\); if a frame file "
                                         r"or a row of frames\.csv is missing, every later row is "
                                         r"paired with the wrong image$"):
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, np.arange(19))


def test_ground_truth_rows_of_absent_frames_refused_without_frames_csv(tmp_path):
    """Without frames.csv a removed first file shifts the ids by position: ignoring the unknown
    truth row scored every frame against its neighbour's truth (e_M 251 px for 0.06; review).
    Refused, saying why."""
    root = _dataset(tmp_path / "d", truth=True)
    (root / "frames.csv").unlink()
    (root / "frames" / "000000.png").unlink()
    with pytest.raises(ValueError, match=r"ground_truth\.csv: frame 19 is not in the dataset \(1 "
                                         r"unknown frame ids\): without frames\.csv the frames are "
                                         r"numbered by position .*give frames\.csv with the ids "
                                         r"ground_truth\.csv uses$"):
        read_dataset(root)


def test_frames_csv_row_count_names_the_missing_file(tmp_path):
    root = _dataset(tmp_path / "d")
    (root / "frames" / "000010.png").unlink()
    with pytest.raises(ValueError, match=r"frames\.csv: 20 rows but the dataset has 19 images "
                                         r"\(\S*frames: 000010\.png missing between 000009\.png "
                                         r"and 000011\.png\)$"):
        read_dataset(root)


def test_frames_csv_skipping_the_missing_files_frame_is_read(tmp_path):
    root = _dataset(tmp_path / "d")
    (root / "frames" / "000010.png").unlink()
    _drop_row(root / "frames.csv", 10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, np.r_[0:10, 11:20])


def test_frame_ids_with_gaps_over_consecutive_files_are_read(tmp_path):
    """A PLUS import writes its frames as 000000.png... with the recording's ids (gaps where
    frames were left out) in frames.csv: the files' positions, not their numbers, pair them."""
    ids = np.array([0, 1, 4, 5, 9])
    root = tmp_path / "d"
    write_dataset(root, camera=Camera(W, H), frames=[np.zeros((H, W), np.uint8)] * 5,
                  timestamps=ids / 25.0, frame_ids=ids)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ds = read_dataset(root)
    np.testing.assert_array_equal(ds.frame_ids, ids)


def test_ground_truth_rows_of_frames_not_in_the_dataset_ignored(tmp_path):
    root = _dataset(tmp_path / "d", truth=True)
    (root / "frames" / "000010.png").unlink()
    _drop_row(root / "frames.csv", 10)
    with pytest.warns(UserWarning, match=r"ground_truth\.csv: 1 row for a frame not in the "
                                         r"dataset ignored \(frame 10\): only the dataset's "
                                         r"frames are scored"):
        ds = read_dataset(root)
    np.testing.assert_allclose(ds.ground_truth[:, 0, 2], np.r_[0:10, 11:20])
    (root / "frames" / "000000.png").unlink()
    (root / "frames" / "000019.png").unlink()
    _drop_row(root / "frames.csv", 0)
    _drop_row(root / "frames.csv", 19)
    with pytest.warns(UserWarning, match=r"ground_truth\.csv: 3 rows for frames not in the "
                                         r"dataset ignored \(frames 0, 10, 19\)"):
        ds = read_dataset(root)
    assert ds.ground_truth.shape == (17, 3, 3)


def test_ground_truth_scored_on_the_frames_present(tmp_path):
    from fusedmosaic.evaluation.metrics import evaluate_output
    from fusedmosaic.io import write_homographies_csv

    root = _dataset(tmp_path / "d", truth=True)
    (root / "frames" / "000000.png").unlink()
    _drop_row(root / "frames.csv", 0)
    out = tmp_path / "out"
    out.mkdir()
    G = np.repeat(np.eye(3)[None], 19, axis=0)  # frame -> frame 1 (the first one present)
    G[:, 0, 2] = np.arange(19)
    write_homographies_csv(out / "homographies.csv", np.arange(1, 20), G)
    with pytest.warns(UserWarning, match=r"ground_truth\.csv: 1 row for a frame not in the "
                                         r"dataset ignored \(frame 0\): only the dataset's "
                                         r"frames are scored; the truth is taken relative to "
                                         r"frame 1, the dataset's first$"):
        result = evaluate_output(out, root)
    assert result["frames"] == 19 and result["e_M_px"] == pytest.approx(0.0, abs=1e-9)


def test_camera_yaml_that_is_not_yaml(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text("this is : not : yaml [\n")
    with pytest.raises(ValueError, match=r"camera\.yaml: cannot parse as OpenCV FileStorage YAML "
                                         r"with image_width, image_height\[, camera_matrix, "
                                         r"\.\.\.\]: none of camera\.yaml's keys in it \(read "
                                         r"'this is' as a key\)"):
        read_camera_yaml(path)


def test_camera_yaml_misspelt_key_warned(tmp_path):
    path = tmp_path / "camera.yaml"
    path.write_text("%YAML:1.0\nimage_width: 32\nimage_height: 24\nfov_mask_radus: 10\n")
    with pytest.warns(UserWarning, match=r"camera\.yaml: unknown key 'fov_mask_radus' \(did you "
                                         r"mean 'fov_mask_radius'\?\) ignored; camera\.yaml's keys "
                                         r"are image_width, image_height, camera_matrix, "
                                         r"distortion_coefficients, .*fov_mask_radius$"):
        camera = read_camera_yaml(path)
    assert camera.fov_mask_radius is None
    path.write_text("%YAML:1.0\nimage_widht: 32\nimage_height: 24\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # refused: no warning besides
        with pytest.raises(ValueError, match=r"camera\.yaml: missing key 'image_width' "
                                             r"\('image_widht' is not a camera\.yaml key: "
                                             r"misspelt\?\)"):
            read_camera_yaml(path)


def test_camera_yaml_keys_of_calibration_tools_silent(tmp_path):
    """OpenCV's calibration sample and ROS camera_info write keys camera.yaml does not use."""
    path = tmp_path / "camera.yaml"
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    fs.write("calibration_time", "Mon Jan  1 00:00:00 2024")
    fs.write("nframes", 20)
    fs.write("image_width", W)
    fs.write("image_height", H)
    fs.write("board_width", 9)
    fs.write("board_height", 6)
    fs.write("square_size", 1.0)
    fs.write("flags", 0)
    fs.write("fisheye_model", 0)
    fs.write("camera_matrix", np.array([[40.0, 0, 15.5], [0, 40, 11.5], [0, 0, 1]]))
    fs.write("distortion_coefficients", np.zeros((5, 1)))
    fs.write("avg_reprojection_error", 0.2)
    fs.write("per_view_reprojection_errors", np.zeros((20, 1)))
    fs.write("extrinsic_parameters", np.zeros((20, 6)))
    fs.release()
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_camera_yaml(path)
    path.write_text("image_width: 32\nimage_height: 24\ncamera_name: scope\n"
                    "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [40, 0, 15.5, 0, 40, 11.5, 0, "
                    "0, 1]\ndistortion_model: plumb_bob\ndistortion_coefficients:\n  rows: 1\n"
                    "  cols: 5\n  data: [0, 0, 0, 0, 0]\nrectification_matrix:\n  rows: 3\n"
                    "  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\nprojection_matrix:\n"
                    "  rows: 3\n  cols: 4\n  data: [40, 0, 15.5, 0, 0, 40, 11.5, 0, 0, 0, 1, 0]\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_camera_yaml(path)


def test_dataset_warnings_kept_in_report_json(tmp_path):
    """What reading the dataset warned of (a gap in the numbered files, an unknown camera.yaml
    key) qualifies the results: report.json's warnings keep it, and the terminal summary does not
    repeat what was shown as it happened."""
    import json

    from fusedmosaic.runner import run_dataset
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(n_frames=8, laps=8 / 37.5,
                                                                width=160, height=160))
    for name in ("frames.csv", "ground_truth.csv", "frames/000003.png"):
        (root / name).unlink()
    camera = root / "camera.yaml"
    camera.write_text(camera.read_text() + "pixel_sise_um: 2\n")
    with pytest.warns(UserWarning) as heard:
        summary = run_dataset(root, "emt", tmp_path / "out", report=False, progress=False)
    texts = [str(w.message) for w in heard]
    gap = next(t for t in texts if "000003.png missing between 000002.png and 000004.png" in t)
    key = next(t for t in texts if "unknown key 'pixel_sise_um' (did you mean 'pixel_size_um'" in t)
    report = json.loads((tmp_path / "out" / "report.json").read_text())
    assert gap in report["warnings"] and key in report["warnings"]
    assert len(report["warnings"]) == len(set(report["warnings"]))
    # frame_status is one per frame in the dataset's order; frame_ids names them
    assert report["frame_ids"] == [0, 1, 2, 4, 5, 6, 7]
    assert len(report["frame_status"]) == len(report["frame_ids"])
    assert "missing between" not in summary and "pixel_sise_um" not in summary


def test_pairwise_statuses_name_frame_ids_across_a_gap(tmp_path):
    """Frames 5 and 6 removed (files and frames.csv rows), frame 7 black: report.json's statuses
    named positions ('pair (4, 5)', 'chain broken at frame 5') where homographies.csv and the
    warning name ids 4 and 7 (review)."""
    from fusedmosaic.estimation.pairwise import run_pairwise
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "d", FetoscopyOptions(n_frames=12, laps=12 / 37.5,
                                                                width=160, height=160))
    for k in (5, 6):
        (root / "frames" / f"{k:06d}.png").unlink()
        _drop_row(root / "frames.csv", k)
        _drop_row(root / "ground_truth.csv", k)
    cv2.imwrite(str(root / "frames" / "000007.png"), np.zeros((160, 160, 3), np.uint8))
    ds = read_dataset(root)
    result = run_pairwise(ds, progress=False)
    status = dict(zip(ds.frame_ids.tolist(), result.status, strict=True))
    assert status[7].startswith("unplaced: pair (4, 7) not registered: too few features")
    assert status[8] == status[11] == "unplaced: chain broken at frame 7"
    assert any("breaks at frame 7: pair (4, 7)" in w for w in result.details["warnings"])
