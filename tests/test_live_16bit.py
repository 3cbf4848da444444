"""Live sessions (fusedmosaic live, runner.run_igtl) on 16-bit frames, as pCLE systems export
them: mosaicked in 8 bits with one scale for the session, recorded as received (16-bit PNG);
8-bit and 16-bit frames not mixed; RGBA frames taken without their alpha."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest
from _igtl_sender import Sender, image_message, robot_events

from fusedmosaic.cli import main
from fusedmosaic.estimation.translation import run_ncc
from fusedmosaic.evaluation import frame_errors, mosaic_error
from fusedmosaic.io import read_dataset, read_homographies_csv
from fusedmosaic.simulation import PcleOptions, simulate_pcle

pytestmark = pytest.mark.realtime

N = 20


@pytest.fixture(scope="module")
def pcle(tmp_path_factory):
    """A clean pCLE scan, 192x160 8-bit gray frames (every one reaching 255), 10 frames/s."""
    return read_dataset(simulate_pcle(tmp_path_factory.mktemp("live16") / "pcle", PcleOptions(
        width=192, height=160, n_frames=N, speed_um_per_frame=12.0, radius_um=150.0,
        contact_loss=False, stick_slip=False)))


def _stream(ds, image_of, *, robot: bool = False):
    """The scan's events, each frame k sent as image_of(k, frame); robot: with the robot's
    positions (device RobotToBase), else the images alone."""
    events = []
    for t, message in robot_events(ds):
        if message[2:14].rstrip(b"\0") == b"IMAGE":
            k = int(np.argmin(np.abs(np.asarray(ds.timestamps) - t)))
            events.append((t, image_message(image_of(k, ds.frames[k]), t)))
        elif robot:
            events.append((t, message))
    return events


def _live(ds, tmp_path, events, *extra, method="ncc"):
    sender = Sender(events, speed=1.0, delay=0.1)
    code = main(["--quiet", "live", f"127.0.0.1:{sender.port}", "--method", method,
                 "--camera", str(ds.root / "camera.yaml"), "--record", str(tmp_path / "rec"),
                 "--out", str(tmp_path / "out"), "--no-report", "--frame-timeout", "2",
                 *extra])
    sender.join()
    return code


def _report(tmp_path) -> dict:
    return json.loads((tmp_path / "out" / "report.json").read_text())


@pytest.mark.parametrize("factor, bits, atol_px", [(257, 16, 1e-6), (16, 12, 0.05)],
                         ids=["full-16-bit", "12-bit"])
def test_16_bit_frames_are_mosaicked_as_their_8_bit_equivalent(pcle, tmp_path, factor, bits,
                                                               atol_px):
    """The 8-bit scan sent as 16-bit data (v * 257: 16 bits in use; v * 16, a 12-bit
    sensor's: 12 bits) is processed as the 8-bit scan: the session's 8-bit frames are
    round(v * factor * 255 / (2^bits - 1)), v exactly (257) or within one grey level (16); the
    placements match offline ncc on the 8-bit scan within atol_px (1e-6 px, 0.05 px) when no
    frame was dropped, else (frames dropped while busy: the chain registers across them) within
    0.5 px, and the truth within 1 px either way. The recording holds the frames as received
    (16-bit PNG) and report.json the session's scale."""
    events = _stream(pcle, lambda k, im: im.astype(np.uint16) * factor)
    assert _live(pcle, tmp_path, events) == 0
    report = _report(tmp_path)
    live = report["live"]
    assert report["frame_bits_in_use"] == bits
    assert live["source"]["frame_bits_in_use"] == bits and live["source"]["frames_clipped"] == 0
    assert live["source"]["frame_bits_chosen_by"] == "the first 16-bit frame, received frame 0"
    assert live["source"]["frames_refused"] == {} and report["warnings"] == []
    for k in (0, N - 1):  # recorded as received
        recorded = cv2.imread(str(tmp_path / "rec" / "frames" / f"{k:06d}.png"),
                              cv2.IMREAD_UNCHANGED)
        np.testing.assert_array_equal(recorded, pcle.frames[k].astype(np.uint16) * factor)
    _, G = read_homographies_csv(tmp_path / "out" / "homographies.csv")
    processed = np.isfinite(G).all(axis=(1, 2))
    assert processed.sum() == live["frames_processed"] > N // 2
    offline = run_ncc(pcle, progress=False).homographies  # the 8-bit scan
    tol = atol_px if processed.all() else 0.5
    np.testing.assert_allclose(G[processed][:, :2, 2], offline[processed][:, :2, 2], atol=tol)
    assert mosaic_error(frame_errors(G[processed], pcle.ground_truth[processed], 192, 160)) < 1.0
    # the recording re-runs offline as the session saw it (its own scale: the same bits here)
    rec = read_dataset(tmp_path / "rec", allow_untracked=True)
    if processed.all():
        np.testing.assert_allclose(run_ncc(rec, progress=False).homographies, G, atol=1e-6)
    rec.frames[0]
    assert rec.frames.bits_in_use == bits


@pytest.mark.parametrize("bit_depth", [None, 10, 12])
def test_a_later_frame_above_the_session_scale(pcle, tmp_path, capsys, bit_depth):
    """The first frames dim (10 bits: v * 4), the later ones brighter (v * 16: 12 bits). The
    scale taken from the first frame is raised at frame 5, one warning naming it and
    --bit-depth (a dim first frame, kept, clipped the rest of the session; review); --bit-depth
    10 keeps 10 bits and clips the later frames, told once; --bit-depth 12 nothing to say. The
    final outputs are composed on the recording's sampled scale (12 bits) in every case."""
    events = _stream(pcle, lambda k, im: im.astype(np.uint16) * (4 if k < 5 else 16))
    extra = [] if bit_depth is None else ["--bit-depth", str(bit_depth)]
    assert _live(pcle, tmp_path, events, *extra) == 0
    err = capsys.readouterr().err
    report = _report(tmp_path)
    source = report["live"]["source"]
    assert report["frame_bits_in_use"] == 12  # the outputs: the recording's scale
    if bit_depth is None:
        assert err.count("warning:") == 1, err
        assert ("received frame 5 (recorded as frame 5) has 16-bit values up to 4080, above the "
                "10-bit range (0-1023) taken from the first 16-bit frame, received frame 0: the "
                "live scale is raised to 12 bits from this frame on") in err
        assert source["frame_bits_raised"] == [{"received_frame": 5, "bits": 12}]
        assert source["frames_clipped"] == 0 and source["frame_bits_in_use"] == 12
        assert source["frame_bits_chosen_by"] == "the first 16-bit frame, received frame 0"
    elif bit_depth == 10:
        assert err.count("warning:") == 1, err
        assert ("received frame 5 (recorded as frame 5) has 16-bit values up to 4080, above the "
                "10-bit range (0-1023) given by --bit-depth: clipped to 255") in err
        assert "Give --bit-depth 12" in err
        assert source["frames_clipped"] == N - 5 and source["frame_bits_raised"] == []
        assert source["frame_bits_in_use"] == 10
    else:
        assert "warning:" not in err, err
        assert source["frames_clipped"] == 0 and source["frame_bits_in_use"] == 12
        assert source["frame_bits_chosen_by"] == "--bit-depth"
    assert report["live"]["frames_recorded"] == N and source["frames_refused"] == {}
    # the recording keeps every frame as received: an offline re-run takes its own scale
    assert cv2.imread(str(tmp_path / "rec" / "frames" / f"{N - 1:06d}.png"),
                      cv2.IMREAD_UNCHANGED).max() == 255 * 16


@pytest.mark.parametrize("first, then", [(8, 16), (16, 8)])
def test_8_and_16_bit_frames_are_not_mixed(pcle, tmp_path, capsys, first, then):
    """Frames of the other pixel type than the first accepted one are refused per frame (not
    recorded, not processed), with the reason, as gray after colour frames are."""
    dtype = {8: np.uint8, 16: np.uint16}

    def image_of(k, im):
        bits = first if k < 10 else then
        return im.astype(dtype[bits]) * (16 if bits == 16 else 1)

    assert _live(pcle, tmp_path, _stream(pcle, image_of)) == 0
    err = capsys.readouterr().err
    why = f"a {then}-bit image after {first}-bit ones (a recording is all 8-bit or all 16-bit)"
    assert (f"received frame 10 refused, neither processed nor recorded: {why}") in err
    live = _report(tmp_path)["live"]
    assert live["source"]["frames_refused"] == {why: N - 10}
    assert live["source"]["frames_refused_first"] == {why: 10}
    assert live["frames_recorded"] == 10
    assert ("frame_bits_in_use" in _report(tmp_path)) == (first == 16)


@pytest.mark.parametrize("bits", [8, 16])
def test_rgba_frames_are_taken_without_their_alpha(pcle, tmp_path, bits):
    """Colour frames with an alpha channel (8- or 16-bit): mosaicked and recorded as colour,
    the alpha dropped, as offline."""
    dtype, factor = (np.uint8, 1) if bits == 8 else (np.uint16, 257)

    def rgba(k, im):  # (BGRA: image_message sends it reversed, the receiver reverses it back)
        grey = im.astype(dtype) * factor
        return cv2.merge([grey, grey, grey, np.full_like(grey, 7)])

    assert _live(pcle, tmp_path, _stream(pcle, rgba)) == 0
    report = _report(tmp_path)
    assert report["live"]["source"]["frames_refused"] == {}
    assert report["live"]["frames_processed"] > N // 2
    recorded = cv2.imread(str(tmp_path / "rec" / "frames" / "000003.png"), cv2.IMREAD_UNCHANGED)
    assert recorded.shape == (160, 192, 3) and recorded.dtype == dtype
    np.testing.assert_array_equal(recorded[:, :, 1], pcle.frames[3].astype(dtype) * factor)


def test_16_bit_kalman_robot_session(pcle, tmp_path):
    """The reviewer's case: kalman-robot on 12-bit frames and the robot's positions."""
    events = _stream(pcle, lambda k, im: im.astype(np.uint16) * 16, robot=True)
    assert _live(pcle, tmp_path, events, "--transform", "RobotToBase",
                 method="kalman-robot") == 0
    report = _report(tmp_path)
    assert report["frame_bits_in_use"] == 12 and report["live"]["frames_without_sample"] == []
    assert report["live"]["frames_processed"] > N // 2


@pytest.mark.parametrize("value", ["7", "17"])
def test_bit_depth_is_checked_before_connecting(pcle, tmp_path, capsys, value):
    code = main(["--quiet", "live", "127.0.0.1:1", "--method", "ncc", "--camera",
                 str(pcle.root / "camera.yaml"), "--record", str(tmp_path / "rec"), "--out",
                 str(tmp_path / "out"), "--bit-depth", value])
    assert code == 2
    assert "bit depth (--bit-depth): must be an integer in 8..16" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())


def test_a_frame_of_another_size_is_refused_without_blaming_a_pixel_type(pcle, tmp_path,
                                                                         capsys):
    """camera.yaml gives a size, no pixel type: the reason names the sizes only."""
    events = _stream(pcle, lambda k, im: (im if k < 10 else im[:100, :120]).astype(np.uint16))
    assert _live(pcle, tmp_path, events) == 0
    why = "an image of another size than camera.yaml's 192x160 (width x height)"
    source = _report(tmp_path)["live"]["source"]
    assert source["frames_refused"] == {why: N - 10}
    assert source["frames_refused_details"] == {why: "a 120x100 image"}
    assert f"{why}: a 120x100 image" in capsys.readouterr().err
