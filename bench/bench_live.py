"""Live replay on this machine (`fusedmosaic run --live`, estimation/live.py): SYN sequences at
25 frames/s fed to lba-emt as a live source, and the pCLE circle (10 frames/s, accurate and
noisy robot) to kalman-robot. The 400x400 sequences and the pCLE circle are also streamed over
OpenIGTLink (`fusedmosaic live`, runner.run_igtl) by a sender in another process, in real time,
as PLUS Server would: the same measures with a real socket, decoding, recording and wall-clock time.

One run. Each configuration simulates its sequence on disk (frames read outside the timed
calls), then replays it: frames at their timestamps with the newest tracker / robot sample, a
one-slot capture queue (frames arriving while one is processed are dropped except the newest),
the virtual clock advanced by each call's measured wall time. Per configuration: frames dropped,
latency (arrival -> add_frame returns) and processing time per processed frame, e_M of the
placed frames against the simulator's truth (px), and the same run offline (every frame,
interpolated tracker poses) for comparison.

    python bench/bench_live.py [--frames 300] [--out bench/results/live.json]

Writes the JSON and a markdown table beside it (live.md).
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from _common import BenchRun, bench_args, fmt, md_table, run_note
from bench_sequential import FRAMES_PER_LAP

from fusedmosaic.estimation.live import replay_live
from fusedmosaic.estimation.sequential import SequentialOptions, run_lba_emt
from fusedmosaic.estimation.translation import run_kalman_robot
from fusedmosaic.evaluation import frame_errors, mosaic_error, position_errors_um
from fusedmosaic.io import read_dataset, read_homographies_csv
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.simulation import FetoscopyOptions, PcleOptions, simulate_fetoscopy, simulate_pcle

CONFIGS = {  # label -> (frame size, detector, detection max side)
    "400x400 ORB": ((400, 400), "orb", None),
    "400x400 SIFT": ((400, 400), "sift", None),
    "720x576 ORB, detection at 512": ((720, 576), "orb", 512),
    "1280x720 ORB, detection at 512": ((1280, 720), "orb", 512),
}


def main() -> None:
    args = bench_args(__doc__, frames=300, work=True,
                      out=Path("bench/results/live.json")).parse_args()
    bench = BenchRun(args.work)
    rows = []
    work = bench.work
    try:
        for label, (size, detector, side) in CONFIGS.items():
            root = simulate_fetoscopy(work / label.split()[0], FetoscopyOptions(
                n_frames=args.frames, laps=args.frames / FRAMES_PER_LAP, width=size[0],
                height=size[1]), overwrite=True)
            ds = read_dataset(root)
            options = SequentialOptions(features=FeatureOptions(detector=detector,
                                                                max_image_side=side))
            live = replay_live(ds, "lba-emt", options=options, progress=False)
            offline = run_lba_emt(ds, progress=False, options=options)

            def e_M(res, ds=ds):
                return mosaic_error(frame_errors(res.homographies, ds.ground_truth,
                                                 ds.camera.width, ds.camera.height))

            rows.append(row(label, "lba-emt", ds, live, e_M(live), e_M(offline), "px"))
            if size == (400, 400):
                streamed, G = over_igtl(root, work / f"igtl-{detector}", options)
                rows.append(row(f"{label}, over OpenIGTLink", "lba-emt (live)", ds, streamed,
                                e_M(SimpleNamespace(homographies=G)), e_M(offline), "px"))
        root = simulate_pcle(work / "pcle", PcleOptions(trajectory="circle"), overwrite=True)
        for robot_file, which in (("robot.csv", "accurate"), ("robot_noisy.csv", "noisy")):
            ds = read_dataset(root, robot_file=robot_file)
            live = replay_live(ds, "kalman-robot", progress=False)
            offline = run_kalman_robot(ds, progress=False)

            def mean_um(res, ds=ds):
                cam = ds.camera
                e = position_errors_um(res.homographies, ds.ground_truth, cam.width,
                                       cam.height, cam.pixel_size_um)
                return float(np.nanmean(e))

            rows.append(row(f"pCLE circle 512x448, {which} robot", "kalman-robot", ds, live,
                            mean_um(live), mean_um(offline), "µm"))
            streamed, G = over_igtl(root, work / f"igtl-{which}", None, robot_file)
            rows.append(row(f"pCLE circle 512x448, {which} robot, over OpenIGTLink",
                            "kalman-robot (live)", ds, streamed,
                            mean_um(SimpleNamespace(homographies=G)), mean_um(offline), "µm"))
    finally:
        bench.cleanup()
    bench.write_results(args.out, markdown, frames=args.frames, rows=rows)


# The sender: tests/_igtl_sender.py in another process (its own interpreter and GIL, as PLUS
# Server is another program): the dataset's frames and 40 Hz tracker samples in real time.
SENDER = """
import sys
sys.path.insert(0, sys.argv[1])
from _igtl_sender import Sender, dataset_events, robot_events
from fusedmosaic.io import read_dataset
robot = sys.argv[3] != "-"
ds = read_dataset(sys.argv[2], robot_file=sys.argv[3] if robot else "robot.csv")
sender = Sender(robot_events(ds) if robot else dataset_events(ds), delay=0.5)
print(sender.port, flush=True)
sender.join()
"""


def over_igtl(root: Path, work: Path, options, robot_file: str | None = None
              ) -> tuple[SimpleNamespace, np.ndarray]:
    """Streams the dataset at `root` over OpenIGTLink to run_igtl (lba-emt, or kalman-robot
    with the robot positions of `robot_file`); its report's "live" entry (as replay_live's
    details) and the homographies."""
    from fusedmosaic.runner import run_igtl

    tests = Path(__file__).resolve().parent.parent / "tests"
    sender = subprocess.Popen([sys.executable, "-c", SENDER, str(tests), str(root),
                               robot_file or "-"], stdout=subprocess.PIPE, text=True)
    try:
        port = int(sender.stdout.readline())
        tracked = robot_file is None
        run_igtl(f"127.0.0.1:{port}", work / "out", record=work / "rec",
                 camera=root / "camera.yaml",
                 transform_device="SensorToTracker" if tracked else "RobotToBase",
                 hand_eye=root / "hand_eye.txt" if tracked else None, options=options,
                 overwrite_record=True, progress=False, report=False,
                 method="lba-emt" if tracked else "kalman-robot")
    finally:
        sender.wait(timeout=60)
    report = json.loads((work / "out" / "report.json").read_text())
    _, G = read_homographies_csv(work / "out" / "homographies.csv")
    return SimpleNamespace(details=report), G


def row(label, method, ds, live, error_live, error_offline, unit) -> dict:
    d = live.details["live"]
    r = {"configuration": label, "method": method, "frames": len(ds),
         "frame_interval_ms": d["frame_interval_ms"], "frames_dropped": d["frames_dropped"],
         "dropped": d["dropped"],
         "latency_ms": d["latency_ms"], "processing_ms": d["processing_ms"],
         "error_live": error_live, "error_offline": error_offline, "error_unit": unit}
    print(f"{label}: dropped {d['frames_dropped']}/{len(ds)} {d['dropped']}, latency median "
          f"{d['latency_ms']['median']:.1f} p95 {d['latency_ms']['p95']:.1f} ms, error "
          f"{error_live:.3f} (offline {error_offline:.3f}) {unit}", flush=True)
    return r


def markdown(res: dict) -> str:
    lines = ["# Live replay on this machine", "",
             run_note(res, "bench_live.py") + " Frames at their timestamps, newest "
             "tracker/robot sample, one-slot capture queue; latency = wait + processing of the "
             "processed frames; error of the placed frames (e_M px for lba-emt, mean position "
             "error µm for kalman-robot) live and offline (every frame, interpolated tracker "
             "poses).", ""]
    rows = [[r["configuration"], r["method"], fmt(r["frame_interval_ms"], 0),
             f"{r['frames_dropped']}/{r['frames']}", fmt(r["processing_ms"]["median"], 1),
             fmt(r["latency_ms"]["median"], 1), fmt(r["latency_ms"]["p95"], 1),
             fmt(r["latency_ms"]["max"], 1),
             f"{fmt(r['error_live'], 3)} {r['error_unit']}",
             f"{fmt(r['error_offline'], 3)} {r['error_unit']}"] for r in res["rows"]]
    lines += md_table(["sequence", "method", "frame interval ms", "dropped",
                       "processing median ms", "latency median ms", "latency p95 ms",
                       "latency max ms", "error live", "error offline"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
