"""Offline pose methods after review 44 (B 1-7, A 3): emt honours pair_selection; the cameras'
baseline without an N x N array; the plane std's Cholesky path timed apart; EMT-guided pairs and
emt with frame 0 untracked; the tracker poses and every BundleOptions field checked up front; a
tracker origin near the plane recentred, and a singular frame left unplaced instead of failing
the run.

Scenes: the SYN circle at 24 frames (laps as the paper's overlap), 400 x 400."""

import csv
import dataclasses
import json
import shutil

import numpy as np
import pytest

from fusedmosaic import _core
from fusedmosaic.estimation import bundle
from fusedmosaic.estimation import plane as plane_module
from fusedmosaic.estimation.bundle import (
    UNPLACED_SINGULAR,
    BundleOptions,
    predicted_homographies,
    run_ba,
    run_ba_emt,
    run_emt,
)
from fusedmosaic.estimation.plane import camera_baseline_mm, point_set_diameter
from fusedmosaic.estimation.world import (
    ORIGIN_PLANE_FRACTION,
    origin_near_plane,
    tracked_world,
)
from fusedmosaic.evaluation.metrics import frame_errors, rereferenced
from fusedmosaic.io import read_dataset
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

N = 24


@pytest.fixture(scope="module")
def work(tmp_path_factory):
    return tmp_path_factory.mktemp("review44")


@pytest.fixture(scope="module")
def base(work):
    return simulate_fetoscopy(work / "base", FetoscopyOptions(n_frames=N, laps=N / 37.5))


def tracking_variant(src, dst, change):
    """A copy of dataset src whose tracking.csv rows (lists of strings) pass through change."""
    if dst.exists():
        return dst
    shutil.copytree(src, dst)
    path = dst / "tracking.csv"
    with path.open(newline="") as f:
        rows = list(csv.reader(f))
    with path.open("w", newline="") as f:
        csv.writer(f).writerows([rows[0], *change(rows[1:])])
    return dst


def e_M(result, dataset) -> float:
    """Mean e_j over the placed frames, in the result's reference grid."""
    G = result.homographies
    placed = np.flatnonzero(np.isfinite(G).all(axis=(1, 2)))
    r = int(placed[0])
    truth = rereferenced(dataset.ground_truth, r)
    cam = dataset.camera
    return float(np.mean(frame_errors(G[placed], truth[placed], cam.width, cam.height)))


# ---- B1: emt honours pair_selection ---------------------------------------------------------


@pytest.mark.parametrize(("selection", "attempted"),
                         [("all", N * (N - 1) // 2), ("window", 2 * N - 3)])
def test_emt_matches_the_pairs_of_its_pair_selection(base, selection, attempted):
    """Before, emt matched the EMT-guided pairs whatever pair_selection said, and report.json
    recorded the ignored value."""
    ds = read_dataset(base)
    r = run_emt(ds, progress=False, options=BundleOptions(pair_selection=selection, window=2))
    assert r.details["pairs"]["attempted"] == attempted
    assert r.parameters["pair_selection"] == selection
    assert set(r.status) == {"placed"} and np.isfinite(r.plane).all()


def test_emt_default_is_emt_guided(base):
    ds = read_dataset(base)
    guided = run_emt(ds, progress=False)
    assert guided.parameters["pair_selection"] == "emt-guided"
    assert N - 1 <= guided.details["pairs"]["attempted"] < N * (N - 1) // 2
    # options given for another field keep the method's own selection (pair_selection None):
    # emt matched every pair when given BundleOptions(min_overlap=0.5) (final review)
    tuned = run_emt(ds, progress=False, options=BundleOptions(min_overlap=0.5))
    assert tuned.parameters["pair_selection"] == "emt-guided"
    assert tuned.details["pairs"]["attempted"] < N * (N - 1) // 2
    assert BundleOptions().pair_selection is None


def test_ba_emt_default_is_all_pairs(base):
    r = run_ba_emt(read_dataset(base), progress=False, options=BundleOptions(min_overlap=0.5))
    assert r.parameters["pair_selection"] == "all"
    assert r.details["pairs"]["attempted"] == N * (N - 1) // 2


# ---- B2: camera_baseline_mm ----------------------------------------------------------------


def brute_force(points):
    points = np.asarray(points, float)
    return float(np.max(np.linalg.norm(points[:, None] - points[None], axis=2)))


def point_sets():
    rng = np.random.default_rng(44)
    yield "gaussian", rng.normal(0, 10, (300, 3))
    yield "few", rng.normal(0, 10, (4, 3))
    yield "two", rng.normal(0, 10, (2, 3))
    yield "sphere", (lambda v: 7 * v / np.linalg.norm(v, axis=1, keepdims=True))(
        rng.normal(size=(200, 3)))
    t = rng.uniform(-5, 5, 150)
    yield "collinear", np.c_[1 + 2 * t, -3 + 0.5 * t, 4 - t]
    u, v = rng.uniform(-5, 5, (2, 150))
    yield "coplanar", np.c_[u, v, 0.3 * u - 2 * v + 1]
    a = np.linspace(0, 2 * np.pi, 120, endpoint=False)  # every point a hull vertex
    yield "circle", np.c_[10 * np.cos(a), 10 * np.sin(a), np.full(120, 5.0)]
    yield "duplicates", np.repeat(rng.normal(0, 3, (20, 3)), 5, axis=0)
    yield "one point repeated", np.tile([1.0, 2.0, 3.0], (10, 1))
    yield "grid", np.stack(np.meshgrid(*[np.arange(4.0)] * 3), -1).reshape(-1, 3)


@pytest.mark.parametrize(("name", "points"), list(point_sets()), ids=lambda x: x
                         if isinstance(x, str) else "")
def test_point_set_diameter_equals_the_brute_force(name, points, monkeypatch):
    monkeypatch.setattr(plane_module, "_DISTANCE_BLOCK", 7)  # several blocks
    assert point_set_diameter(points) == pytest.approx(brute_force(points), rel=1e-12, abs=0)


@pytest.mark.parametrize("n", [3, 50])
def test_point_set_diameter_of_non_finite_points_is_nan(n):
    """As over all pairs (a NaN point among 4 gave 0.0, among more qhull's error)."""
    points = np.random.default_rng(2).normal(size=(n, 3))
    for bad in (np.nan, np.inf):
        points[1, 2] = bad
        assert np.isnan(point_set_diameter(points))


def test_camera_baseline_mm_equals_the_brute_force():
    rng = np.random.default_rng(5)
    for n, spread in ((2, 1.0), (40, 30.0), (500, 0.01)):
        poses = np.c_[rng.normal(0, 0.5, (n, 3)), rng.normal(0, spread, (n, 3))]
        centres = np.array([-_core.rotation_from_angle_axis(p[:3]).T @ p[3:] for p in poses])
        assert camera_baseline_mm(poses) == pytest.approx(brute_force(centres), rel=1e-12)
    # cameras translating along a line (a straight pull-back), and in a plane
    line = np.c_[np.zeros((50, 3)), np.outer(np.linspace(-3, 7, 50), [0.6, 0.0, 0.8])]
    assert camera_baseline_mm(line) == pytest.approx(10.0, rel=1e-12)
    assert camera_baseline_mm(line[:1]) == 0.0


def test_camera_baseline_mm_builds_no_n_by_n_array(monkeypatch):
    """6000 cameras: no temporary of N x N (the old one held 6000^2 x 3 doubles, 860 MB)."""
    import tracemalloc

    rng = np.random.default_rng(1)
    poses = np.c_[rng.normal(0, 0.1, (6000, 3)), rng.normal(0, 20, (6000, 3))]
    tracemalloc.start()
    try:
        camera_baseline_mm(poses)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 60e6


# ---- B3: the plane std, timed apart ----------------------------------------------------------


def test_plane_std_is_timed_apart_from_problem_setup(base):
    ds = read_dataset(base)
    r = run_ba_emt(ds, progress=False, options=BundleOptions(pair_selection="window"))
    assert r.details["plane_relative_std"] is not None
    assert 0 < r.details["plane_relative_std"] < 0.25
    assert r.timings["plane_std"] > 0
    assert r.details["solver"]["plane_std_time_s"] == r.timings["plane_std"]
    off = run_ba_emt(ds, progress=False,
                     options=BundleOptions(pair_selection="window", plane_std_max_frames=0))
    assert off.timings["plane_std"] == 0 and off.details["plane_relative_std"] is None
    # the same adjustment either way (the covariance is computed after it)
    np.testing.assert_allclose(off.poses, r.poses, rtol=0, atol=1e-9)


# ---- B4: frame 0 without a tracker sample --------------------------------------------------


@pytest.fixture(scope="module")
def late(base, work):
    """The tracker comes on after frame 4 (samples up to t = 0.17 s dropped)."""
    root = tracking_variant(base, work / "late", lambda rows: [r for r in rows
                                                                if float(r[0]) > 0.17])
    return read_dataset(root, allow_untracked=True)


def test_emt_guided_selection_and_emt_without_frame_0_tracked(late):
    assert not late.pose_valid[:5].any() and late.pose_valid[5:].all()
    r = run_emt(late, progress=False)
    assert r.status[:5] == ["unplaced: no tracker sample"] * 5
    assert set(r.status[5:]) == {"placed"}
    np.testing.assert_allclose(r.homographies[5], np.eye(3), atol=1e-12)  # the reference
    assert e_M(r, late) < 100.0
    guided = run_ba_emt(late, progress=False, options=BundleOptions(pair_selection="emt-guided"))
    assert np.isfinite(guided.homographies).all()
    assert e_M(guided, late) < 1.0


# ---- B5: the tracker poses checked on entry --------------------------------------------------


@pytest.mark.parametrize("run", [run_ba_emt, run_emt])
def test_a_dataset_without_tracking_is_refused_naming_the_file(base, work, run):
    root = work / "no_tracking"
    if not root.exists():
        shutil.copytree(base, root)
        (root / "tracking.csv").unlink()
    method = "ba-emt" if run is run_ba_emt else "emt"
    with pytest.raises(ValueError, match=rf"no_tracking/tracking\.csv: file not found; method "
                                         rf"'{method}' needs EM tracker poses"):
        run(read_dataset(root), progress=False)


@pytest.mark.parametrize("run", [run_ba_emt, run_emt])
@pytest.mark.parametrize(("change", "message"), [
    (lambda d: {"pose_valid": None}, r"needs the tracker's camera poses .*got None"),
    (lambda d: {"cam_from_world": d.cam_from_world[:-2]},
     rf"cam_from_world must hold one pose .* shape \({N}, 6\), got \({N - 2}, 6\)"),
    (lambda d: {"pose_valid": d.pose_valid[:, None]}, rf"pose_valid must be \({N},\) booleans"),
    (lambda d: {"cam_from_world": np.where(np.arange(N)[:, None] == 7, np.nan,
                                           d.cam_from_world)},
     r"the tracker pose of frame 7 \(row 7 of cam_from_world\) is marked valid but holds NaN"),
])
def test_unusable_tracker_poses_are_refused_naming_the_dataset(base, run, change, message):
    ds = read_dataset(base)
    bad = dataclasses.replace(ds, **change(ds))
    with pytest.raises(ValueError, match=rf"base: method '(ba-emt|emt)'.*{message}"):
        run(bad, progress=False)


def test_one_frame_is_refused_as_such(base, work):
    root = work / "one"
    if not root.exists():
        shutil.copytree(base, root)
        for f in sorted((root / "frames").iterdir())[1:]:
            f.unlink()
        for name in ("frames.csv", "ground_truth.csv"):
            lines = (root / name).read_text().splitlines(keepends=True)
            (root / name).write_text("".join(lines[:2]))
    ds = read_dataset(root)
    assert len(ds.frames) == 1
    for run in (run_emt, run_ba_emt, run_ba):
        with pytest.raises(ValueError, match=r"one: method '(emt|ba-emt|ba)' registers pairs "
                                             r"of frames, and the dataset has 1 frame$"):
            run(ds, progress=False)


# ---- B6 + A3: every BundleOptions field checked up front ------------------------------------


BAD_OPTIONS = [
    ({"max_points_per_pair": 0}, r"BundleOptions\.max_points_per_pair must be an integer >= 1"),
    ({"max_points_per_pair": -1}, r"BundleOptions\.max_points_per_pair must be an integer >= 1"),
    ({"max_points_per_pair": 2.5}, r"BundleOptions\.max_points_per_pair .*got 2\.5"),
    ({"seed": -1}, r"BundleOptions\.seed must be an integer >= 0"),
    ({"window": 0}, r"BundleOptions\.window must be an integer >= 1, got 0$"),
    ({"window": 2.5}, r"BundleOptions\.window must be an integer"),
    ({"pair_selection": "window", "window": -3}, r"BundleOptions\.window must be"),
    ({"min_overlap": float("nan")}, r"BundleOptions\.min_overlap must be a fraction in \(0, 1\]"),
    ({"min_overlap": 5.0}, r"BundleOptions\.min_overlap must be a fraction in \(0, 1\]"),
    ({"min_overlap": 0.0}, r"BundleOptions\.min_overlap must be a fraction in \(0, 1\]"),
    ({"max_pairs_per_frame": -3}, r"BundleOptions\.max_pairs_per_frame must be an integer >= 0"),
    ({"min_pair_separation": -1}, r"BundleOptions\.min_pair_separation must be an integer >= 0"),
    ({"min_pair_separation": True}, r"BundleOptions\.min_pair_separation must be an integer"),
    ({"plane_std_max_frames": -1}, r"BundleOptions\.plane_std_max_frames must be an integer"),
    ({"motion_gate_chi2": float("nan")}, r"BundleOptions\.motion_gate_chi2 must be > 0"),
    ({"motion_gate_chi2": "x"}, r"BundleOptions\.motion_gate_chi2 must be > 0"),
    ({"pair_selection": "every"}, r"BundleOptions\.pair_selection must be 'all', 'window' or "),
    ({"emt_sigma": (1.0, 2.0)}, r"BundleOptions\.emt_sigma must be 6 finite"),
    ({"features": FeatureOptions(detector="surf")},
     r"BundleOptions\.features\.detector must be 'sift' or 'orb'"),
    ({"features": None}, r"BundleOptions\.features must be a FeatureOptions, got NoneType"),
    ({"sigma_v_px": -1.0}, r"BundleOptions\.sigma_v_px"),
    ({"max_iterations": 0}, r"BundleOptions\.max_iterations"),
    ({"num_threads": 0}, r"BundleOptions\.num_threads"),
    ({"loss": "l1"}, r"BundleOptions\.loss"),
]


@pytest.mark.parametrize("run", [run_ba_emt, run_emt, run_ba])
@pytest.mark.parametrize(("fields", "message"), BAD_OPTIONS,
                         ids=[str(f) for f, _ in BAD_OPTIONS])
def test_bad_options_are_refused_before_the_front_end(base, monkeypatch, run, fields, message):
    def front_end(*args, **kwargs):
        raise AssertionError("the front end ran before the options were checked")

    monkeypatch.setattr(bundle, "register_frames", front_end)
    options = dataclasses.replace(BundleOptions(), **fields)
    with pytest.raises(ValueError, match=message):
        run(read_dataset(base), progress=False, options=options)


def test_matching_options_changed_after_construction_are_refused(base, monkeypatch):
    monkeypatch.setattr(bundle, "register_frames", lambda *a, **k: pytest.fail("front end"))
    options = BundleOptions()
    options.matching.min_inliers = 2
    with pytest.raises(ValueError, match=r"BundleOptions\.matching\.min_inliers: expected an "
                                         r"integer >= 4, got 2"):
        run_ba_emt(read_dataset(base), progress=False, options=options)


def test_options_of_another_type_are_refused(base):
    with pytest.raises(ValueError, match=r"options must be a BundleOptions, got dict"):
        run_emt(read_dataset(base), progress=False, options={"window": 2})


def test_no_limit_on_pairs_per_frame_is_allowed(base):
    ds = read_dataset(base)
    limited = run_emt(ds, progress=False, options=BundleOptions(
        pair_selection="emt-guided", max_pairs_per_frame=0))
    free = run_emt(ds, progress=False, options=BundleOptions(
        pair_selection="emt-guided", max_pairs_per_frame=None, min_pair_separation=0))
    assert free.details["pairs"]["attempted"] > limited.details["pairs"]["attempted"]


# ---- B7: origin near the plane; a singular frame ----------------------------------------------


def test_origin_near_plane_criterion():
    """Cameras 30 mm from the plane z = dist (normal along the optical axes, +z), the origin
    dist from it on their side: recentred when dist < ORIGIN_PLANE_FRACTION * 30."""
    poses = np.zeros((5, 6))
    poses[:, 3] = np.linspace(-5, 5, 5)

    def scene(dist):  # camera centres (-x, 0, dist - 30); pi = n / d for z - dist = 0
        return poses + [0, 0, 0, 0, 0, 30 - dist], np.array([0, 0, -1 / dist])

    assert not origin_near_plane(*scene(30))  # the paper's virtual camera among the cameras
    assert origin_near_plane(*scene(1))  # D / d = 30
    bound = 30 * ORIGIN_PLANE_FRACTION
    assert not origin_near_plane(*scene(bound * 1.01))
    assert origin_near_plane(*scene(bound * 0.99))
    far, near = scene(200), scene(-0.5)  # far behind the cameras; just beyond the plane
    assert not origin_near_plane(*far) and origin_near_plane(*near)
    assert origin_near_plane(poses, np.array([np.inf, 0, 0]))  # the plane through the origin
    assert not origin_near_plane(poses, np.zeros(3))  # the plane at infinity
    world = tracked_world(scene(1)[0], plane=scene(1)[1])
    assert world is not None and np.allclose(world.centre, [0, 0, -29])  # the middle camera
    assert np.array_equal(world.rotation, np.eye(3))
    assert tracked_world(scene(1)[0]) is None  # no plane given: as before
    assert tracked_world(scene(30)[0], plane=scene(30)[1]) is None


@pytest.fixture(scope="module")
def near_plane(base, work):
    """The tracker's origin moved 29 mm towards the plane: 1 mm from it, the cameras ~29 mm."""
    def shift(rows):
        for r in rows:
            r[3] = repr(float(r[3]) - 29.0)
        return rows

    return read_dataset(tracking_variant(base, work / "near_plane", shift))


def test_ba_emt_and_emt_recentre_a_world_whose_origin_is_near_the_plane(near_plane, base):
    truth = np.array(json.loads((near_plane.root / "truth_plane.json").read_text())["plane"])
    shifted = near_plane.cam_from_world.copy()  # truth plane moved with the origin: d = 1 mm
    d = 1 / np.linalg.norm(truth) - 29.0
    assert 0.5 < d < 1.5 and origin_near_plane(shifted, truth / np.linalg.norm(truth) / d)
    r = run_ba_emt(near_plane, progress=False)
    assert set(r.status) == {"placed"}
    assert e_M(r, near_plane) < 1.0
    assert 1 / np.linalg.norm(r.plane) == pytest.approx(d, abs=0.5)  # in the tracker's world
    emt = run_emt(near_plane, progress=False)
    assert set(emt.status) == {"placed"}
    # as good as on the same recording with the tracker's origin where it was (the tracker
    # noise, not the origin, sets the EMT baseline's error; measured 35.8 px near the plane)
    ds = read_dataset(base)
    assert e_M(emt, near_plane) < 1.25 * e_M(run_emt(ds, progress=False), ds)


def test_a_singular_frame_is_left_unplaced_not_the_whole_table():
    K = np.array([[300.0, 0, 200], [0, 300, 200], [0, 0, 1]])
    plane = np.array([0.0, 0.0, -1 / 30])  # z = 30
    poses = np.zeros((5, 6))
    poses[:, 3] = np.linspace(-4, 4, 5)
    poses[2, 5] = -30.0  # frame 2's centre (x, 0, 30): on the plane
    with pytest.raises(ValueError, match="singular"):
        _core.frame_to_reference(poses, plane, K)
    G = predicted_homographies(poses, plane, K)
    assert np.isnan(G[2]).all() and np.isfinite(G[[0, 1, 3, 4]]).all()
    expected = _core.frame_to_reference(poses[[0, 1, 3, 4]], plane, K)
    np.testing.assert_array_equal(G[[0, 1, 3, 4]], expected)
    # the reference itself singular: the first regular frame becomes the reference
    G = predicted_homographies(poses[2:], plane, K)
    assert np.isnan(G[0]).all()
    np.testing.assert_allclose(G[1], np.eye(3), atol=1e-12)
    with pytest.raises(ValueError, match=r"frame 0, the reference, cannot be placed: its "
                                         r"homography through the estimated plane is singular"):
        predicted_homographies(poses[2:], plane, K, reference=0)
    # no pose at all: every row NaN (before: frame 0 without a pose raised)
    assert np.isnan(predicted_homographies(np.full((3, 6), np.nan), plane, K)).all()
    assert UNPLACED_SINGULAR.startswith("unplaced: ")
