"""Images and videos a user hands to ``qcarlab detect``: finding them, reading their frames, writing
overlays. One-line errors (InputError, exit 2) for what cannot be read.

    for src in expand_paths(["photos/", "drive.mp4"]):
        for index, frame in frames_of(src, every=5):
            ...
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from qcarlab.errors import InputError

try:  # also when OpenCV was loaded before qcarlab (its environment variables were read then)
    cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_ERROR)
except AttributeError:  # pragma: no cover - an OpenCV without its logging module
    pass

__all__ = ["H264_HINT", "IMAGE_EXT", "VIDEO_EXT", "Source", "VideoOut", "check_image_size", "expand_paths", "frames_of",
           "image_size", "read_depth", "read_image"]

IMAGE_EXT = (".jpg", ".jpeg", ".png", ".bmp", ".tif", ".tiff", ".webp", ".ppm", ".pgm")
VIDEO_EXT = (".mp4", ".avi", ".mov", ".mkv", ".m4v", ".webm", ".mpg", ".mpeg")


@dataclass(frozen=True)
class Source:
    """One file to read: an image or a video."""

    path: Path
    kind: str  # "image" | "video"


def _kind(p: Path) -> str | None:
    ext = p.suffix.lower()
    return "image" if ext in IMAGE_EXT else "video" if ext in VIDEO_EXT else None


def expand_paths(paths: Sequence[str | Path]) -> list[Source]:
    """Images and videos of ``paths``; a folder gives the images and videos in it (sorted, not
    its sub-folders). A missing path, an unknown extension or an empty folder is an error."""
    out: list[Source] = []
    if not paths:
        raise InputError("give at least one image, video or folder")
    for raw in paths:
        p = Path(raw)
        if p.is_dir():
            found = [Source(q, _kind(q)) for q in sorted(p.iterdir()) if q.is_file() and _kind(q)]
            if not found:
                raise InputError(f"{p}: no images ({', '.join(IMAGE_EXT[:4])}, ...) or videos "
                                 f"({', '.join(VIDEO_EXT[:4])}, ...) in this folder")
            out += found
        elif p.is_file():
            kind = _kind(p)
            if kind is None:
                raise InputError(f"{p}: not an image or a video by its extension "
                                 f"(images: {', '.join(IMAGE_EXT)}; videos: {', '.join(VIDEO_EXT)})")
            out.append(Source(p, kind))
        else:
            raise InputError(f"{p}: no such file or folder")
    return out


def image_size(data: bytes | np.ndarray) -> tuple[int, int] | None:
    """(width, height) from an image file's header without decoding it (PNG, JPEG, BMP, GIF,
    PNM); None for another format or a header that does not say."""
    head = bytes(data[:65536])
    if head[:8] == b"\x89PNG\r\n\x1a\n" and head[12:16] == b"IHDR":
        return int.from_bytes(head[16:20], "big"), int.from_bytes(head[20:24], "big")
    if head[:2] == b"BM" and len(head) >= 26:
        return abs(int.from_bytes(head[18:22], "little", signed=True)), abs(int.from_bytes(head[22:26], "little",
                                                                                              signed=True))
    if head[:4] == b"GIF8" and len(head) >= 10:
        return int.from_bytes(head[6:8], "little"), int.from_bytes(head[8:10], "little")
    if head[:2] == b"\xff\xd8":  # JPEG: the first start-of-frame marker
        i = 2
        while i + 9 < len(head):
            if head[i] != 0xFF:
                i += 1
                continue
            marker = head[i + 1]
            if 0xC0 <= marker <= 0xCF and marker not in (0xC4, 0xC8, 0xCC):
                return int.from_bytes(head[i + 7:i + 9], "big"), int.from_bytes(head[i + 5:i + 7], "big")
            if marker in (0xD8, 0x01) or 0xD0 <= marker <= 0xD7 or marker == 0xFF:
                i += 1 if marker == 0xFF else 2
                continue
            i += 2 + int.from_bytes(head[i + 2:i + 4], "big")
        return None
    if head[:1] == b"P" and head[1:2] in b"123456" and len(head) > 2:
        words: list[bytes] = []
        for line in head[2:].split(b"\n"):
            words += line.split(b"#", 1)[0].split()
            if len(words) >= 2:
                try:
                    return int(words[0]), int(words[1])
                except ValueError:
                    return None
    return None


def check_image_size(data: bytes | np.ndarray, where: object) -> None:
    """InputError, before any decoding, for an image whose header says it is larger than
    :data:`qcarlab.MAX_IMAGE_PIXELS` (a few kB can claim 30,000 x 30,000 px)."""
    from qcarlab import MAX_IMAGE_PIXELS

    size = image_size(data)
    if size is not None and size[0] * size[1] > MAX_IMAGE_PIXELS:
        raise InputError(f"{where}: the image is {size[0]} x {size[1]} px, over the {MAX_IMAGE_PIXELS / 1e6:g} "
                         "megapixels qcarlab reads")


def _as_bgr(img: np.ndarray, where: Path) -> np.ndarray:
    if img.dtype == np.uint16:
        img = (img // 257).astype(np.uint8)
    elif img.dtype != np.uint8:
        raise InputError(f"{where}: unsupported pixel type {img.dtype}")
    if img.ndim == 2:
        return cv2.cvtColor(img, cv2.COLOR_GRAY2BGR)
    if img.shape[2] == 4:
        return cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    if img.shape[2] == 1:
        return cv2.cvtColor(img[..., 0], cv2.COLOR_GRAY2BGR)
    return np.ascontiguousarray(img)


def read_image(path: str | Path) -> np.ndarray:
    """A BGR uint8 image (grey, 16-bit and alpha images converted)."""
    p = Path(path)
    data = np.fromfile(str(p), np.uint8) if p.is_file() else None
    if data is not None:
        check_image_size(data, p)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data is not None and data.size else None
    if img is None:
        raise InputError(f"{p}: cannot read this image (not an image file, or damaged)")
    if min(img.shape[:2]) < 8:
        raise InputError(f"{p}: the image is {img.shape[1]}x{img.shape[0]} px; at least 8 x 8 is needed")
    return _as_bgr(img, p)


def frames_of(src: Source, every: int = 1) -> Iterator[tuple[int, np.ndarray]]:
    """``(frame index, BGR frame)`` of an image (index 0) or of every ``every``-th video frame."""
    if src.kind == "image":
        yield 0, read_image(src.path)
        return
    cap = cv2.VideoCapture(str(src.path))
    if not cap.isOpened():
        raise InputError(f"{src.path}: cannot open this video (unknown codec or damaged)")
    try:
        index, seen = 0, 0
        while True:
            ok = cap.grab()
            if not ok:
                break
            if index % every == 0:
                ok, frame = cap.retrieve()
                if not ok or frame is None:
                    raise InputError(f"{src.path}: frame {index} cannot be decoded")
                seen += 1
                yield index, _as_bgr(frame, src.path)
            index += 1
        if seen == 0:
            raise InputError(f"{src.path}: the video has no frames")
    finally:
        cap.release()


def video_fps(path: Path) -> float:
    cap = cv2.VideoCapture(str(path))
    try:
        fps = float(cap.get(cv2.CAP_PROP_FPS) or 0.0)
    finally:
        cap.release()
    return fps if np.isfinite(fps) and 0.5 <= fps <= 1000.0 else 30.0


def read_depth(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A depth image in metres (float32, 0 = no data): ``.npy`` in metres, or a 16-bit PNG in
    millimetres (the RealSense convention); with ``shape`` (H, W) it must be that size."""
    p = Path(path)
    if p.suffix.lower() == ".npy":
        try:
            d = np.load(p, allow_pickle=False)
        except (OSError, ValueError) as exc:
            raise InputError(f"{p}: cannot read this depth array ({exc})") from None
        if d.ndim != 2 or not np.issubdtype(d.dtype, np.number):
            raise InputError(f"{p}: a depth array is 2-D numbers (metres), got {d.dtype} {d.shape}")
        d = d.astype(np.float32)
    elif p.suffix.lower() == ".png":
        data = np.fromfile(str(p), np.uint8) if p.is_file() else None
        if data is not None:
            check_image_size(data, p)
        d = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data is not None and data.size else None
        if d is None or d.ndim != 2 or d.dtype != np.uint16:
            raise InputError(f"{p}: a depth PNG is one 16-bit channel in millimetres")
        d = d.astype(np.float32) / 1000.0
    else:
        raise InputError(f"{p}: depth is a .npy (metres) or a 16-bit .png (millimetres)")
    d = np.where(np.isfinite(d) & (d > 0), d, 0.0).astype(np.float32)
    if shape is not None and d.shape != tuple(shape):
        raise InputError(f"{p}: the depth image is {d.shape[1]}x{d.shape[0]}, the colour image "
                         f"{shape[1]}x{shape[0]}: they must be aligned")
    return d


H264_HINT = ("wrote MPEG-4 Part 2 video (OpenCV), which browsers may not play; for H.264 install PyAV: "
             "pip install 'qcarlab[video]'")


class VideoOut:
    """An MP4 written frame by frame, opened on the first frame's size.

    With PyAV (``pip install 'qcarlab[video]'``) the video is H.264 (libx264), ``yuv420p`` with
    the index at the front (``+faststart``): the MP4 browsers play. Without it, OpenCV writes
    MPEG-4 Part 2 (``mp4v``), which Chromium and Firefox do not play; ``codec`` then is
    ``"mpeg4"`` and ``note`` is a line saying so and how to get H.264.

        video = VideoOut(Path("out.mp4"), fps=10)
        for frame in frames:          # BGR uint8
            video.write(frame)
        video.close()                 # video.codec: "h264" (PyAV) or "mpeg4" (OpenCV)
    """

    def __init__(self, path: Path, fps: float, prefer_h264: bool = True):
        self.path, self.fps, self._w = path, fps, None
        self._av = _pyav() if prefer_h264 else None
        self.codec = "h264" if self._av is not None else "mpeg4"
        self.note = None if self._av is not None else H264_HINT
        self._container = self._stream = None

    def _open_av(self, w: int, h: int) -> None:
        from fractions import Fraction

        av = self._av
        try:
            self._container = av.open(str(self.path), "w", format="mp4", options={"movflags": "+faststart"})
        except (OSError, av.FFmpegError) as exc:
            raise InputError(f"{self.path}: cannot write a video here ({exc})") from None
        rate = Fraction(self.fps).limit_denominator(1001)
        self._stream = self._container.add_stream("libx264", rate=rate)
        # yuv420p halves the chroma: H.264 wants even sizes, so an odd width or height gets a pixel more
        self._stream.width, self._stream.height = w + w % 2, h + h % 2
        self._stream.pix_fmt = "yuv420p"
        self._stream.options = {"crf": "23", "preset": "medium"}

    def write(self, frame: np.ndarray) -> None:
        if self._w is None and self._container is None:
            h, w = frame.shape[:2]
            self._size = (w, h)
            if self._av is not None:
                self._open_av(w, h)
            else:
                self._w = cv2.VideoWriter(str(self.path), cv2.VideoWriter_fourcc(*"mp4v"), self.fps, (w, h))
                if not self._w.isOpened():
                    raise InputError(f"{self.path}: cannot write a video here")
        if (frame.shape[1], frame.shape[0]) != self._size:
            frame = cv2.resize(frame, self._size)
        if self._container is None:
            self._w.write(frame)
            return
        w, h = self._size
        if (w % 2, h % 2) != (0, 0):
            frame = cv2.copyMakeBorder(frame, 0, h % 2, 0, w % 2, cv2.BORDER_REPLICATE)
        if frame.ndim == 2:
            frame = cv2.cvtColor(frame, cv2.COLOR_GRAY2BGR)
        vf = self._av.VideoFrame.from_ndarray(np.ascontiguousarray(frame[:, :, :3]), format="bgr24")
        for packet in self._stream.encode(vf):
            self._container.mux(packet)

    def close(self) -> None:
        if self._w is not None:
            self._w.release()
        if self._container is not None:
            try:
                for packet in self._stream.encode():
                    self._container.mux(packet)
            finally:
                self._container.close()
                self._container = None


def _pyav():
    """PyAV when it is installed and has an H.264 encoder (its wheels carry libx264), else None."""
    try:
        import av
        from av.codec import Codec

        Codec("libx264", "w")
    except Exception:  # not installed, or a build without libx264: OpenCV's writer instead
        return None
    return av
