"""`fusedmosaic run`: dataset -> method -> outputs, written atomically (design, output contract)."""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np

from fusedmosaic import methods

# What each method needs from the dataset beyond frames and camera.yaml.
NEEDS_TRACKING = {"ba-emt", "lba-emt", "emt"}
NEEDS_CAMERA_MATRIX = {"ba", "ba-emt", "lba-emt", "emt"}
NEEDS_ROBOT = {"robot", "kalman-robot"}
NEEDS_PIXEL_SIZE = {"ncc", "robot", "kalman-robot"}


def run_dataset(dataset_root: str | Path, method: str, out: str | Path, *, fps: float = 25.0,
                robot_file: str = "robot.csv", allow_untracked: bool = False,
                progress: bool = True, blend: str | None = None, options=None) -> str:
    """Runs `method` on a dataset folder and writes the output contract into `out`.

    blend: mosaic blending, by default the method's own preference (MethodResult.blend).
    options: the method's options dataclass (None: the method's defaults)."""
    from fusedmosaic.compositing import compose_mosaic
    from fusedmosaic.io import OutputWriter, read_dataset

    timings: dict[str, float] = {}
    run_method = methods.get(method)  # unknown method fails before any reading
    t0 = time.perf_counter()
    dataset = read_dataset(dataset_root, fps=fps, robot_file=robot_file,
                           allow_untracked=allow_untracked)
    if method in NEEDS_TRACKING:
        dataset.require_tracking(method)
    if method in NEEDS_CAMERA_MATRIX:
        dataset.camera.require_camera_matrix(method)
    if method in NEEDS_ROBOT:
        dataset.require_robot(method)
    if method in NEEDS_PIXEL_SIZE:
        dataset.require_pixel_size(method)
    timings["read_dataset"] = time.perf_counter() - t0

    result = run_method(dataset, progress=progress, options=options)
    timings.update(result.timings)
    G = result.homographies
    placed = np.isfinite(G).all(axis=(1, 2))

    t0 = time.perf_counter()
    cam = dataset.camera
    mosaic = compose_mosaic(((k, dataset.frames[k]) for k in np.flatnonzero(placed)), G,
                            cam.width, cam.height, mask=cam.fov_mask(),
                            blend=blend or result.blend)
    timings["compose_mosaic"] = time.perf_counter() - t0

    report = {
        "method": method,
        "paper_name": methods.REGISTRY[method][1],
        "dataset": str(Path(dataset_root).resolve()),
        "frames": len(G),
        "placed": int(placed.sum()),
        "parameters": result.parameters,
        "timings_s": timings,
        "frame_status": result.status,
        **result.details,
    }
    if dataset.ground_truth is not None:
        from fusedmosaic.evaluation import drift_ratio, frame_errors, mosaic_error

        e = frame_errors(G, dataset.ground_truth, cam.width, cam.height)
        report["metrics"] = {"e_M_px": mosaic_error(e), "drift_ratio": drift_ratio(e),
                             "max_e_j_px": float(np.nanmax(e)) if placed.any() else None}
    with OutputWriter(out) as w:
        w.write_homographies(dataset.frame_ids, G)
        if result.poses is not None:
            w.write_poses(dataset.frame_ids, result.poses)
        if result.plane is not None:
            from fusedmosaic import _core

            plane = np.asarray(result.plane, float)
            dist = [None if not np.isfinite(p).all() else _core.camera_plane_distance(p, plane)
                    for p in (result.poses if result.poses is not None else [])]
            w.write_json("plane.json", {"plane": plane.tolist(),
                                        "normal": (plane / np.linalg.norm(plane)).tolist(),
                                        "distance_mm": float(1.0 / np.linalg.norm(plane)),
                                        "camera_plane_distance_mm": dist})
        w.write_image("mosaic.png", mosaic)
        w.write_json("report.json", report)
    msg = f"{method}: placed {int(placed.sum())}/{len(G)} frames -> {out}"
    if "metrics" in report:
        msg += f" (e_M = {report['metrics']['e_M_px']:.3f} px)"
    return msg
