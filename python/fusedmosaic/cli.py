"""`fusedmosaic simulate|calibrate|import|run|live|evaluate|demo|bench`: the command-line
entry point."""

from __future__ import annotations

import argparse
import dataclasses
import io
import os
import re
import sys
import time
import typing
import warnings
from pathlib import Path

import numpy as np

from fusedmosaic._entry import OutputsWrittenInterrupt, signals_as_interrupt


# --------------------------------------------------------------------------------------------
# Options generated from the simulators' dataclasses, so the CLI never drifts from the library.
def _add_dataclass_options(parser: argparse.ArgumentParser, cls: type) -> None:
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        flag = "--" + f.name.replace("_", "-")
        hint = hints[f.name]
        default = f.default if f.default is not dataclasses.MISSING else None
        if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
            default = f.default_factory()  # type: ignore[misc]
        args = typing.get_args(hint)
        base = next((a for a in args if a is not type(None)), hint) if args else hint
        help_text = f.metadata.get("help", "") + f" (default: {default})"
        if base is bool:
            parser.add_argument(flag, action=argparse.BooleanOptionalAction, default=default,
                                help=help_text)
        elif typing.get_origin(base) in (list, tuple):
            item = typing.get_args(base)[0] if typing.get_args(base) else str
            parser.add_argument(flag, nargs="*", type=item, default=default, help=help_text)
        else:
            parser.add_argument(flag, type=base, default=default, help=help_text,
                                choices=f.metadata.get("choices"))


def _dataclass_from_args(cls: type, args: argparse.Namespace):
    return cls(**{f.name: getattr(args, f.name) for f in dataclasses.fields(cls)})


def _check_dataset_target(out: str, overwrite: bool) -> None:
    """The dataset folder simulate / import write: absent or empty, or with --overwrite an
    earlier dataset; checked before any work, with the messages naming the flag. Creates
    nothing (write_dataset creates the folder and its parents)."""
    from fusedmosaic.io.dataset import check_not_current_folder, check_replaceable_dataset
    from fusedmosaic.io.output import check_output_dir

    target = check_output_dir(out, "dataset folder", create_parent=False)
    if target.is_dir():  # (even empty: renamed over, the current folder left the shell in a
        # deleted folder, "0.0 MB" said, and simulate fetoscopy failing on ./camera.yaml after
        # writing it: review 47)
        check_not_current_folder(target)
    if target.is_dir() and any(target.iterdir()):
        if not overwrite:
            raise ValueError(f"{target}: exists and is not empty (choose another folder, or pass "
                             "--overwrite to replace the dataset in it)")
        check_replaceable_dataset(target)  # not the cwd, a parent of it, or a non-dataset


_OPTION_CLASSES = r"(?:FetoscopyOptions|PcleOptions|CheckerboardOptions)"


def _option_flags(message: str, renamed: dict[str, str] | None = None) -> str:
    """A simulator's message in the command's words: "FetoscopyOptions.n_frames" ->
    "--n-frames" (or ``renamed[field]``), and a bare "PcleOptions: " dropped."""
    renamed = renamed or {}
    message = re.sub(rf"\b{_OPTION_CLASSES}\.(\w+)",
                     lambda m: renamed.get(m.group(1), "--" + m.group(1).replace("_", "-")),
                     message)
    return re.sub(rf"\b{_OPTION_CLASSES}: ", "", message)


def _cmd_simulate(args: argparse.Namespace) -> int:
    from fusedmosaic.io.output import created_folders_removed_on_failure

    t0 = time.perf_counter()
    _check_dataset_target(args.out, args.overwrite)
    try:
        options = _simulation_options(args)
        options.validate()  # before anything is computed or created
        with created_folders_removed_on_failure(args.out):  # (Ctrl-C, a full disk)
            out = _simulate(args, options)
    except ValueError as exc:  # "FetoscopyOptions.n_frames: ..." -> "--n-frames: ..."
        raise ValueError(_option_flags(str(exc))) from None
    size = sum(p.stat().st_size for p in Path(out).rglob("*") if p.is_file())
    _say(args, f"wrote {args.kind} dataset to {out} ({size / 1e6:.1f} MB) "
               f"in {time.perf_counter() - t0:.1f} s")
    if args.kind == "fetoscopy":
        _warn_low_overlap(out)
    return 0


def _warn_low_overlap(root: Path) -> None:
    """Warns when consecutive simulated frames move by more than half their smaller side (few
    features can match): --laps is per sequence, so few --n-frames make big steps."""
    from fusedmosaic.evaluation.metrics import positions_px
    from fusedmosaic.io import read_camera_yaml, read_homographies_csv
    from fusedmosaic.simulation.fetoscopy import SYN_FRAMES_PER_LAP

    # (the ground truth and the image size only: a dataset simulated with a tracker gap at its
    # start or end is read by run only with --allow-untracked)
    camera = read_camera_yaml(root / "camera.yaml")
    w, h = camera.width, camera.height
    c = positions_px(read_homographies_csv(root / "ground_truth.csv")[1], w, h)
    if len(c) < 2:
        return
    step = float(np.median(np.linalg.norm(np.diff(c, axis=0), axis=1)))
    if step > 0.5 * min(w, h):
        print(f"fusedmosaic: warning: consecutive frames move by {step:.0f} px (median), more "
              f"than half of the {min(w, h)} px side: they barely overlap, and the sequential "
              "methods (lba-emt's window, pairwise) register consecutive frames. --laps is per "
              f"sequence; the SYN motion is ~{SYN_FRAMES_PER_LAP:g} frames per lap (e.g. --laps "
              f"{len(c) / SYN_FRAMES_PER_LAP:.2f} for {len(c)} frames)", file=sys.stderr)


def _simulation_options(args: argparse.Namespace):
    """The simulator's options from the flags (not validated yet)."""
    from fusedmosaic import simulation

    if args.kind == "fetoscopy":
        options = _dataclass_from_args(simulation.FetoscopyOptions, args)
        if options.black_frames == []:  # bare --black-frames: the paper's list (Sec. 4.2.3)
            paper = simulation.PAPER_BLACK_FRAMES
            if options.n_frames <= max(paper):
                raise ValueError(f"--black-frames: the paper's list ({', '.join(map(str, paper))}"
                                 f"; Sec. 4.2.3) needs --n-frames >= {max(paper) + 1}, got "
                                 f"{options.n_frames}; or list the frames to black out")
            options.black_frames = list(paper)
        return options
    if args.kind == "pcle":
        return _dataclass_from_args(simulation.PcleOptions, args)
    return _dataclass_from_args(simulation.CheckerboardOptions, args)


def _simulate(args: argparse.Namespace, options) -> Path:
    from fusedmosaic import simulation

    write = {"fetoscopy": simulation.simulate_fetoscopy, "pcle": simulation.simulate_pcle,
             "checkerboard": simulation.simulate_checkerboard}[args.kind]
    return Path(write(args.out, options, overwrite=args.overwrite))


def _cmd_run(args: argparse.Namespace) -> int:
    from fusedmosaic.io.dataset import check_fps
    from fusedmosaic.runner import check_compositing_options, run_dataset

    if args.fps is not None:
        check_fps(args.fps, "--fps")
    options = None
    overrides: dict = {}
    from fusedmosaic.runner import NEEDS_ROBOT, NEEDS_TRACKING

    _tracker_calibration(args, NEEDS_TRACKING)
    if args.tracker_time_offset:
        from fusedmosaic.io.tracking import check_time_offset

        check_time_offset(args.tracker_time_offset, "--tracker-time-offset")
        if args.method not in NEEDS_TRACKING | NEEDS_ROBOT:
            raise ValueError(f"--tracker-time-offset applies to the methods that use "
                             f"tracking.csv or the robot file "
                             f"({', '.join(sorted(NEEDS_TRACKING | NEEDS_ROBOT))}), not "
                             f"{args.method}")
    if args.robot_file is not None and args.method not in NEEDS_ROBOT:
        raise ValueError(f"--robot-file applies to the methods that use the robot "
                         f"({', '.join(sorted(NEEDS_ROBOT))}), not {args.method}")
    if args.motion_sigma_from:
        if args.method not in ("ba-emt", "lba-emt"):
            raise ValueError(f"--motion-sigma-from applies to ba-emt and lba-emt, not "
                             f"{args.method}")
        from fusedmosaic.estimation.motion import motion_sigma_from_recording

        overrides["motion_sigma"] = tuple(motion_sigma_from_recording(args.motion_sigma_from))
    overrides.update(_emt_sigma(args) | _visual_sigma(args))
    if args.flat_field:
        if args.method not in ("ncc", "kalman-robot"):
            raise ValueError(f"--flat-field applies to ncc and kalman-robot, not {args.method}")
        from fusedmosaic.estimation.translation import RobotPriorOptions

        options = RobotPriorOptions(flat_field=True)
    if args.pair_selection:
        if args.method not in ("ba", "ba-emt", "emt"):
            raise ValueError(f"--pair-selection applies to ba, ba-emt and emt, not {args.method}")
        overrides["pair_selection"] = args.pair_selection
    features = _feature_options(args)
    if features is not None:
        if args.method not in FEATURE_METHODS:
            raise ValueError(f"--detector / --max-features / --clahe / --detect-max-side / "
                             f"--orb-fast-threshold / --keep-specular apply to "
                             f"{', '.join(FEATURE_METHODS)}, not {args.method}")
        overrides["features"] = features
        if args.method == "pairwise":
            from fusedmosaic.estimation.pairwise import PairwiseOptions

            options = PairwiseOptions(features=features)
            overrides = {}
    if args.preset is not None or args.loop_pairs is not None or args.guided_sift:
        if args.method != "lba-emt":
            raise ValueError(f"--preset / --loop-pairs / --guided-sift apply to lba-emt, not "
                             f"{args.method}")
        overrides.update(_lba_overrides(args))
    if args.method == "lba-emt" and (overrides or args.preset is not None):
        from fusedmosaic.estimation.sequential import SequentialOptions

        options = SequentialOptions.preset(args.preset or "syn", **overrides)
    elif overrides:
        from fusedmosaic.estimation.bundle import BundleOptions

        options = BundleOptions(**overrides)
    blend, canvas = _blend_options(args), _canvas_options(args)
    check_compositing_options(blend, canvas, names=COMPOSITING_FLAGS)  # errors name the flags
    summary = run_dataset(args.dataset, args.method, args.out, fps=args.fps,
                          robot_file="robot.csv" if args.robot_file is None else args.robot_file,
                          allow_untracked=args.allow_untracked,
                          progress=_progress(args), options=options, blend=blend,
                          canvas=canvas, video=args.video, report=not args.no_report,
                          live=args.live, tracker_time_offset=args.tracker_time_offset,
                          stop_on_unreadable=args.stop_on_unreadable)
    _say_summary(args, summary)
    return 0


def _tracker_calibration(args: argparse.Namespace, methods) -> None:
    """--calibration CALIB.json: calibrate's tracker time offset and noise in place of
    --tracker-time-offset and (ba-emt / lba-emt) --tracker-rot-sigma / --tracker-trans-sigma;
    refused beside any of them (0 included) or for a method not among `methods` (those that
    use the EM tracker). Leaves args.tracker_time_offset a number (0 when neither is given)."""
    if args.calibration is not None:
        from fusedmosaic.estimation.calibration import read_tracker_calibration

        if args.method not in methods:
            raise ValueError(f"--calibration (an EM tracker's, from calibrate) applies to "
                             f"{', '.join(sorted(methods))}, not {args.method}")
        given = [flag for flag, value in (("--tracker-time-offset", args.tracker_time_offset),
                                          ("--tracker-rot-sigma", args.tracker_rot_sigma),
                                          ("--tracker-trans-sigma", args.tracker_trans_sigma))
                 if value is not None]
        if given:
            raise ValueError(f"--calibration gives the tracker's time offset and noise; "
                             f"{' / '.join(given)} beside it would contradict it: give one or "
                             "the other")
        cal = read_tracker_calibration(args.calibration, dataset=getattr(args, "dataset", None))
        args.tracker_time_offset = cal.time_offset_s
        said = f"tracker time offset {cal.time_offset_s:+.4f} s"
        if cal.time_offset_note:
            said += f" ({cal.time_offset_note})"
        if args.method in ("ba-emt", "lba-emt"):
            args.tracker_rot_sigma = cal.rot_sigma_deg
            args.tracker_trans_sigma = cal.trans_sigma_mm
            said += (f", tracker noise {cal.rot_sigma_deg:.3g} deg / {cal.trans_sigma_mm:.3g} mm "
                     "per axis")
            if getattr(args, "visual_sigma", None) is None:  # (bench/bench_visual_sigma.py)
                said += ("; the keypoints keep the paper's 1 px, which goes with its looser "
                         "1 deg / 1 mm: measure their noise with --visual-sigma auto (README)")
        _say(args, f"from {args.calibration}: {said}")
    if args.tracker_time_offset is None:
        args.tracker_time_offset = 0.0


def _emt_sigma(args: argparse.Namespace) -> dict:
    """{"emt_sigma": (rad x3, mm x3)} from --tracker-rot-sigma / --tracker-trans-sigma (the
    other one the paper's), {} without them; only ba-emt and lba-emt weigh the tracker."""
    if args.tracker_rot_sigma is None and args.tracker_trans_sigma is None:
        return {}
    if args.method not in ("ba-emt", "lba-emt"):
        raise ValueError(f"--tracker-rot-sigma / --tracker-trans-sigma apply to ba-emt and "
                         f"lba-emt, not {args.method}")
    from fusedmosaic.estimation.consistency import default_emt_sigma

    sigma = default_emt_sigma()
    for flag, value, axes, scale in (("--tracker-rot-sigma", args.tracker_rot_sigma, slice(0, 3),
                                      np.pi / 180.0),
                                     ("--tracker-trans-sigma", args.tracker_trans_sigma,
                                      slice(3, 6), 1.0)):
        if value is None:
            continue
        if not (np.isfinite(value) and value > 0):
            raise ValueError(f"{flag} must be a standard deviation > 0, got {value}")
        sigma[axes] = value * scale
    return {"emt_sigma": tuple(float(v) for v in sigma)}


def _visual_sigma(args: argparse.Namespace) -> dict:
    """{"sigma_v_px": px or "auto"} from --visual-sigma, {} without it (the options' 1 px);
    only ba-emt and lba-emt weigh the images against a prior (ba's visual cost alone does not
    depend on it)."""
    if args.visual_sigma is None:
        return {}
    if args.method not in ("ba-emt", "lba-emt"):
        raise ValueError(f"--visual-sigma applies to ba-emt and lba-emt, not {args.method}")
    if args.visual_sigma == "auto":
        return {"sigma_v_px": "auto"}
    try:
        value = float(args.visual_sigma)
    except ValueError:
        value = None
    if value is None or not (np.isfinite(value) and value > 0):
        raise ValueError(f"--visual-sigma must be 'auto' or a standard deviation > 0 (px), got "
                         f"{args.visual_sigma!r}")
    return {"sigma_v_px": value}


def _lba_overrides(args: argparse.Namespace) -> dict:
    """lba-emt's overrides from --loop-pairs and --guided-sift."""
    out = {}
    if args.guided_sift:
        if getattr(args, "detector", None) == "orb":  # (recorded in report.json as if used)
            raise ValueError("--guided-sift applies to --detector sift (ORB's matching is "
                             "guided already)")
        from fusedmosaic.registration.pairs import MatchOptions

        out["matching"] = MatchOptions(guided_sift=True)
    return out | _loop_pairs(args)


def _loop_pairs(args: argparse.Namespace) -> dict:
    if args.loop_pairs is None:
        return {}
    if args.loop_pairs < 0:
        raise ValueError(f"--loop-pairs must be >= 0, got {args.loop_pairs}")
    return {"loop_pairs": args.loop_pairs}


def _cmd_import(args: argparse.Namespace) -> int:
    from fusedmosaic.io.output import created_folders_removed_on_failure
    from fusedmosaic.io.plus import import_plus_sequence
    from fusedmosaic.io.tracking import check_time_offset

    args.tracker_time_offset = args.tracker_time_offset or 0.0  # (None: not given)
    check_time_offset(args.tracker_time_offset, "--tracker-time-offset")
    _check_dataset_target(args.out, args.overwrite)
    # a failure leaves no folder (import_plus_sequence's promise), its parents included
    with created_folders_removed_on_failure(args.out):
        summary = import_plus_sequence(
            args.sequence, args.out, camera=args.camera, hand_eye=args.hand_eye,
            transform=None if args.transform == "auto" else args.transform,
            overwrite=args.overwrite, tracker_time_offset=args.tracker_time_offset)
    _say(args, f"imported {summary}")
    return 0


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from fusedmosaic.estimation.calibration import (
        CalibrationOptions,
        calibrate_recording,
        check_calibration_output,
        write_calibration,
    )
    from fusedmosaic.io.dataset import check_fps
    from fusedmosaic.io.output import check_output_dir, created_folders_removed_on_failure
    from fusedmosaic.runner import check_out_outside_dataset

    if args.fps is not None:
        check_fps(args.fps, "--fps")
    match = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", args.board)
    if match is None:
        raise ValueError(f"--board: expected inner corners as COLUMNSxROWS (e.g. 9x6), got "
                         f"{args.board!r}")
    options = CalibrationOptions(
        board_cols=int(match.group(1)), board_rows=int(match.group(2)),
        square_mm=args.square_mm, distortion=args.distortion, lens_model=args.lens_model,
        every=args.every,
        max_views=args.max_views, rot_sigma_deg=args.tracker_rot_sigma,
        trans_sigma_mm=args.tracker_trans_sigma, time_offset=_time_offset(args.time_offset),
        max_time_offset_s=args.max_time_offset)
    options.validate(names={
        "board_cols": "--board", "board_rows": "--board", "square_mm": "--square-mm",
        "distortion": "--distortion", "lens_model": "--lens-model", "every": "--every",
        "max_views": "--max-views",
        "rot_sigma_deg": "--tracker-rot-sigma", "trans_sigma_mm": "--tracker-trans-sigma",
        "time_offset": "--time-offset", "max_time_offset_s": "--max-time-offset"})
    # nothing created before the work: a failed calibration leaves no folder behind (a failed
    # hand-eye, below, keeps the intrinsics written)
    check_output_dir(args.out, create_parent=False)
    check_out_outside_dataset(Path(args.out), Path(args.recording))
    check_calibration_output(args.out)  # a user's own camera.yaml there: refused before work
    with created_folders_removed_on_failure(args.out):
        result = calibrate_recording(args.recording, options, fps=args.fps,
                                     progress=not args.quiet)
        written = write_calibration(args.out, result)
    r = result.report
    intr = r["intrinsics"]
    K = result.camera.camera_matrix
    model = " (fisheye model)" if intr["lens_model"] == "fisheye" else ""
    _say(args, f"board found in {r['board_found']} of {r['frames_searched']} frames "
               f"({r['distinct_views']} distinct views); intrinsics{model} from {intr['views']} "
               f"views: RMS reprojection {intr['rms_px']:.3f} px, "
               f"fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} px")
    if r["frame_times"] != "frames.csv" and result.hand_eye is not None:
        _say(args, f"frame times: {r['frame_times']}")
    he = r["hand_eye"]
    if "skipped" in he:
        _say(args, f"hand-eye skipped: {he['skipped']}")
    elif "failed" not in he:
        _say_hand_eye(args, he)
    files = "camera.yaml and hand_eye.txt" if result.hand_eye is not None else "camera.yaml"
    _say(args, f"wrote {', '.join(written)} to {args.out} (copy {files} into the datasets "
               "recorded with this scope)")
    # a camera.yaml run refuses (its lens model folds over inside the frame, warned above):
    # written for inspection, but no success
    lens = ("" if result.camera_error is None else
            f"{args.out}/camera.yaml: its lens model folds over inside the frame, so run refuses "
            "it (calibration.json intrinsics.undistortion; the warning above says where and what "
            "to change)")
    if result.hand_eye_error is not None:
        raise ValueError(f"hand-eye failed: {result.hand_eye_error} (the intrinsics are written: "
                         f"{args.out}/camera.yaml)" + (f"; {lens}" if lens else ""))
    if lens:
        raise ValueError(lens)
    return 0


def _say_hand_eye(args: argparse.Namespace, he: dict) -> None:
    """calibrate's summary of a hand-eye (calibration.json's "hand_eye")."""
    offset = he["tracker_time_offset"]
    # against the video: with the shift import gave the recording's tracking.csv (import.json)
    total, imported = offset.get("total_s", offset["applied_s"]), offset.get("import_shift_s")
    if offset.get("estimated"):
        shift = offset["estimate_s"] * 1e3
        _say(args, f"tracker time offset {shift:+.1f} +- {offset['std_s'] * 1e3:.1f} ms "
                   + (f"(applied: the frame at t takes the tracker sample at t {shift:+.1f} ms; "
                      f"give recordings of this set-up run/import --tracker-time-offset "
                      f"{total:.4f}, or run --calibration with this "
                      f"calibration.json: one or the other, not both)" if offset["applied_s"]
                      else f"(not applied: {offset.get('reason', 'not significant')})"))
    else:  # the reason was in calibration.json only
        _say(args, f"tracker time offset {offset['applied_s'] * 1e3:+.1f} ms: not estimated ("
                   + offset.get("reason", "as given with --time-offset") + ")")
    if imported:
        _say(args, f"the recording's tracking.csv was shifted by {imported:+.4f} s at import "
                   f"(import.json): the tracker's clock is {total:+.4f} s ahead of the video's "
                   "in all, which run --calibration with this calibration.json applies (less "
                   "a shift its dataset had at import)")
    if "still_views" in he:
        source = (f"{he['still_views']} still views ({he['tracker_samples']} tracker samples "
                  "taken while the board pose held)")
        noise = "the tracker's own"
    else:
        source = f"{he['views']} frames (the tracker interpolated at the frame times)"
        noise = "after interpolation between samples, below a sample's"
    boot = he["standard_errors"]["bootstrap"]
    scale = he["board_scale"]
    _say(args, f"hand-eye from {source}: expected error {he['rotation_error_rms_deg']:.3f} deg, "
               f"{he['translation_error_rms_mm']:.3f} mm RMS (bootstrap over {boot['clusters']} "
               "groups of views; the intrinsics' errors add to it); tracker noise seen "
               f"{he['tracker_sigma_deg']:.3f} deg, {he['tracker_sigma_mm']:.3f} mm per axis "
               f"({noise}); {len(he['views_beyond_3_sigma'])} views beyond 3 sigma")
    _say(args, f"board against tracker scale {scale['ratio']:.4f} +- {scale['std']:.4f} (1: the "
               "square size and the tracker's mm agree)"
               + (f"; applied: by the tracker the squares measure "
                  f"{scale['square_mm_implied']:.3f} mm" if scale["applied"] else ""))
    if "warning" in he:
        _say(args, f"warning: {he['warning']}")


def _time_offset(text: str) -> float | str:
    if text == "auto":
        return text
    try:
        return float(text)
    except ValueError:
        raise ValueError(f"--time-offset: expected 'auto' or seconds, got {text!r}") from None


def _cmd_live(args: argparse.Namespace) -> int:
    from fusedmosaic.estimation.sequential import SequentialOptions
    from fusedmosaic.io.tracking import check_time_offset
    from fusedmosaic.runner import check_compositing_options, check_live_limits, run_igtl

    _tracker_calibration(args, {"lba-emt"})
    overrides = _lba_overrides(args)
    if args.motion_sigma_from:
        from fusedmosaic.estimation.motion import motion_sigma_from_recording

        overrides["motion_sigma"] = tuple(motion_sigma_from_recording(args.motion_sigma_from))
    overrides.update(_emt_sigma(args) | _visual_sigma(args))
    features = _feature_options(args)
    if features is not None:
        overrides["features"] = features
    if args.method == "lba-emt":
        options = SequentialOptions.preset(args.preset or "syn", **overrides)
    elif overrides or args.preset is not None:
        raise ValueError("--preset / --loop-pairs / --guided-sift / --motion-sigma-from / "
                         f"--tracker-*-sigma / --visual-sigma / feature flags apply to lba-emt, "
                         f"not {args.method}")
    else:
        options = None
    check_live_limits(args.max_frames, args.duration, args.frame_timeout,
                      names={"max_frames": "--max-frames", "duration_s": "--duration",
                             "frame_timeout_s": "--frame-timeout"})
    check_time_offset(args.tracker_time_offset, "--tracker-time-offset")
    if args.view_interval is not None and args.preview is None and args.serve_mosaic is None:
        raise ValueError("--view-interval applies to --preview / --serve-mosaic (the mosaic as "
                         "it grows); neither is given")
    blend, canvas = _blend_options(args), _canvas_options(args)
    check_compositing_options(blend, canvas, names=COMPOSITING_FLAGS)
    if args.method == "lba-emt" and args.hand_eye is None:
        # (a line on stderr, as warnings are shown, under --quiet too; README's live lines
        # give --hand-eye: without it a simulated 4 deg / 6 mm offset gave e_M 6.8 px, not 0.4)
        print("fusedmosaic: warning: live: no --hand-eye: the tracker's sensor is taken as the "
              "camera (sensor_from_camera the identity); a sensor mounted off the camera "
              "places every frame off, and the recording keeps no hand_eye.txt: give "
              "calibrate's hand_eye.txt", file=sys.stderr)
    summary = run_igtl(args.address, args.out, record=args.record, camera=args.camera,
                       transform_device=args.transform, image_device=args.image_device,
                       hand_eye=args.hand_eye, rgb=not args.bgr, options=options,
                       max_frames=args.max_frames, duration_s=args.duration,
                       frame_timeout_s=args.frame_timeout,
                       overwrite_record=args.overwrite_record, progress=_progress(args),
                       blend=blend, canvas=canvas, video=args.video,
                       report=not args.no_report, method=args.method,
                       tracker_time_offset=args.tracker_time_offset,
                       preview=args.preview, serve_mosaic=args.serve_mosaic,
                       view_interval_s=(1.0 if args.view_interval is None
                                        else args.view_interval),
                       bit_depth=args.bit_depth,
                       say=lambda text: _say(args, text),
                       # (what went wrong reaches stderr under --quiet too, as warnings do)
                       warn=lambda text: print(f"fusedmosaic: warning: {text}",
                                               file=sys.stderr))
    _say_summary(args, summary)
    return 0


FEATURE_METHODS = ("lba-emt", "ba-emt", "ba", "emt", "pairwise")


def _feature_options(args: argparse.Namespace):
    """FeatureOptions from --detector/--max-features/--clahe/--detect-max-side/
    --orb-fast-threshold/--keep-specular, or None."""
    from fusedmosaic.registration.features import FeatureOptions

    if (args.detector is None and args.max_features is None and not args.clahe
            and args.detect_max_side is None and args.orb_fast_threshold is None
            and not args.keep_specular):
        return None
    options = FeatureOptions(clahe=args.clahe, max_image_side=args.detect_max_side,
                             mask_specular=not args.keep_specular)
    if args.detector is not None:
        options.detector = args.detector
    if args.max_features is not None:
        options.max_features = args.max_features
    if args.orb_fast_threshold is not None:
        if options.detector != "orb":  # (recorded in report.json as if it had been used)
            raise ValueError("--orb-fast-threshold applies to --detector orb (SIFT has no FAST "
                             "threshold)")
        options.orb_fast_threshold = args.orb_fast_threshold
    options.validate(names={"max_image_side": "--detect-max-side",
                            "detector": "--detector",
                            "max_features": "--max-features",
                            "orb_fast_threshold": "--orb-fast-threshold"})
    return options


# compositing option fields -> the flags that set them (for check_compositing_options' messages)
COMPOSITING_FLAGS = {"blend": "--blend", "border_px": "--border", "bands": "--bands",
                     "max_pixels": "--max-canvas-pixels", "tile_size": "--tile-size"}


def _blend_options(args: argparse.Namespace):
    """BlendOptions from --blend/--border/--bands/--gain-compensation/--keep-specular (blend
    None: the method's preference); None when no compositing flag is given."""
    from fusedmosaic.compositing import BlendOptions

    if args.bands is not None and args.blend != "multiband":
        what = "the method's own blending" if args.blend is None else f"--blend {args.blend}"
        raise ValueError(f"--bands sets the pyramid levels of --blend multiband; it does not "
                         f"apply to {what}")
    if (args.blend is None and not args.border and args.bands is None
            and not args.gain_compensation and not args.keep_specular):
        return None
    return BlendOptions(blend=args.blend, border_px=args.border or 0.0,
                        bands=args.bands if args.bands is not None else BlendOptions.bands,
                        gain_compensation=args.gain_compensation,
                        mask_specular=False if args.keep_specular else None)


def _canvas_options(args: argparse.Namespace):
    from fusedmosaic.compositing import CanvasOptions

    canvas = CanvasOptions()
    if args.max_canvas_pixels is not None:
        canvas.max_pixels = args.max_canvas_pixels
    if args.tile_size is not None:
        canvas.tile_size = args.tile_size
    canvas.alpha = args.alpha
    return canvas


def _measure(value, digits: int) -> str:
    """An evaluation measure as text; "n/a" for an undefined one (None, or NaN from older
    evaluation files)."""
    return "n/a" if value is None or np.isnan(value) else f"{value:.{digits}f}"


def _format_table(results: list[dict]) -> str:
    from fusedmosaic.evaluation.metrics import evaluation_notes

    header = f"{'output':<40} {'placed':>7} {'e_M px':>9} {'max e_j':>9} {'drift':>7}"
    lines = [header, "-" * len(header)]
    for r in results:
        lines.append(f"{Path(r['output']).name[:40]:<40} {r['placed']:>4}/{r['frames']:<2} "
                     f"{_measure(r['e_M_px'], 3):>9} {_measure(r['max_e_j_px'], 3):>9} "
                     f"{_measure(r['drift_ratio'], 2):>7}")
        if r.get("frames_scored", r["frames"]) < r["frames"]:
            lines.append(f"  e_M over {r['frames_scored']} of {r['frames']} frames (placed, "
                         "with a ground-truth homography)")
        lines += [f"  {note}" for note in evaluation_notes(r)]
        if r.get("drift_ratio_note"):
            lines.append(f"  drift {_measure(r['drift_ratio'], 2)}: {r['drift_ratio_note']}")
        for key, which in (("position_all_um", "all "), ("position_sampled_um", "")):
            if key in r:
                s = r[key]
                stats = " ".join(f"{k} {_measure(s[k], 1)}" for k in ("mean", "max", "std",
                                                                      "median"))
                frames = f"{which}{s['n']}" if which else f"{s['n']} frames"
                lines.append(f"{'':<40} position error µm ({frames}): {stats}")
    return "\n".join(lines)


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from fusedmosaic.evaluation import compare_position_errors, evaluate_output
    from fusedmosaic.evaluation.metrics import check_positions_n, read_truth_dataset
    from fusedmosaic.io.output import OutputWriter, check_output_dir, is_under

    if args.positions is not None:
        check_positions_n(args.positions, "--positions")
    outs = [Path(args.out), *(Path(p) for p in args.compare or [])]
    # Where the results go is checked first; nothing is written until everything succeeded.
    json_path = Path(args.json) if args.json else outs[0] / "evaluation.json"
    md_path = json_path.with_suffix(".md")
    if json_path.is_dir():
        raise ValueError(f"--json {json_path}: is a folder; give a file name, e.g. "
                         f"{json_path / 'evaluation.json'}")
    if md_path == json_path:
        raise ValueError(f"--json {json_path}: the report goes to NAME.md beside NAME.json; "
                         "give a .json file name")
    truth = Path(args.truth)
    if truth.is_dir() and is_under(json_path.parent, truth, or_equal=True):
        # (e.g. its video.json would be read as a second recording beside frames/)
        raise ValueError(f"--json {json_path}: would be written inside the truth dataset "
                         f"folder {truth}, which it would corrupt; choose a path outside it")
    try:
        check_output_dir(json_path.parent, "folder of the evaluation JSON",
                         create_parent=False)
    except ValueError as exc:
        raise ValueError(f"--json {json_path}: {exc}") from None
    plots = md_path.stem + "_plots"
    older = _check_report_destination(json_path, plots, report=not args.no_report)
    # read once for every output, the --positions frames and the report (a video dataset is
    # decoded end to end when read: 3 passes for one comparison; review)
    dataset = read_truth_dataset(args.truth)
    results = [evaluate_output(o, dataset, positions_n=args.positions,
                               allow_other_dataset=args.allow_other_dataset) for o in outs]
    # (shown on the terminal, and in evaluation.md beside the scores they put in doubt)
    notes = []
    for r in results:
        for key, kind in (("dataset_warning", "warning"), ("truth_note", "note"),
                          ("provenance_note", "note")):
            if key in r:
                print(f"fusedmosaic: {kind}: {r[key]}", file=sys.stderr)
                notes.append(f"**{kind.capitalize()}:** {r[key]}")
    report: dict = {"results": results}
    if len(results) > 1 and "position_errors_um" in results[0]:
        # with --positions, on the frames its statistics are over, as seed 004 (Sec. IV-B)
        # tests its n = 13 / 25 evenly spaced images (among the frames with a truth); else on
        # every frame
        frames = (slice(None) if args.positions is None
                  else _sampled_indices(dataset, results[0]["position_sampled_frames"]))
        sample = ({"frames": "all"} if args.positions is None
                  else {"frames": "positions", "positions": args.positions})
        base = _position_errors(results[0], dataset)[frames]
        report["wilcoxon"] = []
        for r in results[1:]:
            other = _position_errors(r, dataset)[frames]
            pair = {"a": results[0]["output"], "b": r["output"], **sample}
            both = int((~np.isnan(base) & ~np.isnan(other)).sum())
            if both < 2:  # this pair has no test; the others still do
                pair.update(n=both, statistic=None, p_value=None, note=(
                    f"n/a: {both} frame{'' if both == 1 else 's'} placed by both (the test "
                    "needs at least 2)"))
            else:
                pair.update(compare_position_errors(base, other))
            report["wilcoxon"].append(pair)
    loaded = None if args.no_report else _load_for_report(outs, dataset)
    _say(args, _format_table(results))
    for w in report.get("wilcoxon", []):
        over = "" if w["frames"] == "all" else f" at the {w['positions']} evenly spaced frames"
        _say(args, f"Wilcoxon signed-rank {Path(w['a']).name} vs {Path(w['b']).name}{over}: "
                   + _wilcoxon_text(w))
    if loaded is not None:  # the µm statistics, the tests and the drift notes in the .md too
        notes += _evaluation_md_notes(results, report.get("wilcoxon", []),
                                      [run.label for run in loaded[0]])
    # json, .md and plots replace the previous evaluation of that name as one set, or not at
    # all; an evaluation of the output folder it is written into goes when that folder is run
    # again.
    here = json_path.parent.resolve()
    expects = [json_path.name] + ([] if loaded is None else [md_path.name, plots + "/"])
    with OutputWriter(json_path.parent, record=f"evaluation:{json_path.name}",
                      stale_after_run=any(o.resolve() == here for o in outs), expects=expects,
                      replaces=older) as w:
        w.write_json(json_path.name, report)  # strict JSON: NaN / inf as null
        if loaded is not None:
            from fusedmosaic.evaluation.report import EVALUATION_TITLE, write_report

            runs, truth = loaded
            with w.named_errors(md_path.name, "the report") as staged:
                write_report(staged.parent, runs, truth, name=md_path.name,
                             title=EVALUATION_TITLE, plots_dir=plots, notes=notes)
    _say(args, f"wrote {json_path}")
    if loaded is not None:
        _say(args, f"wrote {md_path} (plots in {md_path.parent / plots})")
    return 0


def _wilcoxon_text(w: dict) -> str:
    """A Wilcoxon entry of evaluation.json as text: "p = ... (n = ...)", with the pairs ranked
    when ties (|difference| <= WILCOXON_ZERO) were dropped, or its note when it has no test."""
    if w["p_value"] is None:
        return w["note"]
    n = f"n = {w['n']}"
    if w.get("n_ranked", w["n"]) != w["n"]:
        n += f", {w['n_ranked']} ranked"
    return f"p = {w['p_value']:.3g} ({n})" + (f": {w['note']}" if w.get("note") else "")


def _position_errors(result: dict, truth) -> np.ndarray:
    """An evaluate_output result's µm position errors per frame as an array: NaN where it has
    none (null: unplaced, or no truth), inf for the frames it lists as "position_at_infinity"
    (null in the JSON too, but placed: the Wilcoxon test ranks them as the worst instead of
    dropping them as unplaced; review 52). `truth`: the truth Dataset (its frame ids)."""
    errors = np.array([np.nan if e is None else e for e in result["position_errors_um"]],
                      np.float64)
    at_infinity = result.get("position_at_infinity") or []
    if at_infinity:
        errors[np.isin(np.asarray(truth.frame_ids), at_infinity)] = np.inf
    return errors


def _sampled_indices(truth, sampled_ids: list[int]) -> np.ndarray:
    """Positions (rows of position_errors_um) of the frames --positions sampled; `truth`: the
    truth Dataset."""
    return np.flatnonzero(np.isin(truth.frame_ids, sampled_ids))


def _evaluation_md_notes(results: list[dict], wilcoxon: list[dict], labels: list[str]) -> list:
    """evaluation.md's notes beside its table: the drift ratio's notes, the µm position
    statistics (seed 004, Tables I-II) and the Wilcoxon tests."""
    from fusedmosaic.evaluation.metrics import evaluation_notes

    notes = [f"**{label}:** {note}" for label, r in zip(labels, results, strict=True)
             for note in evaluation_notes(r)]
    notes += [f"**Drift ratio ({label}):** {r['drift_ratio_note']}"
              for label, r in zip(labels, results, strict=True) if r.get("drift_ratio_note")]
    rows = []
    for label, r in zip(labels, results, strict=True):
        for key, which in (("position_all_um", "all"), ("position_sampled_um", "evenly spaced")):
            if key in r:
                s = r[key]
                rows.append(f"| {label} | {which} | {s['n']} | "
                            + " | ".join(_measure(s[k], 2) for k in ("mean", "max", "std",
                                                                      "median")) + " |")
    if rows:
        sampled = results[0].get("position_sampled_frames")
        notes.append("\n".join(
            ["## Position errors (µm)", "",
             "Distance between estimated and true image positions (seed 004, Sec. IV-B)"
             + (f"; evenly spaced frames: {', '.join(map(str, sampled))}." if sampled else "."),
             "", "| method | frames | n | mean | max | std | median |",
             "|---|---|---|---|---|---|---|", *rows]))
    if wilcoxon:
        by_output = {r["output"]: label for label, r in zip(labels, results, strict=True)}
        from fusedmosaic.evaluation.metrics import WILCOXON_ZERO

        lines = ["## Wilcoxon signed-rank tests", "",
                 f"Paired position errors (µm) per frame; differences of at most "
                 f"{WILCOXON_ZERO:g} µm are ties, not ranked; a frame placed at infinity "
                 "counts as the largest difference; frames only one output places are not "
                 "paired (counted in the p column's note).", "",
                 "| a | b | frames | n | ranked | p |",
                 "|---|---|---|---|---|---|"]
        for w in wilcoxon:
            over = "all" if w["frames"] == "all" else f"{w['positions']} evenly spaced"
            p = w["note"] if w["p_value"] is None else (
                f"{w['p_value']:.3g}" + (f" ({w['note']})" if w.get("note") else ""))
            lines.append(f"| {by_output.get(w['a'], w['a'])} | {by_output.get(w['b'], w['b'])} "
                         f"| {over} | {w['n']} | {w.get('n_ranked', '–')} | {p} |")
        notes.append("\n".join(lines))
    return notes


def _demo_dataset_options(data: Path) -> dict:
    """The simulator options of the dataset an earlier demo left in ``data`` (its
    simulation.json), so that a demo with other --frames / --motion simulates again instead of
    reusing it. Anything else in that folder is the user's: ValueError naming it."""
    from fusedmosaic.io.output import read_json_object

    try:
        info = read_json_object(data / "simulation.json")
    except (OSError, ValueError):
        info = {}
    if (info.get("simulator") != "fetoscopy" or not isinstance(info.get("options"), dict)
            or not (data / "camera.yaml").is_file()):
        raise ValueError(f"{data}: exists and is not a sequence a fusedmosaic demo simulated "
                         "(no simulation.json or camera.yaml); choose another --out, or move it")
    return info["options"]


def _check_report_destination(json_path: Path, plots: str, *, report: bool) -> list[str]:
    """NAME.json, and NAME.md and NAME_plots/ beside it, are replaced only when a fusedmosaic
    evaluation wrote them: recorded in the folder's manifest, or (older versions, no record)
    NAME.json is an evaluation, and then NAME.md if it starts with the report's title line and
    NAME_plots/ if it holds only PNG files. Otherwise they are the user's: NAME.json is an
    error; the report's files are an error when there is a report to write, and left alone
    without.

    Returns the older version's names for OutputWriter(replaces=...): replaced, or removed when
    not written again (--no-report), so only what is surely ours."""
    from fusedmosaic.io.output import read_json_object, read_manifest

    md_path = json_path.with_suffix(".md")
    sets = read_manifest(json_path.parent) or {}
    recorded = {f for s in sets.values() for f in s["files"]}
    older: list[str] = []
    if f"evaluation:{json_path.name}" not in sets:
        try:
            previous = read_json_object(json_path)
        except (OSError, ValueError):
            previous = {}
        if _is_evaluation(previous):
            plots_dir = json_path.parent / plots
            if _is_evaluation_report(md_path):
                older.append(md_path.name)
            if plots_dir.is_dir() and not plots_dir.is_symlink() and all(
                    p.is_file() and not p.is_symlink() and p.suffix.lower() == ".png"
                    for p in plots_dir.iterdir()):
                older.append(plots + "/")
        elif json_path.exists() or json_path.is_symlink():
            raise ValueError(f"--json {json_path}: exists and is not an evaluation fusedmosaic "
                             "wrote; choose another --json name, or move that file")
    if not report:
        return older
    if md_path.exists() and md_path.name not in recorded and md_path.name not in older:
        raise ValueError(f"--json {json_path}: the report would replace {md_path}, which no "
                         "fusedmosaic evaluation wrote; choose another --json name, move that "
                         "file, or pass --no-report")
    plots_dir = json_path.parent / plots
    if (plots_dir.exists() and not any(f.startswith(plots + "/") for f in recorded)
            and plots + "/" not in older):
        raise ValueError(f"--json {json_path}: the report's plots would go into {plots_dir}, "
                         "a folder no fusedmosaic evaluation wrote; choose another --json name, "
                         "move that folder, or pass --no-report")
    return older


def _is_evaluation(obj: dict) -> bool:
    """An evaluation JSON as `evaluate` writes it: a non-empty "results" list of results of
    evaluate_output (with the keys every version wrote). {"results": [...]} alone is a common
    layout of a user's own files."""
    from fusedmosaic.evaluation.metrics import RESULT_KEYS

    results = obj.get("results")
    return (isinstance(results, list) and len(results) > 0
            and all(isinstance(r, dict) and all(k in r for k in RESULT_KEYS) for r in results))


def _is_evaluation_report(md_path: Path) -> bool:
    """NAME.md starts with the line write_report writes first for `evaluate` (its title)."""
    from fusedmosaic.evaluation.report import EVALUATION_TITLE

    if not md_path.is_file() or md_path.is_symlink():
        return False
    try:
        with md_path.open("rb") as f:
            first = f.readline(200)
    except OSError:
        return False
    return first.rstrip(b"\r\n") == f"# {EVALUATION_TITLE}".encode()


def _load_for_report(outs: list[Path], truth_dataset):
    """What evaluation.md shows (e_j of every output on one plot, poses, plane, timing), read
    and checked before anything is written; `truth_dataset`: the truth Dataset."""
    from fusedmosaic.evaluation.report import load_run, truth_from_dataset

    truth = truth_from_dataset(truth_dataset)
    runs = [load_run(o, truth.frame_ids) for o in outs]
    labels = [r.label for r in runs]
    for r in runs:  # the same method twice: tell them apart by folder
        if labels.count(r.label) > 1:
            r.label = f"{r.label} ({Path(r.output).name})"
    return runs, truth


def _cmd_demo(args: argparse.Namespace) -> int:
    from fusedmosaic.io.output import check_output_dir

    if args.frames < 2:  # a mosaic needs two frames (lba-emt registers a pair to start)
        raise ValueError(f"--frames must be >= 2, got {args.frames}")
    try:  # the simulator's bounds (frame count, tracker samples) before anything is made
        _demo_options(args).validate()
    except ValueError as exc:
        raise ValueError(_option_flags(str(exc), {"n_frames": "--frames"})) from None
    if (Path(args.out) / "camera.yaml").is_file() or (Path(args.out) / "frames").is_dir():
        raise ValueError(f"{args.out}: is a dataset folder; writing the demo there would corrupt "
                         "it: choose --out outside it")
    made = not Path(args.out).exists()
    root = check_output_dir(args.out, "demo folder")
    try:
        return _demo_into(args, root)
    except BaseException:  # Ctrl-C / SIGTERM in the simulation: no empty OUT left behind
        if made and root.is_dir() and not any(root.iterdir()):
            root.rmdir()
        raise


def _demo_asked(args: argparse.Namespace) -> dict:
    """The FetoscopyOptions fields the demo sets."""
    from fusedmosaic import simulation

    asked = {"n_frames": args.frames, "motion": args.motion}
    if args.motion == "syn":
        # the SYN pace whatever the length (150 frames: the paper's 4 laps); at 4 laps, 12
        # frames were 120 degrees apart and no method could place them (ba-emt 277 px)
        asked["laps"] = args.frames / simulation.fetoscopy.SYN_FRAMES_PER_LAP
    return asked


def _demo_options(args: argparse.Namespace):
    from fusedmosaic import simulation

    return simulation.FetoscopyOptions(**_demo_asked(args))


# Below this many frames the drift ratio's quarters hold under 10 frames each, at errors of
# ~0.1 px: their ratio is noise, not drift.
DEMO_DRIFT_MIN_FRAMES = 40


def _demo_summary(method: str, result: dict, seconds: float) -> list[str]:
    """What the demo says of its result: the figures (the drift ratio flagged as noise on a
    short sequence), what they mean, and "Look at:" (the files follow)."""
    n = result["frames"]
    short = ""
    if n < DEMO_DRIFT_MIN_FRAMES:
        short = (f" (not meaningful below about {DEMO_DRIFT_MIN_FRAMES} frames: its quarters "
                 f"hold {max(n // 4, 1)} of the {n})")
    return [f"[demo] {method}: {result['placed']}/{n} frames placed, e_M = "
            f"{_measure(result['e_M_px'], 3)} px, drift ratio "
            f"{_measure(result['drift_ratio'], 2)}{short}; {seconds:.0f} s in all.",
            "[demo] e_M: mean error of the frames' placement against the simulator's truth, in "
            "frame-0 pixels; drift ratio: mean error over the last "
            "quarter of the frames / over the first (about 1: the error does not grow).",
            "[demo] Look at:"]


def _demo_into(args: argparse.Namespace, root: Path) -> int:
    import json

    from fusedmosaic import methods, simulation
    from fusedmosaic.compositing import (
        BlendOptions,
        CanvasOptions,
        plan_canvas,
        render_mosaic,
        write_mosaic_png,
    )
    from fusedmosaic.evaluation import evaluate_output
    from fusedmosaic.io import read_dataset, read_homographies_csv
    from fusedmosaic.io.output import OutputWriter
    from fusedmosaic.runner import frames_to_compose, run_dataset

    data = root / "dataset"
    t0 = time.perf_counter()
    earlier = None
    if data.is_symlink() or (data.exists() and not (data.is_dir() and not any(data.iterdir()))):
        earlier = _demo_dataset_options(data)
    asked = _demo_asked(args)
    if earlier is not None and all(earlier.get(k) == v for k, v in asked.items()):
        _say(args, f"[demo] reusing the simulated sequence in {data}")
    else:
        if earlier is not None:
            pace = ""
            if (earlier.get("n_frames"), earlier.get("motion")) == (args.frames, args.motion):
                pace = f" over {earlier.get('laps')} laps (the demo's: {asked.get('laps'):g})"
            _say(args, f"[demo] {data} holds a {earlier.get('motion')} sequence of "
                       f"{earlier.get('n_frames')} frames{pace}; simulating the one asked for")
        simulation.simulate_fetoscopy(data, simulation.FetoscopyOptions(**asked),
                                      overwrite=earlier is not None)
        _say(args, f"[demo] simulated a {args.motion} fetoscopy sequence ({args.frames} frames, "
                   f"EM tracker at 40 Hz, ground truth): {data}")
    names = methods.available()
    if not names:
        raise SystemExit("no mosaicking method is registered yet")
    method = names[0]
    out = root / method
    _say(args, f"[demo] running {method} ({methods.REGISTRY[method][1]}) ...")
    run_dataset(data, method, out, progress=_progress(args),
                blend=BlendOptions("multiband"), video=out / "creation.mp4")
    # The paper's demonstration look (seed 000 Sec. 4.2): linear blending with a thin black
    # border per frame, which shows where each frame was stitched; of the frames mosaic.png
    # shows (those it left out, report.json mosaic.skipped_frames, are left out here too), in
    # one piece or tile by tile as mosaic.png, and not at all when mosaic.png was skipped.
    dataset = read_dataset(data)
    ids, G = read_homographies_csv(out / "homographies.csv")
    mosaic = json.loads((out / "report.json").read_text(encoding="utf-8")).get("mosaic") or {}
    left_out = [int(k) for k in (mosaic.get("skipped_frames") or {})]
    G = np.where(np.isin(ids, left_out)[:, None, None], np.nan, G)
    cam = dataset.camera
    frames, mask = frames_to_compose(dataset)  # lba-emt: undistorted pixels
    # (highlights masked as mosaic.png's were: report.json mosaic.mask_specular, the method's)
    canvas = CanvasOptions()
    seams_blend = BlendOptions("linear", border_px=1.5,
                               mask_specular=bool(mosaic.get("mask_specular", False)))
    plan = None
    if mosaic.get("file"):
        plan = plan_canvas(G, cam.width, cam.height, max_pixels=canvas.max_pixels,
                           absurd_area_factor=canvas.absurd_area_factor)
    result = evaluate_output(out, data)
    with OutputWriter(out, record="demo", stale_after_run=True,
                      expects=["mosaic_seams.png"] * (plan is not None) + ["evaluation.json"]
                      ) as w:
        if plan is not None and plan.pixels > canvas.in_memory_pixels:
            with w.named_errors("mosaic_seams.png", "the image") as staged:
                write_mosaic_png(staged, frames, G, cam.width, cam.height, mask=mask,
                                 blend=seams_blend, canvas=canvas, plan=plan)
        elif plan is not None:
            w.write_image("mosaic_seams.png", render_mosaic(
                frames, G, cam.width, cam.height, mask=mask, blend=seams_blend, plan=plan,
                max_pixels=canvas.max_pixels).image)
        w.write_json("evaluation.json", result)
    _say(args, _format_table([result]))
    for line in _demo_summary(method, result, time.perf_counter() - t0):
        _say(args, line)
    for name, what in (("report.md", "report: accuracy per frame, poses vs tracker vs truth, "
                                     "plane, timing (plots in plots/)"),
                       ("mosaic.png", "mosaic, multi-band blending"),
                       ("mosaic_seams.png", "mosaic, linear blending with each frame's border"),
                       ("creation.mp4", "video of the sequential creation")):
        if (out / name).exists():
            _say(args, f"  {out / name}  {what}")
    return 0


def _cmd_bench(args: argparse.Namespace) -> int:
    from fusedmosaic.evaluation.benchmark import (
        BenchOptions,
        check_json_destination,
        format_benchmark,
        run_benchmark,
        write_json,
    )

    options = BenchOptions(frames=args.frames, detector=args.detector,
                           pcle_frames=args.pcle_frames, offline=args.offline, seed=args.seed)
    try:
        options.check()
    except ValueError as exc:  # "frames: ..." -> "--frames: ..."
        raise ValueError(re.sub(r"^(\w+)", lambda m: "--" + m.group(1).replace("_", "-"),
                                str(exc))) from None
    json_path = Path(args.json) if args.json else None
    if json_path is not None:  # checked before the measuring; a user's file is not replaced
        try:
            check_json_destination(json_path)
        except ValueError as exc:
            raise ValueError(f"--json {exc}") from None
    result = run_benchmark(options, say=lambda text: _say(args, text))
    _say(args, format_benchmark(result))
    if json_path is not None:
        write_json(json_path, result)
        _say(args, f"wrote {json_path}")
    return 1 if args.strict and not result["all_ok"] else 0


def _progress(args: argparse.Namespace) -> bool:
    """Progress bars only for a person watching a terminal."""
    return not getattr(args, "quiet", False) and sys.stderr.isatty()


def _say(args: argparse.Namespace, text: str) -> None:
    if not getattr(args, "quiet", False):
        _print_out(text)


def _print_out(text: str) -> None:
    """`text` on stdout, at once. A reader that went away (`fusedmosaic run ... | head -1`) is
    no error: stdout only informs, the outputs are files and the exit status says whether they
    were written (the summary of a complete run into a closed pipe was "error: Broken pipe",
    exit 1; review 47). From there stdout goes to the null device, and the command goes on."""
    try:
        print(text, flush=True)
    except BrokenPipeError:
        null = os.open(os.devnull, os.O_WRONLY)
        try:  # (fd 1 itself, so that the text still buffered is flushed there at exit)
            os.dup2(null, sys.stdout.fileno())
        except (OSError, ValueError):  # stdout is no file (replaced by a caller)
            sys.stdout = open(os.devnull, "w")  # noqa: SIM115 (open until exit)
        finally:
            os.close(null)


def _say_summary(args: argparse.Namespace, summary: str) -> None:
    """A run's summary, said once its outputs are in OUT (a Ctrl-C while it prints says so, not
    "interrupted" alone, which tells that nothing was left; review Z 47)."""
    try:
        _say_summary_lines(args, summary)
    except OutputsWrittenInterrupt:
        raise
    except KeyboardInterrupt:
        raise OutputsWrittenInterrupt(args.out) from None


def _say_summary_lines(args: argparse.Namespace, summary: str) -> None:
    """The summary; under --quiet its warnings (the checks after the fusion: a tracker or
    robot in another convention) still reach stderr, as every other warning does."""
    if not getattr(args, "quiet", False):
        _print_out(summary)
        return
    from fusedmosaic.runner import WARNING_LINE

    for line in summary.splitlines():
        if line.startswith(WARNING_LINE):
            print(f"fusedmosaic: warning: {line[len(WARNING_LINE):]}", file=sys.stderr)


def build_parser() -> argparse.ArgumentParser:
    from fusedmosaic import __version__, methods, simulation

    parser = argparse.ArgumentParser(
        prog="fusedmosaic",
        description="Drift-free mosaics of a planar surface from an endoscope video fused with "
                    "an external pose source: an EM tracker (fetoscopy) or a robot (confocal "
                    "endomicroscopy). `fusedmosaic demo` runs it all on simulated data.")
    parser.add_argument("--quiet", action="store_true", help="print nothing but errors")
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    quiet = argparse.ArgumentParser(add_help=False)  # --quiet after the command works too
    quiet.add_argument("--quiet", action="store_true", default=argparse.SUPPRESS,
                       help="print nothing but errors (no progress bars)")

    sim = sub.add_parser("simulate", help="write a simulated dataset (with ground truth)")
    sim_sub = sim.add_subparsers(dest="kind", required=True)
    for kind, cls, what in (
            ("fetoscopy", simulation.FetoscopyOptions, "fetoscopy dataset"),
            ("pcle", simulation.PcleOptions, "pcle dataset"),
            ("checkerboard", simulation.CheckerboardOptions,
             "tracked checkerboard recording, for `fusedmosaic calibrate`")):
        p = sim_sub.add_parser(kind, help=f"{what} (see fusedmosaic.simulation)",
                               parents=[quiet])
        p.add_argument("out", help="output dataset folder (must not exist or be empty)")
        p.add_argument("--overwrite", action="store_true",
                       help="replace an earlier dataset in OUT with everything in it (OUT must "
                            "hold camera.yaml or simulation.json, and not be the current folder "
                            "or hold it)")
        _add_dataclass_options(p, cls)
        p.set_defaults(func=_cmd_simulate)

    run = sub.add_parser("run", help="mosaic a dataset with one method", parents=[quiet])
    run.add_argument("dataset", help="dataset folder (camera.yaml, frames/ or video, tracking "
                                     "or robot file; see the README's dataset contract)")
    run.add_argument("--method", required=True,
                     help="one of: " + (", ".join(methods.available()) or "(none yet)"))
    run.add_argument("--out", required=True, help="output folder")
    run.add_argument("--fps", type=float, default=None,
                     help="frame rate giving the frame times when the dataset has no frames.csv "
                          "(default: the video's own frame rate, else 25)")
    run.add_argument("--robot-file", default=None,
                     help="robot / kalman-robot: robot positions file inside the dataset "
                          "(default robot.csv)")
    _add_tracker_time_offset_flag(
        run, "the sample for the frame at time t is tracking.csv's (robot / kalman-robot: the "
             "robot file's) at t + S")
    run.add_argument("--pair-selection", choices=["all", "emt-guided", "window"],
                     help="ba / ba-emt / emt: which image pairs to match (default: all for ba and "
                          "ba-emt as in the paper, emt-guided for emt)")
    run.add_argument("--flat-field", action="store_true",
                     help="ncc / kalman-robot: divide the frames by the fibre bundle's fixed "
                          "pattern (the mean of the recording's frames) before registration")
    run.add_argument("--allow-untracked", action="store_true",
                     help="flag frames outside the tracker's (or the robot's) time span "
                          "instead of failing (implied by --live)")
    run.add_argument("--stop-on-unreadable", action="store_true",
                     help="fail at a frame that cannot be read (a damaged PNG, an undecodable "
                          "video frame); by default it is taken as a frame without visual "
                          "content, flagged (report.json unreadable_frames, a warning) and left "
                          "out of the mosaic")
    run.add_argument("--live", action="store_true",
                     help="lba-emt / kalman-robot / ncc / robot: replay the recording as a live "
                          "source on this "
                          "machine (frames at their timestamps with the newest tracker/robot "
                          "sample; frames arriving while one is processed are dropped, except "
                          "the newest); report.json 'live' gives drops and latency")
    _add_lba_flags(run)
    _add_feature_flags(run, "features (lba-emt, ba-emt, ba, emt, pairwise)")
    _add_compositing_flags(run)
    run.set_defaults(func=_cmd_run)

    imp = sub.add_parser(
        "import", parents=[quiet],
        help="turn a PLUS toolkit sequence file (tracked video, .mha/.mhd) into a dataset")
    imp.add_argument("sequence", help="PLUS sequence metafile (*.seq.mha, *.igs.mha, or .mhd "
                                      "with its data file)")
    imp.add_argument("out", help="dataset folder to write (must not exist or be empty)")
    _add_tracked_camera_flags(
        imp, transform="the sensor's transform field, tracker_from_sensor (default "
                       "SensorToTracker; stored inverted it is inverted back; 'auto' takes the "
                       "single *ToTracker / *ToReference field)", default="SensorToTracker",
        camera_help="; without it camera.yaml holds the image size only: a checkerboard "
                    "recording for `fusedmosaic calibrate`, which writes the camera.yaml")
    imp.add_argument("--overwrite", action="store_true",
                     help="replace an earlier dataset in OUT")
    _add_tracker_time_offset_flag(
        imp, "tracking.csv is written on the video's clock, its timestamps shifted by -S")
    imp.set_defaults(func=_cmd_import)

    cal = sub.add_parser(
        "calibrate", parents=[quiet],
        help="camera intrinsics and hand-eye transform from a tracked checkerboard recording",
        description="Finds a checkerboard in the recording's frames (frames/ or video.*, "
                    "frames.csv, tracking.csv as in a dataset; camera.yaml optional), computes "
                    "the intrinsics and lens distortion (OpenCV calibrateCamera) and, with "
                    "tracking.csv, the hand-eye transform sensor_from_camera (maximum likelihood "
                    "under the tracker's noise), and writes camera.yaml, hand_eye.txt and "
                    "calibration.json to --out.")
    cal.add_argument("recording", help="recording folder (frames/ or video.*, frames.csv, "
                                       "tracking.csv)")
    cal.add_argument("--board", required=True,
                     help="inner corners, COLUMNSxROWS (e.g. 9x6 for a board of 10x7 squares; "
                          "columns + rows odd for the hand-eye)")
    cal.add_argument("--square-mm", type=float, required=True, help="side of a square, mm")
    cal.add_argument("--out", required=True, help="output folder")
    cal.add_argument("--lens-model", choices=("pinhole", "fisheye"), default="pinhole",
                     help="pinhole: OpenCV's standard model (default); fisheye: OpenCV's "
                          "fisheye (equidistant) model, for wide-angle scopes")
    cal.add_argument("--distortion", type=int, default=None, choices=(0, 4, 5, 8),
                     help="distortion coefficients estimated: 0 none, 4 k1 k2 p1 p2, 5 + k3 "
                          "(default), 8 rational model; fisheye: 4 k1..k4 (default) or 0")
    cal.add_argument("--every", type=int, default=1,
                     help="search every n-th frame for the board (default 1)")
    cal.add_argument("--max-views", type=int, default=60,
                     help="at most this many views, spread over the recording, for the "
                          "intrinsics (default 60; the hand-eye uses all)")
    cal.add_argument("--tracker-rot-sigma", type=float, default=1.0,
                     help="tracker rotation noise, deg: weights the first hand-eye fit; the "
                          "second uses the noise seen (default 1)")
    cal.add_argument("--tracker-trans-sigma", type=float, default=1.0,
                     help="tracker translation noise, mm (default 1)")
    cal.add_argument("--time-offset", default="auto",
                     help="tracker clock against the frames', s: the frame at time t takes the "
                          "tracker sample at t + OFFSET; 'auto' (default) estimates it from the "
                          "frames filmed while the scope moves")
    cal.add_argument("--max-time-offset", type=float, default=0.5, metavar="S",
                     help="largest clock offset, s, that --time-offset auto considers (default "
                          "0.5; an estimate at this bound is refused)")
    cal.add_argument("--fps", type=float, default=None,
                     help="frame rate giving the frame times when the recording has no "
                          "frames.csv (default: the video's own frame rate, else 25)")
    cal.set_defaults(func=_cmd_calibrate)

    live = sub.add_parser(
        "live", parents=[quiet],
        help="mosaic a live OpenIGTLink stream (e.g. PLUS Server: video + tracker or robot) with "
             "lba-emt or the pCLE methods (kalman-robot, ncc, robot), recording it as a "
             "dataset",
        description="Connects to an OpenIGTLink sender (PLUS Server streaming a tracked "
                    "endoscope, or any sender of IMAGE and TRANSFORM or POSITION messages), "
                    "mosaics each frame (lba-emt, kalman-robot, ncc or robot) as soon as the "
                    "previous one is "
                    "done (frames arriving meanwhile are dropped from the mosaic but recorded), "
                    "records every frame (but those arriving while 256 MiB of frames wait to be "
                    "written: the disk or CPU behind the stream; counted) and tracker / robot "
                    "sample into --record (a dataset: "
                    "re-run it offline with any method; frames outside the tracker's time span "
                    "need run's --allow-untracked), and when the stream ends (sender closes, "
                    "--max-frames, --duration or Ctrl-C) writes --out as `run` does.")
    live.add_argument("address", help="HOST:PORT of the OpenIGTLink sender (port default 18944)")
    live.add_argument("--method", choices=["lba-emt", "kalman-robot", "ncc", "robot"],
                      default="lba-emt",
                      help="lba-emt (EM-tracked endoscope, default), kalman-robot (pCLE: "
                           "--transform is then the robot's device, its translation (or a "
                           "POSITION's) the probe position in mm in the image axes; camera.yaml "
                           "needs pixel_size_um), ncc (pCLE images only, e.g. a hand-held "
                           "probe: a robot stream is recorded, not used) or robot (the robot "
                           "positions only)")
    _add_tracked_camera_flags(
        live, transform="TRANSFORM (or POSITION: position + quaternion) device of the sensor on "
                        "the endoscope, tracker_from_sensor in mm, e.g. SensorToTracker (name "
                        "it so: a sender that streams TrackerToSensor instead is inverted; "
                        "SensorToTrackerTransform is taken too; names over OpenIGTLink's 20 "
                        "bytes are matched by their IGTL_DEVICE_NAME metadata); "
                        "kalman-robot / robot: the robot's; required except for ncc (images "
                        "alone; given, its samples are recorded as robot.csv)",
        default=None, transform_required=False)
    live.add_argument("--image-device", metavar="DEVICE",
                      help="IMAGE device of the video (default: the first one heard)")
    live.add_argument("--bgr", action="store_true",
                      help="colour images are sent BGR (default RGB, as PLUS sends them)")
    live.add_argument("--bit-depth", type=int, metavar="B",
                      help="16-bit frames hold B-bit data (8..16, e.g. 12 for a 12-bit sensor): "
                           "mosaicked in 8 bits as v * 255 / (2^B - 1), one scale for the "
                           "session (default: the bits the largest value so far needs, raised "
                           "when a frame exceeds it, told once; given, values above are "
                           "clipped, told once); recorded as received")
    live.add_argument("--record", required=True, metavar="DATA",
                      help="dataset folder the session is recorded into (new or empty)")
    live.add_argument("--overwrite-record", action="store_true",
                      help="replace an earlier dataset in --record")
    live.add_argument("--out", required=True, help="output folder")
    live.add_argument("--max-frames", type=int, metavar="N",
                      help="stop after N frames received")
    live.add_argument("--duration", type=float, metavar="S", help="stop after S seconds")
    live.add_argument("--frame-timeout", type=float, default=5.0, metavar="S",
                      help="a stream silent for S seconds ends the session (before the first "
                           "frame: an error; default 5)")
    _add_tracker_time_offset_flag(
        live, "the frame at time t takes the sample stamped t + S, and the recording's samples "
              "are written on the video's clock, shifted by -S")
    view = live.add_argument_group(
        "the mosaic as it grows (for the room; from each frame's final placement, linear "
        "blending)")
    view.add_argument("--preview", metavar="FILE.png",
                      help="rewrite this PNG with the mosaic so far (replaced atomically: an "
                           "image viewer that reloads it never shows half an image; shrunk "
                           "when larger than 50 Mpixel: see --max-canvas-pixels)")
    view.add_argument("--serve-mosaic", metavar="[HOST:]PORT",
                      help="send the mosaic as OpenIGTLink IMAGE 'Mosaic' to every client "
                           "connecting here (e.g. 3D Slicer's OpenIGTLinkIF as a client; PORT "
                           "alone listens on 127.0.0.1, 0.0.0.0:PORT on every interface)")
    view.add_argument("--view-interval", type=float, default=None, metavar="S",
                      help="least seconds between updates of --preview / --serve-mosaic "
                           "(default 1; longer while drawing the mosaic takes more than S / 4: "
                           "at least 4x that cost)")
    _add_lba_flags(live, "lba-emt")
    _add_feature_flags(live, "features")
    _add_compositing_flags(live)
    live.set_defaults(func=_cmd_live)

    ev = sub.add_parser("evaluate", help="score an output against a dataset's ground truth",
                        parents=[quiet])
    ev.add_argument("out", help="output folder with homographies.csv")
    ev.add_argument("--truth", required=True, help="dataset folder with ground_truth.csv")
    ev.add_argument("--compare", nargs="*",
                    help="more output folders (translation methods: Wilcoxon signed-rank vs "
                         "the first)")
    ev.add_argument("--positions", type=int, default=None, metavar="N",
                    help="also report position errors at N evenly spaced frames among those "
                         "with a ground truth (seed 004; at most their count), and run "
                         "--compare's Wilcoxon test on those N frames instead of all")
    ev.add_argument("--allow-other-dataset", action="store_true",
                    help="score an output whose report.json records another dataset than "
                         "--truth (camera.yaml or frame pixels differ) with a warning instead "
                         "of refusing")
    ev.add_argument("--json", help="JSON path (default OUT/evaluation.json); the report goes "
                                   "beside it (evaluation.md, evaluation_plots/)")
    ev.add_argument("--no-report", action="store_true", help="skip the .md report and plots")
    ev.set_defaults(func=_cmd_evaluate)

    demo = sub.add_parser("demo", help="simulate, mosaic with the best method, report, video",
                          parents=[quiet])
    demo.add_argument("--out", default="demo_out", help="folder for everything (default demo_out)")
    demo.add_argument("--frames", "--n-frames", type=int, default=150,
                      help="frames to simulate (default 150), at the SYN pace of 37.5 "
                           "frames per lap")
    demo.add_argument("--motion", choices=simulation.fetoscopy.MOTIONS, default="syn",
                      help="syn: the paper's circular SYN sequence; handheld: a free-hand sweep "
                           "over a tilted plane with a circular field of view")
    demo.set_defaults(func=_cmd_demo)

    bench = sub.add_parser(
        "bench", parents=[quiet],
        help="measure this machine against the live budgets (simulated data, ~30 s)",
        description="Measures the live budgets (README, Performance) on this machine with "
                    "simulated data: the lba-emt window step (median <= 5 ms, p95 <= 15 ms) "
                    "and frames/s (>= 25) at "
                    "400x400, kalman-robot frames/s at 512x448 (>= 100), and with --offline "
                    "the ba-emt optimisation over 150 frames (<= 1 s); accuracy against the "
                    "simulator's truth beside them.")
    bench.add_argument("--frames", type=int, default=300,
                       help="SYN frames streamed through lba-emt (>= 60; default 300)")
    bench.add_argument("--detector", choices=("orb", "sift"), default="orb",
                       help="lba-emt's feature detector (default orb, the live choice)")
    bench.add_argument("--pcle-frames", type=int, default=200,
                       help="pCLE frames streamed through kalman-robot, on the simulated circle "
                            "lapped as often as they need (>= 10, at most the simulator's "
                            f"{simulation._options.MAX_FRAMES}; default 200)")
    bench.add_argument("--offline", action="store_true",
                       help="also time ba-emt over 150 frames (~10 s more)")
    bench.add_argument("--seed", type=int, default=0, help="simulation seed (default 0)")
    bench.add_argument("--json", help="also write the measurements to this JSON file")
    bench.add_argument("--strict", action="store_true",
                       help="exit with status 1 when a budget is missed")
    bench.set_defaults(func=_cmd_bench)
    return parser


def _add_tracker_time_offset_flag(parser: argparse.ArgumentParser, effect: str) -> None:
    """--tracker-time-offset S (checked by io.tracking.check_time_offset in the command)."""
    parser.add_argument("--tracker-time-offset", type=float, default=None, metavar="S",
                        help="seconds the tracker's clock is ahead of the video's (calibrate "
                             "measures it: calibration.json hand_eye.tracker_time_offset."
                             f"applied_s): {effect} (default 0)")


def _add_tracked_camera_flags(parser: argparse.ArgumentParser, *, transform: str,
                              default: str | None, camera_help: str | None = None,
                              transform_required: bool | None = None) -> None:
    """--camera (required unless camera_help says what its absence means), --transform
    (required without a default, unless transform_required says otherwise) and --hand-eye:
    what a tracked endoscope's recording or stream does not carry itself (import and live)."""
    parser.add_argument("--camera", required=camera_help is None, metavar="CAMERA.yaml",
                        help="camera.yaml of the endoscope (image size, camera matrix; the "
                             "images' size must match)" + (camera_help or ""))
    parser.add_argument("--transform", default=default,
                        required=(default is None if transform_required is None
                                  else transform_required),
                        metavar="NAME", help=transform)
    parser.add_argument("--hand-eye", metavar="HAND_EYE.txt",
                        help="4x4 sensor_from_camera (default identity)")


def _add_lba_flags(parser: argparse.ArgumentParser, methods: str = "ba-emt / lba-emt") -> None:
    """lba-emt (and ba-emt) estimation flags, shared by run and live (methods: those of the
    subcommand that take them, for the help)."""
    parser.add_argument("--motion-sigma-from", metavar="RECORDING",
                     help=f"{methods}: estimate the constant-velocity prior's Sigma_p from "
                          "an independent recording's truth_poses.csv (paper 000 Sec. 4.2) "
                          "instead of the paper's appendix values")
    parser.add_argument("--tracker-rot-sigma", type=float, metavar="DEG",
                        help=f"{methods}: the tracker's rotation noise per axis in degrees, "
                             "the EMT prior's (default 1 deg, the paper's 0.017 rad); calibrate "
                             "measures it (--calibration takes it from calibration.json)")
    parser.add_argument("--tracker-trans-sigma", type=float, metavar="MM",
                        help=f"{methods}: the tracker's translation noise per axis, mm "
                             "(default: the paper's 1 mm)")
    parser.add_argument("--visual-sigma", metavar="PX|auto",
                        help=f"{methods}: the keypoints' noise per axis in pixels, the visual "
                             "cost's sigma_v (default: the paper's 1 px); auto: measured on the "
                             "recording, by ba-emt over all frames, by lba-emt at its start-up, "
                             "from the registered points' transfer residuals (report.json "
                             "visual_sigma; README: when it helps and when it does not)")
    parser.add_argument("--calibration", metavar="CALIB.json",
                        help=f"tracked methods: the tracker time offset and ({methods}) "
                             "the tracker noise per axis that calibrate measured on a "
                             "recording of the same set-up (its calibration.json), instead of "
                             "--tracker-time-offset / --tracker-rot-sigma / --tracker-trans-sigma")
    parser.add_argument("--preset", choices=["syn", "phb", "ex"],
                     help="lba-emt: the paper's window presets (Sec. 4.2): syn W=5, chi_e=3, "
                          "K=3 x 5 (default); phb W=3, chi_e=1, K=3 x 3 (fewer pairs per frame: "
                          "faster on large frames, bench/results/detect_scale.md); ex W=12, "
                          "chi_e=6, K=3 x 12")
    parser.add_argument("--loop-pairs", type=int, metavar="N",
                     help="lba-emt: spatial loop pairs per frame (default 2; 0 = the paper's "
                          "window alone, which drifts to the tracker's accuracy)")
    parser.add_argument("--guided-sift", action="store_true",
                     help="lba-emt with SIFT: search each pair's keypoints near where the "
                          "predicted motion puts them instead of among all (as ORB's are; "
                          "matching ~30 percent faster, accuracy within the spread of the "
                          "exhaustive search's; MatchOptions.guided_sift)")


def _add_feature_flags(parser: argparse.ArgumentParser, title: str) -> None:
    """Keypoint flags (FeatureOptions), shared by run and live."""
    feat = parser.add_argument_group(title)
    feat.add_argument("--detector", choices=["sift", "orb"],
                      help="keypoint detector: sift (the paper's, default) or orb (detection "
                           "several times cheaper, but more correspondences per pair to "
                           "match: faster on long sequences and large frames, slower in the "
                           "40-frame start-up; bench/results/detect_scale.md)")
    feat.add_argument("--max-features", type=int, metavar="N",
                      help="strongest keypoints kept per frame (default 1000)")
    feat.add_argument("--clahe", action="store_true",
                      help="contrast-limited histogram equalisation before detection "
                           "(low-contrast tissue)")
    feat.add_argument("--detect-max-side", type=int, metavar="PX",
                      help="detect on a copy of each frame shrunk to at most PX pixels on its "
                           "longer side, keypoints mapped back to full resolution (faster on "
                           "HD video; default: full resolution)")
    feat.add_argument("--orb-fast-threshold", type=int, metavar="T",
                      help="ORB's FAST corner threshold, grey levels (default 5; 10 halves ORB "
                           "detection on HD frames at some cost in accuracy; a frame where "
                           "fewer than 90 percent of the keypoints are found is detected again "
                           "at 5, both passes paid for: a threshold too high for the tissue is "
                           "slower than 5, e.g. 20 on the simulator's frames finds 244 of 1000, "
                           "16 vs 13 ms a 400x400 frame)")
    feat.add_argument("--keep-specular", action="store_true",
                      help="keep specular highlights (saturated white spots the scope's light "
                           "makes on wet tissue, fixed to the camera): by default no keypoint "
                           "is taken on them and the mosaic shows the tissue other frames see "
                           "there")


def _add_compositing_flags(parser: argparse.ArgumentParser) -> None:
    """Mosaic, video and report flags, shared by run and live."""
    from fusedmosaic.compositing import BLENDS

    comp = parser.add_argument_group("mosaic, video and report")
    comp.add_argument("--blend", choices=BLENDS,
                      help="linear (feathering, seed 000), multiband (Laplacian pyramid), average "
                           "(seed 004), last (newest on top); default: the method's preference")
    comp.add_argument("--border", type=float, default=0.0, metavar="PX",
                      help="draw each frame's field-of-view edge as a thin black border of PX "
                           "pixels, to show the seams (seed 000 Sec. 4.2; e.g. 1.5; at most "
                           "the median distance to the edge, where it covers half a frame)")
    comp.add_argument("--bands", type=int, default=None, help="multiband pyramid levels, "
                      "1..10 (default 5); each level doubles the padding warped around every "
                      "frame (3 x 2^bands px a side), and more than log2 of the frames' smaller "
                      "side (e.g. 6 for 64 x 64 frames) is lowered to it, with a warning")
    comp.add_argument("--gain-compensation", action="store_true",
                      help="equalise the brightness of overlapping frames (one gain per frame)")
    comp.add_argument("--video", metavar="OUT.mp4",
                      help="also write a video of the mosaic's sequential creation: one video "
                           "frame per frame composed, at the recording's frame rate (real time "
                           "when every frame is placed); --blend multiband shows as linear "
                           "there (multiband needs every frame)")
    comp.add_argument("--no-report", action="store_true",
                      help="skip report.md and its plots")
    comp.add_argument("--max-canvas-pixels", type=int, default=None,
                      help="skip (with a warning) mosaics larger than this many pixels; the "
                           "estimates are still written (default 400 000 000); live: also the "
                           "budget of the --preview / --serve-mosaic view's canvas, whose "
                           "images are shrunk by a whole factor above 50 000 000 pixels (or "
                           "this, if lower)")
    comp.add_argument("--tile-size", type=int, default=None,
                      help="tile size (px) for mosaics rendered tile by tile, 64..8192 "
                           "(default 1024; a tile's accumulator takes its size squared x 16 "
                           "bytes for colour)")
    comp.add_argument("--alpha", action="store_true",
                      help="mosaic.png with an alpha channel (grey + alpha, or RGBA): opaque "
                           "where a frame shows the pixel, transparent elsewhere (black either "
                           "way), to overlay the mosaic on other images")


def _show_warning(message, category, filename, lineno, file=None, line=None) -> None:
    """Warnings from numpy and friends as one line, without the source line they came from."""
    print(f"fusedmosaic: warning: {message}", file=sys.stderr)


def _os_error(exc: OSError) -> str:
    paths = [p for p in (exc.filename, exc.filename2) if p is not None]
    where = " -> ".join(str(p) for p in paths)
    what = exc.strerror or str(exc)
    return f"{where}: {what}" if where else what


# Arguments naming a file or folder to write or read: an empty one (an unset shell variable)
# would otherwise mean the current folder.
PATH_ARGUMENTS = {"out": "OUT", "record": "--record", "preview": "--preview", "json": "--json",
                  "video": "--video", "calibration": "--calibration",
                  "motion_sigma_from": "--motion-sigma-from", "dataset": "DATASET",
                  "recording": "RECORDING", "sequence": "SEQUENCE",
                  "truth": "--truth", "camera": "--camera", "hand_eye": "--hand-eye"}


def main(argv: list[str] | None = None) -> int:
    # A path that is not UTF-8 (io._paths) is printed as its bytes, as report.md writes it: on a
    # strict stdout (a desktop's UTF-8 locale) the summary naming such an OUT raised after the
    # outputs were written, exit 2 (review Z 47). stderr already escapes (backslashreplace).
    if isinstance(sys.stdout, io.TextIOWrapper) and sys.stdout.errors == "strict":
        sys.stdout.reconfigure(errors="surrogateescape")
    parser = build_parser()
    args = parser.parse_args(argv)
    for dest, name in PATH_ARGUMENTS.items():
        value = getattr(args, dest, None)
        if isinstance(value, str) and not value.strip():
            print(f"fusedmosaic: error: {name} is an empty path (an unset shell variable?)",
                  file=sys.stderr)
            return 2
        if dest == "video" and isinstance(value, str):  # (before the computation, not after)
            from fusedmosaic.io._paths import is_utf8, not_utf8_message

            if not is_utf8(value):
                print("fusedmosaic: error: " + not_utf8_message(
                    value, "OpenCV cannot write a video by such a name"), file=sys.stderr)
                return 2
    try:
        with warnings.catch_warnings(), signals_as_interrupt():
            warnings.showwarning = _show_warning
            return args.func(args)
    except ValueError as exc:  # bad input: one clear line, no traceback
        print(f"fusedmosaic: error: {exc}", file=sys.stderr)
        return 2
    except OSError as exc:  # the file system refused (full disk, permissions, ...): exit 1,
        # for every output alike (io.output.OutputWriter.named_errors says why); 2 is for an
        # input or command line to change
        print(f"fusedmosaic: error: {_os_error(exc)}", file=sys.stderr)
        return 1
    except OutputsWrittenInterrupt as exc:
        # held while the outputs were moved in, delivered once they all were: said, as
        # nothing was abandoned. Still 130, the status of an interrupted command: a shell
        # script stops at the user's Ctrl-C only when the command reports it (with 0, a loop
        # over datasets went on to the next one)
        print(f"fusedmosaic: interrupted after the outputs were written to {exc.out_dir}",
              file=sys.stderr)
        return 130
    except KeyboardInterrupt:  # the outputs are written atomically: nothing partial is left
        print("fusedmosaic: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
