"""Seed 000 Eq. 28-29 and seed 004 position statistics against hand-computed values."""

import numpy as np
import pytest

from fusedmosaic.evaluation import (
    compare_position_errors,
    drift_ratio,
    frame_errors,
    grid_points,
    mosaic_error,
    position_errors_um,
    position_stats,
)


def translation(dx: float, dy: float) -> np.ndarray:
    return np.array([[1.0, 0, dx], [0, 1.0, dy], [0, 0, 1.0]])


@pytest.fixture
def truth():
    rng = np.random.default_rng(3)
    G = np.tile(np.eye(3), (20, 1, 1))
    G[:, :2, 2] = rng.normal(0, 50, (20, 2))
    G[:, :2, :2] += rng.normal(0, 0.02, (20, 2, 2))
    G[:, 2, :2] = rng.normal(0, 1e-4, (20, 2))
    G[0] = np.eye(3)
    return G


def test_grid_is_100_by_100_over_the_image():
    pts = grid_points(400, 300)
    assert pts.shape == (10000, 2)
    assert pts.min(axis=0).tolist() == [0, 0]
    assert pts.max(axis=0).tolist() == [399, 299]


def test_truth_against_itself_is_zero_and_shift_is_exact(truth):
    assert mosaic_error(frame_errors(truth, truth, 400, 400)) < 1e-12
    shifted = np.einsum("ij,njk->nik", translation(2.0, 0.0), truth)
    e = frame_errors(shifted, truth, 400, 400)
    np.testing.assert_allclose(e, 2.0, atol=1e-9)
    diag = np.einsum("ij,njk->nik", translation(1.2, -1.6), truth)
    assert mosaic_error(frame_errors(diag, truth, 400, 400)) == pytest.approx(2.0, abs=1e-9)


def test_error_of_a_rotation_about_the_centre_matches_closed_form():
    # Rotation by a small angle about the reference centre: the displacement of each grid point
    # is 2 r sin(a/2), r its distance to the centre; e_j is the mean of that over the grid.
    a = np.deg2rad(1.0)
    c = np.array([199.5, 199.5])
    R = np.array([[np.cos(a), -np.sin(a), 0], [np.sin(a), np.cos(a), 0], [0, 0, 1]])
    G = translation(*c) @ R @ translation(*-c)
    pts = grid_points(400, 400)
    expected = (2 * np.sin(a / 2) * np.linalg.norm(pts - c, axis=1)).mean()
    assert frame_errors(G[None], np.eye(3)[None], 400, 400)[0] == pytest.approx(expected, rel=1e-9)


def test_unplaced_frames_are_nan_and_excluded(truth):
    est = truth.copy()
    est[5:8] = np.nan
    e = frame_errors(est, truth, 400, 400)
    assert np.isnan(e[5:8]).all() and np.isfinite(np.delete(e, [5, 6, 7])).all()
    assert mosaic_error(e) == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(mosaic_error(np.full(4, np.nan)))


def test_drift_ratio_quarters():
    e = np.array([1.0, 1, 1, 1, 2, 2, 2, 2, 3, 3, 3, 3, 4, 4, 4, 4])
    assert drift_ratio(e) == pytest.approx(4.0)
    assert drift_ratio(np.ones(10)) == pytest.approx(1.0)


def test_position_errors_and_stats():
    G_true = np.stack([translation(10.0 * k, 0) for k in range(5)])
    G_est = np.stack([translation(10.0 * k + 3, 4) for k in range(5)])
    err = position_errors_um(G_est, G_true, 512, 448, pixel_size_um=0.5)
    np.testing.assert_allclose(err, 2.5)
    s = position_stats(np.array([1.0, 2, 3, 10]))
    assert (s.n, s.mean, s.max, s.median) == (4, 4.0, 10.0, 2.5)
    assert s.std == pytest.approx(np.std([1, 2, 3, 10]))


def test_wilcoxon_detects_a_consistent_improvement():
    rng = np.random.default_rng(0)
    a = rng.uniform(100, 200, 40)
    b = a * 0.5 + rng.normal(0, 5, 40)
    res = compare_position_errors(a, b)
    assert res["p_value"] < 1e-6 and res["n"] == 40
    same = compare_position_errors(a, a + rng.normal(0, 1, 40))
    assert same["p_value"] > 0.01


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: frame_errors(np.eye(3), np.eye(3)[None], 10, 10),
         r"G_est: expected homographies of shape \(N, 3, 3\)"),
        (lambda: frame_errors(np.tile(np.eye(3), (2, 1, 1)), np.eye(3)[None], 10, 10),
         "differ in frame count: 2 vs 1"),
        (lambda: position_errors_um(np.eye(3)[None], np.eye(3)[None], 10, 10, 0.0),
         "pixel_size_um must be a positive number"),
        (lambda: compare_position_errors(np.array([1.0]), np.array([2.0])),
         "at least 2 frames"),
    ],
)
def test_bad_input(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_a_frame_placed_unusably_counts_against_e_M(truth):
    """Both homographies given, but the estimate sends a grid point (the column x = 0) to
    infinity: e_j is inf, not NaN (a method's unusable placement is not left out of e_M)."""
    est = truth.copy()
    est[3] = [[1.0, 0, 1.0], [0, 1.0, 0], [0.01, 0, 0]]  # regular, but w = 0.01 x
    e = frame_errors(est, truth, 400, 400)
    assert e[3] == np.inf and np.isfinite(np.delete(e, 3)).all()
    assert mosaic_error(e) == np.inf
