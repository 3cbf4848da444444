"""Simulator fixes of review 44 (/tmp/s44/reviewD.md): views past the plane's horizon refused,
texture-size remedies that shrink the texture, tracker gaps flagged exactly as the reader
flags them, option types checked, smooth_noise bounded for elongated textures, the texture's
drawing cost refused up front, and the fetoscopy FOV mask taken from Camera."""

import re
from dataclasses import replace

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.io import Camera
from fusedmosaic.simulation import (
    CheckerboardOptions,
    FetoscopyOptions,
    PcleOptions,
    generate_fetoscopy,
)
from fusedmosaic.simulation.fetoscopy import (
    MAX_TEXTURE_GB,
    MAX_TEXTURE_SECONDS,
    MAX_VIEW_RANGE,
    _geometry,
    _options_box,
    _texture_cost_ratio,
    _view_cosines,
    _view_outline,
)
from fusedmosaic.simulation.textures import (
    _cubic_crop,
    placenta_texture_cost,
    smooth_noise,
)

SMALL = ["--n-frames", "8", "--width", "64", "--height", "64"]


def _refused(argv, message, tmp_path, capsys) -> str:
    """`simulate fetoscopy` exits 2 with `message` (a regex) on stderr, no traceback, and
    writes nothing."""
    out = tmp_path / "sim"
    assert main(["simulate", "fetoscopy", str(out), *argv, "--quiet"]) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert "Traceback" not in err and "Options" not in err
    assert not out.exists()
    return err


# 1. Views past the plane's horizon --------------------------------------------------------------

@pytest.mark.parametrize("changes, lead", [
    (dict(focal_factor=0.4, tilt_deg=50.0), "tilt_deg"),  # a wide scope over a steep placenta
    (dict(focal_factor=0.1, tilt_deg=59.0), "focal_factor"),
    (dict(focal_factor=0.6, tilt_deg=43.0), "tilt_deg"),  # was a texture-size error
    (dict(tilt_deg=40.0, rotation_deg=10.0, focal_factor=0.5), "tilt_deg"),  # the most changed
    (dict(rotation_deg=80.0), "rotation_deg"),
])
def test_handheld_view_past_the_horizon_is_refused(changes, lead):
    o = FetoscopyOptions(motion="handheld", n_frames=20, width=64, height=64, **changes)
    with pytest.raises(ValueError, match=(
            rf"^FetoscopyOptions\.{lead}: frame \d+ .*(reaches past the plane's horizon \(a "
            r"ray \d+\.?\d* deg from the plane's normal meets it behind the camera\)|sees the "
            r"plane \d+x as far as the camera is from it \(a ray 8\d\.?\d* deg from the "
            r"plane's normal\)); a frame may see it at most 20x as far \(87\.1 deg from the "
            r"normal\): lower "
            r"FetoscopyOptions\.tilt_deg or FetoscopyOptions\.rotation_deg, or raise "
            r"FetoscopyOptions\.focal_factor$")):
        generate_fetoscopy(o)


def test_grazing_view_is_refused_in_flag_names(tmp_path, capsys):
    """SYN at focal factor 0.03: the corners' rays are 87.6 deg from the normal, 24x the
    camera's distance away (under the horizon, but far beyond the working distance)."""
    _refused([*SMALL, "--focal-factor", "0.03"],
             r"^fusedmosaic: error: --focal-factor: frame 0 \(and 7 more frames\) sees the "
             r"plane 2\d\.\dx as far as the camera is from it \(a ray 87\.\d deg from the plane's "
             r"normal\); a frame may see it at most 20x as far \(87\.1 deg from the normal\): "
             r"raise --focal-factor\n$", tmp_path, capsys)


def test_cli_wide_scope_steep_plane_is_refused(tmp_path, capsys):
    """`--focal-factor 0.1 --tilt-deg 59` exited 0 with mirrored texture in 43 % of the FOV."""
    _refused([*SMALL, "--motion", "handheld", "--focal-factor", "0.1", "--tilt-deg", "59"],
             r"^fusedmosaic: error: --focal-factor: frame \d+ .*past the plane's horizon.*: "
             r"lower --tilt-deg or --rotation-deg, or raise --focal-factor\n$", tmp_path, capsys)


def test_view_cosines_are_the_ray_angles():
    """_view_cosines: the cosine of the widest corner ray to the normal; the default views stay
    far inside the bound (no configuration that worked is refused)."""
    o = FetoscopyOptions(n_frames=3, width=64, height=64)
    K, _, _, plane, _, _, poses = _geometry(o)
    cos = _view_cosines(poses, plane, K, _view_outline(o, K, None))
    half_diagonal = np.hypot(31.5, 31.5) / (o.focal_factor * o.width)
    np.testing.assert_allclose(cos, np.cos(np.arctan(half_diagonal)), rtol=1e-12)
    hand = FetoscopyOptions(motion="handheld", n_frames=150, width=64, height=64)
    K, _, _, plane, _, _, poses = _geometry(hand)
    assert _view_cosines(poses, plane, K, _view_outline(hand, K, None)).min() > 0.5
    assert 1 / MAX_VIEW_RANGE < 0.5


# 1b. Texture-size remedies: only those that shrink the texture ---------------------------------

def _remedies(message: str) -> list[tuple[str, str]]:
    """("lower" | "raise", field) of every remedy after the message's last ': '."""
    out = []
    for part in message.rsplit(": ", 1)[1].split(", or "):
        way, names = part.split(" ", 1)
        for name in re.split(r", | or ", names):
            out.append((way, name.removeprefix("FetoscopyOptions.")))
    return out


@pytest.mark.parametrize("changes, lead, measure", [
    (dict(motion="handheld", distance_variation=0.89), "distance_variation",
     lambda box: float(np.prod(box[2]))),
    (dict(motion="handheld", rotation_deg=40.0, focal_factor=2.0), "rotation_deg",
     _texture_cost_ratio),
])
def test_texture_message_suggests_only_what_shrinks_it(changes, lead, measure):
    o = FetoscopyOptions(**changes)
    with pytest.raises(ValueError) as info:
        generate_fetoscopy(o)
    message = str(info.value)
    assert message.startswith(f"FetoscopyOptions.{lead}: the camera path needs a ")
    remedies = _remedies(message)
    assert ("lower", lead) in remedies
    base = measure(_options_box(replace(o)))
    for way, name in remedies:
        value = getattr(o, name)
        changed = replace(o, **{name: value // 2 if name == "width" else
                                (value / 2 if way == "lower" else value * 2)})
        assert measure(_options_box(changed)) < base, (way, name)
    # a wider view grows these textures (a tilted plane's far side): not suggested
    if ("lower", "focal_factor") not in remedies:
        try:
            assert measure(_options_box(replace(o, focal_factor=o.focal_factor / 2))) >= base
        except ValueError as error:  # or past the horizon
            assert "horizon" in str(error)


def test_texture_size_message_in_flag_names(tmp_path, capsys):
    _refused(["--motion", "handheld", "--distance-variation", "0.89"],
             r"^fusedmosaic: error: --distance-variation: the camera path needs a \S+x\S+ px "
             r"texture .*; at most 6e\+07 px: lower --width, --radius-mm, --distance-variation, "
             r"--tilt-deg or --step-px, or raise --distance-mm\n$", tmp_path, capsys)


# 3. Tracker gaps the tracker rate cannot make ---------------------------------------------------

@pytest.mark.parametrize("gap, asked", [([5, 5], "frame 5"), ([5, 6], "frames 5..6")])
def test_tracker_gap_too_short_for_the_tracker_is_refused(gap, asked):
    """At 40 Hz / 25 fps a reader flags a frame in a hole of over 75 ms: [5, 5] was silently
    interpolated, [5, 6] flagged frames 4..7."""
    with pytest.raises(ValueError, match=(
            rf"^FetoscopyOptions\.tracker_gap: {asked} cannot be untracked alone with a tracker "
            r"at 40 Hz \(FetoscopyOptions\.tracker_rate_hz\): a reader \(io\.tracking\."
            r"interpolate_camera_poses\) flags the frames inside a hole between valid samples "
            r"over 3 sample spacings \(75 ms\), and the widest hole between frames 4 and "
            rf"{gap[1] + 1} flags none: give a longer gap or a faster tracker$")):
        generate_fetoscopy(FetoscopyOptions(n_frames=20, width=64, height=64, tracker_gap=gap))


def test_tracker_gap_refused_in_flag_names(tmp_path, capsys):
    _refused([*SMALL, "--laps", "0.2", "--tracker-gap", "3", "3"],
             r"^fusedmosaic: error: --tracker-gap: frame 3 cannot be untracked alone with a "
             r"tracker at 40 Hz \(--tracker-rate-hz\)", tmp_path, capsys)


def test_a_faster_tracker_makes_a_one_frame_gap():
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=20, width=64, height=64,
                                                tracker_rate_hz=200.0, tracker_gap=[5, 5]))
    from fusedmosaic.io import TrackingSamples, interpolate_camera_poses
    samples = TrackingSamples(scene.tracker_timestamps, scene.tracker_translations,
                              scene.tracker_quaternions, scene.tracker_valid)
    _, valid = interpolate_camera_poses(samples, scene.timestamps, scene.hand_eye)
    assert np.flatnonzero(~valid).tolist() == [5]


# 4. Option types ------------------------------------------------------------------------------

@pytest.mark.parametrize("options, message", [
    (lambda: FetoscopyOptions(n_frames=10.5), r"^FetoscopyOptions\.n_frames: must be a whole "
     r"number, got 10\.5$"),
    (lambda: FetoscopyOptions(n_frames="10"), r"^FetoscopyOptions\.n_frames: must be a whole "
     r"number, got '10'$"),
    (lambda: FetoscopyOptions(width=True), r"^FetoscopyOptions\.width: must be a whole number, "
     r"got True$"),
    (lambda: FetoscopyOptions(height=float("nan")), r"^FetoscopyOptions\.height: must be a whole "
     r"number, got nan$"),
    (lambda: FetoscopyOptions(noise_multiplier="1"), r"^FetoscopyOptions\.noise_multiplier: "
     r"must be a number, got '1'$"),
    (lambda: FetoscopyOptions(distance_mm=None), r"^FetoscopyOptions\.distance_mm: must be a "
     r"number, got None$"),
    (lambda: FetoscopyOptions(fps=False), r"^FetoscopyOptions\.fps: must be a number, "
     r"got False$"),
    (lambda: PcleOptions(n_frames=5.5), r"^PcleOptions\.n_frames: must be a whole number, "
     r"got 5\.5$"),
    (lambda: PcleOptions(width=256.7), r"^PcleOptions\.width: must be a whole number, "
     r"got 256\.7$"),
    (lambda: PcleOptions(speed_um_per_frame="40"), r"^PcleOptions\.speed_um_per_frame: must "
     r"be a number, got '40'$"),
    (lambda: CheckerboardOptions(board_cols=9.5), r"^CheckerboardOptions\.board_cols: must be "
     r"a whole number, got 9\.5$"),
    (lambda: CheckerboardOptions(frames_per_view="8"), r"^CheckerboardOptions\.frames_per_view: "
     r"must be a whole number, got '8'$"),
    (lambda: CheckerboardOptions(n_views=None), r"^CheckerboardOptions\.n_views: must be a "
     r"whole number, got None$"),
])
def test_non_numeric_options_are_refused_by_name(options, message):
    with pytest.raises(ValueError, match=message):
        options().validate()


def test_integral_floats_become_ints():
    o = FetoscopyOptions(n_frames=4.0, width=64.0, height=np.int64(48))
    o.validate()
    assert (type(o.n_frames), type(o.width), type(o.height)) == (int, int, int)
    p = PcleOptions(n_frames=3.0, width=np.float64(96.0), height=64.0)
    p.validate()
    assert (type(p.n_frames), type(p.width), type(p.height)) == (int, int, int)
    c = CheckerboardOptions(board_cols=9.0, board_rows=6.0, n_views=2.0, frames_per_view=4.0)
    c.validate()
    assert all(type(getattr(c, k)) is int
               for k in ("board_cols", "board_rows", "n_views", "frames_per_view"))


def test_integral_float_sizes_render_as_ints():
    """width=200.0 gave a cv2.error in warpPerspective after the whole scene was computed."""
    a = generate_fetoscopy(FetoscopyOptions(n_frames=3.0, width=64.0, height=48.0))
    b = generate_fetoscopy(FetoscopyOptions(n_frames=3, width=64, height=48))
    for k in range(3):
        np.testing.assert_array_equal(a.render(k), b.render(k))


# 5. smooth_noise's intermediate, bounded ------------------------------------------------------

def _smooth_noise_by_resize(shape, scale_px, rng):
    """smooth_noise as it was (one cv2.resize of the whole padded grid)."""
    h, w = shape
    scale = max(float(scale_px), 1.0)
    gh, gw = int(np.ceil(h / scale)) + 4, int(np.ceil(w / scale)) + 4
    coarse = rng.standard_normal((gh, gw)).astype(np.float32)
    if scale > 1.5:
        coarse = cv2.GaussianBlur(coarse, (0, 0), 0.6)
    big = cv2.resize(coarse, (int(round(gw * scale)), int(round(gh * scale))),
                     interpolation=cv2.INTER_CUBIC)
    o = int(round(2 * scale))
    out = big[o:o + h, o:o + w]
    out = out - out.mean()
    return out / max(float(out.std()), 1e-6)


@pytest.mark.parametrize("shape, scale", [((100, 120), 20.0), ((911, 911), 911 / 6),
                                          ((843, 1336), 1336 / 4), ((50, 300), 300 / 4),
                                          ((64, 64), 2.5)])
def test_smooth_noise_unchanged_for_usual_shapes(shape, scale):
    np.testing.assert_array_equal(smooth_noise(shape, scale, np.random.default_rng(5)),
                                  _smooth_noise_by_resize(shape, scale, np.random.default_rng(5)))


def test_smooth_noise_of_an_elongated_texture_interpolates_only_its_pixels():
    """48 x 340000 px asked cv2.resize for a 283000 x 566000 float image (269 GB)."""
    out = smooth_noise((48, 340_000), 340_000 / 6.0, np.random.default_rng(0))
    assert out.shape == (48, 340_000) and out.dtype == np.float32
    assert abs(float(out.mean())) < 1e-4 and float(out.std()) == pytest.approx(1.0, abs=1e-4)


@pytest.mark.parametrize("grid, scale, shape", [((5, 9), 37.3, (40, 200)),
                                               ((8, 6), 11.0, (33, 20))])
def test_cubic_crop_is_cv2_resize_cropped(grid, scale, shape):
    coarse = np.random.default_rng(1).standard_normal(grid).astype(np.float32)
    size = (int(round(grid[0] * scale)), int(round(grid[1] * scale)))
    o = int(round(2 * scale))
    ref = cv2.resize(coarse, size[::-1], interpolation=cv2.INTER_CUBIC)
    ref = ref[o:o + shape[0], o:o + shape[1]]
    np.testing.assert_allclose(_cubic_crop(coarse, size, (o, o), shape), ref, atol=1e-5)


# 6. The texture's drawing cost, refused up front ----------------------------------------------

@pytest.mark.parametrize("flags", [["--width", "4000", "--height", "4000"],
                                   ["--width", "100000", "--height", "16"]])
def test_a_texture_that_takes_minutes_is_refused(flags, tmp_path, capsys):
    """--width 4000 ran for minutes at 3 GB; --width 100000 --height 16 died with cv2.error
    (a 269 GB allocation)."""
    _refused(["--n-frames", "8", *flags],
             r"^fusedmosaic: error: --width: the camera path needs a \d+x\d+ px texture with "
             r"\d+\.?\d* px vessels .*, which takes about \d+ s and \d\.?\d* GB to draw; at most "
             r"60 s and 3 GB \(textures\.placenta_texture_cost\): lower --focal-factor, --width "
             r"or --radius-mm, or raise --distance-mm\n$", tmp_path, capsys)


def test_texture_cost_grows_with_size_and_vessel_width():
    s0, g0 = placenta_texture_cost((1000, 1000), 9.0)
    assert placenta_texture_cost((2000, 2000), 9.0)[0] > 3.5 * s0
    assert placenta_texture_cost((1000, 1000), 27.0)[0] > 1.5 * s0
    assert placenta_texture_cost((2000, 2000), 9.0)[1] > 3.5 * g0


@pytest.mark.parametrize("changes", [
    dict(width=1280, height=720),  # bench_live / bench_detect_scale's largest frames
    dict(motion="handheld", width=1280, height=720),
    dict(motion="handheld", focal_factor=0.6, lens_model="fisheye",
         lens_distortion=[0.02, -0.01, 0.0, 0.0]),  # bench_fisheye
])
def test_the_benchmarks_textures_stay_within_the_cost(changes):
    assert _texture_cost_ratio(_options_box(FetoscopyOptions(**changes))) < 0.5
    assert MAX_TEXTURE_SECONDS == 60 and MAX_TEXTURE_GB == 3


# 8. The FOV mask is Camera's ------------------------------------------------------------------

@pytest.mark.parametrize("changes", [dict(motion="handheld"),
                                     dict(width=401, height=300, fov_mask_radius=100.3)])
def test_fov_mask_is_the_cameras(changes):
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=2, **changes))
    mask = scene.fov_mask()
    camera = Camera(*scene.size, fov_mask_radius=scene.fov_mask_radius)
    np.testing.assert_array_equal(mask, camera.fov_mask() > 0)
    assert mask.dtype == bool and 0 < mask.mean() < 1
    assert not scene.render(1)[~mask].any()
