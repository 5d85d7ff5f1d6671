"""`moirejax vision`: objects located in a folder of see-through frames, restored images
written, and the error policy's exit codes."""

import json

import cv2
import jax.random as jr
import numpy as np
import pytest

import moirejax as mj
from moirejax.cli._main import main


# (scene, its height in mm) of each frame; the first is the empty view.
POSES = [(None, 0.0), (mj.scene_disc(1.5, -2.0, 8.0, rgb=(0.1, 0.7, 0.2)), 0.0), (mj.scene_disc(-3.0, 2.5, 7.0), 0.0)]


def _png(path, frame) -> None:
    assert cv2.imwrite(str(path), np.round(np.asarray(frame) * 255).astype(np.uint8))


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    """A 256 x 256 Mid unit's device file, a folder of frames and a folder of the empty view."""
    root = tmp_path_factory.mktemp("vision")
    device = mj.preset("mid", height=256, width=256)
    mj.save_device(root / "device.json", device)
    (root / "frames").mkdir()
    for i, (scene, _) in enumerate(POSES):
        _png(root / "frames" / f"frame{i}.png", mj.render_scene(jr.PRNGKey(10 + i), device, scene).frame)
    (root / "reference").mkdir()
    for i, frame in enumerate(mj.empty_scene_reference(jr.PRNGKey(1), device, frames=4)):
        _png(root / "reference" / f"empty{i}.png", frame)
    return root


def test_vision_locates_the_disc_and_writes_restored_images(recording, tmp_path, capsys):
    argv = ["vision", "--device", str(recording / "device.json"), "--frames", str(recording / "frames")]
    argv += ["--reference", str(recording / "reference"), "--restore", str(tmp_path / "restored"), "--json"]
    assert main(argv) == 0
    captured = capsys.readouterr()
    records = [json.loads(line) for line in captured.out.splitlines()]
    assert [r["frame"] for r in records] == [0, 1, 2]
    assert [r["file"] for r in records] == ["frame0.png", "frame1.png", "frame2.png"]
    assert all(r["mode"] == "vision" for r in records)
    assert records[0]["status"] == "empty" and records[0]["objects"] == []
    for record, (scene, _) in zip(records[1:], POSES[1:]):
        assert record["status"] == "ok" and len(record["objects"]) == 1
        (seen,) = record["objects"]
        assert set(seen) == {"x_mm", "y_mm", "yaw_deg", "size_mm", "hue", "colour", "confidence"}
        assert abs(seen["x_mm"] - float(scene.x)) < 0.3 and abs(seen["y_mm"] - float(scene.y)) < 0.3
        assert seen["yaw_deg"] is None and abs(seen["size_mm"] - float(scene.length)) < 0.5
    assert records[1]["objects"][0]["colour"] == "green"
    for i in range(3):
        restored = cv2.imread(str(tmp_path / "restored" / f"frame{i}.png"), cv2.IMREAD_UNCHANGED)
        assert restored is not None and restored.shape == (256, 256, 3) and restored.dtype == np.uint8
    # Nothing half-written is left beside them.
    assert sorted(p.name for p in (tmp_path / "restored").iterdir()) == [f"frame{i}.png" for i in range(3)]
    assert "reference: mean of 4 images of" in captured.err
    # Written again, the folder is not empty: that needs --overwrite (exit 4, naming the flag).
    assert main(argv) == 4
    err = capsys.readouterr().err
    assert "--overwrite" in err and len(err.strip().splitlines()) == 1
    assert main([*argv, "--overwrite"]) == 0


def test_vision_without_a_reference_uses_the_first_frames_and_prints_text(recording, tmp_path, capsys):
    # A recording that starts with five frames of the empty view, then the disc.
    empty = sorted((recording / "reference").iterdir()) + [recording / "frames" / "frame0.png"]
    for i, path in enumerate([*empty, recording / "frames" / "frame1.png"]):
        (tmp_path / f"{i:02d}.png").write_bytes(path.read_bytes())
    assert main(["vision", "--device", str(recording / "device.json"), "--frames", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    assert f"reference: mean of the first 5 frames of {tmp_path}" in captured.err
    lines = captured.out.splitlines()
    assert lines[:5] == [f"frame {i} ({i:02d}.png): empty" for i in range(5)]
    assert lines[5].startswith("frame 5 (05.png): ok: green object at (1.") and len(lines) == 6


def _argv(root) -> list[str]:
    return ["vision", "--device", str(root / "device.json"), "--frames", str(root / "frames")]


@pytest.mark.parametrize(
    "argv, fragment",
    [
        (lambda root: _argv(root)[:3], "required: --frames"),
        (lambda root: [*_argv(root), "--height", "-3"], "--height"),
    ],
)
def test_vision_usage_errors_exit_2(recording, capsys, argv, fragment):
    # argparse's own errors: its usage line, then one line naming the flag.
    with pytest.raises(SystemExit) as info:
        main(argv(recording))
    assert info.value.code == 2
    assert fragment in capsys.readouterr().err.strip().splitlines()[-1]


@pytest.mark.parametrize(
    "change, fragment, code",
    [
        # A frames folder or a reference that does not exist: bad input (3), naming the flag.
        (
            lambda root: ["--frames", str(root / "nowhere")],
            "nowhere: no such dataset, folder or video (given by --frames)",
            3,
        ),
        (
            lambda root: ["--reference", str(root / "none.png")],
            "none.png: no such image, folder of images or video (given by --reference)",
            3,
        ),
        # The restored images would replace the frames: a usage error (2).
        (lambda root: ["--restore", str(root / "frames")], "--restore must not be the --frames folder", 2),
    ],
)
def test_vision_bad_input_is_one_clear_line(recording, capsys, change, fragment, code):
    assert main([*_argv(recording), *change(recording)]) == code
    err = capsys.readouterr().err
    assert fragment in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
