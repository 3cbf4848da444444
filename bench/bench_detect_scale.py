"""LBAVis+EMT with ORB on larger frames: detection at full resolution against detection on a
shrunk copy (FeatureOptions.max_image_side, `fusedmosaic run --detect-max-side`), this machine.

One run. For each frame size, the SYN simulator's circle (as bench_sequential.py, ~37 frames per
lap) is rendered at that size and streamed into SequentialMosaicker with ORB, tracker poses
interpolated from the 40 Hz tracker through the hand-eye transform, once per detection size.
Per configuration: frames/s from add_frame wall time after the start-up (steady state), the
median of each stage per frame, and the accuracy against the simulator's true homographies (e_M
in full-resolution pixels, and divided by the shrink factor: the same error in pixels of the
detection image). Frames are rendered before each timed call (not counted).

Then, at 1280x720 with detection at max side 512, fewer image pairs per frame (matching is the
main cost there): the SYN preset without loop pairs (window pairs only) and the PHB preset
(W = 3, chi_e = 1) with and without loop pairs, against the default (SYN preset, 2 loop pairs).

    python bench/bench_detect_scale.py [--frames 250] [--out bench/results/detect_scale.json]

Writes the JSON and a markdown table beside it (detect_scale.md).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _common import BenchRun, bench_args, fmt, md_table, run_note
from bench_sequential import make_scene, stream, throughput

from fusedmosaic.estimation.sequential import SequentialOptions
from fusedmosaic.evaluation import drift_ratio
from fusedmosaic.registration.features import FeatureOptions

SIZES = ((400, 400), (720, 576), (1280, 720))
SIDES = (None, 512, 400)  # max_image_side; None = full resolution
PAIRS_SIZE, PAIRS_SIDE = (1280, 720), 512
PAIR_CONFIGS = {  # label -> (preset, loop_pairs)
    "SYN preset, 2 loop pairs (default)": ("syn", 2),
    "SYN preset, no loop pairs": ("syn", 0),
    "PHB preset, 2 loop pairs": ("phb", 2),
    "PHB preset, no loop pairs": ("phb", 0),
}


def main() -> None:
    args = bench_args(__doc__, frames=250,
                      out=Path("bench/results/detect_scale.json")).parse_args()
    bench = BenchRun(folder=False)
    rows = []
    for size in SIZES:
        scene, camera, poses, valid = make_scene(args.frames, size)
        for side in SIDES:
            if side is not None and side >= max(size):
                continue  # nothing to shrink
            options = SequentialOptions(features=FeatureOptions(detector="orb",
                                                                max_image_side=side))
            rows.append(measure(scene, camera, poses, valid, args.frames, size, side, options))
    pair_rows = []
    scene, camera, poses, valid = make_scene(args.frames, PAIRS_SIZE)
    for label, (preset, loops) in PAIR_CONFIGS.items():
        options = SequentialOptions.preset(
            preset, loop_pairs=loops,
            features=FeatureOptions(detector="orb", max_image_side=PAIRS_SIDE))
        row = measure(scene, camera, poses, valid, args.frames, PAIRS_SIZE, PAIRS_SIDE, options)
        pair_rows.append({"configuration": label, "preset": preset, "loop_pairs": loops,
                          **row})
    bench.write_results(args.out, markdown, frames=args.frames, detector="orb", rows=rows,
                        pair_rows=pair_rows)


def measure(scene, camera, poses, valid, frames, size, side, options) -> dict:
    """One streamed run: steady-state throughput, stage medians, accuracy, pairs per frame."""
    run = stream(scene, camera, poses, valid, frames, options)
    t = throughput(run)
    lo = t["steady_from_frame"]
    shrink = 1.0 if side is None else side / max(size)
    e = run["errors"]
    row = {"width": size[0], "height": size[1], "max_image_side": side, "shrink": shrink,
           "frames_per_s_steady": t["frames_per_s_steady"],
           "latency_ms_steady": t["latency_ms_steady"],
           "stage_median_ms": {s: float(np.median(v[lo:]) * 1e3)
                               for s, v in run["stages"].items()},
           "e_M_px": float(np.nanmean(e)),
           "e_M_detection_px": float(np.nanmean(e)) * shrink,
           "max_e_j_px": float(np.nanmax(e)), "drift_ratio": drift_ratio(e),
           "unplaced": run["unplaced"],
           "registered_pairs_per_frame": run["pairs"]["registered_per_frame_after_bootstrap"]}
    stages = {k: round(v, 2) for k, v in row["stage_median_ms"].items()}
    print(f"{size[0]}x{size[1]} side {side}, W={options.window_size} chi_e={options.num_new} "
          f"loops {options.loop_pairs}: {row['frames_per_s_steady']:.1f} frames/s, stages "
          f"{stages}, e_M {row['e_M_px']:.3f} px, unplaced {row['unplaced']}", flush=True)
    return row


def markdown(res: dict) -> str:
    lines = ["# ORB end to end at larger frames: full-resolution detection vs a shrunk copy", "",
             run_note(res, "bench_detect_scale.py",
                      f", {res['frames']} SYN frames per configuration") + " Frames/s from "
             "add_frame wall time after the start-up; stage medians per frame; e_M against "
             "the simulator's true homographies, in full-resolution pixels and in pixels of the "
             "detection image.", ""]
    rows = [[f"{r['width']}x{r['height']}", r["max_image_side"] or "full",
             fmt(r["frames_per_s_steady"], 1), fmt(r["latency_ms_steady"]["median"], 1),
             fmt(r["stage_median_ms"]["features"], 1), fmt(r["stage_median_ms"]["matching"], 1),
             fmt(r["stage_median_ms"]["window_solve"], 2), fmt(r["e_M_px"], 3),
             fmt(r["e_M_detection_px"], 3), fmt(r["drift_ratio"]), r["unplaced"]]
            for r in res["rows"]]
    lines += md_table(["frames", "detect max side", "frames/s", "latency median ms",
                       "features ms", "matching ms", "window solve ms", "e_M px",
                       "e_M px (detection scale)", "drift", "unplaced"], rows)
    w, h = PAIRS_SIZE
    lines += ["", f"Fewer pairs per frame at {w}x{h}, detection at max side {PAIRS_SIDE}:", ""]
    rows = [[r["configuration"], fmt(r["registered_pairs_per_frame"], 1),
             fmt(r["frames_per_s_steady"], 1),
             fmt(r["latency_ms_steady"]["median"], 1), fmt(r["stage_median_ms"]["matching"], 1),
             fmt(r["stage_median_ms"]["window_solve"], 2), fmt(r["e_M_px"], 3),
             fmt(r["max_e_j_px"], 2), fmt(r["drift_ratio"]), r["unplaced"]]
            for r in res["pair_rows"]]
    lines += md_table(["configuration", "registered pairs per frame",
                       "frames/s", "latency median ms", "matching ms", "window solve ms",
                       "e_M px", "max e_j px", "drift", "unplaced"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
