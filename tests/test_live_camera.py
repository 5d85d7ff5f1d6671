"""Frame sources: in-order folders and videos, latest-frame semantics, reconnection, corrupt and truncated input."""

import threading
import time

import cv2
import numpy as np
import pytest

from moirejax.live import CallableSource, FolderSource, Frame, Reconnect, SourceEvent, VideoSource
from moirejax.live._camera import to_frame


FAST = Reconnect(max_attempts=3, initial_delay_s=0.005, max_delay_s=0.02)


def drain(source, limit=10_000, timeout=10.0):
    """All items up to and including the final event; fails instead of hanging."""
    items = []
    with source:
        for _ in range(limit):
            item = source.get(timeout=timeout)
            assert item is not None, f"source produced nothing for {timeout} s after {items[-3:]}"
            items.append(item)
            if isinstance(item, SourceEvent) and item.final:
                return items
    raise AssertionError("no final event")


def frames_of(items):
    return [x for x in items if isinstance(x, Frame)]


def events_of(items):
    return [x for x in items if isinstance(x, SourceEvent)]


def write_frames(folder, n, *, colour=False):
    for i in range(n):
        value = 10 * i + 5
        image = np.full((24, 32, 3) if colour else (24, 32), value, np.uint8)
        cv2.imwrite(str(folder / f"frame_{i}.png"), image)


def test_folder_in_natural_order(tmp_path):
    write_frames(tmp_path, 12)  # frame_10 must come after frame_9
    (tmp_path / "notes.txt").write_text("not an image")
    items = drain(FolderSource(tmp_path, queue_size=2))
    frames = frames_of(items)
    assert [f.index for f in frames] == list(range(12))
    np.testing.assert_allclose([f.gray[0, 0] for f in frames], [(10 * i + 5) / 255 for i in range(12)], rtol=1e-6)
    assert all(f.gray.dtype == np.float32 and f.color is None for f in frames)
    assert [e.status for e in events_of(items)] == ["end_of_stream"]
    assert all(b.stamp >= a.stamp for a, b in zip(frames, frames[1:]))


def test_colour_frames_keep_bgr(tmp_path):
    image = np.zeros((8, 8, 3), np.uint8)
    image[..., 2] = 200  # red in BGR
    cv2.imwrite(str(tmp_path / "a.png"), image)
    (frame,) = frames_of(drain(FolderSource(tmp_path)))
    np.testing.assert_array_equal(frame.color, image)
    np.testing.assert_allclose(frame.gray, 0.299 * 200 / 255, atol=1e-3)


def test_corrupt_image_is_an_event(tmp_path):
    write_frames(tmp_path, 5)
    (tmp_path / "frame_2.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not really a png")
    items = drain(FolderSource(tmp_path))
    assert [f.index for f in frames_of(items)] == [0, 1, 3, 4]
    corrupt = [e for e in events_of(items) if e.status == "corrupt_frame"]
    assert len(corrupt) == 1 and corrupt[0].index == 2 and "frame_2.png" in corrupt[0].message
    assert items[-1].status == "end_of_stream"


def test_missing_folder_fails_to_open(tmp_path):
    items = drain(FolderSource(tmp_path / "absent"))
    assert len(items) == 1 and items[0].status == "open_failed" and items[0].final


def test_latest_frame_semantics_with_slow_consumer():
    n = 300

    def fast(i):
        return None if i >= n else np.full((16, 16), i % 256, np.uint8)

    source = CallableSource(fast, latest=True)
    received, pending_frames = [], []
    with source:
        while True:
            item = source.get(timeout=10)
            assert item is not None
            pending_frames.append(sum(isinstance(x, Frame) for x in list(source._items)))
            if isinstance(item, SourceEvent):
                assert item.final and item.status == "end_of_stream"
                break
            received.append(item.index)
            time.sleep(0.002)  # slow consumer
    assert max(pending_frames) <= 1  # one overwritten slot, no queue
    assert received == sorted(received) and len(set(received)) == len(received)
    assert source.dropped > 0
    assert source.delivered + source.dropped == n
    assert received[-1] == n - 1  # the newest frame is never lost


def test_in_order_mode_drops_nothing():
    n = 100
    source = CallableSource(lambda i: None if i >= n else np.full((8, 8), i / n, np.float32), queue_size=3)
    items = []
    with source:
        for item in source:
            items.append(item)
            time.sleep(0.0005)
            assert len(source._items) <= 3 + 1  # the final event is always accepted
    assert [f.index for f in frames_of(items)] == list(range(n))
    assert source.dropped == 0


def test_vanishing_source_reconnects_then_gives_up():
    calls = []

    def vanishing(i):
        calls.append(i)
        return np.zeros((8, 8), np.uint8) if i < 5 else None

    items = drain(CallableSource(vanishing, live=True, latest=False, reconnect=FAST))
    assert [f.index for f in frames_of(items)] == list(range(5))
    statuses = [e.status for e in events_of(items)]
    assert statuses == ["reconnecting"] * 3 + ["source_lost"]
    assert items[-1].final and calls.count(5) == 4  # first failure + three attempts


def test_source_that_returns_reconnects():
    gaps = [2]  # frame 3 fails twice, then the source is back

    def flaky(i):
        if i == 3 and gaps[0] > 0:
            gaps[0] -= 1
            return None
        return None if i >= 6 else np.zeros((8, 8), np.uint8)

    items = drain(CallableSource(flaky, live=True, latest=False, reconnect=FAST))
    assert [f.index for f in frames_of(items)][:6] == list(range(6))
    statuses = [e.status for e in events_of(items)]
    assert statuses[:3] == ["reconnecting", "reconnecting", "reconnected"]
    assert statuses[-1] == "source_lost"


def test_exception_in_callable_is_a_corrupt_frame():
    def broken(i):
        if i == 1:
            raise RuntimeError("simulator hiccup")
        return None if i >= 3 else np.zeros((8, 8), np.float32)

    items = drain(CallableSource(broken))
    assert [(type(x).__name__, x.index) for x in items] == [
        ("Frame", 0),
        ("SourceEvent", 1),
        ("Frame", 2),
        ("SourceEvent", 3),
    ]
    assert "simulator hiccup" in items[1].message


def test_unopenable_live_video_backs_off(tmp_path):
    items = drain(VideoSource(tmp_path / "absent.mp4", live=True, reconnect=FAST))
    assert [e.status for e in items] == ["reconnecting"] * 3 + ["source_lost"]
    items = drain(VideoSource(tmp_path / "absent.mp4"))
    assert [e.status for e in items] == ["open_failed"]


def write_video(path, n, fourcc="mp4v"):
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*fourcc), 30, (64, 48))
    assert writer.isOpened()
    for i in range(n):
        frame = np.zeros((48, 64, 3), np.uint8)
        frame[:, : 2 * i + 2] = (0, 255, 0)
        writer.write(frame)
    writer.release()


def test_video_file_in_order(tmp_path):
    path = tmp_path / "clip.mp4"
    write_video(path, 20)
    items = drain(VideoSource(path))
    frames = frames_of(items)
    assert [f.index for f in frames] == list(range(20))
    assert frames[0].color.shape == (48, 64, 3) and frames[0].gray.shape == (48, 64)
    assert items[-1].status == "end_of_stream"


def test_video_replayed_at_a_camera_rate(tmp_path):
    path = tmp_path / "clip.mp4"
    write_video(path, 12)
    # A replay is a camera: latest-frame delivery by default, every frame stamped when due.
    assert VideoSource(path, replay_fps=30).latest
    frames = frames_of(drain(VideoSource(path, replay_fps=400, latest=False)))
    assert [f.index for f in frames] == list(range(12))
    stamps = np.array([f.stamp for f in frames])
    # Stamps are never earlier than their due time after the first (a lower bound only).
    assert np.all(stamps - stamps[0] >= np.arange(12) / 400 - 2e-3)
    with pytest.raises(ValueError, match="replay_fps"):
        VideoSource(path, replay_fps=0)


@pytest.mark.parametrize("keep", [0.1, 0.5, 0.9])
def test_truncated_mp4_ends_cleanly(tmp_path, keep):
    # OpenCV's MP4 writer puts the index (moov atom) last: a truncated file cannot be opened.
    path = tmp_path / "clip.mp4"
    write_video(path, 30)
    data = path.read_bytes()
    path.write_bytes(data[: int(keep * len(data))])
    items = drain(VideoSource(path))
    assert items[-1].final and items[-1].status in {"open_failed", "truncated", "end_of_stream"}
    assert len(frames_of(items)) < 30


def test_truncated_avi_reports_truncation(tmp_path):
    # Motion-JPEG AVI streams without its index: frames up to the cut, then "truncated".
    path = tmp_path / "clip.avi"
    write_video(path, 30, "MJPG")
    data = path.read_bytes()
    path.write_bytes(data[: int(0.6 * len(data))])
    items = drain(VideoSource(path))
    indices = [f.index for f in frames_of(items)]
    assert 0 < len(indices) < 30 and indices == list(range(len(indices)))
    assert items[-1].final and items[-1].status == "truncated"


def test_close_unblocks_a_waiting_producer():
    source = CallableSource(lambda i: np.zeros((8, 8), np.uint8), queue_size=2)
    source.start()
    assert isinstance(source.get(timeout=5), Frame)
    time.sleep(0.05)  # the producer now waits on a full queue
    source.close()
    assert not source._thread.is_alive()
    remaining = []
    while (item := source.get(timeout=1)) is not None:
        remaining.append(item)
    assert remaining[-1].final and remaining[-1].status == "closed"
    assert threading.active_count() >= 1


def test_frame_conversion():
    assert to_frame(np.full((4, 4), 65535, np.uint16), 0, 0.0).gray.max() == 1.0
    bgra = np.zeros((4, 4, 4), np.uint8)
    bgra[..., 1] = 255
    frame = to_frame(bgra, 0, 0.0)
    assert frame.color.shape == (4, 4, 3) and frame.color[0, 0, 1] == 255
    colour_float = to_frame(np.full((4, 4, 3), 0.5, np.float64), 0, 0.0)
    assert colour_float.color.dtype == np.uint8 and colour_float.color[0, 0, 0] == 128
    assert to_frame(np.full((4, 4), 2.0), 0, 0.0).gray.max() == 1.0
    from moirejax.live._camera import CorruptFrameError

    for bad in (np.full((4, 4), np.nan), np.zeros((0, 4)), np.zeros((4, 4), np.int64), np.zeros((4, 4, 2))):
        with pytest.raises(CorruptFrameError):
            to_frame(bad, 0, 0.0)
