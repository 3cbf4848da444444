"""Session 46 review E: PairVis (--method pairwise) and its visual registration: the chain's
start, a lone frame without content, the break warning's count, streamed features, feature
option checks, and emt_guided_pairs' bounded work."""

import threading
import weakref

import cv2
import numpy as np
import pytest

from fusedmosaic.estimation.pairwise import chain_homographies, run_pairwise
from fusedmosaic.io import read_dataset
from fusedmosaic.registration import pair_selection
from fusedmosaic.registration.features import (
    MAX_FEATURES,
    FeatureExtractor,
    FeatureOptions,
    extract_features,
)
from fusedmosaic.registration.pair_selection import (
    MAX_OVERLAPS_PER_FRAME,
    emt_guided_pairs,
    footprint_polygons,
    kept_pairs,
    overlap_fraction,
)
from fusedmosaic.registration.pairs import MatchOptions, match_pairs
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy

SIDE = 160


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    """30 simulated SYN frames, 160x160 (every consecutive pair registers)."""
    return simulate_fetoscopy(tmp_path_factory.mktemp("pw") / "d", FetoscopyOptions(
        n_frames=30, laps=30 / 37.5, width=SIDE, height=SIDE))


def _dataset(root, n: int | None = None, replace: dict | None = None):
    """The dataset's first n frames in memory, frames k replaced by replace[k]."""
    ds = read_dataset(root)
    n = len(ds.frames) if n is None else n

    class Frames(list):
        unreadable: dict = {}

    ds.frames = Frames(ds.frames[k] for k in range(n))
    ds.frame_ids = ds.frame_ids[:n]
    for k, image in (replace or {}).items():
        ds.frames[k] = image(ds.frames[k])
    return ds


def _defocused(image):  # 20 SIFT keypoints, 6 matches with frame 1 (too few: 15)
    return cv2.GaussianBlur(image, (0, 0), 6)


def _black(image):
    return np.zeros_like(image)


def _placed(result) -> int:
    return int(np.isfinite(result.homographies).all(axis=(1, 2)).sum())


# ---- 1: the chain starts at the first frame registered to the next ----------------------------

def test_a_first_frame_with_features_that_does_not_register_moves_the_start(sequence):
    """Frame 0 defocused (it has keypoints but matches nothing): 1 of 10 frames placed, where a
    black frame 0 (no keypoints) moved the chain's start and placed 9 (review)."""
    result = run_pairwise(_dataset(sequence, 10, {0: _defocused}), progress=False)
    assert _placed(result) == 9
    why = "pair (0, 1) not registered: too few matches (6 < 15)"
    assert result.status == [f"unplaced: before the chain's first frame ({why})"] + ["placed"] * 9
    assert result.details["warnings"] == [
        "the pairwise chain starts at frame 1, the first frame registered to the next one: the "
        f"1 frame(s) before it are unplaced (frame 0: {why})"]
    np.testing.assert_array_equal(result.homographies[1], np.eye(3))
    # a black frame 0 as before, its status now naming its pair too
    black = run_pairwise(_dataset(sequence, 10, {0: _black}), progress=False)
    assert _placed(black) == 9
    assert black.status[0].startswith("unplaced: before the chain's first frame (pair (0, 1) "
                                      "not registered: too few features (0, ")


# ---- 5: a lone frame without content --------------------------------------------------------

def test_a_single_black_frame_is_refused(sequence):
    """A 1-frame dataset whose frame is black was 'placed 1/1', exit 0, a black mosaic and no
    warning (review); a single frame with content is still placed."""
    with pytest.raises(ValueError, match=r": its only frame \(0\) has no visual content to place "
                                         r"\(too few features \(0 < 15\)\)$"):
        run_pairwise(_dataset(sequence, 1, {0: _black}), progress=False)
    result = run_pairwise(_dataset(sequence, 1), progress=False)
    assert result.status == ["placed"] and _placed(result) == 1


# ---- 6: the break warning counts every unplaced frame --------------------------------------

def test_the_break_warning_counts_the_frames_before_the_start(sequence):
    """Frames 0 and 5 black of 10: 6 unplaced (0 and 5-9), the warning said 5 of 10 (review)."""
    result = run_pairwise(_dataset(sequence, 10, {0: _black, 5: _black}), progress=False)
    assert _placed(result) == 4
    assert result.details["warnings"][1].startswith(
        "the pairwise chain breaks at frame 5: pair (4, 5) not registered (too few features "
        "(")
    assert "), so 6 of 10 frames are unplaced (PairVis" in result.details["warnings"][1]


# ---- 4: features streamed, two frames at a time -------------------------------------------------

def test_pairwise_keeps_a_bounded_number_of_frames_features(sequence, monkeypatch):
    """run_pairwise held every frame's features (O(N): ~7.5 GB for a 10-minute recording;
    review); streamed, a few frames' at a time, with the same result as every frame's
    features extracted first and the pairs matched after."""
    ds = _dataset(sequence)
    cam = ds.camera
    features = extract_features(ds.frames, range(30), cam.fov_mask(), FeatureOptions(),
                                undistortion=cam.undistortion())
    matches = match_pairs(features, [(k, k + 1) for k in range(29)], (cam.width, cam.height),
                          MatchOptions())
    expected = chain_homographies([m.H_lm if m.ok else None for m in matches])
    del features, matches

    lock = threading.Lock()
    alive, peak = [0], [0]
    extract = FeatureExtractor.extract

    def dropped() -> None:
        with lock:
            alive[0] -= 1

    def counted(self, image, frame_id=0):
        f = extract(self, image, frame_id)
        with lock:
            alive[0] += 1
            peak[0] = max(peak[0], alive[0])
        weakref.finalize(f, dropped)
        return f

    monkeypatch.setattr(FeatureExtractor, "extract", counted)
    result = run_pairwise(ds, progress=False)
    assert peak[0] <= 12, peak  # (all 30 before)
    np.testing.assert_array_equal(result.homographies, expected)
    assert result.details["pairs"]["registered"] == 29
    assert result.details["pairs"]["mean_correspondences"] > 15


# ---- 2, 7c: feature options -------------------------------------------------------------------

def test_max_features_is_bounded_and_detection_errors_name_the_frame(sequence, monkeypatch):
    """--max-features accepted up to 2^31 - 1; ORB reserves memory for that many and failed
    with cv2.error: std::bad_alloc, a raw traceback (review). Capped, with the flag named; and
    a detector's cv2.error becomes a ValueError naming the frame and the option."""
    names = {"max_features": "--max-features"}
    for n in (MAX_FEATURES + 1, 2**31 - 1):
        with pytest.raises(ValueError, match=rf"^--max-features must be an integer in "
                                             rf"1..1000000 \(keypoints per frame\), got {n}$"):
            FeatureOptions(detector="orb", max_features=n).validate(names)
    FeatureOptions(detector="orb", max_features=MAX_FEATURES).validate(names)

    class OutOfMemory:
        def detectAndCompute(self, image, mask):  # noqa: N802 (OpenCV's name)
            raise cv2.error("std::bad_alloc")

    monkeypatch.setattr(FeatureExtractor, "_detector", lambda self, *a, **k: OutOfMemory())
    frame = _dataset(sequence, 1).frames[0]
    with pytest.raises(ValueError, match=r"^frame 7: ORB detection failed on the 160x160 image "
                                         r"\(std::bad_alloc\) with max_features "
                                         r"\(--max-features\) 500000; fewer keypoints"):
        FeatureExtractor(FeatureOptions(detector="orb", max_features=500_000)).extract(frame, 7)


@pytest.mark.parametrize("field", ["clahe", "mask_specular"])
def test_boolean_feature_options_are_checked(field):
    """FeatureOptions(clahe='no') applied CLAHE ('no' is truthy; review)."""
    for bad in ("no", 0, None):
        with pytest.raises(ValueError, match=rf"^{field} must be True or False, got {bad!r}$"):
            FeatureOptions(**{field: bad}).validate()
    FeatureOptions(**{field: np.bool_(True)}).validate()


# ---- 8: emt_guided_pairs' work per frame is bounded -------------------------------------------

def _all_overlaps_pairs(predicted, width, height, *, min_overlap, max_per_frame, fov_radius,
                        temporal_window, min_separation):
    """emt_guided_pairs computing every older frame's overlap (what it did before the review)."""
    polys = footprint_polygons(predicted, width, height, fov_radius)
    pairs = []
    for l, poly in enumerate(polys):
        if poly is None:
            pairs += [(l, m) for m in (l - 1,) if m >= 0]
            continue
        if l >= 1 and polys[l - 1] is None:
            pairs.append((l, l - 1))
        candidates = [(frac, m) for m in range(l) if polys[m] is not None
                      for frac in (overlap_fraction(poly, polys[m]),) if frac >= min_overlap]
        pairs += kept_pairs(l, candidates, temporal_window, max_per_frame, min_separation)
    return pairs


@pytest.mark.parametrize("scene", ["hovering", "walk", "rectangles"])
def test_emt_guided_pairs_bounds_the_overlaps_per_frame(scene, monkeypatch):
    """A scope held over one area: every footprint overlapped every other and each frame's
    overlap was computed with all older frames (2000 frames 14 s; review). Now in order of an
    upper bound, until the choice is settled or MAX_OVERLAPS_PER_FRAME: the same pairs here."""
    rng = np.random.default_rng(["hovering", "walk", "rectangles"].index(scene))
    n = 400
    G = np.tile(np.eye(3), (n, 1, 1))
    if scene == "hovering":
        G[:, :2, 2] = rng.normal(0, 5, (n, 2))
    else:
        G[:, :2, 2] = np.cumsum(rng.normal(0, 12, (n, 2)), axis=0)
        G[:, 0, 0] = G[:, 1, 1] = rng.uniform(0.8, 1.2, n)
        G[:, 2, :2] = rng.normal(0, 2e-4, (n, 2))
        G[rng.random(n) < 0.05] = np.nan
    kw = dict(min_overlap=0.3, max_per_frame=20, fov_radius=None if scene == "rectangles"
              else 150.0, temporal_window=2, min_separation=4)
    counts: dict[int, int] = {}
    overlap = pair_selection.overlap_fraction

    def counted(a, b, *args):
        counts[id(a)] = counts.get(id(a), 0) + 1
        return overlap(a, b, *args)

    monkeypatch.setattr(pair_selection, "overlap_fraction", counted)
    pairs = emt_guided_pairs(G, 320, 320, **kw)
    assert max(counts.values()) <= MAX_OVERLAPS_PER_FRAME + kw["temporal_window"]
    monkeypatch.undo()
    assert pairs == _all_overlaps_pairs(G, 320, 320, **kw)
