"""Checks after a fusion: do the tracker and the images agree, is the geometry plausible, did the
solver converge? They flag what the costs cannot: tracker data in another convention than the
dataset contract's (quaternions w first, metres, an inverted hand-eye) still gives a usable
mosaic, because the images dominate it, but wrong poses.csv and plane.json.

The EMT prior (seed 000 Eq. 19) assumes the tracker's camera poses scatter around the true ones
by ``emt_sigma`` per axis. After BAVis+EMT or LBAVis+EMT the estimate follows the images where
they constrain it, so the per-axis difference estimate - tracker, divided by emt_sigma, has an
RMS near 1 for a tracker as noisy as assumed, and grows with the disagreement. Measured on the
simulator (median over frames of the larger of the rotation and translation ratios; SYN and
hand-held sequences, ba-emt): 0.7-0.8 at the assumed noise, 1.3 / 1.9 / 2.6 / 3.9 at 2 / 3 / 4 / 6
times it; quaternions stored w first 4-16 (8.4 on the SYN circle, ba-emt and lba-emt alike);
hand_eye.txt inverted ~4 for a 60 deg / 20 mm hand-eye, but ~1 for the simulator's default
4 deg / 6 mm one, which this check cannot tell from noise (README). Translations in metres agree
(everything shrinks by 1000) but put the plane ~0.1 mm from the cameras.
"""

from __future__ import annotations

import copy
import numbers
from collections.abc import Callable

import numpy as np

from fusedmosaic import _core
from fusedmosaic.estimation.plane import MIN_BASELINE_RATIO, baseline_ratio, camera_baseline_mm
from fusedmosaic.estimation.world import poses_to_aligned, tracked_world

# Above this ratio of the tracker-estimate disagreement to the prior's noise, a warning: at
# twice the assumed noise the prior weighs the tracker 4x too much (~1.3 measured there).
MAX_NOISE_RATIO = 2.0
# Camera-plane distances an endoscope images a surface at (fetoscopes: 10-50 mm); outside,
# the tracker's unit is the likely cause.
PLANE_DISTANCE_RANGE_MM = (1.0, 2000.0)
# Above this relative standard deviation of pi (sqrt(trace(Cov_pi)) / |pi| given the costs) the
# images barely observe the plane (as SequentialOptions.startup_max_plane_std): a 50-frame
# hand-held sequence through a 60 px field stop registered 2 pairs, 5.3, plane 7.8 mm for 29,
# ba-emt / lba-emt e_M 166 px against the tracker alone's 91. Normal runs: 0.002-0.11.
MAX_PLANE_RELATIVE_STD = 0.25
# motion_prior_agreement: above this ratio of the tracker's squared departures from constant
# velocity (median, per component) to what Sigma_p and Sigma_EMT allow, a warning; from fewer
# triples of tracked frames, not judged.
MAX_MOTION_DEPARTURE = 3.0
MIN_MOTION_TRIPLES = 8
TRACKING_CONVENTIONS = ("tracking.csv holds tracker_from_sensor (not its inverse) with "
                        "quaternions x, y, z, w and translations in mm")
CONVENTIONS = TRACKING_CONVENTIONS + ", and hand_eye.txt holds sensor_from_camera (not its inverse)"
# ... and the clocks: video frames timed at a wrong rate (a header's 30 fps for 25) pair the
# frames with other samples, read as the same disagreement (ba-emt 7.9 x the noise).
TIMING = (", and that the frames' times match the tracker's (frames.csv or --fps, "
          "--tracker-time-offset)")
CONVENTIONS_AND_TIMING = CONVENTIONS + TIMING
# What to do about a tracker that disagrees with the images: {} names how to give its noise.
TRACKER_NOISE_ADVICE = ("If the tracker is that noisy, give its noise ({}); otherwise check that "
                        + CONVENTIONS_AND_TIMING)
# ... for a dataset without hand_eye.txt: the advice above blamed the contents of a file that is
# not there (a hand_eye.txt saved as hand_eye.txt.txt; review 47)
NO_HAND_EYE_ADVICE = ("There is no hand_eye.txt: the hand-eye transform was taken as the "
                      "identity (the camera at the tracker's sensor); if the camera is not there, "
                      "give sensor_from_camera as hand_eye.txt (calibrate measures it). If the "
                      "tracker is that noisy, give its noise ({}); otherwise check that "
                      + TRACKING_CONVENTIONS + TIMING)


def default_emt_sigma() -> np.ndarray:
    """The EMT prior's standard deviations (rad x3, mm x3) when none are given (the paper's)."""
    return np.asarray(_core.BundleAdjusterOptions().emt_sigma, np.float64)


def check_emt_sigma(sigma, what: str = "emt_sigma") -> tuple[float, ...]:
    """Six finite standard deviations > 0 (rad x3, mm x3), as a tuple; ValueError otherwise."""
    values = np.asarray(sigma, dtype=np.float64).ravel() if sigma is not None else None
    if values is None or values.size != 6 or not (np.isfinite(values).all() and
                                                  (values > 0).all()):
        raise ValueError(f"{what} must be 6 finite standard deviations > 0 (rad x3, mm x3), "
                         f"got {sigma!r}")
    return tuple(float(v) for v in values)


def tracker_agreement(poses: np.ndarray, tracker_poses: np.ndarray, tracker_valid: np.ndarray,
                      plane, emt_sigma=None, *, source: str = "tracking.csv",
                      plane_relative_std: float | None = None,
                      registered_pairs: int | None = None, hand_eye_given: bool = True) -> dict:
    """How far the estimated cam_from_world poses (N, 6) lie from the tracker's (N, 6; valid
    (N,)), per axis, against the prior's noise ``emt_sigma`` (None: the default), how far the
    plane lies from the cameras, and whether the images observe it (``plane_relative_std``, of
    ``registered_pairs``; None: not judged). Returns the figures and "warnings" (messages
    naming ``source``; empty when all is plausible). ``hand_eye_given`` False: the tracker's
    poses had no hand_eye.txt (the identity), which a disagreement's advice then says."""
    sigma = default_emt_sigma() if emt_sigma is None else np.asarray(emt_sigma, np.float64)
    poses = np.asarray(poses, np.float64)
    tracker_poses = np.asarray(tracker_poses, np.float64)
    ok = (np.isfinite(poses).all(axis=1) & np.isfinite(tracker_poses).all(axis=1)
          & np.asarray(tracker_valid, bool))
    out: dict = {"frames": int(ok.sum()), "warnings": []}
    if not ok.any():
        return out
    # Compared in the world the EMT prior works in (world.tracked_world: centred on a tracked
    # camera when the tracker's origin is far): t of cam_from_world carries the rotation
    # noise times the distance from the origin, so with a field generator 300 mm away a
    # consistent tracker read 3.2 x its noise (ba-emt, aligned, 0.82).
    world = tracked_world(tracker_poses, ok)
    aligned = poses_to_aligned(poses[ok], world), poses_to_aligned(tracker_poses[ok], world)
    diff = np.empty((int(ok.sum()), 6))
    for i, (x, z) in enumerate(zip(*aligned, strict=True)):
        relative = (_core.rotation_from_angle_axis(x[:3])
                    @ _core.rotation_from_angle_axis(z[:3]).T)
        diff[i, :3] = _core.angle_axis_from_rotation(relative)
        diff[i, 3:] = x[3:] - z[3:]
    rms = lambda a: np.sqrt(np.mean(a**2, axis=1))  # noqa: E731  per frame, over 3 axes
    rotation_deg = float(np.degrees(np.median(rms(diff[:, :3]))))
    translation_mm = float(np.median(rms(diff[:, 3:])))
    ratio = float(max(np.median(rms(diff[:, :3] / sigma[:3])),
                      np.median(rms(diff[:, 3:] / sigma[3:]))))
    out.update(rotation_rms_deg=rotation_deg, translation_rms_mm=translation_mm,
               noise_ratio=ratio, emt_sigma=sigma.tolist())
    if ratio > MAX_NOISE_RATIO:
        out["warnings"].append(
            f"{source}: the tracker disagrees with the images: the adjusted camera poses differ "
            f"from the tracker's by {rotation_deg:.2f} deg / {translation_mm:.2f} mm per axis "
            f"(median over {out['frames']} frames), {ratio:.1f} x the noise the EMT prior "
            f"assumes ({np.degrees(sigma[:3].max()):.2g} deg / {sigma[3:].max():.2g} mm). "
            + (TRACKER_NOISE_ADVICE if hand_eye_given else NO_HAND_EYE_ADVICE).format(
                "--tracker-rot-sigma / --tracker-trans-sigma; calibrate measures it")
            + ". The mosaic follows the images; poses.csv and plane.json are unreliable")
    if plane is not None and np.isfinite(plane).all() and np.linalg.norm(plane) > 0:
        distance = float(np.median([_core.camera_plane_distance(x, np.asarray(plane, float))
                                    for x in poses[ok]]))
        out["plane_distance_mm"] = distance
        ratio = baseline_ratio(poses[ok], np.asarray(plane, float))
        out["baseline_ratio"] = ratio if np.isfinite(ratio) else None
        low, high = PLANE_DISTANCE_RANGE_MM
        if ratio < MIN_BASELINE_RATIO:
            # (before the unit check: a still camera's plane is out of range, the unit is not
            # the cause)
            out["warnings"].append(
                f"{source}: the camera barely translated: its centres lie within "
                f"{camera_baseline_mm(poses[ok]):.2g} mm of each other, {100 * ratio:.2g} % of "
                f"the plane's depth along their axes (distance {distance:.3g} mm, median), so "
                "the images show "
                "no parallax and the plane's distance is not measured (a camera held still or "
                "only turning about its axis). The mosaic does not depend on it; plane.json's "
                "distance and poses.csv's translations are unreliable")
        elif not low <= abs(distance) <= high:
            # (before the plane's uncertainty: a tracker in metres puts the plane at 0.03 mm
            # with a relative std of 12 over 253 registered pairs, which blamed the
            # registrations; review)
            unit = " (metres?)" if abs(distance) < low else " (micrometres?)"
            loose = ("" if plane_relative_std is None
                     or not plane_relative_std > MAX_PLANE_RELATIVE_STD else
                     f"; its relative standard deviation is {plane_relative_std:.2g}")
            out["warnings"].append(
                f"{source}: the plane lies {distance:.3g} mm from the cameras (median), outside "
                f"the {low:g}-{high:g} mm an endoscope views a surface from: check that the "
                f"tracker's translations are in mm{unit}, and camera.yaml's focal length in "
                "pixels (a plane fitted to few or wrong registrations, or through a wrong lens, "
                f"is out of scale too{loose}); poses.csv and plane.json are out of scale")
        elif plane_relative_std is not None and plane_relative_std > MAX_PLANE_RELATIVE_STD:
            pairs = "" if registered_pairs is None else f" from {registered_pairs} registered pairs"
            out["warnings"].append(
                f"{source}: the images barely observe the plane: its relative standard "
                f"deviation{pairs} is "
                f"{'unbounded' if np.isinf(plane_relative_std) else f'{plane_relative_std:.2g}'}"
                f" (above {MAX_PLANE_RELATIVE_STD:g}; plane {distance:.3g} mm from the cameras, "
                "or assumed there when unbounded): frames "
                "placed without a registered pair (prior-only) follow the tracker through this "
                "plane and may be far off, and plane.json is unreliable (too few registrations: "
                "a small field of view, weak texture, or frames too far apart; unbounded, also a "
                "camera that barely translated while lba-emt's start-up watched, its plane then "
                "assumed nominal_plane_distance_mm away)")
    return out


def motion_prior_agreement(samples: np.ndarray, times, motion_sigma, emt_sigma=None, *,
                           source: str = "tracking.csv") -> dict:
    """Does Sigma_p allow the motion the tracker saw? The tracker's departures from constant
    velocity over each triple of consecutive tracked frames (motion.triple_departures, whitened
    by Sigma_p and the samples' own noise Sigma_EMT, in the prior's world) have a squared median
    of chi2(1)'s when both are right; per component, their ratio ("departure_scale"). Above
    MAX_MOTION_DEPARTURE on a component, a warning: a Sigma_p far stiffer than the recording's
    motion makes the fusion shrink the motion (SYN 40 frames with Sigma_p from a 150-frame SYN
    recording, 13x slower: plane 11 mm instead of 30, cameras 9 mm off, no other sign) -- or
    the tracker is noisier than emt_sigma. Returns the figures and "warnings"."""
    from fusedmosaic.estimation.motion import CHI2_1_MEDIAN, triple_departures

    samples = np.asarray(samples, np.float64)
    samples = poses_to_aligned(samples, tracked_world(samples))
    times = np.asarray(times, np.float64)
    nominal = float(np.median(np.diff(times))) if len(times) > 1 else None
    sigma = default_emt_sigma() if emt_sigma is None else np.asarray(emt_sigma, np.float64)
    departure = triple_departures(samples, times, nominal, motion_sigma=motion_sigma,
                                  emt_sigma=sigma)
    w = np.array([d[0] for k in range(2, len(samples))
                  if (d := departure(k - 2, k - 1, k)) is not None]).reshape(-1, 6)
    out: dict = {"triples": len(w), "warnings": []}
    if len(w) < MIN_MOTION_TRIPLES:
        return out
    scale = np.median(w**2, axis=0) / CHI2_1_MEDIAN
    out["departure_scale"] = scale.tolist()
    worst = int(np.argmax(scale))
    if scale[worst] > MAX_MOTION_DEPARTURE:
        axis = ("rx", "ry", "rz", "tx", "ty", "tz")[worst]
        out["warnings"].append(
            f"{source}: the tracker's motion departs from constant velocity "
            f"{np.sqrt(scale[worst]):.1f} x as much as the motion prior Sigma_p and the "
            f"tracker's noise allow (component {axis}, median over {len(w)} triples of "
            "frames): a Sigma_p too stiff for this motion (--motion-sigma-from a recording "
            "of another pace or kind) makes the fusion shrink the motion, and poses.csv and "
            "plane.json come out of scale; estimate it from a recording of this motion, or "
            "leave the default. Or the tracker is noisier than the EMT prior assumes: give "
            "its noise (--tracker-rot-sigma / --tracker-trans-sigma; calibrate measures it)")
    return out


def add_tracker_agreement(details: dict, poses: np.ndarray, dataset, plane,
                          emt_sigma=None, motion_sigma=None) -> None:
    """tracker_agreement of a pose method's result on ``dataset`` (its tracking.csv poses) into
    its ``details``: "tracker_agreement", and the warnings first in "warnings". The details'
    "plane_relative_std" (None or NaN: not computed) and pairs.registered judge whether the
    images observe the plane. With a ``motion_sigma`` the user gave (not the paper's default,
    which is loose), also motion_prior_agreement: "motion_prior_agreement"."""
    std = details.get("plane_relative_std")
    source = str(dataset.root / "tracking.csv")
    agreement = tracker_agreement(poses, dataset.cam_from_world, dataset.pose_valid, plane,
                                  emt_sigma, source=source,
                                  plane_relative_std=None if std is None or np.isnan(std) else std,
                                  registered_pairs=details.get("pairs", {}).get("registered"),
                                  hand_eye_given=getattr(dataset, "hand_eye_file", "") is not None)
    warnings = agreement.pop("warnings")
    if motion_sigma is not None:
        samples = np.where(np.asarray(dataset.pose_valid, bool)[:, None],
                           dataset.cam_from_world, np.nan)
        motion = motion_prior_agreement(samples, dataset.timestamps, motion_sigma, emt_sigma,
                                        source=source)
        stiff = motion.pop("warnings")
        if stiff:  # the likelier cause of a disagreement too: said first, and there
            warnings = stiff + [w + " (or, first, the motion prior: see the warning before)"
                                if w.startswith(f"{source}: the tracker disagrees") else w
                                for w in warnings]
        details["motion_prior_agreement"] = motion
    details["warnings"] = warnings + details.get("warnings", [])
    details["tracker_agreement"] = agreement


class TransferResiduals:
    """The registered points' transfer residuals (Eq. 13: frame-m inliers transferred into
    frame l through the estimated poses and plane, minus their frame-l matches; pixels, x and
    y pooled) gathered pair by pair in bounded memory: a histogram of |r| on 1 % wide bins,
    the count and the sum of squares. Their robust standard deviation (1.4826 x the median
    |r|) measures the keypoints' noise, sigma_v of the visual cost: on SYN (60 frames) 0.0908
    px at ba-emt's estimate against 0.0902 at the true homographies. ``add`` replaces the
    arrays and never mutates them (a shallow copy is a snapshot; SequentialMosaicker's
    rollback)."""

    LOW_PX, RATIO, BINS = 1e-4, 1.01, 1700  # |r| in [1e-4, ~2e3) px, beyond: the last bin

    def __init__(self) -> None:
        self.counts = np.zeros(self.BINS, np.int64)
        self.points = self.pairs = 0
        self.sum_squares = 0.0

    def add(self, cam_l, cam_m, plane, points_l, points_m, camera_matrix) -> None:
        """One pair's residuals at cam_l / cam_m (cam_from_world, (6,)) and ``plane``; the
        non-finite ones (a camera on the plane) are left out, and a pair whose poses or plane
        are not finite (an unplaced frame) as a whole."""
        if not all(np.isfinite(np.asarray(x, np.float64)).all() for x in (cam_l, cam_m, plane)):
            return
        transferred = _core.transfer_points(np.asarray(points_m, np.float64), cam_l, cam_m,
                                            plane, camera_matrix)
        d = transferred - np.asarray(points_l, np.float64)
        r = np.abs(d[np.isfinite(d).all(axis=1)]).ravel()
        if not r.size:
            return
        bins = np.log(np.maximum(r, self.LOW_PX) / self.LOW_PX) / np.log(self.RATIO)
        bins = np.minimum(bins.astype(np.int64), self.BINS - 1)
        self.counts = self.counts + np.bincount(bins, minlength=self.BINS)
        self.points += r.size // 2
        self.pairs += 1
        self.sum_squares += float(np.sum(r**2))

    @classmethod
    def of(cls, pairs, pose, plane, camera_matrix) -> TransferResiduals:
        """The residuals of `pairs` ((frame_l, frame_m, points_l, points_m)) at the poses
        `pose(frame)` and `plane`."""
        residuals = cls()
        for l, m, pl, pm in pairs:
            residuals.add(pose(l), pose(m), plane, pl, pm, camera_matrix)
        return residuals

    def copy(self) -> TransferResiduals:
        """A snapshot (add replaces, never mutates, what it holds)."""
        return copy.copy(self)

    def robust_std(self) -> float:
        """1.4826 x the median |r| (the bin's geometric centre, within 0.5 %); NaN when
        empty."""
        total = int(self.counts.sum())
        if not total:
            return float("nan")
        median_bin = int(np.searchsorted(np.cumsum(self.counts), (total + 1) / 2))
        return float(1.4826 * self.LOW_PX * self.RATIO ** (median_bin + 0.5))

    def summary(self, sigma_v_px: float) -> dict:
        """"points", "pairs", "robust_std_px", "rms_px" (NaN-free: None when empty),
        "sigma_v_px" and "ratio" (robust_std_px / sigma_v_px)."""
        out: dict = {"points": self.points, "pairs": self.pairs, "sigma_v_px": float(sigma_v_px)}
        if not self.points:
            return out | {"robust_std_px": None, "rms_px": None, "ratio": None}
        std = self.robust_std()
        return out | {"robust_std_px": std,
                      "rms_px": float(np.sqrt(self.sum_squares / (2 * self.points))),
                      "ratio": std / float(sigma_v_px)}


def visual_agreement(residuals: TransferResiduals, sigma_v_px: float, *, source: str,
                     knob: str | None) -> dict:
    """residuals.summary with "warnings": one when the residuals' robust standard deviation is
    over MAX_NOISE_RATIO x ``sigma_v_px``, the visual cost's assumed noise (``knob``: the
    option that gives it, None when the visual cost alone decides, ba's, where its scale
    weighs nothing against another cost). ``source``: the dataset, named in the message."""
    out = residuals.summary(sigma_v_px) | {"warnings": []}
    ratio = out["ratio"]
    if knob is not None and ratio is not None and ratio > MAX_NOISE_RATIO:
        out["warnings"].append(
            f"{source}: the registered points lie {out['robust_std_px']:.2f} px (robust std, "
            f"{out['points']} points) off their transfer through the adjusted poses and plane, "
            f"{ratio:.1f} x the visual cost's {sigma_v_px:g} px: the images are weighed more "
            "than their noise allows against the tracker. If the keypoints are that noisy, give "
            f"{knob} {out['robust_std_px']:.2g}; otherwise the scene is not a plane or the "
            "lens distortion is not in camera.yaml")
    return out


# sigma_v "auto" (BundleOptions / SequentialOptions.sigma_v_px, `--visual-sigma auto`; not the
# default, see SequentialOptions.sigma_v_px): the visual cost's noise measured on the recording.
# The adjustment is solved with the paper's 1 px first (Sec. 4.2), the registered points' transfer
# residuals at that estimate give their robust std (TransferResiduals), and the adjustment is
# solved again from there with it (ba-emt: all frames; lba-emt: its start-up, whose value the
# window then keeps). The paper's 1 px goes with its real fetoscopic keypoints; the simulator's
# are ~0.09 px off, so with 1 px the images were weighed 1/120 of their worth against the tracker
# and its noise leaked into the estimate as it grew: Fig. 9's max/min 1.39-3.66 over seeds 0-7 and
# 11 (4 of 9 above 2), 1.00-1.02 with the measured value (bench/bench_lba_experiments.py). From
# fewer than SIGMA_V_MIN_POINTS points the paper's value is kept; SIGMA_V_FLOOR_PX bounds the
# weight: keypoints are not localised better than ~1/20 px on real images (noise-free renderings
# measure less, and a smaller sigma_v would leave the tracker's prior no weight where the images
# see the plane). Where the images barely observe the plane, or the second solve does not
# converge, the 1 px solve is kept.
SIGMA_V_AUTO = "auto"
SIGMA_V_START_PX = 1.0
SIGMA_V_MIN_POINTS = 200
SIGMA_V_FLOOR_PX = 0.05


def check_sigma_v(value, what: str) -> float | str:
    """`value` when it is "auto" or a finite sigma_v > 0 (px), else ValueError naming `what`."""
    if isinstance(value, str) and value == SIGMA_V_AUTO:
        return value
    if not (isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)
            and np.isfinite(value) and value > 0):
        raise ValueError(f"{what} must be 'auto' (measured on the recording) or a standard "
                         f"deviation > 0 in pixels, got {value!r}")
    return float(value)


def starting_sigma_v(value) -> float:
    """The sigma_v an adjustment starts with: the given one, or SIGMA_V_START_PX for "auto"."""
    return SIGMA_V_START_PX if value == SIGMA_V_AUTO else float(value)


def given_sigma_v_report(sigma_v_px) -> dict:
    """report.json "visual_sigma" before (or without) a measurement: the option's mode ("given"
    or "auto") and the sigma_v an adjustment starts with."""
    return {"mode": SIGMA_V_AUTO if sigma_v_px == SIGMA_V_AUTO else "given",
            "sigma_v_px": starting_sigma_v(sigma_v_px)}


def auto_sigma_v(start_px: float, termination: str, plane_relative_std: float,
                 residuals: Callable[[], TransferResiduals], what: str) -> tuple[float, dict]:
    """sigma_v "auto" after the first solve of `what` (with `start_px`, its `termination` and
    pi's `plane_relative_std`, NaN when not estimated): the value to solve again with, and its
    report (measured_sigma_v). `start_px` (nothing to solve again) when it did not converge
    (its residuals are then the distance to the minimum, not the keypoints' noise; its
    iteration warning stands; `residuals` is not called), or when the images barely observe
    the plane (relative std above MAX_PLANE_RELATIVE_STD: weighed up, the few pairs sent the
    plane off, a 45 px field stop with 90 pairs: std 2.4 at 1 px, unbounded at 0.15 px,
    singular homographies; review Z, session 49)."""
    if termination != "CONVERGENCE":
        return start_px, {"mode": SIGMA_V_AUTO, "start_px": start_px, "sigma_v_px": start_px,
                          "note": f"{what} ended {termination}: the keypoints' noise not "
                                  f"measured; the paper's {start_px:g} px kept"}
    sigma, report = measured_sigma_v(residuals(), start_px)
    std = plane_relative_std
    if sigma != start_px and not (np.isnan(std) or std <= MAX_PLANE_RELATIVE_STD):
        return start_px, report | {
            "sigma_v_px": start_px,
            "note": f"the images barely observe the plane (relative std {std:.2g} at "
                    f"{start_px:g} px, above {MAX_PLANE_RELATIVE_STD:g}): weighed up, its few "
                    f"pairs could send it off; the paper's {start_px:g} px kept"}
    return sigma, report


def measured_sigma_v(residuals: TransferResiduals, start_px: float = SIGMA_V_START_PX
                     ) -> tuple[float, dict]:
    """sigma_v "auto": the residuals' robust std (at least SIGMA_V_FLOOR_PX), or `start_px`
    from fewer than SIGMA_V_MIN_POINTS points; and the report of it (report.json
    "visual_sigma": "mode", "sigma_v_px" used, "measured_px", "points", "pairs", "note")."""
    std = residuals.robust_std() if residuals.points else float("nan")
    report = {"mode": SIGMA_V_AUTO, "start_px": float(start_px),
              "measured_px": float(std) if np.isfinite(std) else None,
              "points": int(residuals.points), "pairs": int(residuals.pairs)}
    if residuals.points < SIGMA_V_MIN_POINTS or not np.isfinite(std):
        sigma = float(start_px)
        report["note"] = (f"{residuals.points} registered points (< {SIGMA_V_MIN_POINTS}): too "
                          f"few to measure the keypoints' noise; the paper's {start_px:g} px kept")
    elif std < SIGMA_V_FLOOR_PX:
        sigma = SIGMA_V_FLOOR_PX
        report["note"] = (f"measured {std:.3g} px, below the {SIGMA_V_FLOOR_PX:g} px floor "
                          "(keypoints are not localised better on real images)")
    else:
        sigma = float(std)
    return sigma, report | {"sigma_v_px": sigma}


def add_robot_agreement(details: dict, source: str, pixel_size_um: float | None,
                        frame_times: str = "frames.csv") -> None:
    """robot_agreement of a kalman-robot result from its ``details`` (trajectories_px X_m and
    X_r, confidences c_img; frames whose c_img is None were not processed and are left out,
    so a dropped frame's interval falls in the next step) into them: "robot_agreement", and
    the warnings first in "warnings"."""
    c_img = details["confidences"]["c_img"]
    rows = [k for k, c in enumerate(c_img) if c is not None]
    paths = details["trajectories_px"]
    agreement = robot_agreement(paths["X_m"][rows], paths["X_r"][rows],
                                np.array([c_img[k] for k in rows], float), source=source,
                                pixel_size_um=pixel_size_um, frame_times=frame_times)
    details["warnings"] = agreement.pop("warnings") + details.get("warnings", [])
    details["robot_agreement"] = agreement


def solver_warning(summary, max_iterations: int, what: str = "the adjustment", *,
                   knob: str = "max_iterations", uses_tracker: bool = True,
                   noise_ratio: float | None = None) -> str | None:
    """A message when Ceres stopped without converging (iteration limit, or failure), else
    None. ``summary`` is a SolveSummary (or its as_dict(), with ba / ba-emt's
    "continued_from" when Levenberg-Marquardt's stop was solved on with dogleg) or a
    WindowStepSummary; a field it lacks (e.g. the message of an older build's or a test's
    summary) reads as None. At the iteration limit the message names the likely cause: with
    the run's tracker_agreement ``noise_ratio`` the tracker only when it disagrees (above
    MAX_NOISE_RATIO), else the cost's conditioning, and ``knob``, the option that raises the
    limit; without one (None: not judged) a disagreeing tracker as a common cause, and no
    tracker when the cost has no tracker term (``uses_tracker`` False: ba)."""
    get = summary.get if isinstance(summary, dict) else (
        lambda key: getattr(summary, key, None))
    termination = get("termination")
    if termination in ("CONVERGENCE", "USER_SUCCESS", "NO_RESIDUALS", None):
        return None
    if termination == "NO_CONVERGENCE":
        first = get("continued_from")
        also = ""
        if first and first.get("iterations") is not None and get("iterations") is not None:
            also = (", and so did its continuation from there with Powell's dogleg "
                    f"({get('iterations') - first['iterations']} more iterations)")
        if noise_ratio is not None and not np.isfinite(noise_ratio):
            noise_ratio = None
        if not uses_tracker:
            cause = f"raise {knob}"
        elif noise_ratio is None:
            cause = f"a tracker disagreeing with the images is a common cause; else raise {knob}"
        elif noise_ratio > MAX_NOISE_RATIO:
            cause = (f"the tracker disagrees with the images, {noise_ratio:.1f} x the EMT prior's "
                     "noise in tracker_agreement: the likely cause, see its warning; else raise "
                     f"{knob}")
        else:
            # (80 SYN frames tracked at the last 5 only, or 5 mm from the plane, with a tracker
            # at 0.85 / 0.73 x its noise: Levenberg-Marquardt stopped at 100 iterations)
            cause = (f"not the tracker, which agrees with the images at {noise_ratio:.2f} x the "
                     "EMT prior's noise in tracker_agreement: the costs hold some directions only "
                     "weakly, e.g. the scale and the plane when few frames are tracked or the "
                     f"camera is close to the plane; raise {knob}")
        return (f"{what} stopped at its iteration limit ({max_iterations}) before converging"
                f"{also}: the estimates are not at the cost's minimum ({cause})")
    message = get("message")
    return f"{what} failed: Ceres {termination}" + (f": {message}" if message else "")


# pCLE (seed 004): the robot's steps against the image registrations', on the frames the image
# side trusts (c_img > 0.5) that move >= 2 px. Measured on the simulator (circle, spiral, a
# slow 5 um/frame path; robot noise included): median length ratio 0.99-1.15, median cosine
# 0.97-1.0; robot positions in mm instead of um 0.001; x and y swapped cosine -0.57, y flipped
# 0.19 (a 40-frame circle).
ROBOT_RATIO_RANGE = (0.5, 2.0)
MIN_ROBOT_COSINE = 0.7
MIN_ROBOT_STEPS = 5  # fewer compared steps: no check


def robot_agreement(image_px: np.ndarray, robot_px: np.ndarray, c_img, *,
                    source: str = "robot.csv", pixel_size_um: float | None = None,
                    frame_times: str = "frames.csv") -> dict:
    """Do the robot's positions (N, 2 px, X_r) move like the image registrations' chain (N, 2,
    X_m)? Per step, on steps whose image confidence c_img (N,) exceeds 0.5 and that move >= 2
    px: the median ratio of the step lengths (robot / image) and the median cosine between the
    steps. Returns the figures and "warnings" (naming ``source``). ``frame_times``
    (Dataset.frame_times): where the frame times the robot is sampled at come from; when not
    frames.csv (an assumed frame rate) the warnings name it too, a wrong rate being as likely a
    cause as the robot's units or axes."""
    d_image = np.diff(np.asarray(image_px, np.float64), axis=0)
    d_robot = np.diff(np.asarray(robot_px, np.float64), axis=0)
    c = np.asarray(c_img, np.float64)[1:]
    length = np.linalg.norm(d_image, axis=1)
    with np.errstate(invalid="ignore"):
        ok = (np.isfinite(d_image).all(axis=1) & np.isfinite(d_robot).all(axis=1) & (c > 0.5)
              & (length >= 2.0))
    out: dict = {"steps": int(ok.sum()), "warnings": []}
    if ok.sum() < MIN_ROBOT_STEPS:
        return out
    robot_length = np.linalg.norm(d_robot[ok], axis=1)
    ratio = float(np.median(robot_length / length[ok]))
    moving = robot_length > 0
    cosine = float(np.median(np.sum(d_image[ok][moving] * d_robot[ok][moving], axis=1)
                             / (length[ok][moving] * robot_length[moving]))) if moving.any() \
        else float("nan")
    out.update(length_ratio=ratio, median_cosine=cosine)
    pixel = "" if pixel_size_um is None else f" ({pixel_size_um:g} µm/px)"
    times = ("" if frame_times.startswith("frames.csv") else
             f", or the frame times the robot is sampled at, {frame_times}: give the "
             "recording's frame rate (--fps) or a frames.csv")
    low, high = ROBOT_RATIO_RANGE
    if not low <= ratio <= high:
        unit = (" (x 0.001: mm instead of µm?)" if 0.0005 < ratio < 0.002 else
                " (x 1000: nm?)" if 500 < ratio < 2000 else "")
        out["warnings"].append(
            f"{source}: the robot's steps are {ratio:.3g} x the image registrations' (median "
            f"over {out['steps']} confident steps), where 1 is expected{unit}: check that the "
            f"robot positions are in µm and camera.yaml's pixel_size_um{pixel}{times}")
    if cosine < MIN_ROBOT_COSINE:  # also False for NaN (a robot standing still: the ratio)
        out["warnings"].append(
            f"{source}: the robot moves in other directions than the images show (median "
            f"cosine {cosine:.2f} between their steps over {out['steps']} confident steps, 1 "
            "expected): check that the robot's x and y are in the image axes (x right, y down), "
            f"not swapped or flipped{times}")
    return out
