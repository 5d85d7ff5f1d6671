"""Cameras by name: the listing of `moirejax cameras`, `find_camera` by name, serial and path,
its one-line errors, and `live --source` resolving a name (enumeration faked: no hardware here)."""

import importlib.resources
import json
import sys
from types import SimpleNamespace

import cv2
import pytest

from moirejax.cli._main import main
from moirejax.live import _camera, CameraDevice, find_camera, list_cameras


def info(index, name, path, backend, vid=None, pid=None):
    """What `cv2_enumerate_cameras.enumerate_cameras(backend)` yields for one camera."""
    return SimpleNamespace(index=index, name=name, path=path, vid=vid, pid=pid, backend=backend)


# Linux: GStreamer and V4L2 both report each /dev/video device; two identical webcams.
FOUND = [
    info(0, "HD Pro Webcam C920", "/dev/video0", cv2.CAP_GSTREAMER, 0x046D, 0x082D),
    info(2, "USB Camera: Moire Pad", "/dev/video2", cv2.CAP_GSTREAMER, 0x0C45, 0x6366),
    info(0, "HD Pro Webcam C920", "/dev/video0", cv2.CAP_V4L2, 0x046D, 0x082D),
    info(2, "USB Camera: Moire Pad", "/dev/video2", cv2.CAP_V4L2, 0x0C45, 0x6366),
    info(4, "Integrated Webcam", "/dev/video4", cv2.CAP_V4L2),
    info(6, "Integrated Webcam", "/dev/video6", cv2.CAP_V4L2),
]


@pytest.fixture
def cameras(monkeypatch, tmp_path):
    """The cameras of FOUND, with the moiré pad's serial in a /dev/v4l/by-id link."""
    by_id = tmp_path / "by-id"
    by_id.mkdir()
    (by_id / "usb-Sonix_Moire_Pad_SN4711-video-index0").symlink_to("/dev/video2")
    (by_id / "usb-Logitech_C920_A1B2C3-video-index0").symlink_to("/dev/video0")
    monkeypatch.setattr(_camera, "_PERSISTENT_LINK_FOLDERS", (str(by_id),))
    monkeypatch.setattr(_camera, "_enumerate_cameras", lambda: list(FOUND))
    return by_id


def test_each_device_is_listed_once_through_its_preferred_backend(cameras):
    listed = list_cameras()
    assert [(c.index, c.name, c.backend) for c in listed] == [
        (cv2.CAP_V4L2 + 0, "HD Pro Webcam C920", "V4L2"),
        (cv2.CAP_V4L2 + 2, "USB Camera: Moire Pad", "V4L2"),
        (cv2.CAP_V4L2 + 4, "Integrated Webcam", "V4L2"),
        (cv2.CAP_V4L2 + 6, "Integrated Webcam", "V4L2"),
    ]
    assert listed[1].usb_id == "0C45:6366" and listed[2].usb_id is None
    assert listed[1].aliases == (str(cameras / "usb-Sonix_Moire_Pad_SN4711-video-index0"),)
    assert listed[2].aliases == ()


def test_cameras_command_lists_index_name_backend_and_says_what_it_cannot(cameras, capsys):
    assert main(["cameras"]) == 0
    out, err = capsys.readouterr()
    lines = out.splitlines()
    assert lines[0].split() == ["index", "name", "backend", "usb", "id", "path"]
    row = next(line for line in lines if "Moire Pad" in line)
    assert row.split()[0] == "202" and "V4L2" in row and "0C45:6366" in row and row.endswith("/dev/video2")
    assert "202: also " + str(cameras / "usb-Sonix_Moire_Pad_SN4711-video-index0") in lines
    assert "Resolutions and frame rates: cv2-enumerate-cameras does not report them" in err

    assert main(["cameras", "--json"]) == 0
    listed = json.loads(capsys.readouterr().out)
    assert [c["index"] for c in listed] == [200, 202, 204, 206]
    assert CameraDevice(**{**listed[1], "aliases": tuple(listed[1]["aliases"])}) == list_cameras()[1]


def test_no_cameras_is_said_not_an_error(monkeypatch, capsys):
    monkeypatch.setattr(_camera, "_enumerate_cameras", lambda: [])
    assert main(["cameras"]) == 0
    assert capsys.readouterr().err.strip() == "no cameras found"


def test_find_camera_by_name_substring_serial_path_and_usb_id(cameras):
    assert find_camera("HD Pro Webcam C920") == 200
    assert find_camera("hd pro webcam c920") == 200  # case does not matter
    assert find_camera("C920") == 200
    assert find_camera("Moire Pad") == 202
    assert find_camera("SN4711") == 202  # the serial number, from the by-id link
    assert find_camera("/dev/video4") == 204
    assert find_camera("046d:082d") == 200


def test_several_or_no_matches_are_one_line_errors_listing_the_cameras(cameras, monkeypatch):
    with pytest.raises(ValueError) as ambiguous:
        find_camera("Integrated Webcam")  # two identical cameras: exact names match twice
    message = str(ambiguous.value)
    assert "\n" not in message and message.startswith("Integrated Webcam: 2 cameras match: ")
    assert "204 'Integrated Webcam' (V4L2, /dev/video4)" in message and "/dev/video6" in message
    with pytest.raises(ValueError, match=r"^webcam: 3 cameras match"):
        find_camera("webcam")
    with pytest.raises(ValueError) as missing:
        find_camera("GelSight Mini")
    message = str(missing.value)
    assert "\n" not in message and message.startswith("GelSight Mini: no camera's name, serial, path or USB id")
    assert all(str(index) in message for index in (200, 202, 204, 206))
    monkeypatch.setattr(_camera, "_enumerate_cameras", lambda: [])
    with pytest.raises(ValueError, match="cameras found: none$"):
        find_camera("GelSight Mini")


def test_without_the_extra_the_error_says_how_to_install_it(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "cv2_enumerate_cameras", None)  # import fails
    with pytest.raises(ImportError, match=r"pip install 'moirejax\[cameras\]'"):
        list_cameras()
    assert main(["cameras"]) == 2
    (line,) = capsys.readouterr().err.splitlines()
    assert line == "moirejax cameras: error: finding cameras by name needs the `cameras` extra: " + (
        "pip install 'moirejax[cameras]'"
    )


def test_the_package_is_asked_backend_by_backend(monkeypatch):
    enumeration = pytest.importorskip("cv2_enumerate_cameras")

    def enumerate_cameras(backend):
        return [c for c in FOUND if c.backend == backend]

    monkeypatch.setattr(enumeration, "supported_backends", (cv2.CAP_GSTREAMER, cv2.CAP_V4L2))
    monkeypatch.setattr(enumeration, "enumerate_cameras", enumerate_cameras)
    assert [c.index for c in list_cameras()] == [200, 202, 204, 206]


EXAMPLE = str(importlib.resources.files("moirejax").joinpath("fits", "examples", "mid-sim-unit3.json"))


@pytest.fixture
def live_sources(monkeypatch):
    """The `source` that `moirejax live` hands `run_live` (which then stops the command)."""
    import moirejax.live

    seen = []

    def run_live(device, source, **kwargs):
        seen.append(source)
        raise KeyboardInterrupt

    monkeypatch.setattr(moirejax.live, "run_live", run_live)
    return seen


def test_live_source_takes_a_camera_name_and_an_index_is_still_an_index(cameras, live_sources, monkeypatch, capsys):
    assert main(["live", "--device", EXAMPLE, "--source", "SN4711"]) == 130
    assert "camera 'SN4711': index 202" in capsys.readouterr().err

    def no_enumeration():
        raise AssertionError("an index must not be looked up")

    monkeypatch.setattr(_camera, "_enumerate_cameras", no_enumeration)
    assert main(["live", "--device", EXAMPLE, "--source", "0"]) == 130
    assert live_sources == ["202", "0"]


def test_live_source_that_names_no_camera_fails_before_the_run(cameras, live_sources, capsys):
    assert main(["live", "--device", EXAMPLE, "--source", "GelSight Mini"]) == 3
    (line,) = capsys.readouterr().err.splitlines()
    assert line.startswith("moirejax live: error: GelSight Mini: no camera's name") and "(given by --source)" in line
    # A missing video file is a missing file, not a camera.
    assert main(["live", "--device", EXAMPLE, "--source", "session.mp4"]) == 3
    assert "session.mp4: not 'sim', a camera index" in capsys.readouterr().err
    assert live_sources == []


def test_the_python_api_opens_a_camera_by_name_as_the_cli_does(cameras, monkeypatch):
    # `open_source` (and with it `open_sensor` and `run_live`) resolves a name through the
    # same `find_camera`; the capture is not opened here, only its spec is checked.
    from moirejax.live import _run

    opened = []

    def capture(spec, **kwargs):
        opened.append(spec)
        return _run.CallableSource(lambda index: None)

    monkeypatch.setattr(_run, "VideoSource", capture)
    _run.open_source("SN4711")
    _run.open_source("0")
    assert opened == [str(cv2.CAP_V4L2 + 2), "0"]
    with pytest.raises(ValueError, match="Integrated Webcam"):
        _run.open_source("Integrated")
    with pytest.raises(FileNotFoundError):
        _run.open_source("missing/recording.mp4")
