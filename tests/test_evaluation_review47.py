"""Review N (session 47), finding L2: `evaluate` said "frame 0 unplaced" for every dataset whose
frame ids do not start at 0 (ids 100..115, every frame placed)."""

import shutil

import numpy as np

from fusedmosaic.evaluation import evaluate_output
from fusedmosaic.evaluation.metrics import evaluation_notes
from fusedmosaic.io import read_homographies_csv, write_homographies_csv
from fusedmosaic.simulation import PcleOptions, simulate_pcle


def _renumbered(src, dst, offset):
    """A copy of dataset `src` with every frame id (frames.csv, ground_truth.csv) + offset."""
    shutil.copytree(src, dst)
    lines = (dst / "frames.csv").read_text().splitlines()
    rows = [line.split(",", 1) for line in lines[1:]]
    (dst / "frames.csv").write_text("\n".join(
        [lines[0], *(f"{int(k) + offset},{rest}" for k, rest in rows)]) + "\n")
    ids, G = read_homographies_csv(dst / "ground_truth.csv")
    write_homographies_csv(dst / "ground_truth.csv", ids + offset, G)
    return dst


def test_no_unplaced_note_when_frame_ids_start_above_0(tmp_path):
    src = simulate_pcle(tmp_path / "p", PcleOptions(n_frames=16, width=128, height=112))
    data = _renumbered(src, tmp_path / "p100", 100)
    ids, G = read_homographies_csv(data / "ground_truth.csv")
    assert ids[0] == 100
    out = tmp_path / "out"
    out.mkdir()
    write_homographies_csv(out / "homographies.csv", ids, G)  # every frame placed (the truth)
    result = evaluate_output(out, data)
    assert (result["reference_frame"], result["first_frame"]) == (100, 100)
    assert result["e_M_px"] < 1e-6
    assert evaluation_notes(result) == []
    # frame 100 unplaced: the grid is frame 101's, and the note names frame 100
    G_late = G.copy()
    G_late[0] = np.nan
    G_late[1:] = np.linalg.inv(G[1]) @ G[1:]
    write_homographies_csv(out / "homographies.csv", ids, G_late)
    result = evaluate_output(out, data)
    assert result["reference_frame"] == 101
    assert evaluation_notes(result) == [
        "scored in frame 101's pixel grid: the output's reference frame (the one it writes as "
        "the identity; frame 100 unplaced), the truth taken to it"]
