"""Live replay: a recorded dataset fed to a streaming mosaicker as a live source would feed it.

``fusedmosaic run DATA --method lba-emt --live`` (or ``kalman-robot``, ``ncc``, ``robot``)
answers "what would this recording have looked like live, on this machine?":

- frame k arrives at its timestamp (relative to frame 0's) and gets the newest tracker (or robot)
  sample taken at or before that time, as a live loop has it: no interpolation towards a sample
  that has not arrived yet (a sample stamped a rounding error after the frame, as a robot
  sampled at the frame times is, counts as at it); a sample older than ``max_sample_age_s`` (by
  default 3 typical sample spacings, io.tracking.sample_spacing: the offline gap rule) counts
  as none (a dropout), so the frame is placed from the images and the priors (report.json
  "live": "frames_without_sample"). A robot position is extrapolated to the frame time along
  its motion since the newest sample at least half a typical spacing before the newest one
  (io.igtl.extrapolation_base: an accurate robot held 14 ms lags the probe and the filter
  follows the lag: pCLE spiral e_M 10.5 px offline, 27.0 held, 10.5 extrapolated; along the
  last two samples, 1 ms apart for a robot reporting in pairs, an error of the newest grew 20
  times 19 ms later); a tracker pose is held (EM noise ~1 mm; extrapolating it measured no
  better on SYN: e_M 0.136 held, 0.144 extrapolated, 0.144 offline);
- frames are processed one at a time, each as soon as the previous one is done; when frames
  arrived while the mosaicker was busy, only the newest of them is processed and the others are
  dropped (a capture queue of one frame: the live view never falls behind), with the status
  "unplaced: dropped ...";
- the clock is virtual: each call's measured wall time (or ``processing_time(k)``, for what-if
  studies and tests) advances it, so the replay runs as fast as the machine allows and the drops
  are those the measured times imply. Frames are read from disk outside the timed calls.

Latency of a processed frame = waiting (arrival until the previous frame is done) + its own
processing; the result of ``add_frame`` (for lba-emt the provisional placement shown live) is
then available. The homographies written are the final ones (lba-emt: after the frame's window
step), as in the offline run.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

import numpy as np
from tqdm import tqdm

from fusedmosaic.io.igtl import extrapolation_base
from fusedmosaic.io.tracking import (
    GAP_SPACINGS,
    camera_pose_from_sample,
    check_time_offset,
    sample_spacing,
)
from fusedmosaic.methods import MethodResult, ms_stats

__all__ = ["LIVE_METHODS", "replay_live", "check_live_method", "newest_sample_index",
           "extrapolated_robot"]

LIVE_METHODS = ("lba-emt", "kalman-robot", "ncc", "robot")
# the pCLE methods: RobotPriorMosaicker's estimate of each (translation.ESTIMATES)
TRANSLATION_ESTIMATES = {"kalman-robot": "fused", "ncc": "image", "robot": "robot"}
DROPPED = "unplaced: dropped (live replay: arrived while frame {busy} was being processed)"


def takes_samples(method: str) -> bool:
    """Whether `method` uses a tracker or robot sample per frame (ncc: the images alone)."""
    return TRANSLATION_ESTIMATES.get(method) != "image"


def check_live_method(method: str) -> None:
    """ValueError unless `method` has a streaming form (LIVE_METHODS)."""
    if method not in LIVE_METHODS:
        raise ValueError(f"live replay: method {method!r} has no streaming form; use one of "
                         f"{', '.join(LIVE_METHODS)}")


def newest_sample_index(sample_times: np.ndarray, t: float, max_age_s: float) -> int | None:
    """Index of the newest sample taken at or before ``t`` and at most ``max_age_s`` before it;
    None when there is none (``sample_times`` increasing). "At or before" allows for rounding:
    a sample up to max(1 µs, 16 ulp of t) after t counts as at t (a robot sampled at the frame
    times, its stamps sums of periods: 0.30000000000000004 for frame 3 at 0.3 s took the sample
    100 ms older, and the replay differed from offline by up to 9.4 px; review)."""
    tol = max(1e-6, 16.0 * float(np.spacing(abs(t))))
    i = int(np.searchsorted(sample_times, t + tol, side="right")) - 1
    if i < 0 or t - sample_times[i] > max_age_s:
        return None
    return i


def _schedule(arrival: np.ndarray, process: Callable[[int], float]) -> tuple[list, dict]:
    """Runs `process(k)` (returns its duration, s) on the frames a one-slot capture queue hands
    over; returns the dropped frames as (k, frame being processed) and the latency per
    processed frame (s)."""
    n = len(arrival)
    dropped, latency = [], {}
    free_at, k, busy = -np.inf, 0, -1
    while k < n:
        if arrival[k] >= free_at:  # idle: frame k is taken when it arrives
            j = k
        else:  # busy: the newest frame that arrived meanwhile is taken, the others dropped
            j = int(np.searchsorted(arrival, free_at, side="right")) - 1
            dropped += [(i, busy) for i in range(k, j)]
        start = max(arrival[j], free_at)
        free_at = start + process(j)
        latency[j] = free_at - arrival[j]
        busy, k = j, j + 1
    return dropped, latency


def replay_live(dataset, method: str, *, options=None, progress: bool = True,
                max_sample_age_s: float | None = None,
                processing_time: Callable[[int], float] | None = None) -> MethodResult:
    """Replays `dataset` through the streaming form of `method` (``LIVE_METHODS``) as a live
    source: see the module docstring. ``options``: the method's options (SequentialOptions or
    RobotPriorOptions). ``max_sample_age_s``: the newest tracker / robot sample older than this
    at a frame's time is not used; None = 3 x the typical spacing of the valid samples
    (io.tracking.sample_spacing), the offline path's gap rule (interpolate_camera_poses).
    ``processing_time``: k -> seconds (finite, >= 0), replaces the measured time of frame k's
    call (what-if studies, tests)."""
    check_live_method(method)
    if max_sample_age_s is not None and not (np.isfinite(max_sample_age_s)
                                             and max_sample_age_s >= 0):
        raise ValueError(f"live replay: max_sample_age_s must be a finite number >= 0, got "
                         f"{max_sample_age_s}")
    n = len(dataset)
    times = np.asarray(dataset.timestamps, dtype=np.float64)
    arrival = times - times[0]
    stream = _streaming(dataset, method, options, max_sample_age_s)
    finals: dict[int, object] = {}  # dataset index -> final result
    order: list[int] = []  # dataset index of each processed frame, in order
    processing: dict[int, float] = {}  # the clock's advance per processed frame, s
    measured = 0.0
    bar = tqdm(total=n, desc=f"{method} live", disable=not progress, leave=False)

    def process(k: int) -> float:
        nonlocal measured
        image = dataset.frames[k]  # read before the timed call: a live frame is in memory
        t0 = time.perf_counter()
        results = stream.feed(k, image)
        elapsed = time.perf_counter() - t0
        measured += elapsed
        order.append(k)
        take(results)
        bar.update(k + 1 - bar.n)
        if processing_time is None:
            processing[k] = elapsed
        else:
            given = float(processing_time(k))
            if not (np.isfinite(given) and given >= 0):
                raise ValueError(f"live replay: processing_time({k}) must be a finite number "
                                 f">= 0, got {given}")
            processing[k] = given
        return processing[k]

    def take(results) -> None:
        for r in results:  # the mosaicker numbers the frames it was given 0, 1, ...
            finals[order[r.frame_id]] = r

    try:
        dropped, latency = _schedule(arrival, process)
        if method == "lba-emt":
            take(stream.mosaicker.flush())
    finally:
        bar.close()
    status = [None] * n
    for k, busy in dropped:
        status[k] = DROPPED.format(busy=int(dataset.frame_ids[busy]))
    processed = order  # dataset index of each frame given to the mosaicker, in order
    if method == "robot" and processed and stream.no_sample.issuperset(processed):
        from fusedmosaic.estimation.translation import no_robot_sample_error

        raise no_robot_sample_error(
            str(dataset.root / dataset.robot_file), len(processed),
            f"live replay: none at or up to {1e3 * stream.max_age:.3g} ms before each frame")
    order = sorted(latency)
    details = {"live": {
        "frames_processed": len(latency), "frames_dropped": len(dropped),
        "dropped": [int(dataset.frame_ids[k]) for k, _ in dropped],
        **_timing_details([latency[k] for k in order], [processing[k] for k in order],
                          stream.ages),
        "frame_interval_ms": _interval_ms(arrival),
        "max_sample_age_s": stream.max_age,
        # processed frames whose newest sample was missing or older than max_sample_age_s
        "frames_without_sample": [int(dataset.frame_ids[k]) for k in sorted(stream.no_sample)],
        "processing_time": "measured" if processing_time is None else "given"}}
    if method == "lba-emt":  # (the mosaicker numbers the frames it was given)
        details.update(_lba_checks(stream.mosaicker,
                                   lambda i: int(dataset.frame_ids[processed[i]]),
                                   str(dataset.root)))
    if method in TRANSLATION_ESTIMATES:  # a chain starting after frame 0 warns as offline
        ids = [int(dataset.frame_ids[k]) for k in processed]
        details.update(_translation_checks(
            method, stream.mosaicker.origin_frames, ids, [finals[k] for k in processed],
            dataset.robot_file, details["live"]["frames_without_sample"], stream.max_age))
    return _streamed_result(method, status, finals, getattr(stream.mosaicker, "plane", None),
                            details, measured, {"live": True, **stream.parameters},
                            ids=dataset.frame_ids)


def _streamed_result(method: str, status: list, finals: dict, plane, details: dict,
                     processing_s: float, parameters: dict, ids=None) -> MethodResult:
    """The MethodResult of a streamed run over len(status) frames: the final homography, pose
    and status of each frame in `finals` (index -> FrameResult), `status` for the others; for
    lba-emt also details["plane_history"], per frame the plane of the step that made it
    final. ids: the frames' ids (None: their indices, a live recording's)."""
    n = len(status)
    G = np.full((n, 3, 3), np.nan)
    poses = np.full((n, 6), np.nan) if method == "lba-emt" else None
    for k, r in finals.items():
        G[k], status[k] = r.homography, r.status
        if poses is not None:
            poses[k] = r.pose
    if method == "lba-emt":
        details["plane_history"] = [None if k not in finals or finals[k].plane is None
                                    else np.asarray(finals[k].plane).tolist() for k in range(n)]
    else:  # kalman-robot, ncc, robot: what the offline run reports (translation._run), None /
        # NaN where a frame was not processed; runner.add_streamed_checks compares X_m and X_r
        from fusedmosaic.estimation.translation import ESTIMATES, frame_columns, name_anchor

        details.update(frame_columns([finals.get(k) for k in range(n)],
                                     np.arange(n) if ids is None else ids))
        # (estimate, and frame_columns' ncc_score, sigma_robot0_px and per_frame_ms, were
        # missing: a script reading them failed on a live run's report.json; review 51)
        details["estimate"] = ESTIMATES[TRANSLATION_ESTIMATES[method]][1]
        # the mosaicker counts the frames it was given, not the dropped ones: its "against
        # frame N" named the N-th processed frame, another one of the recording
        recorded = {r.index: k for k, r in finals.items()}

        def id_of(count: int) -> int:
            k = recorded[count]  # (the anchor was processed, so final)
            return int(k if ids is None else ids[k])

        for k, r in finals.items():
            status[k] = name_anchor(r.status, id_of)
    return MethodResult(G, status, poses=poses, plane=None if plane is None else np.asarray(plane),
                        timings={"processing": processing_s}, parameters=parameters,
                        details=details, blend="linear" if method == "lba-emt" else "average",
                        undistorted=method == "lba-emt", mask_specular=method == "lba-emt",
                        # robot places every frame from its samples, frame 0 ("placed") too:
                        # run checks them all for a black image, as offline (translation._run)
                        images_seen=method != "robot")


def _lba_checks(mosaicker, frame_name=None, source: str = "the stream") -> dict:
    """report.json entries of a streamed lba-emt run that the offline one has: the plane's
    relative std and the registered pairs (for consistency.tracker_agreement's plane check),
    the visual residuals' agreement with sigma_v and how sigma_v was decided, and the start-up's
    and window steps' solver warnings, and the tracker's (frame_name: the mosaicker's frame
    number -> the frame's id, which the tracker warning names; source: the images, named by the
    visual warning)."""
    from fusedmosaic.estimation.sequential import live_solver_warnings, observed_plane_std

    agreement = mosaicker.visual_agreement(source=source)
    return {"plane_relative_std": observed_plane_std(mosaicker),
            "pairs": {"registered": mosaicker.pair_counts["registered"]},
            "visual_agreement": agreement,
            "visual_sigma": mosaicker.visual_sigma,
            "warnings": agreement.pop("warnings") + live_solver_warnings(mosaicker, frame_name)}


def _translation_checks(method: str, origin_frames: dict, ids: list, results: list,
                        robot_name: str, no_sample: list, max_age: float | None,
                        dropped: tuple[int, str] = (0, "")) -> dict:
    """A streamed pCLE method's report.json entries that the offline run gives: the warnings
    when its chain starts after frame 0 (frame 0 blank, no robot sample at it) or never
    (translation.origin_warnings), with images ncc_inconsistent (with ncc's warning when most
    registrations disagree), with a robot the frames without a sample (``no_sample``: their
    ids; none within ``max_age`` s before the frame, None: the source's bound; ``dropped``:
    how many of them because the source no longer kept their samples, and what it keeps) and
    their warning, for kalman-robot the warning when the robot placed most frames that had a
    registration (translation.add_unused_registrations); ids / results: the id /
    FrameResult of each frame given to the mosaicker, in order."""
    from fusedmosaic.estimation.translation import (
        add_frames_without_robot_sample,
        add_inconsistency,
        add_unused_registrations,
        origin_warnings,
    )

    estimate = TRANSLATION_ESTIMATES[method]
    checks = {"warnings": origin_warnings(origin_frames, ids, len(ids), estimate, robot_name)}
    if estimate != "robot":
        add_inconsistency(checks, results, ids, estimate)
    if estimate != "image":
        why = ("none at the frame or recent enough before it" if max_age is None else
               f"none at or up to {1e3 * max_age:.0f} ms before the frame")
        if dropped[0]:
            why += (f"; for {dropped[0]} of them, the samples of their time were no longer "
                    f"kept ({dropped[1]})")
        add_frames_without_robot_sample(checks, no_sample, len(ids), estimate, robot_name, why)
    if estimate == "fused":
        add_unused_registrations(checks, results, ids)
    return checks


def _timing_details(latency_s: list, processing_s: list, ages_s: list) -> dict:
    """report.json "live" timings, ms: latency (arrival -> result) and processing per processed
    frame (median / p95 / max), and the age of the newest sample at the frame times."""
    return {"latency_ms": ms_stats(np.array(latency_s) * 1e3),
            "processing_ms": ms_stats(np.array(processing_s) * 1e3),
            "sample_age_ms": ({"median": float(np.median(ages_s) * 1e3),
                               "max": float(np.max(ages_s) * 1e3)} if ages_s else None)}


def _interval_ms(times) -> float | None:
    """Median frame interval, ms (None for one frame)."""
    return float(np.median(np.diff(times)) * 1e3) if len(times) > 1 else None


@dataclass
class _Stream:
    """A streaming mosaicker and feed(k, image): hands it frame k with its newest sample and
    returns the results made final by that call."""

    mosaicker: object
    feed: Callable
    max_age: float
    parameters: dict
    no_sample: set = field(default_factory=set)
    ages: list = field(default_factory=list)  # age of the sample used, per frame given one (s)


def extrapolated_robot(robot, i: int, t: float, max_age: float,
                       spacing: float | None = None) -> np.ndarray:
    """The robot position at time t from its newest sample i: extrapolated along the motion
    since sample j, the newest at least half a typical spacing before i
    (io.igtl.extrapolation_base, as IgtlSource.position_at; ``spacing``: sample_spacing of the
    robot's times, None: computed), when it is at most max_age before i (a live loop's best
    guess; an accurate robot's sample held 14 ms at 40 µm/frame and 10 frames/s lags ~6 µm,
    and the filter, trusting the robot, follows the lag: pCLE spiral e_M 10.5 -> 27 px), else
    held. (Along i-1 and i, 1 ms apart for a robot reporting in pairs, a 1 µm error of sample i
    was 20 µm 19 ms later; 1 µm of noise: median 6.2 µm, p95 33.3 at 12 frames/s, now 0.9 and
    3.1; review.)"""
    xy = robot.xy_um[i]
    times = robot.timestamps
    if spacing is None:
        spacing = sample_spacing(times) if len(times) > 1 else 0.0
    j = extrapolation_base(times, i, spacing)
    if j is None:
        return xy
    dt = times[i] - times[j]
    if not 0 < dt <= max_age:
        return xy
    return xy + (xy - robot.xy_um[j]) * ((t - times[i]) / dt)


def _max_age(sample_times: np.ndarray, given: float | None) -> float:
    if given is not None:
        return float(given)
    return GAP_SPACINGS * sample_spacing(sample_times) if len(sample_times) > 1 else 0.0


def streaming_mosaicker(method: str, camera, options, where: str,
                        robot_file: str = "robot.csv") -> tuple[object, dict]:
    """The streaming mosaicker of `method` (LIVE_METHODS; options None: its defaults) and the
    parameters report.json records for it, as the offline run records them (translation._run
    for kalman-robot). `where` names the caller in errors."""
    if method == "lba-emt":
        from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions

        options = SequentialOptions() if options is None else options
        return SequentialMosaicker(camera, options), asdict(options)
    from fusedmosaic.estimation.translation import RobotPriorMosaicker, RobotPriorOptions

    options = RobotPriorOptions() if options is None else options
    estimate = TRANSLATION_ESTIMATES[method]
    if options.flat_field and estimate != "robot":
        raise ValueError(f"{where}: flat_field needs the fibre pattern of the whole recording "
                         "(not known live); run without --flat-field")
    mosaicker = RobotPriorMosaicker(camera, options, estimate=estimate)
    return mosaicker, {"estimate": estimate, "pixel_size_um": mosaicker.pixel_size_um,
                       "robot_file": robot_file if estimate != "image" else None,
                       **asdict(options)}


def _streaming(dataset, method: str, options, max_age: float | None) -> _Stream:
    if method == "lba-emt":
        dataset.require_tracking(method)
        mosaicker, parameters = streaming_mosaicker(method, dataset.camera, options,
                                                    "live replay")
        tracking = dataset.tracking
        ok = np.ones(len(tracking.timestamps), bool) if tracking.valid is None else tracking.valid
        sample_times = tracking.timestamps[ok]
        translations, quaternions = tracking.translations[ok], tracking.quaternions[ok]
        stream = _Stream(mosaicker, None, _max_age(sample_times, max_age), parameters)

        def feed(k: int, image) -> list:
            t = float(dataset.timestamps[k])
            i = newest_sample_index(sample_times, t, stream.max_age)
            if i is None:
                stream.no_sample.add(k)
            else:
                stream.ages.append(max(0.0, t - sample_times[i]))
            pose = None if i is None else camera_pose_from_sample(
                translations[i], quaternions[i], dataset.hand_eye)
            mosaicker.add_frame(image, t, pose)
            return mosaicker.finalized()

        stream.feed = feed
        return stream
    if not takes_samples(method):  # ncc: as offline, no pixel size needed
        mosaicker, parameters = streaming_mosaicker(method, dataset.camera, options,
                                                    "live replay")
        stream = _Stream(mosaicker, None, 0.0, parameters)
        stream.feed = lambda k, image: [mosaicker.add_frame(image, float(dataset.timestamps[k]),
                                                            None)]
        return stream
    dataset.require_robot(method)
    dataset.require_pixel_size(method)
    mosaicker, parameters = streaming_mosaicker(method, dataset.camera, options, "live replay",
                                                dataset.robot_file)
    robot = dataset.robot
    stream = _Stream(mosaicker, None, _max_age(robot.timestamps, max_age), parameters)
    spacing = sample_spacing(robot.timestamps) if len(robot.timestamps) > 1 else 0.0

    def feed(k: int, image) -> list:
        t = float(dataset.timestamps[k])
        i = newest_sample_index(robot.timestamps, t, stream.max_age)
        if i is None:
            stream.no_sample.add(k)
            return [mosaicker.add_frame(image, t, None)]
        stream.ages.append(max(0.0, t - robot.timestamps[i]))
        return [mosaicker.add_frame(image, t, extrapolated_robot(robot, i, t, stream.max_age,
                                                                spacing))]

    stream.feed = feed
    return stream


# ---------------------------------------------------------------------------- a live source
SESSION_ENDED = "unplaced: not processed (the session ended before its turn; recorded)"
# A session hearing frames but no valid sample of its tracker (robot) device this long says so.
NO_SAMPLE_WARNING_S = 3.0
DROPPED_LIVE = "unplaced: dropped (live: arrived while frame {busy} was being processed)"
# (a frame before the first processed one: "while frame ? was being processed" was said)
DROPPED_FIRST = "unplaced: dropped (live: a newer frame had arrived when the session took one)"


@dataclass
class LiveSession:
    """What `live_session` measured: per recorded frame (recording ids 0, 1, ...) the final
    result (`finals`), the frames processed in order, their latency (arrival -> result, s) and
    processing time (s), the frames without a usable tracker sample, why the session stopped,
    the final plane (lba-emt) and the mosaicker's parameters."""

    finals: dict = field(default_factory=dict)
    processed: list = field(default_factory=list)
    latency: dict = field(default_factory=dict)
    processing: dict = field(default_factory=dict)
    no_sample: list = field(default_factory=list)
    # of no_sample, the frames whose samples the source had dropped from its history
    # (io.igtl.HISTORY_S), and what it keeps
    no_sample_dropped: list = field(default_factory=list)
    history: str = ""
    ages: list = field(default_factory=list)
    stopped_by: str = ""
    plane: object = None
    parameters: dict = field(default_factory=dict)  # the mosaicker's, for report.json
    # kalman-robot: RobotPriorMosaicker.origin_frames (indices into `processed`)
    origin_frames: dict | None = None
    # lba-emt: report.json entries of the mosaicker's (plane_relative_std, pairs, warnings)
    checks: dict = field(default_factory=dict)


def live_session(source, camera, *, method: str = "lba-emt", hand_eye=None, options=None,
                 max_frames: int | None = None, duration_s: float | None = None,
                 frame_timeout_s: float = 5.0, max_sample_age_s: float | None = None,
                 on_result: Callable | None = None,
                 tracker_time_offset: float = 0.0,
                 on_final: Callable | None = None,
                 on_loop_end: Callable | None = None) -> LiveSession:
    """Runs `method` (lba-emt: the tracker pose at each frame's time; kalman-robot: the robot
    position, the source's translation in mm taken as the probe position in the image axes)
    live on `source` (an io.igtl.IgtlSource, or anything with its next_frame / pose_at /
    position_at / received): takes the newest frame as soon as the previous one is done, until
    the stream ends, the frame numbered max_frames - 1 (the source's numbering: the recording's
    frame ids when on_frame renumbers them, as run_igtl does, which records no more) is
    processed, `duration_s` passed, or Ctrl-C (KeyboardInterrupt ends the session normally;
    the mosaickers are transactional, an interrupted call leaves them as before). When frames
    keep coming for NO_SAMPLE_WARNING_S without a valid sample of the source's tracker (robot)
    device, a warning says so once (naming the devices heard instead: a misnamed --transform);
    at the end too, for a session that had none. on_result(frame, result) is called after each
    frame (provisional for lba-emt); on_final(index, image, result) once a frame's result is
    final (the image is kept until then: a live mosaic view). tracker_time_offset: s, the
    tracker's (robot's) clock ahead of the video's, as calibrate measures it: the frame at time
    t takes the sample at t + offset. on_loop_end() is called once no more frames are taken,
    before lba-emt's last steps (run_igtl's Ctrl-C guard for the outputs starts there). The
    caller records the frames (the source's on_frame) and writes the outputs."""
    from fusedmosaic.io.igtl import StreamTimeout

    check_live_method(method)
    offset = check_time_offset(tracker_time_offset)
    mosaicker, parameters = streaming_mosaicker(method, camera, options, "live session")
    session = LiveSession(parameters=parameters)
    sample_at = _sample_at(method, source, hand_eye, max_sample_age_s)
    start = time.monotonic()
    first_frame = None  # time.monotonic() when the first frame was taken
    warned = False
    tracker_said = False  # the tracker disagreement said (_warn_tracker_disagreement)

    images: dict = {}  # frame index -> image, until its result is final (on_final only)

    def take(results) -> None:
        for r in results:  # the mosaicker numbers the frames it was given 0, 1, ...
            index = session.processed[r.frame_id]
            session.finals[index] = r
            if on_final is not None:
                on_final(index, images.pop(index, None), r)

    try:
        while True:
            left = None if duration_s is None else duration_s - (time.monotonic() - start)
            if left is not None and left <= 0:
                session.stopped_by = f"{duration_s:g} s passed (--duration)"
                break
            try:
                frame = source.next_frame(frame_timeout_s if left is None
                                          else min(frame_timeout_s, left))
            except ValueError as exc:  # silence, a reset or a corrupt message
                if left is not None and left <= frame_timeout_s and isinstance(exc,
                                                                              StreamTimeout):
                    continue  # the duration ran out first: stopped above
                if not session.processed:
                    raise
                session.stopped_by = f"the stream failed: {exc}"  # what was done is kept
                break
            if frame is None:
                session.stopped_by = "the sender closed the stream"
                break
            misses = getattr(source, "history_misses", 0)
            sample, age = sample_at(frame.timestamp + offset)
            if sample is None and takes_samples(method):
                session.no_sample.append(frame.index)
                if getattr(source, "history_misses", 0) > misses:
                    _dropped_from_history(session, source, method, frame.index)
            elif age is not None:
                session.ages.append(age)
            session.processed.append(frame.index)  # before the call: flush() numbers it
            if on_final is not None:
                images[frame.index] = frame.image
            t0 = time.perf_counter()
            try:
                result = mosaicker.add_frame(frame.image, frame.timestamp, sample)
            except BaseException:  # the mosaicker is as before the call
                session.processed.pop()
                images.pop(frame.index, None)
                raise
            done = time.perf_counter()
            session.latency[frame.index] = done - frame.arrival
            session.processing[frame.index] = done - t0
            take(mosaicker.finalized() if method == "lba-emt" else [result])
            if method == "lba-emt" and not tracker_said and mosaicker.tracker_episode:
                _warn_tracker_disagreement(mosaicker, session)
                tracker_said = True
            if on_result is not None:
                on_result(frame, result)
            first_frame = time.monotonic() if first_frame is None else first_frame
            if not warned and time.monotonic() - first_frame >= NO_SAMPLE_WARNING_S:
                warned = _warn_without_samples(source, method, time.monotonic() - first_frame)
            if max_frames is not None and frame.index + 1 >= max_frames:
                session.stopped_by = f"{max_frames} frames recorded (--max-frames)"
                break
    except KeyboardInterrupt:
        session.stopped_by = "interrupted (Ctrl-C or a stop signal)"
    if on_loop_end is not None:
        on_loop_end()
    if session.processed and not warned:  # a short session: said at its end
        _warn_without_samples(source, method, None)
    if session.processed and method == "lba-emt":
        from fusedmosaic.io.output import signals_deferred

        with signals_deferred():  # a second Ctrl-C / SIGTERM waits for the last step
            take(mosaicker.flush())
    session.plane = getattr(mosaicker, "plane", None)
    session.origin_frames = getattr(mosaicker, "origin_frames", None)
    if method == "lba-emt":  # (the tracker warning names the source's frames)
        session.checks = _lba_checks(mosaicker, lambda i: session.processed[i])
    return session


def _warn_tracker_disagreement(mosaicker, session: LiveSession) -> None:
    """Says, as it begins, the first stretch where most tracker samples of final frames were
    gated or dropped (sequential.tracker_warning; the session's checks word it again at its
    end, with where it ended): in theatre the operator hears of a tracker disagreeing with the
    images (a sensor near metal, a convention mix-up) while it lasts, not after."""
    import warnings

    from fusedmosaic.estimation.sequential import tracker_warning

    warnings.warn(f"live session: {tracker_warning(mosaicker, lambda i: session.processed[i])}",
                  stacklevel=3)


def _dropped_from_history(session: LiveSession, source, method: str, index: int) -> None:
    """Notes that frame `index` got no sample because the source had dropped those of its
    time from its history (told as "none recent enough", the cause unnamed; review); warns
    at the first."""
    session.no_sample_dropped.append(index)
    if len(session.no_sample_dropped) > 1:
        return
    import warnings

    session.history = getattr(source, "history_text", "")
    kind = "tracker" if method == "lba-emt" else "robot"
    warnings.warn(f"live session: frame {index} got no {kind} sample: the samples of its time "
                  f"were no longer kept ({session.history}); such frames are listed in "
                  "report.json live frames_without_sample_dropped", stacklevel=3)


def _warn_without_samples(source, method: str, elapsed_s: float | None) -> bool:
    """Warns (once: returns True) when `source` has had no valid sample of its tracker (robot)
    device, naming what it heard instead; elapsed_s: since the first frame (None: the
    session's end)."""
    if not takes_samples(method) or getattr(source, "valid_samples", 1):
        return False
    import warnings

    device = getattr(source, "transform_device", "the tracker")
    invalid = dict(getattr(source, "invalid_samples", {}))  # (the receiving thread adds to it)
    heard = sorted(getattr(source, "ignored_devices", ()))
    if invalid:
        instead = ("its samples are all invalid: "
                   + ", ".join(f"{n} x {why}" for why, n in invalid.items()))
    else:
        instead = ("other devices heard: " + ", ".join(heard) if heard else
                   "no other device heard either")
    kind = "tracker" if method == "lba-emt" else "robot"
    when = ("in the whole session" if elapsed_s is None else
            f"in the {elapsed_s:.2g} s since the first frame")
    warnings.warn(f"live session: no valid {kind} sample (TRANSFORM or POSITION) of {device} "
                  f"{when} ({instead}): the frames get no {kind} sample; check --transform",
                  stacklevel=3)
    return True


def _sample_at(method: str, source, hand_eye, max_age: float | None) -> Callable:
    """t -> (the tracker pose (lba-emt) or robot position in µm (kalman-robot) at t from the
    live source, or None; the sample's age)."""
    if method == "lba-emt":
        return lambda t: source.pose_at(t, hand_eye, max_age_s=max_age)
    if not takes_samples(method):  # (a robot stream is recorded, not used)
        return lambda t: (None, None)

    def robot_at(t: float):
        position, age = source.position_at(t, max_age_s=max_age)
        return (None if position is None else position[:2] * 1e3), age  # mm -> µm

    return robot_at


def session_result(session: LiveSession, timestamps, dropped: list[int], *,
                   source_details: dict, method: str = "lba-emt") -> MethodResult:
    """The MethodResult of a live session over the recorded frames (their timestamps): final
    homographies and poses of the processed frames; the others "unplaced" with why (dropped
    while busy, or the session ended before their turn)."""
    n = len(timestamps)
    status = [SESSION_ENDED] * n
    busy_at = {}
    order = [*session.processed, n]
    for a, b in zip(order[:-1], order[1:], strict=True):  # frames after a processed one
        for k in range(a + 1, b):
            busy_at[k] = a
    for k in dropped:
        if k < n:
            status[k] = (DROPPED_LIVE.format(busy=busy_at[k]) if k in busy_at else
                         DROPPED_FIRST)
    details = {"live": {
        "source": source_details, "stopped_by": session.stopped_by,
        "frames_recorded": n, "frames_processed": len(session.processed),
        "frame_interval_ms": _interval_ms(timestamps),
        "frames_dropped": len(dropped), "dropped": [int(k) for k in dropped],
        **_timing_details([session.latency[k] for k in session.processed],
                          [session.processing[k] for k in session.processed], session.ages),
        "frames_without_sample": [int(k) for k in session.no_sample],
        # of those, the frames whose samples had been dropped from the source's history
        "frames_without_sample_dropped": [int(k) for k in session.no_sample_dropped],
    }}
    details.update(session.checks)
    if method in TRANSLATION_ESTIMATES and session.origin_frames is not None \
            and session.processed:
        details.update(_translation_checks(
            method, session.origin_frames, [int(k) for k in session.processed],
            [session.finals[k] for k in session.processed], "the robot stream",
            [int(k) for k in session.no_sample], None,
            dropped=(len(session.no_sample_dropped), session.history)))
    return _streamed_result(method, status, session.finals, session.plane, details,
                            float(sum(session.processing.values())),
                            {"live": "openigtlink", **session.parameters})
