"""Review 54 (black-box CLI review): a video cut short inside a frame's chunk."""

import cv2
import numpy as np
import pytest

from fusedmosaic.io import FrameSource, read_dataset
from fusedmosaic.io.video import _avi_whole_frames
from tests.test_dataset_review51 import _avi, _shown


def test_avi_cut_inside_a_frame_leaves_that_frame_out(tmp_path):
    """Cut inside frame 9's chunk: FFmpeg decodes what the file holds of frame 9 (an MJPG
    frame's top, another view or grey below) and it was read as a whole frame (one such frame
    moved a 27-frame lba-emt run's e_M 0.14 -> 5.7 px). The 9 whole frames are read, the warning
    says frame 9 is left out."""
    root, data, chunks, images = _avi(tmp_path / "d")
    cut = chunks[9] + 8 + (chunks[10] - chunks[9]) // 2
    (root / "video.avi").write_bytes(bytes(data[:cut]))
    assert _avi_whole_frames(root / "video.avi") == 9
    capture = cv2.VideoCapture(str(root / "video.avi"))
    decoded = 0
    while capture.grab():
        decoded += 1
    capture.release()
    assert decoded == 10  # frame 9 in part
    with pytest.warns(UserWarning, match=r"video\.avi: its header counts 12 frames but 10 decode "
                                         r"\(a truncated file, .*\): the 9 whole ones are read; "
                                         r"frame 9, cut inside its chunk at the file's end and "
                                         r"decoded in part, is left out$"):
        ds = read_dataset(root)
    assert len(ds) == 9
    assert _shown(ds, images) == list(range(9))
    np.testing.assert_allclose(ds.timestamps, np.arange(9) / 25.0)


def test_avi_cut_between_chunks_keeps_every_decoded_frame(tmp_path):
    root, data, chunks, images = _avi(tmp_path / "d")
    (root / "video.avi").write_bytes(bytes(data[:chunks[9]]))
    assert _avi_whole_frames(root / "video.avi") == 9
    with pytest.warns(UserWarning, match=r"12 frames but 9 decode .*: the 9 are read$"):
        frames = FrameSource.open(root)
    assert len(frames) == 9


def test_whole_frames_of_what_is_not_an_avi(tmp_path):
    root, data, _, _ = _avi(tmp_path / "d")
    assert _avi_whole_frames(root / "video.avi") == 12
    (tmp_path / "x.avi").write_bytes(b"RIFX" + bytes(data[4:]))
    assert _avi_whole_frames(tmp_path / "x.avi") is None
    (tmp_path / "x.mkv").write_bytes(bytes(data))
    assert _avi_whole_frames(tmp_path / "x.mkv") is None


def test_an_unnumbered_png_among_numbered_frames_is_refused(tmp_path):
    """frames/thumb.png beside 000000.png ... was read as the last frame, with no word."""
    from fusedmosaic.io.video import sort_frame_names

    with pytest.raises(ValueError, match=r"^frames: 'thumb\.png' \(and 1 more\) has no number "
                                         r"in its name, beside numbered frames \(e\.g\. "
                                         r"'000000\.png'\): frames are ordered by the numbers "
                                         r"in their names; remove the files that are not "
                                         r"frames, or rename them$"):
        sort_frame_names(["000001.png", "thumb.png", "000000.png", "zcover.png"])
    assert sort_frame_names(["b.png", "a.png"]) == ["a.png", "b.png"]  # none numbered: by name
    # the numbered names' pattern without a number: a sequence's first file, as some tools name it
    assert sort_frame_names(["frame2.png", "frame.png", "frame1.png"]) == [
        "frame.png", "frame1.png", "frame2.png"]
    root, _, _, _ = _avi(tmp_path / "d")
    (root / "video.avi").unlink()
    (root / "frames").mkdir()
    for k in range(3):
        cv2.imwrite(str(root / "frames" / f"{k:06d}.png"), np.zeros((48, 64), np.uint8))
    cv2.imwrite(str(root / "frames" / "thumb.png"), np.zeros((48, 64), np.uint8))
    with pytest.raises(ValueError, match=r"frames: 'thumb\.png' has no number in its name"):
        read_dataset(root)


def test_a_principal_point_outside_the_frame_is_warned_about(tmp_path):
    """cx = 900 px for a 200 px wide frame ran without a word (review 54)."""
    from fusedmosaic.io import Camera

    K = np.array([[240.0, 0, 900.5], [0, 240.0, 99.5], [0, 0, 1]])
    with pytest.warns(UserWarning, match=r"camera_matrix: principal point \(900\.5, 99\.5\) px "
                                         r"lies outside the 200x200 frame: calibrated at another "
                                         r"resolution or crop, or cx and cy mistyped\?"):
        Camera(200, 200, camera_matrix=K)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        Camera(200, 200, camera_matrix=np.array([[240.0, 0, 199.0], [0, 240.0, 0.5], [0, 0, 1]]))


def test_an_alpha_channel_that_is_not_opaque_is_named_once(tmp_path):
    """A BGRA frame's alpha was dropped without a word: as a field-of-view mask it was lost."""
    import warnings

    frames = tmp_path / "frames"
    frames.mkdir()
    rng = np.random.default_rng(0)
    alpha = np.zeros((48, 64), np.uint8)
    cv2.circle(alpha, (32, 24), 20, 255, -1)
    for k in range(3):
        image = np.dstack([rng.integers(0, 256, (48, 64, 3), np.uint8), alpha])
        cv2.imwrite(str(frames / f"{k:06d}.png"), image)
    source = FrameSource.open(tmp_path)
    with pytest.warns(UserWarning, match=r"000000\.png: its alpha channel is not opaque "
                                         r"everywhere, and is ignored .*fov_mask_radius") as w:
        images = [source[k] for k in range(3)]
    assert len([x for x in w if "alpha" in str(x.message)]) == 1
    assert all(image.shape == (48, 64, 3) for image in images)
    for k in range(3):  # an opaque alpha: nothing to say
        cv2.imwrite(str(frames / f"{k:06d}.png"),
                    np.dstack([images[k], np.full((48, 64), 255, np.uint8)]))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        source = FrameSource.open(tmp_path)
        assert source[0].shape == (48, 64, 3)


@pytest.mark.parametrize("count", ["kept", "zero"])
def test_avi_cut_inside_its_last_frame_with_its_count(tmp_path, count):
    """Cut inside frame 11's chunk with the header still counting 12 frames (or counting none:
    a recorder that stopped before writing it): all 12 decode, frame 11 in part, and it was read
    as whole, without a word (review 54)."""
    root, data, chunks, images = _avi(tmp_path / "d")
    length = int.from_bytes(data[chunks[11] + 4:chunks[11] + 8], "little")
    data = data[:chunks[11] + 8 + length // 2]
    if count == "zero":  # MainAVIHeader.dwTotalFrames and the stream header's dwLength
        for tag, offset in ((b"avih", 16), (b"strh", 32)):
            at = data.index(tag) + 8 + offset
            data[at:at + 4] = (0).to_bytes(4, "little")
    (root / "video.avi").write_bytes(bytes(data))
    with pytest.warns(UserWarning, match=r"video\.avi: the file ends inside frame 11's chunk "
                                         r"\(cut short, or its recorder stopped mid-frame\): that "
                                         r"frame decodes in part and is left out; the 11 whole "
                                         r"ones are read"):
        ds = read_dataset(root)
    assert len(ds) == 11 and _shown(ds, images) == list(range(11))
