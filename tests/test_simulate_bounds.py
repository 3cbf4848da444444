"""Bounds of `simulate`, `demo` and `bench` (review C, /tmp/s41/reviewC.md): a huge frame count
refused before anything is computed, naming the option; bench's --pcle-frames checked before
measuring; pCLE cell and fibre sizes bounded by the field of view; what simulate writes is what
run reads (frame spacing, tracker / robot rates, tracker and robot positions); messages in the
command's option names; the field-of-view rule and signed lengths; the demo's summary."""

import re

import pytest

from fusedmosaic.cli import DEMO_DRIFT_MIN_FRAMES, _demo_summary, build_parser, main
from fusedmosaic.evaluation.benchmark import BenchOptions, max_pcle_frames
from fusedmosaic.io import read_dataset
from fusedmosaic.io.tracking import (
    MAX_FRAME_SPACING_S,
    MAX_ROBOT_UM,
    MAX_SAMPLE_TO_FRAME_SPACING,
    MAX_TRANSLATION_MM,
)
from fusedmosaic.simulation import (
    PAPER_BLACK_FRAMES,
    CheckerboardOptions,
    FetoscopyOptions,
    PcleOptions,
    generate_pcle,
    simulate_fetoscopy,
)
from fusedmosaic.simulation._options import MAX_FRAMES, MAX_SAMPLES, sample_times
from fusedmosaic.simulation.pcle import max_n_frames

SMALL = {"fetoscopy": ["--n-frames", "3", "--width", "64", "--height", "64"],
         "pcle": ["--n-frames", "3", "--width", "64", "--height", "64"],
         "checkerboard": ["--n-views", "2", "--width", "128", "--height", "128"]}


def _refused(argv, message, tmp_path, capsys):
    """argv exits 2 at once with `message` (a regex) on stderr, no traceback, and creates
    nothing under tmp_path."""
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert re.search(message, err), err
    assert "Traceback" not in err and "Options" not in err
    assert list(tmp_path.iterdir()) == []
    return err


def _simulate_refused(kind, flags, message, tmp_path, capsys, small=True):
    out = tmp_path / "sim"
    return _refused(["simulate", kind, str(out), *(SMALL[kind] if small else []), *flags,
                     "--quiet"], message, tmp_path, capsys)


# 1. A huge frame count, refused before anything is computed, naming the option ---------------

@pytest.mark.parametrize("kind, flags, message", [
    ("fetoscopy", ["--n-frames", "10000000"],
     rf"^fusedmosaic: error: --n-frames: 1e\+07 frames; at most {MAX_FRAMES} "),
    ("fetoscopy", ["--n-frames", "100000000"], r"^fusedmosaic: error: --n-frames: 1e\+08 frames"),
    ("pcle", ["--n-frames", "10000000"], r"^fusedmosaic: error: --n-frames: 1e\+07 frames"),
    ("pcle", ["--speed-um-per-frame", "1e-6"],
     r"^fusedmosaic: error: --speed-um-per-frame \(--n-frames 0: the whole path\): "
     rf"3\.14159e\+09 frames; at most {MAX_FRAMES}"),
    ("checkerboard", ["--n-views", "100000"],
     rf"^fusedmosaic: error: --n-views x --frames-per-view: 800000 frames; at most {MAX_FRAMES}"),
])
def test_a_huge_frame_count_is_refused_up_front(kind, flags, message, tmp_path, capsys):
    _simulate_refused(kind, flags, message, tmp_path, capsys, small=False)


def test_demo_refuses_a_huge_frame_count_naming_frames(tmp_path, capsys):
    out = tmp_path / "d"
    err = _refused(["demo", "--out", str(out), "--frames", "100000000"],
                   rf"^fusedmosaic: error: --frames: 1e\+08 frames; at most {MAX_FRAMES}",
                   tmp_path, capsys)
    assert "--n-frames" not in err


def test_tracker_samples_name_the_frame_count_when_it_is_the_cause(tmp_path, capsys):
    """MAX_FRAMES frames at 0.2 fps (5 s apart, which run takes) last 5e5 s: 2e7 samples at
    40 Hz. The message names the frames and the frame rate, not only the tracker's rate."""
    _simulate_refused("fetoscopy", ["--n-frames", str(MAX_FRAMES), "--fps", "0.2"],
                      rf"^fusedmosaic: error: --n-frames: {MAX_FRAMES} frames at 0\.2 fps "
                      r"\(--fps\) last 5e\+05 s, over which the tracker at 40 Hz "
                      r"\(--tracker-rate-hz\) takes 2e\+07 samples; at most "
                      + re.escape(f"{MAX_SAMPLES:.3g}"),
                      tmp_path, capsys, small=False)


@pytest.mark.parametrize("kind, flags, message", [
    ("fetoscopy", ["--tracker-margin-s", "1e30"],
     r"^fusedmosaic: error: --tracker-margin-s: 1e\+30 s on both sides of the 0\.08 s of the "
     r"frames at 40 Hz \(--tracker-rate-hz\) is 8e\+31 tracker samples; at most 1e\+07"),
    ("pcle", ["--robot-margin-s", "1e30"],
     r"^fusedmosaic: error: --robot-margin-s: 1e\+30 s on both sides .* robot samples"),
    ("checkerboard", ["--tracker-margin-s", "1e30"], r"^fusedmosaic: error: --tracker-margin-s: "),
    # the rate still named when the rate is the cause
    ("fetoscopy", ["--tracker-rate-hz", "1e300"],
     r"^fusedmosaic: error: --tracker-rate-hz: 1e\+300 Hz over the 0\.08 s"),
    ("pcle", ["--n-frames", "100000", "--fps", "1", "--speed-um-per-frame", "0.001"],
     r"^fusedmosaic: error: --n-frames: 100000 frames at 1 fps \(--fps\): .* 1e\+08 steps of "
     r"the contact dynamics \(1 ms each\); at most 1e\+07"),
])
def test_sample_counts_name_the_margin_or_frames_when_they_are_the_cause(
        kind, flags, message, tmp_path, capsys):
    _simulate_refused(kind, flags, message, tmp_path, capsys)


def test_sample_times_names_the_margin_in_the_api():
    with pytest.raises(ValueError, match=r"^FetoscopyOptions\.tracker_margin_s: 1e\+12 s on "
                                         r"both sides .*\(FetoscopyOptions\.tracker_rate_hz\)"):
        sample_times(FetoscopyOptions(tracker_margin_s=1e12), "tracker", 1.0)


# 2. bench --pcle-frames -----------------------------------------------------------------------

def test_bench_pcle_frames_upper_bound_checked_before_measuring(tmp_path, capsys):
    """--pcle-frames past the simulator's bound failed after the lba-emt stage, in PcleOptions'
    names. The bench laps the circle as often as the frames need (past one lap the probe went
    straight on, where the texture bounded the sequence at 234 frames)."""
    from fusedmosaic.evaluation.benchmark import _bench_pcle_options

    most = max_pcle_frames()
    assert 1000 < most <= MAX_FRAMES
    BenchOptions(pcle_frames=most).check()
    assert _bench_pcle_options(200).laps == 3.0  # 79 frames a lap
    for value in (most + 1, 1000000):
        with pytest.raises(ValueError, match=rf"^pcle_frames: at most {most} \(the simulator's "
                                             rf"bounds\), got {value}$"):
            BenchOptions(pcle_frames=value).check()
        assert main(["bench", "--frames", "60", "--pcle-frames", str(value)]) == 2
        said = capsys.readouterr()
        assert said.err == (f"fusedmosaic: error: --pcle-frames: at most {most} (the "
                            f"simulator's bounds), got {value}\n")
        assert "[bench]" not in said.out  # nothing measured
    help_text = " ".join(build_parser()._subparsers._group_actions[0].choices["bench"]
                         .format_help().split())
    assert f"lapped as often as they need (>= 10, at most the simulator's {MAX_FRAMES}" \
        in help_text


def test_bench_frames_upper_bound(capsys):
    assert main(["bench", "--frames", str(MAX_FRAMES + 1)]) == 2
    said = capsys.readouterr()
    assert said.err == (f"fusedmosaic: error: --frames: at most {MAX_FRAMES} (the simulator's "
                        f"bound), got {MAX_FRAMES + 1}\n")
    assert "[bench]" not in said.out


def test_max_n_frames_bisects_the_validation():
    o = PcleOptions(width=64, height=64)
    most = max_n_frames(o)
    assert 0 < most < MAX_FRAMES
    PcleOptions(width=64, height=64, n_frames=most).validate()
    with pytest.raises(ValueError, match="the frames span up to"):
        PcleOptions(width=64, height=64, n_frames=most + 1).validate()


# 3. pCLE cell size and fibre spacing ---------------------------------------------------------

@pytest.mark.parametrize("flags, message", [
    (["--cell-size-um", "1e30"],
     r"^fusedmosaic: error: --cell-size-um: a cell \(--cell-size-um 1e\+30 µm = 1e\+30 px at "
     r"--pixel-size-um 1 µm\) must be at most 0\.5 x the field of view's 64 px \(the frame\): "
     r"32 µm"),
    (["--cell-size-um", "1e5"], r"^fusedmosaic: error: --cell-size-um: a cell .* at most 0\.5 x"),
    (["--cell-size-um", "40", "--fov-mask-radius", "20"],
     r"^fusedmosaic: error: --cell-size-um: .* the field of view's 40 px \(--fov-mask-radius x "
     r"2\): 20 µm"),
    (["--pixel-size-um", "1e-6"], r"^fusedmosaic: error: --pixel-size-um: a cell \(--cell-size-um "
                                  r"12 µm = 1\.2e\+07 px"),
    (["--fibre-spacing-px", "1e30"],
     r"^fusedmosaic: error: --fibre-spacing-px: must be at most 0\.125 x the field of view's "
     r"64 px \(the frame\): 8 px, got 1e\+30"),
    (["--fibre-spacing-px", "9"], r"^fusedmosaic: error: --fibre-spacing-px: must be at most"),
])
def test_pcle_cell_size_and_fibre_spacing_bounded_by_the_field_of_view(
        flags, message, tmp_path, capsys):
    _simulate_refused("pcle", flags, message, tmp_path, capsys)


def test_pcle_cells_and_fibres_at_their_bounds_render_tissue():
    """The largest cell and fibre spacing allowed still show tissue (no all-black frames, no
    invalid-cast warning; pytest turns warnings into errors)."""
    scene = generate_pcle(PcleOptions(n_frames=3, width=64, height=64, cell_size_um=32.0,
                                      fibre_spacing_px=8.0, contact_loss=False))
    frame = scene.render(1)
    assert frame.max() > 100 and frame.std() > 5


# 4. What simulate writes, run reads ----------------------------------------------------------

@pytest.mark.parametrize("kind, flags, message", [
    ("fetoscopy", ["--fps", "0.05"],
     rf"^fusedmosaic: error: --fps: frames 20 s apart \(0\.05 fps\), more than the "
     rf"{MAX_FRAME_SPACING_S:g} s run accepts between frames"),
    ("pcle", ["--fps", "0.05"], r"^fusedmosaic: error: --fps: frames 20 s apart"),
    ("checkerboard", ["--fps", "0.05"], r"^fusedmosaic: error: --fps: frames 20 s apart"),
    ("fetoscopy", ["--fps", "1e30"],
     r"^fusedmosaic: error: --fps: a tracker at 40 Hz \(--tracker-rate-hz\) against frames at "
     rf"1e\+30 fps \(--fps\) samples every 2\.5e\+28 frames, more than the "
     rf"{MAX_SAMPLE_TO_FRAME_SPACING:g} frames apart run accepts"),
    ("checkerboard", ["--fps", "1e30"], r"^fusedmosaic: error: --fps: a tracker at 40 Hz"),
    ("pcle", ["--fps", "1e30"], r"^fusedmosaic: error: --fps: a robot at 50 Hz"),
    ("pcle", ["--robot-rate-hz", "0.001"],
     r"^fusedmosaic: error: --robot-rate-hz: a robot at 0\.001 Hz \(--robot-rate-hz\) against "
     r"frames at 10 fps"),
    ("fetoscopy", ["--trans-sigma-mm", "1e30"],
     r"^fusedmosaic: error: --trans-sigma-mm: a tracker translation noise of 1e\+30 mm "
     r"\(--trans-sigma-mm x --noise-multiplier\) .* beyond the "
     + re.escape(f"{MAX_TRANSLATION_MM:g} mm")),
    ("fetoscopy", ["--noise-multiplier", "1e30"],
     r"^fusedmosaic: error: --noise-multiplier: a tracker rotation noise of 1e\+30 deg"),
    ("fetoscopy", ["--rot-sigma-deg", "1e30"],
     r"^fusedmosaic: error: --rot-sigma-deg: a tracker rotation noise of 1e\+30 deg "
     r"\(--rot-sigma-deg x --noise-multiplier\); at most 180 deg"),
    ("fetoscopy", ["--noise-multiplier", "100", "--trans-sigma-mm", "1e4"],
     r"^fusedmosaic: error: --trans-sigma-mm: a tracker translation noise of 1e\+06 mm"),
    ("fetoscopy", ["--distance-mm", "1e7"],
     r"^fusedmosaic: error: --distance-mm: the camera moves up to 2e\+07 mm from the tracker's "
     r"origin"),
    ("checkerboard", ["--trans-sigma-mm", "1e30"],
     r"^fusedmosaic: error: --trans-sigma-mm: a tracker translation noise of 1e\+30 mm"),
    ("checkerboard", ["--rot-sigma-deg", "1e30"],
     r"^fusedmosaic: error: --rot-sigma-deg: at most 180 deg"),
    ("pcle", ["--robot-noise", "1e30"],
     r"^fusedmosaic: error: --robot-noise: .* beyond the " + re.escape(f"{MAX_ROBOT_UM:g} µm")),
])
def test_simulate_refuses_what_run_would_refuse(kind, flags, message, tmp_path, capsys):
    _simulate_refused(kind, flags, message, tmp_path, capsys)


def test_the_frame_rate_bounds_are_the_readers(tmp_path):
    """Just inside the bounds, the dataset reads back with every frame tracked; just outside,
    the simulator refuses it."""
    o = {"n_frames": 3, "width": 64, "height": 64, "laps": 0.05}
    slow = 1.0 / MAX_FRAME_SPACING_S
    fast = 0.99 * MAX_SAMPLE_TO_FRAME_SPACING * FetoscopyOptions().tracker_rate_hz
    for fps in (slow, fast):
        data = simulate_fetoscopy(tmp_path / f"fps{fps:g}", FetoscopyOptions(fps=fps, **o))
        ds = read_dataset(data)
        assert ds.pose_valid.all() and len(ds) == 3
    for fps in (0.99 * slow, fast / 0.98):
        with pytest.raises(ValueError, match=r"^FetoscopyOptions\.fps: "):
            FetoscopyOptions(fps=fps, **o).validate()


def test_robot_and_tracker_bounds_accept_the_defaults_and_the_paper_noise():
    FetoscopyOptions(noise_multiplier=10.0).validate()  # paper 000 Sec. 4.2.2 goes to nu = 10
    PcleOptions(robot_noise=3.0).validate()
    CheckerboardOptions(rot_sigma_deg=30.0, trans_sigma_mm=10.0).validate()


# 5. Messages in the command's words ----------------------------------------------------------

def test_texture_message_names_the_option_and_rounds_the_size(tmp_path, capsys):
    err = _simulate_refused(
        "fetoscopy", ["--focal-factor", "1e30"],
        r"^fusedmosaic: error: --focal-factor: the camera path needs a \d\.?\d*e\+31x"
        r"\d\.?\d*e\+31 px texture .*; at most 6e\+07 px: lower --focal-factor, --width or "
        r"--radius-mm, or raise --distance-mm", tmp_path, capsys)
    assert not re.search(r"\d{10}", err) and "radius_mm" not in err


def test_pixel_size_named_when_it_makes_the_cell_under_a_pixel(tmp_path, capsys):
    _simulate_refused("pcle", ["--pixel-size-um", "1e30"],
                      r"^fusedmosaic: error: --pixel-size-um: a pixel of 1e\+30 µm is larger "
                      r"than a cell \(--cell-size-um 12 µm\)", tmp_path, capsys)


def test_checkerboard_board_out_of_view_mentions_the_lens(tmp_path, capsys):
    _simulate_refused("checkerboard", ["--k1", "1e30"],
                      r"^fusedmosaic: error: no view shows the whole 9x6 board inside the 128x128 "
                      r"image through the lens \(--k1, --k2, --p1, --p2 = 1e\+30, 0\.1, 0\.0008, "
                      r"-0\.0005\): raise --distance-mm, lower --square-mm, or give a milder lens",
                      tmp_path, capsys)


def test_bare_black_frames_needs_the_papers_length(tmp_path, capsys):
    last = max(PAPER_BLACK_FRAMES)
    _simulate_refused("fetoscopy", ["--n-frames", "20", "--black-frames"],
                      rf"^fusedmosaic: error: --black-frames: the paper's list \(7, 11, .*, "
                      rf"{last}; Sec\. 4\.2\.3\) needs --n-frames >= {last + 1}, got 20",
                      tmp_path, capsys, small=False)


# 6. Field of view and signed lengths ---------------------------------------------------------

@pytest.mark.parametrize("value", ["3", "15.9", "-2"])
def test_fetoscopy_fov_gets_the_pcle_rule(value, tmp_path, capsys):
    _simulate_refused("fetoscopy", ["--fov-mask-radius", value],
                      r"^fusedmosaic: error: --fov-mask-radius: a field of at least 16 px \(0: the "
                      rf"whole frame, -1: auto\), got {float(value)}", tmp_path, capsys)


def test_fetoscopy_fov_accepts_auto_none_and_16_px():
    for r in (-1.0, 0.0, 16.0):
        FetoscopyOptions(n_frames=3, fov_mask_radius=r).validate()


@pytest.mark.parametrize("flag", ["--contact-loss-um", "--stick-um"])
def test_pcle_contact_heights_are_not_negative(flag, tmp_path, capsys):
    _simulate_refused("pcle", [flag, "-1"], rf"^fusedmosaic: error: {flag}: must be >= 0, got -1",
                      tmp_path, capsys)


def test_signed_offsets_are_accepted_and_their_help_says_what_the_sign_means():
    FetoscopyOptions(n_frames=3, hand_eye_offset_mm=-6.0).validate()
    CheckerboardOptions(hand_eye_offset_mm=-6.0, principal_offset_px=-8.0).validate()
    sub = build_parser()._subparsers._group_actions[0].choices["simulate"]
    kinds = sub._subparsers._group_actions[0].choices
    fetoscopy = " ".join(kinds["fetoscopy"].format_help().split())
    checkerboard = " ".join(kinds["checkerboard"].format_help().split())
    assert "(0 = co-located; negative: the opposite way)" in fetoscopy
    assert "negative: left and down" in checkerboard
    assert "negative: the opposite way" in checkerboard


# 7. The demo's summary -----------------------------------------------------------------------

def test_demo_summary_explains_its_figures_and_flags_a_short_drift_ratio():
    result = {"placed": 20, "frames": 20, "e_M_px": 0.135, "drift_ratio": 4.34}
    lines = _demo_summary("lba-emt", result, 9.2)
    assert lines[0] == ("[demo] lba-emt: 20/20 frames placed, e_M = 0.135 px, drift ratio 4.34 "
                        f"(not meaningful below about {DEMO_DRIFT_MIN_FRAMES} frames: its "
                        "quarters hold 5 of the 20); 9 s in all.")
    assert lines[1].startswith("[demo] e_M: mean error of the frames' placement against the "
                               "simulator's truth, in frame-0 pixels; drift ratio: ")
    assert lines[-1] == "[demo] Look at:"
    long = _demo_summary("lba-emt", {**result, "frames": 150, "placed": 150,
                                     "drift_ratio": 1.04}, 47)
    assert "drift ratio 1.04; 47 s in all." in long[0] and "not meaningful" not in long[0]
    assert long[1] == lines[1]
    none = _demo_summary("lba-emt", {**result, "drift_ratio": None}, 1)
    assert "drift ratio n/a (not meaningful" in none[0]
