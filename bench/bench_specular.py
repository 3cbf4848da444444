"""Specular highlights: fetoscopic sequences whose scope carries 3 light fibres (1 mm off the
optical axis), each mirrored in the wet tissue as a saturated highlight fixed to the camera
(FetoscopyOptions.specular_lights), mosaicked with the highlights masked (the default:
FeatureOptions.mask_specular, BlendOptions.mask_specular) and kept (`run --keep-specular`, the
baseline a pipeline without highlight handling gives), and the same sequence without lights as
the reference, in one run: e_M / drift of lba-emt, ba-emt and pairwise, the mosaic's mean
difference from the light-free frames composed at the true homographies, and the fraction of
the mosaic the highlights whiten (every channel > 30 grey levels above that truth).

Cases: SYN circles (152 frames, ~40 px between frames), hand-held (150 frames, ~30 px) and a
slow hand-held sweep (4 px between frames: a highlight's keypoints then agree with the true
motion's to within RANSAC's threshold).

    python bench/bench_specular.py [--seeds 2] [--out bench/results/specular.json]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from _common import BenchRun, bench_args, fmt, md_table, run_note
from bench_lens import METHODS, case_medians
from bench_lens import measure as bench_measure

from fusedmosaic.compositing import render_mosaic
from fusedmosaic.io import read_dataset
from fusedmosaic.simulation import FetoscopyOptions, simulate_fetoscopy
from fusedmosaic.simulation.fetoscopy import generate_fetoscopy

LIGHTS = 3  # METHODS: bench_lens's (lba-emt, ba-emt, pairwise)
SEQUENCES = {
    "syn": dict(motion="syn", n_frames=152),
    "handheld": dict(motion="handheld", n_frames=150),
    "slow handheld": dict(motion="handheld", n_frames=150, step_px=4.0),
}
VARIANTS = ("no lights", "masked", "kept")
WHITENED = 30.0  # grey levels above the truth, every channel: a highlight pasted in


def truth_mosaic(options: FetoscopyOptions, G_true: np.ndarray):
    """The light-free, noise-free frames composed at the true homographies."""
    scene = generate_fetoscopy(options)
    return render_mosaic([scene.pinhole(k) for k in range(scene.n_frames)], G_true, *scene.size,
                         mask=scene.fov_mask())


def measure(data: Path, out: Path, truth, keep: bool) -> dict:
    from fusedmosaic.compositing import BlendOptions
    from fusedmosaic.estimation.bundle import BundleOptions
    from fusedmosaic.estimation.pairwise import PairwiseOptions
    from fusedmosaic.estimation.sequential import SequentialOptions
    from fusedmosaic.registration.features import FeatureOptions

    features = FeatureOptions(mask_specular=not keep)
    options = {"lba-emt": SequentialOptions.preset("syn", features=features),
               "ba-emt": BundleOptions(features=features),
               "pairwise": PairwiseOptions(features=features)}
    return bench_measure(data, out, truth, options, BlendOptions(None, mask_specular=not keep),
                         lambda mosaic, origin: {"whitened_fraction":
                                                 whitened(mosaic, origin, truth)})


def whitened(mosaic: np.ndarray, origin, truth) -> float:
    """Fraction of the pixels both show where every channel of the mosaic is WHITENED grey
    levels above the truth's."""
    x0, y0 = origin
    tx0, ty0 = truth.plan.x0, truth.plan.y0
    ax0, ay0 = max(x0, tx0), max(y0, ty0)
    ax1 = min(x0 + mosaic.shape[1], tx0 + truth.image.shape[1])
    ay1 = min(y0 + mosaic.shape[0], ty0 + truth.image.shape[0])
    a = mosaic[ay0 - y0:ay1 - y0, ax0 - x0:ax1 - x0].astype(np.float64)
    b = truth.image[ay0 - ty0:ay1 - ty0, ax0 - tx0:ax1 - tx0].astype(np.float64)
    both = truth.covered[ay0 - ty0:ay1 - ty0, ax0 - tx0:ax1 - tx0] & (a.sum(axis=2) > 0)
    white = ((a - b).min(axis=2) > WHITENED) & both
    return float(white.sum() / max(int(both.sum()), 1))


def main() -> None:
    args = bench_args(__doc__, seeds=2, out=Path("bench/results/specular.json"),
                      work=True).parse_args()
    bench = BenchRun(args.work)
    work = bench.work
    runs = []
    for seed in range(args.seeds):
        run = {"seed": seed}
        for name, kw in SEQUENCES.items():
            run[name] = {}
            for variant in VARIANTS:
                print(f"seed {seed}, {name}, {variant}", flush=True)
                lights = 0 if variant == "no lights" else LIGHTS
                options = FetoscopyOptions(seed=seed, specular_lights=lights, **kw)
                data = work / f"{name.replace(' ', '_')}_{seed}_{lights}"
                if not (data / "frames.csv").exists():
                    simulate_fetoscopy(data, options, overwrite=True)
                truth = truth_mosaic(options, read_dataset(data).ground_truth)
                run[name][variant] = measure(
                    data, work / f"out_{name.replace(' ', '_')}_{seed}_{variant.replace(' ', '_')}",
                    truth, keep=variant == "kept")
        runs.append(run)
    median = {name: case_medians([r[name] for r in runs], VARIANTS) for name in SEQUENCES}
    bench.write_results(args.out, markdown, seeds=args.seeds, lights=LIGHTS, sequences=SEQUENCES,
                        runs=runs, median=median)


def markdown(res: dict) -> str:
    lines = ["# Specular highlights: masked vs kept", "",
             run_note(res, "bench_specular.py", f", {res['seeds']} seeds")
             + f" {res['lights']} light fibres 1 mm off the optical axis, highlight sigma 5 px "
             "(400x400, f = 480 px). Medians over the seeds. 'masked': the default (no "
             "keypoints on highlights, highlights not pasted); 'kept': `--keep-specular`; "
             "'no lights': the same sequence without highlights. Mosaic difference: mean "
             "absolute grey-level difference of mosaic.png from the light-free frames composed "
             "at the true homographies; whitened: fraction of the mosaic every channel of which "
             f"is > {WHITENED:.0f} grey levels above that truth.", ""]
    rows = []
    for name in SEQUENCES:
        for variant in VARIANTS:
            for m in METHODS:
                e = res["median"][name][variant][m]
                rows.append([name, variant, m, fmt(e["e_M_px"], 3), fmt(e["drift_ratio"], 2),
                             fmt(e.get("mosaic_difference"), 2),
                             fmt(100 * e["whitened_fraction"], 3),
                             fmt(e.get("features_s"), 2)])
    lines += md_table(["sequence", "highlights", "method", "e_M px", "drift ratio",
                       "mosaic difference (grey)", "whitened %", "features s"], rows)
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
