"""README's --calibration recipe against the simulator's truth: a tracker noise measured by
`fusedmosaic calibrate` (on the checkerboard simulator's recording: its EM tracker, 0.9 deg /
0.25 mm per axis) given to ba-emt / lba-emt on fetoscopy sequences simulated with that tracker,
with the keypoints' noise measured on the recording (--visual-sigma auto, session 49), given
(0.1 px, the simulator's) or the paper's 1 px (the default), against the paper's 1 deg / 1 mm.
The paper pairs its loose tracker noise with sigma_v 1 px, about 10 x what the simulator's
keypoints are off; the true tracker noise with sigma_v 1 px weighs the tracker too much (review
N of session 47, finding M3, and its research).

    python bench/bench_visual_sigma.py [--seeds 3] [--frames 60]
        [--out bench/results/visual_sigma.json]
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from _common import BenchRun, add_options, bench_args, fmt, md_table, run_note

from fusedmosaic.cli import main as cli
from fusedmosaic.estimation.calibration import read_tracker_calibration

VISUAL_SIGMA_PX = 0.1
CONFIGS = {  # label: extra run flags (CAL: the calibration.json)
    "defaults (the paper's 1 deg / 1 mm / 1 px)": [],
    "--calibration": ["--calibration", "CAL"],
    f"--calibration --visual-sigma {VISUAL_SIGMA_PX:g}":
        ["--calibration", "CAL", "--visual-sigma", str(VISUAL_SIGMA_PX)],
    "--visual-sigma auto": ["--visual-sigma", "auto"],
    "--calibration --visual-sigma auto": ["--calibration", "CAL", "--visual-sigma", "auto"],
}
METHODS = ("lba-emt", "ba-emt")


def _run(data: Path, method: str, out: Path, extra: list[str]) -> float:
    assert cli(["--quiet", "run", str(data), "--method", method, "--out", str(out),
                "--no-report", *extra]) == 0, (data, method, extra)
    return json.loads((out / "report.json").read_text())["metrics"]["e_M_px"]


def main() -> None:
    ap = bench_args(__doc__, seeds=3, frames=60)
    args = add_options(ap, out=Path("bench/results/visual_sigma.json")).parse_args()
    bench = BenchRun()
    work = bench.work
    assert cli(["--quiet", "simulate", "checkerboard", str(work / "board")]) == 0
    assert cli(["--quiet", "calibrate", str(work / "board"), "--board", "9x6", "--square-mm",
                "2", "--out", str(work / "scope")]) == 0
    cal = work / "scope" / "calibration.json"
    measured = read_tracker_calibration(cal)
    noise = {"rot_sigma_deg": measured.rot_sigma_deg, "trans_sigma_mm": measured.trans_sigma_mm}
    laps = args.frames * 4 / 150  # the SYN circle's pace (4 laps in 150 frames)
    errors = {m: {c: [] for c in CONFIGS} for m in METHODS}
    for seed in range(args.seeds):
        data = work / f"syn{seed}"
        assert cli(["--quiet", "simulate", "fetoscopy", str(data), "--n-frames",
                    str(args.frames), "--laps", repr(laps), "--rot-sigma-deg", "0.9",
                    "--trans-sigma-mm", "0.25", "--seed", str(seed)]) == 0
        for method in METHODS:
            for k, (label, extra) in enumerate(CONFIGS.items()):
                extra = [str(cal) if e == "CAL" else e for e in extra]
                e = _run(data, method, work / f"o{seed}-{method}-{k}", extra)
                errors[method][label].append(e)
                print(f"seed {seed} {method} {label}: e_M {e:.4f} px", flush=True)
    bench.write_results(args.out, markdown, seeds=args.seeds, frames=args.frames, laps=laps,
                        tracker_noise_calibrated=noise, visual_sigma_px=VISUAL_SIGMA_PX,
                        e_M_px=errors)


def markdown(res: dict) -> str:
    noise = res["tracker_noise_calibrated"]
    lines = ["# --calibration's tracker noise with and without --visual-sigma", "",
             run_note(res, "bench_visual_sigma.py", f", seeds 0-{res['seeds'] - 1}")
             + f" SYN circle, {res['frames']} frames ({res['laps']:.2f} laps), tracker "
             "simulated with 0.9 deg / 0.25 mm per axis; calibrate on the default checkerboard "
             f"recording measured {json.dumps(noise)}. e_M in px per seed, and the mean.", ""]
    for method, by_config in res["e_M_px"].items():
        rows = [[label, " / ".join(fmt(e, 3) for e in v), fmt(float(np.mean(v)), 3)]
                for label, v in by_config.items()]
        lines += [f"## {method}", ""] + md_table(["run flags", "e_M per seed", "mean"], rows)
        lines.append("")
    return "\n".join(lines)


if __name__ == "__main__":
    main()
