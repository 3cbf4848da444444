"""Bad input to `fusedmosaic run`: each case ends with a clear error and no partial output."""

import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.io import Camera, write_dataset
from fusedmosaic.runner import run_dataset

K = np.array([[300.0, 0, 79.5], [0, 300.0, 59.5], [0, 0, 1]])


def noise_frames(n, seed=0):
    rng = np.random.default_rng(seed)
    return [rng.integers(0, 255, (120, 160), dtype=np.uint8) for _ in range(n)]


@pytest.fixture
def untracked(tmp_path):
    return write_dataset(tmp_path / "data", camera=Camera(160, 120, camera_matrix=K),
                         frames=noise_frames(4), timestamps=np.arange(4) / 25.0)


def test_ba_emt_without_tracking_csv(untracked, tmp_path):
    with pytest.raises(ValueError, match=r"tracking\.csv: file not found; method 'ba-emt' needs"):
        run_dataset(untracked, "ba-emt", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_camera_matrix_required_for_pose_methods(tmp_path):
    data = write_dataset(tmp_path / "data", camera=Camera(160, 120), frames=noise_frames(3),
                         timestamps=np.arange(3) / 25.0)
    with pytest.raises(ValueError, match=r"camera\.yaml.*camera_matrix.*'ba'"):
        run_dataset(data, "ba", tmp_path / "out", progress=False)


@pytest.mark.parametrize("method", ["ba", "pairwise"])
def test_no_registrable_pair(untracked, tmp_path, method):
    with pytest.raises(ValueError, match="could be registered"):
        run_dataset(untracked, method, tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_ba_with_untextured_reference_frame(tmp_path):
    """Frames 1-3 register with each other, frame 0 (the output's reference) is black: the
    visual-only adjustment cannot place anything relative to it and says so."""
    import cv2

    rng = np.random.default_rng(1)
    scene = cv2.GaussianBlur(rng.integers(0, 255, (200, 260), dtype=np.uint8), (5, 5), 1.5)
    frames = [np.zeros((120, 160), np.uint8)] + [scene[8 * k:8 * k + 120, 6 * k:6 * k + 160]
                                                 for k in (1, 2, 3)]
    data = write_dataset(tmp_path / "data", camera=Camera(160, 120, camera_matrix=K),
                         frames=frames, timestamps=np.arange(4) / 25.0)
    with pytest.raises(ValueError, match=r"data: frame 0, the reference of every output "
                       r"homography, has no registered pair \([1-9]\d* pairs registered between "
                       r"other frames\).*ba-emt and lba-emt"):
        run_dataset(data, "ba", tmp_path / "out", progress=False)
    assert not (tmp_path / "out").exists()


def test_unknown_method_and_cli_error_line(untracked, tmp_path, capsys):
    with pytest.raises(ValueError, match="unknown method 'nope'; available: lba-emt, ba-emt"):
        run_dataset(untracked, "nope", tmp_path / "out")
    code = main(["run", str(untracked), "--method", "pairwise", "--out", str(tmp_path / "o")])
    assert code == 2
    assert "fusedmosaic: error:" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("run", "method"),
    [("run_bundle", "'ba-emt'"), ("run_emt", "'emt'")],
)
def test_library_entry_points_check_the_camera_matrix(tmp_path, run, method):
    """Called directly (not through run_dataset), the pose methods still refuse a K whose
    layout is wrong (here transposed), naming the file and the method."""
    from fusedmosaic.estimation import bundle
    from fusedmosaic.io import read_dataset

    data = write_dataset(tmp_path / "data", camera=Camera(160, 120, camera_matrix=K.T),
                         frames=noise_frames(3), timestamps=np.arange(3) / 25.0)
    with pytest.raises(ValueError, match=rf"camera\.yaml: camera_matrix.*{method} needs"):
        getattr(bundle, run)(read_dataset(data), progress=False)
