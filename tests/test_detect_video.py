"""``qcarlab detect ... --out`` writes video a browser plays: H.264, yuv420p, the index first
(faststart), through PyAV; without PyAV, OpenCV's MPEG-4 Part 2 and a one-line note (issue 29)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from test_perception_lanes import road


def _drive(path, size=(640, 480), frames=6):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), 10, size)
    for k in range(frames):
        img, _ = road(*size)
        writer.write(np.roll(img, 8 * k, axis=1))
    writer.release()
    return path


def _top_level_boxes(data: bytes) -> list[str]:
    boxes, i = [], 0
    while i + 8 <= len(data):
        size = int.from_bytes(data[i:i + 4], "big")
        boxes.append(data[i + 4:i + 8].decode("latin-1"))
        if size == 1:
            size = int.from_bytes(data[i + 8:i + 16], "big")
        if size < 8:
            break
        i += size
    return boxes


def test_detect_video_is_h264_a_browser_plays(cli, tmp_path):
    av = pytest.importorskip("av")
    from qcarlab.media import _pyav

    if _pyav() is None:
        pytest.skip("this PyAV has no libx264 encoder")
    src = _drive(tmp_path / "drive.mp4")
    code, out, err = cli("detect", "lanes", str(src), "--every", "2", "--json", "--out", str(tmp_path / "v"))
    assert code == 0, err
    assert "note:" not in err  # H.264 was written: nothing to warn about
    written = tmp_path / "v" / "drive.mp4"
    with av.open(str(written)) as container:
        stream = container.streams.video[0]
        assert stream.codec_context.name == "h264"
        assert stream.codec_context.pix_fmt == "yuv420p"
        assert sum(1 for _ in container.decode(stream)) == 3
    boxes = _top_level_boxes(written.read_bytes())
    assert boxes.index("moov") < boxes.index("mdat")  # faststart: a browser starts before the end arrives


def test_odd_sized_frames_are_padded_to_even(tmp_path):
    av = pytest.importorskip("av")
    from qcarlab.media import VideoOut, _pyav

    if _pyav() is None:
        pytest.skip("this PyAV has no libx264 encoder")
    video = VideoOut(tmp_path / "odd.mp4", fps=12.5)
    for k in range(4):
        video.write(np.full((241, 321, 3), 40 * k, np.uint8))
    video.close()
    assert video.codec == "h264" and video.note is None
    with av.open(str(tmp_path / "odd.mp4")) as container:
        ctx = container.streams.video[0].codec_context
        assert (ctx.name, ctx.width, ctx.height) == ("h264", 322, 242)


def test_without_pyav_opencv_writes_and_a_note_says_how_to_get_h264(cli, tmp_path, monkeypatch):
    import qcarlab.media as media

    monkeypatch.setattr(media, "_pyav", lambda: None)
    src = _drive(tmp_path / "drive.mp4")
    code, out, err = cli("detect", "lanes", str(src), "--every", "2", "--json", "--out", str(tmp_path / "v"))
    assert code == 0, err
    notes = [line for line in err.splitlines() if line.startswith("note:")]
    assert len(notes) == 1 and "browsers" in notes[0] and "qcarlab[video]" in notes[0]
    assert all(line.startswith("{") for line in out.strip().splitlines())  # --json stdout stays JSON lines
    cap = cv2.VideoCapture(str(tmp_path / "v" / "drive.mp4"))
    n = 0
    while cap.read()[0]:
        n += 1
    assert n == 3
