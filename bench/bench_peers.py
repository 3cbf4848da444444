"""What users would use instead, on the same frames (issue 7, item 3).

* OpenCV's high-level stitcher, `cv2.Stitcher.create(cv2.Stitcher_SCANS)` with its defaults
  (affine model, all-pairs matching, affine bundle adjustment, seam finding, multi-band
  blending), on the SYN and hand-held sequences of bench_table1 (frames as BGR, in memory; the
  circular FOV mask passed as its masks argument when the camera has one). stitch() is called as
  its two halves, estimateTransform() (registration) and composePanorama() (seams, blending),
  timed apart; the time reported is their sum. It runs in a child process with a time limit, so
  a hang or a crash is reported instead of stopping the benchmark. When it succeeds, its
  per-image camera parameters give each frame's frame -> panorama affine map A_k = R_k^-1 (at
  the registration scale; this convention was checked on SYN: R_k^-1 gives sub-pixel e_j, R_k
  hundreds of pixels), so G_k = A_0^-1 A_k is its frame -> frame-0 mapping and e_j (Eq. 28) is
  measured exactly as for our methods; frames it leaves out of the panorama count as unplaced.
  A check independent of that convention: 6 evenly spaced frames are registered into the
  panorama image itself (SIFT + RANSAC homography) and their e_j computed the same way.
* A plain OpenCV pairwise chain: SIFT (cv2.SIFT_create defaults, inside the circular FOV when
  there is one), BFMatcher L2 with Lowe's ratio 0.75, findHomography RANSAC (3 px), at least 15
  inliers; each frame registered to the last placed frame and the homographies chained. On all
  four sequences (with black frames the chain resumes at the next textured frame).

    python bench/bench_peers.py [--quick] [--work DIR] [--stitcher-timeout 600]
                                [--out bench/results/peers.json]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np
from _common import (
    DEFAULT_WORK,
    RESULTS,
    BenchRun,
    bench_args,
    ensure_dataset,
    machine_info,
    sequences,
)

RATIO = 0.75
RANSAC_PX = 3.0
MIN_INLIERS = 15


def load_frames(data: Path):
    from fusedmosaic.io import read_dataset

    ds = read_dataset(data)
    frames = [np.asarray(ds.frames[k]) for k in range(len(ds))]
    return ds, frames


def score(G: np.ndarray, ds) -> dict:
    from fusedmosaic.evaluation import drift_ratio, frame_errors, mosaic_error

    e = frame_errors(G, ds.ground_truth, ds.camera.width, ds.camera.height)
    placed = np.isfinite(e)
    return {
        "e_M_px": mosaic_error(e),
        "max_e_j_px": float(np.nanmax(e)) if placed.any() else None,
        "drift_ratio": drift_ratio(e),
        "unplaced": int((~placed).sum()),
        "e_j_px": [float(x) if np.isfinite(x) else None for x in e],
    }


# -- plain OpenCV chain ------------------------------------------------------------------------


def opencv_chain(data: Path) -> dict:
    ds, frames = load_frames(data)
    n = len(frames)
    mask = ds.camera.fov_mask()
    sift = cv2.SIFT_create()
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    G = np.full((n, 3, 3), np.nan)
    t_feat = t_match = 0.0
    t_start = time.perf_counter()
    prev = None  # (index, keypoints, descriptors) of the last placed frame
    registered = 0
    for k in range(n):
        t0 = time.perf_counter()
        kp, des = sift.detectAndCompute(frames[k], mask)
        t_feat += time.perf_counter() - t0
        if k == 0:
            G[0] = np.eye(3)
            prev = (0, kp, des)
            continue
        if des is None or len(kp) < MIN_INLIERS or prev is None:
            continue
        t0 = time.perf_counter()
        j, kp_j, des_j = prev
        knn = matcher.knnMatch(des, des_j, k=2)
        good = [p[0] for p in knn if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
        H = None
        if len(good) >= MIN_INLIERS:
            src = np.float32([kp[g.queryIdx].pt for g in good])
            dst = np.float32([kp_j[g.trainIdx].pt for g in good])
            H, inl = cv2.findHomography(src, dst, cv2.RANSAC, RANSAC_PX)
            if H is not None and int(inl.sum()) < MIN_INLIERS:
                H = None
        t_match += time.perf_counter() - t0
        if H is None:
            continue  # unplaced; the next frame tries the same last placed frame
        G[k] = G[j] @ H  # frame k -> frame j -> reference
        G[k] /= G[k][2, 2]
        prev = (k, kp, des)
        registered += 1
    total = time.perf_counter() - t_start
    return {
        "peer": "opencv-chain",
        "frames": n,
        "time_s": total,
        "features_s": t_feat,
        "matching_s": t_match,
        "time_per_frame_ms": 1e3 * total / n,
        "registered_pairs": registered,
        **score(G, ds),
    }


# -- cv2.Stitcher (child process) --------------------------------------------------------------


def stitch_child(data: Path, out: Path) -> None:
    """Runs in a child process: the stitcher, then the frame -> frame-0 maps from its cameras."""
    ds, frames = load_frames(data)
    images = [cv2.cvtColor(f, cv2.COLOR_GRAY2BGR) if f.ndim == 2 else f for f in frames]
    mask = ds.camera.fov_mask()
    stitcher = cv2.Stitcher.create(cv2.Stitcher_SCANS)
    # stitch() = estimateTransform() + composePanorama(); called apart to time both halves.
    pano = None
    t0 = time.perf_counter()
    if mask is None:
        status = stitcher.estimateTransform(images)
    else:  # the circular field of view, as our methods get it
        status = stitcher.estimateTransform(images, [mask] * len(images))
    t1 = time.perf_counter()
    if status == cv2.Stitcher_OK:
        status, pano = stitcher.composePanorama()
    t2 = time.perf_counter()
    res = {
        "status": int(status),
        "time_s": t2 - t0,
        "registration_s": t1 - t0,
        "compositing_s": t2 - t1,
        "threads": cv2.getNumThreads(),
        "panorama_shape": None if pano is None else list(pano.shape),
    }
    if status == cv2.Stitcher_OK:
        comp = [int(i) for i in np.asarray(stitcher.component()).ravel()]
        cams = stitcher.cameras()
        s = float(stitcher.workScale())
        S = np.diag([s, s, 1.0])  # full-resolution pixels -> registration-scale pixels
        A = {k: np.linalg.inv(np.asarray(c.R, float)) for k, c in zip(comp, cams, strict=True)}
        G = {}
        if 0 in A:
            for k, a in A.items():
                g = np.linalg.inv(S) @ np.linalg.inv(A[0]) @ a @ S
                G[k] = (g / g[2, 2]).tolist()
        res.update({"component": comp, "work_scale": s, "G": G})
    if pano is not None:
        res["panorama_registration"] = register_into_panorama(pano, frames, mask)
    out.write_text(json.dumps(res))


PANO_CHECK_FRAMES = 6


def register_into_panorama(pano: np.ndarray, frames: list, mask) -> dict:
    """A check that does not rely on the stitcher's camera convention: a few evenly spaced
    frames are registered into the returned panorama image (SIFT + ratio test + RANSAC
    homography); G_k = P_0^-1 P_k with P_k: frame k -> panorama is then frame k -> frame 0."""
    sift = cv2.SIFT_create()
    gray = cv2.cvtColor(pano, cv2.COLOR_BGR2GRAY) if pano.ndim == 3 else pano
    kp_p, des_p = sift.detectAndCompute(gray, None)
    matcher = cv2.BFMatcher(cv2.NORM_L2)
    picks = np.unique(np.round(np.linspace(0, len(frames) - 1, PANO_CHECK_FRAMES)).astype(int))
    P = {}
    for k in picks:
        f = frames[k] if frames[k].ndim == 2 else cv2.cvtColor(frames[k], cv2.COLOR_BGR2GRAY)
        kp, des = sift.detectAndCompute(f, mask)
        if des is None or des_p is None or len(kp) < MIN_INLIERS:
            continue
        knn = matcher.knnMatch(des, des_p, k=2)
        good = [p[0] for p in knn if len(p) == 2 and p[0].distance < RATIO * p[1].distance]
        if len(good) < MIN_INLIERS:
            continue
        src = np.float32([kp[g.queryIdx].pt for g in good])
        dst = np.float32([kp_p[g.trainIdx].pt for g in good])
        H, inl = cv2.findHomography(src, dst, cv2.RANSAC, RANSAC_PX)
        if H is not None and int(inl.sum()) >= MIN_INLIERS:
            P[int(k)] = H
    G = {}
    if 0 in P:
        for k, h in P.items():
            g = np.linalg.inv(P[0]) @ h
            G[k] = (g / g[2, 2]).tolist()
    return {"frames": [int(k) for k in picks], "G": G}


STATUS = {
    0: "OK",
    1: "ERR_NEED_MORE_IMGS",
    2: "ERR_HOMOGRAPHY_EST_FAIL",
    3: "ERR_CAMERA_PARAMS_ADJUST_FAIL",
}


def opencv_stitcher(data: Path, timeout_s: float) -> dict:
    from fusedmosaic.io import read_dataset

    ds = read_dataset(data)
    n = len(ds)
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "stitch.json"
        t0 = time.perf_counter()
        try:
            proc = subprocess.run(
                [sys.executable, __file__, "--stitch-child", str(data), str(out)],
                capture_output=True,
                text=True,
                timeout=timeout_s,
            )
        except subprocess.TimeoutExpired:
            wall = time.perf_counter() - t0
            return {
                "peer": "cv2.Stitcher SCANS",
                "frames": n,
                "success": False,
                "status": f"timeout: no result within {timeout_s:.0f} s (killed)",
                "time_s": wall,
                "time_per_frame_ms": None,
                "e_M_px": None,
                "unplaced": n,
            }
        wall = time.perf_counter() - t0
        if proc.returncode != 0 or not out.is_file():
            return {
                "peer": "cv2.Stitcher SCANS",
                "frames": n,
                "success": False,
                "status": f"child failed (exit {proc.returncode}): {proc.stderr.strip()[-300:]}",
                "time_s": wall,
                "time_per_frame_ms": None,
                "e_M_px": None,
                "unplaced": n,
            }
        res = json.loads(out.read_text())
    ok = res["status"] == 0
    row = {
        "peer": "cv2.Stitcher SCANS",
        "frames": n,
        "success": ok,
        "status": STATUS.get(res["status"], str(res["status"])),
        "time_s": res["time_s"],
        "time_per_frame_ms": 1e3 * res["time_s"] / n,
        "registration_s": res["registration_s"],
        "compositing_s": res["compositing_s"],
        "process_wall_s": wall,
        "opencv_threads": res["threads"],
        "panorama_shape": res["panorama_shape"],
    }
    if ok:
        G = np.full((n, 3, 3), np.nan)
        for k, g in res["G"].items():
            G[int(k)] = np.asarray(g)
        row.update(
            {
                "in_panorama": len(res["component"]),
                "work_scale": res["work_scale"],
                "error_from": "camera parameters (A_k = R_k^-1), frame 0 as reference"
                if res["G"]
                else "frame 0 left out of the panorama: not measurable",
                **(score(G, ds) if res["G"] else {"e_M_px": None, "unplaced": n}),
            }
        )
    else:
        row.update({"e_M_px": None, "unplaced": n})
    check = res.get("panorama_registration")
    if check:
        G = np.full((n, 3, 3), np.nan)
        for k, g in check["G"].items():
            G[int(k)] = np.asarray(g)
        e = score(G, ds)["e_j_px"]
        picked = [e[k] for k in check["frames"] if k != 0]
        found = [x for x in picked if x is not None]
        row["panorama_check"] = {
            "frames": check["frames"],
            "registered": len(check["G"]),
            "e_j_px": {str(k): e[k] for k in check["frames"]},
            "mean_e_j_px": float(np.mean(found)) if found else None,
        }
    return row


def main(argv=None) -> dict:
    ap = bench_args(
        __doc__,
        quick="60-frame sequences",
        work=f"datasets (run_all uses {DEFAULT_WORK})",
        out=RESULTS / "peers.json",
    )
    ap.add_argument(
        "--stitcher-timeout",
        type=float,
        default=600.0,
        help="seconds per stitcher run before it is killed and reported as such",
    )
    ap.add_argument(
        "--stitcher-black",
        action="store_true",
        help="also run the stitcher on the black-frame sequences",
    )
    ap.add_argument("--stitch-child", nargs=2, type=Path, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.stitch_child:
        stitch_child(*args.stitch_child)
        return {}
    bench = BenchRun(args.work)
    args.work = bench.work
    res: dict = {
        "benchmark": "peers on the same frames (bench/bench_peers.py)",
        "quick": args.quick,
        "machine": machine_info(),
        "versions": {"opencv": cv2.__version__, "numpy": np.__version__},
        "chain_settings": {
            "detector": "cv2.SIFT_create() defaults",
            "ratio": RATIO,
            "ransac_px": RANSAC_PX,
            "min_inliers": MIN_INLIERS,
        },
        "rows": [],
    }
    for seq in sequences(args.quick):
        data = ensure_dataset(args.work, seq)
        runs = [opencv_chain(data)]
        if not seq.black or args.stitcher_black:
            runs.append(opencv_stitcher(data, args.stitcher_timeout))
        for r in runs:
            r["sequence"] = seq.name
            res["rows"].append(r)
            e_m = r.get("e_M_px")
            print(
                f"{seq.name:<15} {r['peer']:<19} {r['time_s']:7.1f} s  "
                f"e_M {'-' if e_m is None else f'{e_m:.3f}'} px  unplaced {r.get('unplaced')}"
                f"{'' if r.get('success', True) else '  ' + r['status']}",
                flush=True,
            )
    return bench.finish(res, args.out)


if __name__ == "__main__":
    main(sys.argv[1:])
