"""bench/_common.WindowRecorder, through which bench_latency.py times lba-emt's window steps
and logs them for the C++ replay: it must accept every call the mosaicker makes (a step's
hold_plane included: its absence broke bench_latency unnoticed) and change nothing."""

import sys
from pathlib import Path

import numpy as np

from fusedmosaic import _core
from fusedmosaic.estimation.sequential import SequentialMosaicker, SequentialOptions
from fusedmosaic.evaluation.benchmark import syn_stream

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from _common import WindowRecorder  # noqa: E402


def _stream(camera, scene, poses, valid, n, options, wrap=None):
    m = SequentialMosaicker(camera, options)
    if wrap:
        m.window = wrap(m)
    out = []
    for k in range(n):
        m.add_frame(scene.render(k), float(scene.timestamps[k]), poses[k] if valid[k] else None)
        out += m.finalized()
    out += m.flush()
    return m, np.stack([r.homography for r in sorted(out, key=lambda r: r.frame_id)])


def test_window_recorder_is_transparent_and_logs_every_step(tmp_path):
    n = 52
    scene, camera, poses, valid = syn_stream(n)
    options = SequentialOptions()
    log = tmp_path / "window.txt"

    def wrap(m):
        wopts = _core.SlidingWindowOptions(window_size=options.window_size,
                                           num_new=options.num_new, costs=m._costs)
        return WindowRecorder(m.window, m.K, m._costs, wopts, log)

    _, plain = _stream(camera, scene, poses, valid, n, options)
    m, recorded = _stream(camera, scene, poses, valid, n, options, wrap)
    np.testing.assert_array_equal(recorded, plain)
    rec = m.window
    rec.close()
    steps = (n - options.bootstrap_frames) // options.num_new
    assert len(rec.step_wall_s) >= steps and all(t > 0 for t in rec.step_wall_s)
    lines = log.read_text().splitlines()
    assert sum(x.startswith("step ") for x in lines) == len(rec.step_wall_s)
