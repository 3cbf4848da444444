"""Audit 16, item 9: messages a real recording meets. Tabs in camera.yaml (and OpenCV's parse
errors) named by line, 16-bit frames converted with one scale for the dataset, and a drift ratio
that cannot be computed reported as n/a / null instead of nan / NaN."""

from __future__ import annotations

import json
import shutil

import cv2
import numpy as np
import pytest

from fusedmosaic.cli import main
from fusedmosaic.evaluation.metrics import drift_note, drift_ratio
from fusedmosaic.io import (
    FrameSource,
    read_camera_yaml,
    read_dataset,
    read_homographies_csv,
    write_homographies_csv,
)

# ------------------------------------------------------------------------- camera.yaml: tabs

SPACES = """%YAML:1.0
---
image_width: 400
image_height: 300
camera_matrix: !!opencv-matrix
   rows: 3
   cols: 3
   dt: d
   data: [ 480., 0., 199.5, 0., 480., 149.5, 0., 0., 1. ]
distortion_coefficients: [ -0.1, 0.01, 0., 0., 0. ]
"""


def _write(tmp_path, text: str, name: str = "camera.yaml", bom: bool = False):
    path = tmp_path / name
    path.write_bytes((b"\xef\xbb\xbf" if bom else b"") + text.encode())
    return path


@pytest.mark.parametrize("bom", [False, True])
def test_tab_in_the_indentation_names_the_line(tmp_path, bom):
    """The audit's file (c_tabs): OpenCV said "(skipSpaces)", its parsing function's name."""
    text = ("%YAML:1.0\n---\nimage_width: 400\nimage_height: 400\ncamera_matrix:\n"
            "\t[480, 0, 199.5, 0, 480, 199.5, 0, 0, 1]\n")
    with pytest.raises(ValueError, match=r"camera\.yaml: line 6: a tab character in the "
                                         r"indentation; YAML does not allow tabs there \(their "
                                         r"width is ambiguous\): indent with spaces$"):
        read_camera_yaml(_write(tmp_path, text, bom=bom))
    text = SPACES.replace("   rows", "\trows").replace("   dt", " \t dt")
    with pytest.raises(ValueError, match=r"camera\.yaml: lines 6, 8: a tab character in the "
                                         r"indentation"):
        read_camera_yaml(_write(tmp_path, text, bom=bom))


def test_tabs_between_tokens_are_spaces(tmp_path):
    """YAML allows tabs as separation inside a line (OpenCV does not): read as spaces; comment
    and blank lines may hold tabs anywhere."""
    expected = read_camera_yaml(_write(tmp_path, SPACES))
    text = (SPACES.replace("image_width: 400", "image_width:\t400\t# px")
            .replace("cols: 3", "cols:\t3\t")
            .replace("0., 480., 149.5", "0.,\t480.,\t149.5")
            .replace("---\n", "---\n\t# a comment after a tab\n \t \n"))
    assert "\t" in text
    camera = read_camera_yaml(_write(tmp_path, text, name="tabs.yaml"))
    assert (camera.width, camera.height) == (expected.width, expected.height)
    np.testing.assert_array_equal(camera.camera_matrix, expected.camera_matrix)
    np.testing.assert_array_equal(camera.distortion, expected.distortion)
    # CRLF line ends, and a file that is not UTF-8 (a Latin-1 comment): the same
    crlf = text.replace("\n", "\r\n").encode() + "# caméra\r\n".encode("latin-1")
    (tmp_path / "crlf.yaml").write_bytes(crlf)
    np.testing.assert_array_equal(read_camera_yaml(tmp_path / "crlf.yaml").camera_matrix,
                                  expected.camera_matrix)


def test_tab_after_a_quote_is_left_to_opencv_and_named_by_line(tmp_path):
    """A tab after a quote character may be inside a quoted string: not replaced; OpenCV's
    refusal is named by file and line, in words (no parsing-function name)."""
    text = "image_width: 400\nimage_height: 400\ndistortion_model: 'plumb_bob'\t\n"
    with pytest.raises(ValueError, match=r"camera\.yaml: cannot parse as OpenCV FileStorage "
                                         r"YAML, line 3: a tab character, which OpenCV's YAML "
                                         r"reader does not accept here: replace it with spaces$"):
        read_camera_yaml(_write(tmp_path, text))


@pytest.mark.parametrize(("name", "text", "match"), [
    ("camera.yaml", "image_width: 400\nimage_height: 400\ncamera_matrix: [480, 0, 199.5\n",
     r"camera\.yaml: cannot parse as OpenCV FileStorage YAML, line 3: Missing , between the "
     r"elements$"),
    ("camera.yaml", "image_width: 400\n  image_height: 400\n",
     r"camera\.yaml: cannot parse as OpenCV FileStorage YAML, line 2: Incorrect indentation$"),
    ("camera.yaml", "image_width: 400\n-image_height: 400\n",
     r"camera\.yaml: cannot parse as OpenCV FileStorage YAML, line 2: Key may not start with "
     r"'-'$"),
    ("camera.json", '{"image_width": 400,\n "image_height": }\n',
     r"camera\.json: cannot parse as OpenCV FileStorage JSON, line 2: Unrecognized value$"),
])
def test_opencv_parse_errors_name_the_line_not_the_function(tmp_path, name, text, match):
    with pytest.raises(ValueError, match=match) as info:
        read_camera_yaml(_write(tmp_path, text, name=name))
    assert "parseValue" not in str(info.value) and "parseKey" not in str(info.value)
    with pytest.raises(ValueError, match=match):  # behind a byte order mark: the same lines
        read_camera_yaml(_write(tmp_path, text, name=name, bom=True))


def test_json_with_tabs_is_not_touched(tmp_path):
    """JSON allows tabs anywhere between tokens (and OpenCV reads them): no YAML rule applies."""
    text = '{\n\t"image_width": 400,\n\t"image_height":\t300\n}\n'
    assert read_camera_yaml(_write(tmp_path, text, name="camera.json")).size == (400, 300)


# --------------------------------------------------------------------------- 16-bit frames


def _frames(folder, images) -> list:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for k, image in enumerate(images):
        paths.append(folder / f"{k:06d}.png")
        assert cv2.imwrite(str(paths[-1]), image)
    return paths


def _to_12_bits(image: np.ndarray) -> np.ndarray:
    """8-bit data as a 12-bit sensor's (0-4095), stored in 16 bits: converts back exactly."""
    return np.round(image.astype(np.float64) * 4095 / 255).astype(np.uint16)


def test_16_bit_frames_take_one_scale_from_the_bit_depth_in_use(tmp_path):
    rng = np.random.default_rng(0)
    images = [rng.integers(0, 256, (24, 32, 3), dtype=np.uint8) for _ in range(10)]
    images[4] //= 4  # a dim frame: not stretched, so it stays dim
    paths = _frames(tmp_path / "f12", [_to_12_bits(im) for im in images])
    source = FrameSource(paths, expected_size=(32, 24))
    assert source.bits_in_use is None
    for k in (4, 9, 0):  # any order: the scale comes from frames spread over the sequence
        np.testing.assert_array_equal(source[k], images[k])
    assert source.bits_in_use == 12 and source[0].dtype == np.uint8
    # data scaled to the full 16 bits; grey frames with an alpha channel (ignored)
    paths = _frames(tmp_path / "f16", [im.astype(np.uint16) * 257 for im in images])
    np.testing.assert_array_equal(FrameSource(paths)[4], images[4])
    grey = [cv2.cvtColor(im, cv2.COLOR_BGR2GRAY) for im in images]
    rgba = [cv2.merge([_to_12_bits(g)] * 3 + [np.full_like(g, 65535, np.uint16)]) for g in grey]
    source = FrameSource(_frames(tmp_path / "rgba", rgba))
    np.testing.assert_array_equal(source[2], cv2.merge([grey[2]] * 3))
    assert source.bits_in_use == 12
    # 10-bit data that does not reach the top of its range: still 10 bits (0-1023)
    dim = [(g.astype(np.uint16) * 3 + 200) for g in grey]  # 200..965
    source = FrameSource(_frames(tmp_path / "dim", dim))
    np.testing.assert_array_equal(source[1], np.round(dim[1] * (255 / 1023)).astype(np.uint8))
    assert source.bits_in_use == 10


def test_16_bit_frame_beyond_the_sampled_range_is_clipped_with_one_warning(tmp_path):
    images = [np.full((8, 8), 1000 + k, np.uint16) for k in range(20)]  # 10 bits
    images[1][0, 0] = 5000  # frame 1 is not among the 8 sampled frames (0, 3, 5, 8, ...)
    images[2][0, 0] = 3000
    source = FrameSource(_frames(tmp_path / "f", images))
    assert source[0][0, 0] == round(1000 * 255 / 1023)
    with pytest.warns(UserWarning, match=r"000001\.png: 16-bit values up to 5000, above the "
                                         r"10-bit range \(0-1023\) that 8 frames spread over "
                                         r"the sequence use: clipped to 255"):
        assert source[1][0, 0] == 255
    assert source[2][0, 0] == 255  # clipped again, without a second warning
    assert source.bits_in_use == 10


def test_mixed_bit_depths_and_other_pixel_types_refused(tmp_path, monkeypatch):
    paths = _frames(tmp_path / "mixed", [np.zeros((8, 8), np.uint16), np.zeros((8, 8), np.uint8)])
    source = FrameSource(paths)
    source[0]
    with pytest.raises(ValueError, match=r"000001\.png: 8-bit but .*000000\.png is 16-bit; "
                                         r"frames must be all 8-bit or all 16-bit"):
        source[1]
    for dtype in (np.float32, np.int32, np.int16):
        monkeypatch.setattr(cv2, "imread", lambda *args, dtype=dtype: np.zeros((8, 8), dtype))
        with pytest.raises(ValueError, match=rf"000000\.png: {np.dtype(dtype).name} pixels; "
                                             r"frames must be 8-bit or 16-bit unsigned "
                                             r"integers"):
            FrameSource(paths)[0]


def test_16_bit_grey_video_is_read_in_16_bits(tmp_path):
    """OpenCV's own conversion of a 16-bit grey video keeps the high byte (12-bit data: 0-15)."""
    rng = np.random.default_rng(1)
    grey = [rng.integers(0, 256, (24, 32), dtype=np.uint8) for _ in range(6)]
    path = tmp_path / "video.mkv"
    writer = cv2.VideoWriter(str(path), cv2.CAP_FFMPEG, cv2.VideoWriter_fourcc(*"FFV1"), 10,
                             (32, 24), [cv2.VIDEOWRITER_PROP_DEPTH, cv2.CV_16U,
                                        cv2.VIDEOWRITER_PROP_IS_COLOR, 0])
    if not writer.isOpened():
        pytest.skip("this OpenCV cannot write 16-bit FFV1")
    for g in grey:
        writer.write(_to_12_bits(g))
    writer.release()
    source = FrameSource(video=path, expected_size=(32, 24))
    assert len(source) == 6
    for k in (3, 0, 5):
        np.testing.assert_array_equal(source[k], grey[k])
    assert source.bits_in_use == 12


# ------------------------------------------------ 16-bit datasets through the methods (CLI)


@pytest.fixture(scope="module")
def data(tmp_path_factory):
    """Tiny simulated datasets, each with a copy whose frames hold the same data in 12 bits."""
    root = tmp_path_factory.mktemp("audit16")
    assert main(["--quiet", "simulate", "fetoscopy", str(root / "feto"), "--n-frames", "8",
                 "--laps", "0.1"]) == 0
    assert main(["--quiet", "simulate", "pcle", str(root / "pcle"), "--n-frames", "10",
                 "--width", "128", "--height", "112"]) == 0
    for name in ("feto", "pcle"):
        shutil.copytree(root / name, root / f"{name}16")
        for path in (root / f"{name}16" / "frames").glob("*.png"):
            cv2.imwrite(str(path), _to_12_bits(cv2.imread(str(path), cv2.IMREAD_UNCHANGED)))
    return root


@pytest.mark.parametrize(("dataset", "method"), [
    ("pcle", "ncc"), ("pcle", "kalman-robot"), ("feto", "ba-emt"), ("feto", "lba-emt"),
])
def test_methods_on_16_bit_frames_match_8_bit(data, tmp_path, dataset, method):
    outs = []
    for name in (dataset, f"{dataset}16"):
        outs.append(tmp_path / name)
        assert main(["--quiet", "run", str(data / name), "--method", method, "--out",
                     str(outs[-1]), "--no-report"]) == 0
    (ids8, G8), (ids16, G16) = (read_homographies_csv(o / "homographies.csv") for o in outs)
    np.testing.assert_array_equal(ids8, ids16)
    assert np.isfinite(G16).all()
    np.testing.assert_allclose(G16, G8, rtol=0, atol=1e-9)
    reports = [json.loads((o / "report.json").read_text()) for o in outs]
    assert "frame_bits_in_use" not in reports[0] and reports[1]["frame_bits_in_use"] == 12


# ------------------------------------------------------------------ drift ratio undefined


def test_drift_note_says_why_the_ratio_is_undefined():
    nan = np.nan
    early = np.array([0.0, 0.2, 0.5, 0.7] + [nan] * 26)  # pairwise placing 4/30 (audit 16)
    assert np.isnan(drift_ratio(early))
    assert drift_note(early) == (
        "needs placed frames in both the first and the last quarter of the sequence (frames "
        "0-6; frames 23-29): drift = mean e_j of the last / of the first; none placed in frames "
        "23-29")
    assert drift_note(np.full(8, nan), frame_ids=np.arange(10, 18)).endswith(
        "none placed in frames 10-11 nor in frames 16-17")
    assert drift_note(np.array([0.0, 1.0, 2.0])) == (
        "the first quarter (frame 0) holds only the reference frame, whose e_j is 0 by "
        "construction and left out (with under 8 frames a quarter is one frame): no ratio to it")
    inf_first = np.array([np.inf, 1, 1, 1, 1, 1, 1, np.inf])
    assert np.isnan(drift_ratio(inf_first))  # no RuntimeWarning (warnings are errors here)
    assert "holds a frame placed at infinity" in drift_note(inf_first)
    inf_last = np.array([1.0, 1, 1, 1, 1, 1, 1, np.inf])
    assert drift_ratio(inf_last) == np.inf  # (with a note since review C #8)
    assert drift_note(inf_last) == ("the last quarter (frames 6-7) holds a frame placed at "
                                    "infinity (e_j inf): the ratio is infinite")
    assert drift_ratio(np.ones(10)) == 1.0 and drift_note(np.ones(10)) is None


def _strict_json(path):
    def refuse(constant):
        raise AssertionError(f"{path}: {constant} is not JSON")
    return json.loads(path.read_text(), parse_constant=refuse)


def test_evaluate_prints_na_and_writes_null_for_an_undefined_drift(data, tmp_path, capsys):
    truth = read_dataset(data / "feto").ground_truth
    ids = read_dataset(data / "feto").frame_ids
    out = tmp_path / "early"
    out.mkdir()
    G = truth.copy()
    G[4:] = np.nan  # frames 0-3 of 8 placed: none in the last quarter (6-7)
    write_homographies_csv(out / "homographies.csv", ids, G)
    assert main(["evaluate", str(out), "--truth", str(data / "feto")]) == 0
    printed = capsys.readouterr().out
    row = next(line for line in printed.splitlines() if line.startswith("early"))
    assert row.split()[1:] == ["4/8", "0.000", "0.000", "n/a"]
    assert ("  drift n/a: needs placed frames in both the first and the last quarter of the "
            "sequence (frames 0-1; frames 6-7): drift = mean e_j of the last / of the first; "
            "none placed in frames 6-7\n") in printed
    assert "nan" not in printed.lower()
    result = _strict_json(out / "evaluation.json")["results"][0]
    assert result["drift_ratio"] is None
    assert result["drift_ratio_note"].startswith("needs placed frames in both")
    # nothing scored at all but the reference frame's neighbour gone too: e_M and max e_j n/a
    G[:] = np.nan
    G[0] = np.eye(3)
    write_homographies_csv(out / "homographies.csv", ids, G)
    truthless = tmp_path / "truth"
    shutil.copytree(data / "feto", truthless)
    gt_ids, gt = read_homographies_csv(truthless / "ground_truth.csv")
    gt[0] = np.nan
    write_homographies_csv(truthless / "ground_truth.csv", gt_ids, gt)
    assert main(["evaluate", str(out), "--truth", str(truthless), "--no-report"]) == 0
    row = next(line for line in capsys.readouterr().out.splitlines()
               if line.startswith("early"))
    assert row.split()[1:] == ["1/8", "n/a", "n/a", "n/a"]
    result = _strict_json(out / "evaluation.json")["results"][0]
    assert result["e_M_px"] is None and result["max_e_j_px"] is None
