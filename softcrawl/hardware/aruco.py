"""Bends and positions from photos and videos with ArUco markers (OpenCV's
``cv2.aruco.ArucoDetector``; ``pip install softcrawl[vision]``).

- **Bend from photos** (:func:`bends_from_photos`, ``softcrawl calibrate PHOTO_DIR``): the clamped
  PneuNet photographed side-on, one marker on the clamp (``base_id``) and one on the tip face
  (``tip_id``). The tip angle is the in-plane rotation of the tip marker relative to the base
  marker, deg (its magnitude: a PneuNet bends one way only). The real pressure comes from the
  file name: ``40kpa.jpg``, ``40.5kPa_2.png`` (a number, then ``kpa``).
- **Distance from a video** (:func:`track_video`, ``softcrawl compare --tracked crawl.mp4``): one
  marker of known side ``marker_mm`` on the disk, camera above with the crawl direction along the
  image's +x. Pixels become mm with the marker's median side length in pixels.

Markers: dictionary ``DICT_4X4_50``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from softcrawl.safeio import check_regular_file, read_bytes

#: Largest photo read, bytes.
MAX_PHOTO_BYTES = 64 * 1024 * 1024
#: Largest video read, bytes (an hour of 1080p at 5 Mbit/s is about 2.3 GB).
MAX_VIDEO_BYTES = 4 * 1024 ** 3

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff")
VIDEO_SUFFIXES = (".mp4", ".avi", ".mov", ".mkv")
_KPA = re.compile(r"^(\d+(?:\.\d+)?)\s*kpa", re.IGNORECASE)


def _cv2():
    try:
        import cv2
    except ImportError:
        raise ValueError("reading photos or videos needs OpenCV: pip install 'softcrawl[vision]'") from None
    if not hasattr(cv2, "aruco") or not hasattr(cv2.aruco, "ArucoDetector"):
        raise ValueError("OpenCV >= 4.7 with the aruco module is needed (opencv-python-headless >= 4.13)")
    return cv2


def detector():
    """An ``ArucoDetector`` for ``DICT_4X4_50`` markers."""
    cv2 = _cv2()
    return cv2.aruco.ArucoDetector(cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50),
                                   cv2.aruco.DetectorParameters())


def detect(image, det=None) -> dict[int, np.ndarray]:
    """Markers in a BGR or grey image: ``{id: corners (4, 2) px}`` (corner 0 = the marker's top left)."""
    cv2 = _cv2()
    grey = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) if image.ndim == 3 else image
    corners, ids, _ = (det or detector()).detectMarkers(grey)
    if ids is None:
        return {}
    return {int(i): c.reshape(4, 2).astype(float) for i, c in zip(ids.ravel(), corners)}


def marker_angle_deg(corners: np.ndarray) -> float:
    """In-plane rotation of a marker (its top edge, corner 0 -> 1), deg, counter-clockwise as seen."""
    d = corners[1] - corners[0]
    return math.degrees(math.atan2(-d[1], d[0]))  # image y points down


def bend_from_photo(path: str | Path, base_id: int = 0, tip_id: int = 1) -> float:
    """Tip angle (deg, >= 0) of the clamped PneuNet in one photo.

    Raises:
        ValueError: not a regular file of at most 64 MB, unreadable image, or a marker not found.
    """
    cv2 = _cv2()
    data = np.frombuffer(read_bytes(path, MAX_PHOTO_BYTES), dtype=np.uint8)
    img = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
    if img is None:
        raise ValueError(f"{path}: not a readable image")
    found = detect(img)
    for name, i in (("base", base_id), ("tip", tip_id)):
        if i not in found:
            raise ValueError(f"{path}: {name} marker {i} not found (markers seen: {sorted(found)})")
    diff = marker_angle_deg(found[tip_id]) - marker_angle_deg(found[base_id])
    return abs((diff + 180.0) % 360.0 - 180.0)


def bends_from_photos(folder: str | Path, base_id: int = 0, tip_id: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """``(real_kpa (k,), tip_angle_deg (k,))`` from the photos in ``folder`` (module docstring).

    Raises:
        FileNotFoundError: no folder. ValueError: no photos named ``<kPa>kpa...``, a pressure in a
        name outside ``(0, MAX_REAL_KPA]`` (:func:`softcrawl.hardware.calibration.check_real_kpa`),
        or a photo without both markers.
    """
    from softcrawl.hardware.calibration import check_real_kpa

    folder = Path(folder)
    if not folder.is_dir():
        raise FileNotFoundError(f"{folder}: no such folder")
    pairs = []
    for p in sorted(folder.iterdir()):
        m = _KPA.match(p.name)
        if p.suffix.lower() in IMAGE_SUFFIXES and m:
            pairs.append((check_real_kpa(float(m.group(1)), str(p)), bend_from_photo(p, base_id, tip_id)))
    if not pairs:
        raise ValueError(f"{folder}: no photos named like '40kpa.jpg' ({', '.join(IMAGE_SUFFIXES)})")
    a = np.array(pairs)
    return a[:, 0], a[:, 1]


def track_video(path: str | Path, marker_id: int = 0, marker_mm: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """``(t_s (m,), x_mm (m,))`` of the disk marker's centre along the image +x, frames where it is seen.

    Raises:
        FileNotFoundError: no file ``path``. ValueError (:class:`~softcrawl.safeio.UnsafeFileError`
        for the first two): not a regular file, larger than ``MAX_VIDEO_BYTES``, unreadable video,
        no frame rate, marker seen in < 2 frames, bad ``marker_mm``.
    """
    cv2 = _cv2()
    if not (math.isfinite(marker_mm) and marker_mm > 0):
        raise ValueError(f"marker size must be > 0 mm, got {marker_mm}")
    check_regular_file(path, MAX_VIDEO_BYTES)  # a device or FIFO would be read without end
    cap = cv2.VideoCapture(str(path))
    if not cap.isOpened():
        raise ValueError(f"{path}: not a readable video")
    fps = cap.get(cv2.CAP_PROP_FPS)
    if not (fps and fps > 0):
        raise ValueError(f"{path}: the video has no frame rate")
    det = detector()
    t, cx, side = [], [], []
    k = 0
    while True:
        ok, frame = cap.read()
        if not ok:
            break
        c = detect(frame, det).get(marker_id)
        if c is not None:
            t.append(k / fps)
            cx.append(c[:, 0].mean())
            side.append(np.mean(np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1)))
        k += 1
    cap.release()
    if len(t) < 2:
        raise ValueError(f"{path}: marker {marker_id} seen in {len(t)} of {k} frames (need >= 2)")
    scale = marker_mm / float(np.median(side))
    return np.array(t), (np.array(cx) - cx[0]) * scale


def write_track_csv(t_s, x_mm, path: str | Path) -> Path:
    """Write ``t_s,x_mm`` (the tracked CSV format of :func:`softcrawl.hardware.compare.read_tracked`)."""
    path = Path(path)
    np.savetxt(path, np.c_[t_s, x_mm], delimiter=",", header="t_s,x_mm", comments="", fmt="%.6f")
    return path
