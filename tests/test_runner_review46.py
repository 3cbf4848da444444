"""Review 46 (lead): the run's outputs as the CLI reports them."""

import resource
from contextlib import contextmanager

import pytest

from fusedmosaic.cli import main
from fusedmosaic.simulation import PcleOptions, simulate_pcle


@contextmanager
def file_size_limit(limit: int):
    """Files can grow to `limit` bytes at most (RLIMIT_FSIZE): a write beyond fails with EFBIG
    (Python ignores SIGXFSZ), as on a full disk."""
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    resource.setrlimit(resource.RLIMIT_FSIZE, (limit, hard))
    try:
        yield
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    root = tmp_path_factory.mktemp("runner46") / "pcle"
    simulate_pcle(root, PcleOptions(width=128, height=112, n_frames=20, contact_loss=False,
                                    stick_slip=False))
    return root


def test_a_streamed_mosaic_that_cannot_be_written_names_outs_mosaic_png(pcle, tmp_path,
                                                                           capsys):
    """run --alpha (as a tiled mosaic) streams mosaic.png into the output folder's staging
    copy: a write error named that hidden path (".o.fusedmosaic.tmp-.../mosaic.png: File too
    large"). It names OUT's mosaic.png, and nothing is left behind."""
    out = tmp_path / "o"
    with file_size_limit(20_000):
        code = main(["--quiet", "run", str(pcle), "--method", "robot", "--out", str(out),
                     "--alpha", "--no-report"])
    err = capsys.readouterr().err
    assert code != 0
    assert f"{out / 'mosaic.png'}: the image could not be written (File too large" in err, err
    assert "fusedmosaic.tmp" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == []


@pytest.fixture(scope="module")
def feto(tmp_path_factory):
    root = tmp_path_factory.mktemp("runner46") / "feto"
    assert main(["--quiet", "simulate", "fetoscopy", str(root), "--n-frames", "8",
                 "--width", "160", "--height", "120", "--laps", "0.2"]) == 0
    return root


def test_plane_json_says_its_unit(feto, tmp_path):
    """ba fixes no scale: plane.json's distance_mm was 1.0, in units of the first camera's
    distance to the plane, with nothing saying so. Its "unit" says it (mm for ba-emt)."""
    import json

    units = {}
    for method in ("ba", "ba-emt"):
        out = tmp_path / method
        assert main(["--quiet", "run", str(feto), "--method", method, "--out", str(out),
                     "--no-report"]) == 0
        units[method] = json.loads((out / "plane.json").read_text())["unit"]
    assert units["ba-emt"] == "mm"
    assert units["ba"].startswith("the first frame's camera frame, lengths in units of that "
                                  "camera's distance to the plane") and "not mm" in units["ba"]
