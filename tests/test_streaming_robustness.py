"""Streaming APIs under bad or hostile input (audit 5, items 9-15): RobotPriorMosaicker (pCLE,
paper 004) and the live IncrementalCanvas. Each refused call must name the frame and the
argument and change nothing: the run continued afterwards is identical to an uninterrupted one.
"""

import threading

import numpy as np
import pytest

import fusedmosaic.estimation.translation as translation
from fusedmosaic.compositing import CanvasTooLargeError, IncrementalCanvas, render_mosaic
from fusedmosaic.estimation.translation import (
    MAX_FRAME_GAP_S,
    RobotPriorMosaicker,
    RobotPriorOptions,
)
from fusedmosaic.io import Camera, read_dataset
from fusedmosaic.simulation import PcleOptions, simulate_pcle

# A short clean scan (no contact loss or stick-slip): the perfect robot and the image agree to
# well under a pixel, so any lasting offset after a bad call is the call's doing.
SMALL = PcleOptions(
    width=192,
    height=160,
    n_frames=20,
    speed_um_per_frame=12.0,
    radius_um=150.0,
    contact_loss=False,
    stick_slip=False,
)
BAD = 10  # the frame the bad calls are made at


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    return read_dataset(simulate_pcle(tmp_path_factory.mktemp("pcle") / "small", SMALL))


def _feed(m, dataset, frames, robot=None, out=None):
    robot = dataset.robot_xy_um if robot is None else robot
    out = {} if out is None else out
    for k in frames:
        out[k] = m.add_frame(dataset.frames[k], dataset.timestamps[k], robot[k])
    return out


def _positions(out):
    return np.stack([out[k].position for k in sorted(out)])


@pytest.fixture(scope="module")
def baseline(pcle):
    out = _feed(RobotPriorMosaicker(pcle.camera), pcle, range(len(pcle)))
    assert not any(r.robot_gated for r in out.values())  # nothing to gate on a clean scan
    return out


def _truth(pcle):
    return pcle.ground_truth[:, :2, 2]


# -- RobotPriorMosaicker: refused calls change nothing ------------------------------------------


@pytest.mark.parametrize(
    ("timestamp", "robot", "error", "message"),
    [
        (1e300, None, ValueError, r"frame 10: timestamp 1e\+300.* a unit mix-up \(ms, µs or ns"),
        ("gap", None, ValueError, r"frame 10: timestamp .* 8\.64e\+04 s after the previous frame"),
        (1.7e12, None, ValueError, r"\|t\| <= 1e\+10 s"),
        ("1.2", None, TypeError, r"frame 10: timestamp must be a real number \(s\), got str"),
        (None, None, TypeError, r"frame 10: timestamp must be a real number \(s\), got NoneType"),
        (1 + 0j, None, TypeError, r"frame 10: timestamp must be a real number \(s\), got complex"),
        (None, (1e12, 0.0), ValueError, r"frame 10: robot_xy_um .* beyond the 1e\+09 µm bound"),
        (None, (1e300, 0.0), ValueError, r"frame 10: robot_xy_um .* beyond the 1e\+09 µm bound"),
        (None, (-2e9, 5.0), ValueError, r"frame 10: robot_xy_um .* beyond the 1e\+09 µm bound"),
        (None, "ab", TypeError, r"frame 10: robot_xy_um must be two real numbers \(µm\), got str"),
        (None, "complex", TypeError, r"frame 10: robot_xy_um must be .* got complex values"),
        (None, [1.0, "2"], TypeError, r"frame 10: robot_xy_um must be .* got str values"),
    ],
)
def test_bad_timestamp_or_robot_is_refused_and_changes_nothing(
    pcle, baseline, timestamp, robot, error, message
):
    m = RobotPriorMosaicker(pcle.camera)
    out = _feed(m, pcle, range(BAD))
    t = float(pcle.timestamps[BAD])
    if timestamp == "gap":
        timestamp = float(pcle.timestamps[BAD - 1]) + MAX_FRAME_GAP_S + 1.0
    elif timestamp is None and robot is not None:
        timestamp = t
    if isinstance(robot, str) and robot == "complex":
        robot = pcle.robot_xy_um[BAD].astype(complex)  # no ComplexWarning (warnings are errors)
    elif robot is None:
        robot = pcle.robot_xy_um[BAD]
    with pytest.raises(error, match=message):
        m.add_frame(pcle.frames[BAD], timestamp, robot)
    assert m.frame_count == BAD
    _feed(m, pcle, range(BAD, len(pcle)), out=out)
    np.testing.assert_array_equal(_positions(out), _positions(baseline))


def test_a_reused_capture_buffer_gives_the_same_result(pcle, baseline):
    """Review 6 #10: a live loop that reads every frame into one buffer (cv2's
    VideoCapture.read(image)) overwrote the registration anchor, which was the caller's array."""
    m = RobotPriorMosaicker(pcle.camera)
    buffer = np.empty_like(pcle.frames[0])
    out = {}
    for k in range(len(pcle)):
        np.copyto(buffer, pcle.frames[k])
        out[k] = m.add_frame(buffer, pcle.timestamps[k], pcle.robot_xy_um[k])
    np.testing.assert_array_equal(_positions(out), _positions(baseline))


@pytest.mark.parametrize("convert", [
    lambda a: a.astype(np.uint16) + 60000,  # a 16-bit sensor's pedestal
    lambda a: a.astype(np.float32) + 1e5,
    lambda a: a.astype(np.float32) * 1e12,
    lambda a: a.astype(np.float32) * 1e-12,
    lambda a: a.astype(np.float64) / 255.0], ids=["u16+60000", "f32+1e5", "f32*1e12",
                                                   "f32*1e-12", "f64/255"])
def test_frames_on_another_intensity_scale_place_alike(pcle, baseline, convert):
    """The same images on another affine intensity scale: NCC and SSIM do not depend on it,
    their float32 arithmetic did (a 1e5 pedestal placed frames twice as far off, x 1e12 failed
    with c_match NaN, x 1e-12 fell back to the robot at every frame; review): now the frames
    are mapped onto one scale, and placed as the uint8 frames are (to 0.05 px)."""
    m = RobotPriorMosaicker(pcle.camera)
    out = {k: m.add_frame(convert(np.asarray(pcle.frames[k])), pcle.timestamps[k],
                          pcle.robot_xy_um[k]) for k in range(len(pcle))}
    assert [r.status for r in out.values()] == [r.status for r in baseline.values()]
    np.testing.assert_allclose(_positions(out), _positions(baseline), atol=0.05)


def test_timestamp_beyond_the_float_range_is_refused():
    m = RobotPriorMosaicker(Camera(64, 48, pixel_size_um=1.0), estimate="robot")
    with pytest.raises(ValueError, match=r"frame 0: timestamp 1000000.* is not finite"):
        m.add_frame(None, 10**400, (0.0, 0.0))
    assert m.frame_count == 0


def test_a_day_long_gap_is_accepted():
    """The bound is on the gap, not the clock: a Unix time in s and a gap of 1 day are fine."""
    m = RobotPriorMosaicker(Camera(64, 48, pixel_size_um=1.0), estimate="robot")
    m.add_frame(None, 1.7e9, (0.0, 0.0))
    assert m.add_frame(None, 1.7e9 + MAX_FRAME_GAP_S, (1.0, 2.0)).status == "prior-only"


# -- RobotPriorMosaicker: one caller at a time ---------------------------------------------------


def test_concurrent_add_frame_raises_and_sequential_threads_work(pcle, baseline, monkeypatch):
    inside, release = threading.Event(), threading.Event()
    real = translation.register_ncc

    def slow_register(*args, **kwargs):
        if threading.current_thread().name == "capture":
            inside.set()
            assert release.wait(10.0)
        return real(*args, **kwargs)

    monkeypatch.setattr(translation, "register_ncc", slow_register)
    m = RobotPriorMosaicker(pcle.camera)
    out = _feed(m, pcle, range(3))
    errors = []

    def capture():
        try:
            _feed(m, pcle, [3], out=out)
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    worker = threading.Thread(target=capture, name="capture")
    worker.start()
    assert inside.wait(10.0)
    with pytest.raises(
        RuntimeError,
        match=r"add_frame called while another call is running.*"
        r"not re-entrant; serialise the calls",
    ):
        m.add_frame(pcle.frames[4], pcle.timestamps[4], pcle.robot_xy_um[4])
    with pytest.raises(RuntimeError, match=r"reset called while another call is running"):
        m.reset()
    release.set()
    worker.join(10.0)
    assert not errors and m.frame_count == 4
    # sequential calls from other threads, one after the other, are fine
    for k in range(4, 8):
        t = threading.Thread(target=_feed, args=(m, pcle, [k]), kwargs={"out": out})
        t.start()
        t.join()
    _feed(m, pcle, range(8, len(pcle)), out=out)
    np.testing.assert_array_equal(_positions(out), _positions(baseline))
    assert [out[k].index for k in sorted(out)] == list(range(len(pcle)))
    assert all(out[k].frame_id == out[k].index for k in out)  # the sequential result's name


# -- RobotPriorMosaicker: a grossly wrong robot sample is gated ----------------------------------


def test_single_robot_glitch_is_gated_and_the_run_returns_to_baseline(pcle, baseline):
    """+5 mm on one textured frame (audit 5 #11: that frame 4271 px off and every later one
    ~127 px off on the default scan): the robot is left out there, the next robot displacement
    is taken from the last good sample."""
    robot = pcle.robot_xy_um.copy()
    robot[BAD, 0] += 5000.0
    out = _feed(RobotPriorMosaicker(pcle.camera), pcle, range(len(pcle)), robot)
    assert [k for k, r in out.items() if r.robot_gated] == [BAD]
    r = out[BAD]
    assert r.status == "placed" and r.c_rob == 0.0 and r.c_img >= 0.5
    assert r.displacement_robot[0] > 4000.0  # the rejected displacement is reported
    truth = _truth(pcle)
    err = np.linalg.norm(_positions(out) - truth, axis=1)
    base = np.linalg.norm(_positions(baseline) - truth, axis=1)
    assert err[BAD] < base[BAD] + 0.5, (err[BAD], base[BAD])
    np.testing.assert_allclose(err[BAD + 1 :], base[BAD + 1 :], atol=0.5)
    # the gated disagreement did not enter the sigma_r0 estimate
    assert out[len(pcle) - 1].sigma_robot0 == pytest.approx(
        baseline[len(pcle) - 1].sigma_robot0, rel=0.5
    )


def test_lasting_robot_offset_is_rebased_after_a_few_gated_frames(pcle, baseline):
    robot = pcle.robot_xy_um.copy()
    robot[BAD:, 1] -= 3000.0  # the robot re-homed: every later sample is offset
    out = _feed(RobotPriorMosaicker(pcle.camera), pcle, range(len(pcle)), robot)
    rebase = RobotPriorOptions().robot_gate_rebase
    assert [k for k, r in out.items() if r.robot_gated] == list(range(BAD, BAD + rebase))
    truth = _truth(pcle)
    err = np.linalg.norm(_positions(out) - truth, axis=1)
    base = np.linalg.norm(_positions(baseline) - truth, axis=1)
    np.testing.assert_allclose(err, base, atol=0.5)


def test_robot_gating_off_follows_the_glitch(pcle):
    """The measurement the gate exists for: without it the glitch drags the frame away."""
    robot = pcle.robot_xy_um.copy()
    robot[BAD, 0] += 5000.0
    options = RobotPriorOptions(robot_gate_fraction=None, robot_gate_sigmas=np.inf)
    out = _feed(RobotPriorMosaicker(pcle.camera, options), pcle, range(len(pcle)), robot)
    assert not out[BAD].robot_gated
    assert np.linalg.norm(out[BAD].position - _truth(pcle)[BAD]) > 100.0


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"robot_gate_fraction": 0.0}, r"robot_gate_fraction must be a finite number > 0 or None"),
        ({"robot_gate_sigmas": 0.0}, r"robot_gate_sigmas must be > 0"),
        ({"robot_gate_rebase": 0}, r"robot_gate_rebase must be >= 1"),
    ],
)
def test_bad_gate_options(kwargs, message):
    with pytest.raises(ValueError, match=message):
        RobotPriorOptions(**kwargs)


# -- IncrementalCanvas ---------------------------------------------------------------------------

W = H = 64


def _frame(seed=0, channels=3):
    rng = np.random.default_rng(seed)
    shape = (H, W) if channels == 1 else (H, W, channels)
    return rng.integers(0, 256, shape, dtype=np.uint8)


def _shift(x, y=0.0):
    return np.array([[1.0, 0, x], [0, 1, y], [0, 0, 1]])


def _canvas(**kwargs):
    canvas = IncrementalCanvas(W, H, tile_size=32, **kwargs)
    for k in range(4):
        canvas.add(_frame(k), _shift(20.0 * k, 10.0 * k))
    return canvas


def _reference():
    canvas = _canvas()
    canvas.add(_frame(9), _shift(30.0, 70.0))
    return canvas


def test_stray_far_frame_is_skipped_not_growing_the_bounds():
    canvas = _canvas(max_pixels=1_000_000)
    bounds, tiles = canvas.bounds, len(canvas.tiles)
    assert canvas.add(_frame(5), _shift(1e7)) is None
    assert canvas.skipped == [
        (
            4,
            (
                "would grow the canvas bounds to 10000066 x 96 pixels, above max_pixels 1000000 "
                "(frame lands at x 9999999..10000065, y -1..65: a stray placement?)"
            ),
        )
    ]
    assert canvas.bounds == bounds and len(canvas.tiles) == tiles
    canvas.add(_frame(9), _shift(30.0, 70.0))
    reference = _reference()
    np.testing.assert_array_equal(canvas.render(), reference.render())
    assert canvas.skipped[0][0] == 4 and canvas.frames_added == 5  # numbering goes on


def test_far_frame_within_the_budget_is_kept():
    canvas = _canvas(max_pixels=1_000_000)
    box = canvas.add(_frame(5), _shift(5000.0))
    assert box == (4999, -1, 5065, 65) and canvas.skipped == []
    x0, y0, x1, y1 = canvas.bounds
    assert (x0, x1) == (-1, 5065)
    assert canvas.render().shape == (y1 - y0, x1 - x0, 3)


def test_render_of_a_box_above_the_budget_raises():
    canvas = _canvas(max_pixels=200_000)
    with pytest.raises(
        CanvasTooLargeError,
        match=r"render: the view of x 0\.\.1000, y 0\.\.1000 "
        r"is 1000 x 1000 pixels, above the budget of "
        r"200000 pixels",
    ):
        canvas.render((0, 0, 1000, 1000))
    with pytest.raises(ValueError, match=r"render: empty box"):
        canvas.render((10, 10, 10, 20))
    assert canvas.render().shape[:2] == (
        canvas.bounds[3] - canvas.bounds[1],
        canvas.bounds[2] - canvas.bounds[0],
    )


@pytest.mark.parametrize(
    ("image", "error", "message"),
    [
        (None, TypeError, r"frame 4: image is None; expected an \(H, W\) gray or \(H, W, 3\)"),
        (
            _frame(9).astype(np.float32) / 255,
            ValueError,
            r"frame 4: image is float32, expected uint8: .* \(0\.\.1 floats: np\.clip",
        ),
        (_frame(9).astype(np.float64), ValueError, r"frame 4: image is float64, expected uint8"),
        (
            _frame(9).astype(np.uint16) * 256,
            ValueError,
            r"frame 4: image is uint16, expected uint8: .* \(16-bit: \(image >> 8\)",
        ),
        (_frame(9) > 100, ValueError, r"frame 4: image is bool, expected uint8"),
        (np.dstack([_frame(9, 1)] * 2), ValueError, r"frame 4: expected an \(H, W\) gray or "),
        (_frame(9)[:32], ValueError, r"frame 4: image is 64x32, expected 64x64"),
        (_frame(9, 1), ValueError, r"frame 4: 1 channel\(s\), earlier frames have 3"),
    ],
)
def test_bad_frames_are_refused_and_change_nothing(image, error, message):
    canvas = _canvas()
    with pytest.raises(error, match=message):
        canvas.add(image, _shift(30.0, 70.0))
    canvas.add(_frame(9), _shift(30.0, 70.0))
    reference = _reference()
    assert canvas.bounds == reference.bounds and canvas.frames_added == 5
    np.testing.assert_array_equal(canvas.render(), reference.render())


def test_uint8_contract_matches_the_offline_compositor():
    """The offline compositor reads pixel values at face value (0..255): the uint8 frames the
    live canvas accepts render identically in both."""
    frames = [_frame(k) for k in range(3)]
    G = np.stack([_shift(15.0 * k, 5.0 * k) for k in range(3)])
    offline = render_mosaic(frames, G, W, H, blend="average")
    live = IncrementalCanvas(W, H, blend="average", tile_size=32)
    for image, g in zip(frames, G, strict=True):
        live.add(image, g)
    p = offline.plan
    np.testing.assert_array_equal(live.render((p.x0, p.y0, p.x1, p.y1)), offline.image)


def test_bad_homography_message_names_the_frame():
    canvas = _canvas()
    with pytest.raises(ValueError, match=r"frame 4: homography must be 3x3, got \(2, 3\)"):
        canvas.add(_frame(9), _shift(1.0)[:2])
    assert canvas.add(_frame(9), _shift(30.0, 70.0)) is not None


# ----------------------------------------------------- options refused up front (audit 26)
@pytest.mark.parametrize("field, value, message", [
    ("pyramid_levels", 2.5, r"pyramid_levels must be an integer, got 2\.5"),
    ("ssim_downsample", 2.5, r"ssim_downsample must be an integer, got 2\.5"),
    ("max_displacement_px", np.inf, r"max_displacement_px must be finite and > 0, or None"),
    ("fallback_template_fraction", 1.5, r"fallback_template_fraction must be in \(0, 1\)"),
    ("max_disagreement_px", -1.0, r"max_disagreement_px must be finite and >= 0"),
    ("presmooth_sigma", 1e4, r"presmooth_sigma must be in \[0, 512\] px, got 10000\.0"),
])
def test_robot_prior_options_refused_before_the_first_frame(field, value, message):
    """Before: accepted, then every frame from the second on raised an error naming neither
    the option nor the class (TypeError '>>', OverflowError, cv2.error), or, for a huge
    presmooth_sigma, took seconds to minutes a frame inside cv2.GaussianBlur."""
    from fusedmosaic.estimation.translation import RobotPriorOptions

    with pytest.raises(ValueError, match=rf"RobotPriorOptions\.{message}"):
        RobotPriorOptions(**{field: value})


def _small_camera() -> Camera:
    return Camera(64, 48, np.array([[80.0, 0, 31.5], [0, 80.0, 23.5], [0, 0, 1]]))


@pytest.mark.parametrize("field, value, message", [
    ("gate_sigma_scale", 0.0, r"gate_sigma_scale must be finite and >= 1"),
    ("gate_sigma_scale", np.nan, r"gate_sigma_scale must be finite and >= 1"),
    ("gate_chi2", -1.0, r"gate_chi2 must be > 0"),
    ("motion_gate_chi2", 0.0, r"motion_gate_chi2 must be > 0 \(inf: no gate\), got 0.0"),
    ("max_points_per_pair", 0, r"max_points_per_pair must be an integer >= 1, got 0"),
    ("history_steps", -1, r"history_steps must be an integer >= 0, got -1"),
    ("tracker_reanchor_after", 0.5, r"tracker_reanchor_after must be an integer >= 1"),
    ("startup_wait_frames", True, r"startup_wait_frames must be an integer >= 1, got True"),
    ("motion_max_gap_s", np.nan, r"motion_max_gap_s must be > 0, got nan"),
])
def test_sequential_options_refused_before_the_first_frame(field, value, message):
    """Before: accepted; gate_sigma_scale 0 raised 'scale: must be finite and >= 1' on every
    frame from the first gated step on, max_points_per_pair 0 'add_pair: needs at least 1
    correspondence' on every frame from the start-up's end."""
    from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions

    camera = _small_camera()
    with pytest.raises(ValueError, match=rf"SequentialOptions\.{message}"):
        SequentialMosaicker(camera, SequentialOptions(**{field: value}))
    with pytest.raises(ValueError, match=r"options must be a SequentialOptions, got dict"):
        SequentialMosaicker(camera, {"window_size": 5})


def test_an_overflowing_rotation_vector_is_refused_naming_the_frame():
    """[1e155] x 3 passed the finite check and failed inside the window ('angle_axis: contains
    NaN or infinite values', naming neither the frame nor the argument)."""
    from fusedmosaic.estimation.sequential import SequentialMosaicker

    camera = _small_camera()
    m = SequentialMosaicker(camera)
    frame = np.random.default_rng(0).integers(0, 255, (48, 64), dtype=np.uint8)
    with pytest.raises(ValueError, match=r"frame 0: tracker_pose rotation vector \[1e\+155, "
                       r"1e\+155, 1e\+155\] has a component beyond 1e\+06 rad"):
        m.add_frame(frame, 0.0, np.array([1e155, 1e155, 1e155, 0.0, 0.0, 30.0]))
    assert m.frame_count == 0


@pytest.mark.parametrize("dtype", [bool, np.complex128, object])
def test_robot_prior_colour_frames_of_an_unsupported_type_are_refused(pcle, dtype):
    """A grey frame of these types was refused, the same data as (H, W, 3) BGR was cast to grey
    first: bool came out as 0/1 pixels, complex lost its imaginary part, an object array failed
    inside the conversion."""
    m = RobotPriorMosaicker(pcle.camera)
    grey = np.asarray(pcle.frames[0])
    colour = np.repeat(grey[..., None], 3, axis=2).astype(dtype)
    with pytest.raises(ValueError, match=rf"frame 0: unsupported pixel type {np.dtype(dtype)}"):
        m.add_frame(colour, 0.0, None)
    with pytest.raises(TypeError, match=r"frame 0: image must be a numpy array, got list"):
        m.add_frame(grey.tolist(), 0.0, None)


def test_robot_prior_frames_of_another_pixel_type_are_refused_and_change_nothing(pcle,
                                                                                  baseline):
    """A float 0-1 frame among uint8 ones (a capture path switching) scored c_match ~0.001: the
    SSIM range follows the pixel type. Refused naming both types; the run then goes on as the
    baseline; reset() takes a new first type."""
    m = RobotPriorMosaicker(pcle.camera)
    out = _feed(m, pcle, range(BAD))
    as_float = np.asarray(pcle.frames[BAD], np.float64) / 255.0
    with pytest.raises(ValueError, match=r"frame 10: pixel type float64 differs from the first "
                       r"frame's uint8; all frames of a sequence must have one pixel type"):
        m.add_frame(as_float, pcle.timestamps[BAD], pcle.robot_xy_um[BAD])
    _feed(m, pcle, range(BAD, len(pcle)), out=out)
    np.testing.assert_array_equal(_positions(out), _positions(baseline))
    m.reset()
    assert m.add_frame(as_float, 0.0, None).index == 0
    # floats of another width, and another byte order, are alike
    m.add_frame(as_float.astype(np.float32), 1.0, None)
    m.add_frame(as_float.astype(">f8"), 2.0, None)
    with pytest.raises(ValueError, match=r"frame 3: pixel type uint16 differs from the first "
                       r"frame's float64"):
        m.add_frame(np.asarray(pcle.frames[3], np.uint16), 3.0, None)
