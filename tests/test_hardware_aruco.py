"""ArUco photos (bend) and videos (distance) with synthetic images (skipped without OpenCV:
``pip install softcrawl[vision]``)."""

import numpy as np
import pytest

cv2 = pytest.importorskip("cv2")

from softcrawl.hardware.aruco import bends_from_photos, track_video  # noqa: E402
from softcrawl.hardware.compare import read_tracked  # noqa: E402

DICT = cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_4X4_50)


def _paste(canvas, marker_id, side, centre, angle_deg):
    """Draw marker ``marker_id`` (``side`` px, with a white border) rotated ``angle_deg`` CCW at ``centre``."""
    m = cv2.aruco.generateImageMarker(DICT, marker_id, side)
    m = cv2.copyMakeBorder(m, side // 4, side // 4, side // 4, side // 4, cv2.BORDER_CONSTANT, value=255)
    h = m.shape[0]
    rot = cv2.getRotationMatrix2D((h / 2, h / 2), angle_deg, 1.0)
    rot[:, 2] += np.array(centre) - h / 2
    mask = cv2.warpAffine(np.full_like(m, 255), rot, canvas.shape[1::-1])
    warped = cv2.warpAffine(m, rot, canvas.shape[1::-1], borderValue=255)
    canvas[mask > 0] = warped[mask > 0]
    return canvas


def test_bends_from_photos(tmp_path):
    for kpa, angle in ((20, 12.0), (50, 35.0), (80, 61.5)):
        img = np.full((480, 640), 255, np.uint8)
        _paste(img, 0, 100, (150, 240), 5.0)  # clamp marker, slightly tilted camera
        _paste(img, 1, 100, (450, 240), 5.0 - angle)  # tip marker turned by the bend
        cv2.imwrite(str(tmp_path / f"{kpa}kpa.png"), img)
    (tmp_path / "notes.txt").write_text("ignored")
    real, bend = bends_from_photos(tmp_path)
    assert real.tolist() == [20, 50, 80]
    assert np.allclose(bend, [12.0, 35.0, 61.5], atol=1.0)
    img = np.full((480, 640), 255, np.uint8)
    _paste(img, 0, 100, (150, 240), 0.0)
    cv2.imwrite(str(tmp_path / "90kpa.png"), img)
    with pytest.raises(ValueError, match="tip marker 1 not found"):
        bends_from_photos(tmp_path)


def test_track_video(tmp_path):
    path = tmp_path / "crawl.avi"
    fps, side = 10.0, 80
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (640, 360), isColor=False)
    if not w.isOpened():
        pytest.skip("no MJPG video writer in this OpenCV build")
    for k in range(20):
        img = np.full((360, 640), 255, np.uint8)
        _paste(img, 3, side, (150 + 8 * k, 180), 0.0)  # 8 px per frame = 3 mm per frame for a 30 mm marker
        w.write(img)
    w.release()
    t, x = read_tracked(path, marker_id=3, marker_mm=30.0)
    assert len(t) == 20 and t[1] == pytest.approx(0.1)
    assert x[-1] == pytest.approx(19 * 8 * 30 / side, rel=0.03)
    with pytest.raises(ValueError, match="marker 5 seen in 0"):
        track_video(path, marker_id=5)


def test_cli_calibrate_photo_folder_without_photos(tmp_path, capsys):
    from softcrawl.cli import main

    (tmp_path / "photos").mkdir()
    assert main(["calibrate", str(tmp_path / "photos"), "--out", str(tmp_path / "cal")]) == 2
    assert "no photos named" in capsys.readouterr().err


def test_photo_names_with_implausible_pressures_are_refused(tmp_path):
    """``99999999999999999999kpa.png`` (1e20 kPa) and ``0kpa.png`` are refused, as in the CSV path,
    naming the photo; nothing is fitted."""
    img = _paste(_paste(np.full((480, 640), 255, np.uint8), 0, 80, (160, 240), 0.0), 1, 80, (480, 240), 20.0)
    for name in ("99999999999999999999kpa.png", "0kpa.png"):
        folder = tmp_path / name.split(".")[0]
        folder.mkdir()
        cv2.imwrite(str(folder / "20kpa.png"), img)
        cv2.imwrite(str(folder / name), img)
        with pytest.raises(ValueError, match=rf"{name}: real pressure .* kPa must be in \(0, 100\]"):
            bends_from_photos(folder)


def test_photo_that_is_a_device_link_is_refused(tmp_path):
    (tmp_path / "40kpa.png").symlink_to("/dev/zero")
    with pytest.raises(ValueError, match="not a regular file"):
        bends_from_photos(tmp_path)
