"""Review 54 (black-box CLI review): textureless frames that are not black (a capture card's
uniform "no signal" frame) were placed from the priors, correctly, and then pasted into the
mosaic: a grey veil over the tissue, with no word in report.json."""

import json

import cv2
import numpy as np

from fusedmosaic.runner import BLANK_LEVEL, is_blank


def test_is_blank_judges_texture_inside_the_field_of_view():
    rng = np.random.default_rng(0)
    grey = np.clip(128 + rng.normal(0, 2, (60, 80, 3)), 0, 255).astype(np.uint8)  # noisy grey
    assert is_blank(grey, "prior-only") and not is_blank(grey, "placed")
    tissue = np.clip(128 + rng.normal(0, 12, (60, 80, 3)), 0, 255).astype(np.uint8)
    assert not is_blank(tissue, "prior-only")
    faint = grey.copy()  # a textured patch over 5 % of the field: content
    faint[:12, :20] = rng.integers(60, 200, (12, 20, 3))
    assert not is_blank(faint)
    # a circular field of view, black outside: judged inside it
    mask = np.zeros((60, 80), np.uint8)
    cv2.circle(mask, (40, 30), 25, 255, -1)
    ringed = np.where(mask[..., None] > 0, grey, 0).astype(np.uint8)
    assert is_blank(ringed, mask=mask) and not is_blank(ringed)
    assert is_blank(np.full((60, 80), BLANK_LEVEL, np.uint8))  # black, as before
    blue = np.zeros((60, 80, 3), np.uint8)  # a uniform blue "no signal" screen: per channel
    blue[..., 0] = 200
    assert is_blank(blue, "prior-only")
    # only 8-bit frames are judged by their range (a 16-bit frame's scale is unknown here)
    assert not is_blank((grey[..., 0].astype(np.uint16) * 4), "prior-only")


def test_uniform_grey_frames_are_placed_not_composed(tmp_path):
    from fusedmosaic.runner import run_dataset
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "data", FetoscopyOptions(n_frames=24, width=160,
                                                                  height=160))
    paths = sorted((root / "frames").glob("*.png"))
    for k in range(8, 12):
        cv2.imwrite(str(paths[k]), np.full((160, 160, 3), 128, np.uint8))
    out = tmp_path / "out"
    run_dataset(root, "lba-emt", out, progress=False, report=False)
    report = json.loads((out / "report.json").read_text())
    assert report["frame_status"][8:12] == ["prior-only"] * 4
    skipped = report["mosaic"]["skipped_frames"]
    assert sorted(skipped, key=int) == ["8", "9", "10", "11"]
    assert all(why.startswith("no visual content (textureless") for why in skipped.values())
    assert report["mosaic"]["frames_shown"] == 20


def test_a_ground_truth_that_does_not_fit_costs_the_scores_not_the_run(tmp_path, capsys):
    """Review 54: ground_truth.csv lacking a frame's row blocked `run` (exit 2), though the run
    only scores against it. The mosaic is made, the truth left out with a warning, report.json
    says why; read_dataset and `evaluate --truth` still refuse it."""
    import pytest

    from fusedmosaic.cli import main
    from fusedmosaic.io.dataset import read_dataset
    from fusedmosaic.runner import run_dataset
    from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

    root = simulate_fetoscopy(tmp_path / "data", FetoscopyOptions(n_frames=16, width=160,
                                                                  height=160))
    truth = root / "ground_truth.csv"
    lines = truth.read_text().splitlines(keepends=True)
    truth.write_text("".join(lines[:6] + lines[7:]))  # frame 5's row removed
    no_row = r"ground_truth\.csv: no row for frame 5 \(1 frames missing"
    with pytest.raises(ValueError, match=no_row):
        read_dataset(root)
    ds = read_dataset(root, strict_truth=False)
    assert ds.ground_truth is None and "no row for frame 5" in ds.ignored["ground_truth.csv"]

    out = tmp_path / "out"
    with pytest.warns(UserWarning, match=no_row + r".* -- left out: the run is not scored"):
        run_dataset(root, "lba-emt", out, progress=False, report=False)
    report = json.loads((out / "report.json").read_text())
    assert report["placed"] == 16 and (out / "mosaic.png").is_file()
    assert report["metrics"] is None
    assert report["metrics_note"] == ("not scored: ground_truth.csv left out (inputs_ignored "
                                      "says why)")
    assert "no row for frame 5" in report["inputs_ignored"]["ground_truth.csv"]
    capsys.readouterr()
    assert main(["evaluate", str(out), "--truth", str(root), "--no-report"]) == 2
    assert "no row for frame 5" in capsys.readouterr().err
