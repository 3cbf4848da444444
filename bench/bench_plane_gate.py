"""The window's plane observability gate (SequentialOptions.plane_max_relative_std) on weak and
on normal texture: accuracy and window step time with the gate on (default 0.02) and off (0).

Weak texture: SYN circle (~37 frames per lap) at 200x200 px with SIFT and its low-contrast
retry off (FeatureOptions.sift_min_features=0, as tests/test_plane_gate.py): ~19 inliers per
pair and about two thirds of the frames without a registered pair, so many window steps see
the plane only through one or two pairs between cameras the tracker placed. (With the retry,
the default, every 200 px frame registers and the gate has nothing to do: e_M 0.262 px with and
without it, session 48.) Normal texture: the same motion at 400x400 px (the issue-4 setting)
with the default features, where the gate must change nothing. Tracker
poses are interpolated from the simulated 40 Hz tracker through the hand-eye transform, as
bench_sequential.py streams them. For each run: e_M, max e_j and the drift ratio against the
simulator's truth (Eq. 28-29), the plane depth 1/|pi| range over the frames' steps, the steps
held by the gate, and the window step time (median, p95). The tracker alone with the true plane
is given as the bound a fused estimate should stay under. Gate 0 also skips the computation of
the relative std (one more Jacobian evaluation per step), so on normal texture, where no step
is held, the step times of the two settings give its cost.

    python bench/bench_plane_gate.py [--frames 300 3000] [--out bench/results/plane_gate.json]

Writes the JSON and a markdown table beside it (plane_gate.md).
"""

from __future__ import annotations

import time

import numpy as np
from _common import RESULTS, BenchRun, add_options, bench_args, fmt, machine_info

from fusedmosaic.estimation.bundle import predicted_homographies
from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
from fusedmosaic.evaluation.metrics import drift_ratio, frame_errors
from fusedmosaic.io import Camera, TrackingSamples, interpolate_camera_poses
from fusedmosaic.registration.features import FeatureOptions
from fusedmosaic.simulation.fetoscopy import FetoscopyOptions, generate_fetoscopy

FRAMES_PER_LAP = 37


def stream(n: int, size: int, limit: float, sigma_v="auto") -> dict:
    scene = generate_fetoscopy(FetoscopyOptions(n_frames=n, laps=n / FRAMES_PER_LAP,
                                                width=size, height=size))
    camera = Camera(*scene.size, camera_matrix=scene.camera_matrix,
                    fov_mask_radius=scene.fov_mask_radius)
    samples = TrackingSamples(scene.tracker_timestamps, scene.tracker_translations,
                              scene.tracker_quaternions, scene.tracker_valid)
    poses, valid = interpolate_camera_poses(samples, scene.timestamps, scene.hand_eye)
    weak = size < 400  # (the weak-texture runs keep the few keypoints SIFT finds at first)
    m = SequentialMosaicker(camera, SequentialOptions(
        plane_max_relative_std=limit, history_steps=10 * n, sigma_v_px=sigma_v,
        **({"features": FeatureOptions(sift_min_features=0)} if weak else {})))
    results = {}
    solve_s = []  # each step's solve time with its redo, if any (step_summaries: the last)

    def take(finals) -> None:
        if m.num_steps > len(solve_s):
            solve_s.append(m.last_step_solve_s)
        results.update({r.frame_id: r for r in finals})

    t0 = time.perf_counter()
    for k in range(n):
        m.add_frame(scene.render(k), float(scene.timestamps[k]), poses[k] if valid[k] else None)
        take(m.finalized())
    take(m.flush())
    wall = time.perf_counter() - t0
    G = np.stack([results[k].homography for k in range(n)])
    e = frame_errors(G, scene.homographies, *scene.size)
    tracker = frame_errors(predicted_homographies(np.where(valid[:, None], poses, np.nan),
                                                  scene.plane, scene.camera_matrix),
                           scene.homographies, *scene.size)
    depth = 1 / np.linalg.norm([results[k].plane for k in range(n)], axis=1)
    steps = list(m.step_summaries)
    # (at sigma_v 1 px, as the limit is stated: the window compares x sigma_v, which "auto"
    # measured at the start-up; SequentialOptions.plane_max_relative_std)
    std = np.array([s.plane_relative_std for s in steps]) / m.sigma_v_px
    seen = std[~np.isnan(std)]
    held = sum(s.plane_held for s in steps if not np.isnan(s.plane_relative_std))  # (the gate's)
    step_ms = np.array(solve_s) * 1e3
    status = [results[k].status for k in range(n)]
    return {
        "frames": n, "size_px": size, "plane_max_relative_std": limit,
        "e_M_px": float(np.nanmean(e)), "max_e_j_px": float(np.nanmax(e)),
        "drift_ratio": float(drift_ratio(e)), "unplaced": int(np.isnan(e).sum()),
        "prior_only_frames": status.count("prior-only"),
        "tracker_true_plane_e_M_px": float(np.nanmean(tracker)),
        "tracker_true_plane_max_e_j_px": float(np.nanmax(tracker)),
        "true_depth_mm": float(1 / np.linalg.norm(scene.plane)),
        "depth_min_mm": float(depth.min()), "depth_max_mm": float(depth.max()),
        "steps": len(steps), "steps_seeing_plane": int(seen.size),
        "steps_held_by_gate": int(held), "sigma_v_px": m.sigma_v_px,
        "visual_sigma": m.visual_sigma,
        "relative_std_median": float(np.median(seen)) if seen.size else None,
        "relative_std_max": float(seen.max()) if seen.size else None,
        "step_ms_median": float(np.median(step_ms)),
        "step_ms_p95": float(np.percentile(step_ms, 95)),
        "frames_per_s": n / wall,
    }


def _sigma_label(r: dict) -> str:
    v = r.get("visual_sigma") or {"mode": "given", "sigma_v_px": 1.0}
    return (f"auto ({v['sigma_v_px']:.3g})" if v["mode"] == "auto"
            else f"{v['sigma_v_px']:g}")


def markdown(result: dict) -> str:
    lines = ["# Plane observability gate (bench/bench_plane_gate.py)", "",
             f"{result['machine']['cpu']}; one run each, SIFT, SYN circle ~37 frames per lap; "
             "below 400 px (weak texture) with SIFT's low-contrast retry off "
             "(sift_min_features=0).", "",
             "sigma_v: the visual cost's (px; auto: `--visual-sigma auto`, measured by the "
             "start-up); rel. std at sigma_v 1 px, as the gate's limit is stated.", "",
             "| frames | px | gate | sigma_v | e_M px | max e_j px | drift | depth mm (true) | "
             "held / steps seeing pi | rel. std median / max | step ms median / p95 | tracker + "
             "true plane e_M / max px |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in result["runs"]:
        lines.append(
            f"| {r['frames']} | {r['size_px']} | {r['plane_max_relative_std']:g} | "
            f"{_sigma_label(r)} | {fmt(r['e_M_px'], 3)} | {fmt(r['max_e_j_px'], 1)} | "
            f"{fmt(r['drift_ratio'])} | "
            f"{fmt(r['depth_min_mm'], 1)}-{fmt(r['depth_max_mm'], 1)} "
            f"({fmt(r['true_depth_mm'], 1)}) | "
            f"{r['steps_held_by_gate']} / {r['steps_seeing_plane']} | "
            f"{fmt(r['relative_std_median'], 4)} / {fmt(r['relative_std_max'], 4)} | "
            f"{fmt(r['step_ms_median'])} / {fmt(r['step_ms_p95'])} | "
            f"{fmt(r['tracker_true_plane_e_M_px'], 1)} / "
            f"{fmt(r['tracker_true_plane_max_e_j_px'], 1)} |")
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = bench_args(__doc__)
    ap.add_argument("--frames", type=int, nargs="+", default=[300, 3000],
                    help="weak-texture sequence lengths (the first also at 400 px)")
    args = add_options(ap, out=RESULTS / "plane_gate.json").parse_args()
    bench = BenchRun(folder=False)
    result = {"machine": machine_info(), "runs": []}
    configs = [(n, 200, limit, 1.0) for n in args.frames for limit in (0.0, 0.02)]
    configs += [(args.frames[0], 400, limit, 1.0) for limit in (0.0, 0.02)]
    # --visual-sigma auto on weak texture (session 49: why it is not the default)
    configs += [(n, 200, 0.02, "auto") for n in args.frames]
    for n, size, limit, sigma_v in configs:
        r = stream(n, size, limit, sigma_v)
        print(f"{n} frames {size} px gate {limit:g} sigma_v {sigma_v}: e_M {r['e_M_px']:.3f} max "
              f"{r['max_e_j_px']:.1f} drift {r['drift_ratio']:.2f} depth "
              f"{r['depth_min_mm']:.1f}-{r['depth_max_mm']:.1f} held {r['steps_held_by_gate']}"
              f" step {r['step_ms_median']:.2f} ms", flush=True)
        result["runs"].append(r)
    bench.finish(result, args.out, markdown)


if __name__ == "__main__":
    main()
