import json

import cv2
import numpy as np
import pytest

from moirejax._fileio import DataError, load_schema, validate_json
from moirejax.data import _dataset
from moirejax.data._dataset import (
    DatasetWriter,
    export_recording,
    import_recording,
    open_dataset,
    WRENCH_CONVENTION,
)


DEVICE = {"format": "moirejax-device", "version": 1, "p1": 1.0, "p2": 1.05}
SHAPE = (12, 17)


def _frames(n, seed=0):
    return np.random.default_rng(seed).uniform(0.0, 1.0, size=(n, *SHAPE))


def _wrenches(n, seed=1):
    return np.random.default_rng(seed).normal(size=(n, 6))


def _write(path, n=6, bit_depth=8, **kwargs):
    frames, wrenches = _frames(n), _wrenches(n)
    with DatasetWriter(path, device=DEVICE, bit_depth=bit_depth, source="test", **kwargs) as writer:
        for i in range(n):
            writer.add(frames[i], wrenches[i], t=0.1 * i, contact=i % 2)
    return frames, wrenches


def _rewrite_csv_cell(path, row, column, text):
    """Set one cell of a CSV (row numbers count the header as row 1)."""
    lines = path.read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[row - 1].split(",")
    cells[header.index(column)] = text
    lines[row - 1] = ",".join(cells)
    path.write_text("\n".join(lines) + "\n")


@pytest.mark.parametrize("bit_depth", [8, 16])
def test_write_read_round_trip(tmp_path, bit_depth):
    maxval = 2**bit_depth - 1
    n = 5
    frames, wrenches = _frames(n), _wrenches(n)
    latents = [{"x0": 0.5 * i, "y0": -0.25, "radius": np.nan if i == 0 else 2.0} for i in range(n)]
    with DatasetWriter(
        tmp_path / "ds", device=DEVICE, bit_depth=bit_depth, source="unit test", fps=30.0, seed=7
    ) as writer:
        for i in range(n):
            writer.add(frames[i], wrenches[i], t=0.5 * i, contact=bool(i % 2), latent=latents[i])

    ds = open_dataset(tmp_path / "ds")
    assert len(ds) == n
    assert ds.frame_shape == SHAPE and ds.bit_depth == bit_depth and ds.fps == 30.0
    assert ds.frame_names == tuple(f"{i:06d}.png" for i in range(n))
    assert ds.manifest["wrench_convention"] == WRENCH_CONVENTION
    assert ds.manifest["seed"] == 7 and ds.device == DEVICE
    # repr() in the CSV round-trips float64 exactly.
    np.testing.assert_array_equal(ds.wrenches, wrenches)
    np.testing.assert_array_equal(ds.t, 0.5 * np.arange(n))
    np.testing.assert_array_equal(ds.contact, np.arange(n) % 2 == 1)
    np.testing.assert_array_equal(ds.latents["x0"], 0.5 * np.arange(n))
    assert np.isnan(ds.latents["radius"][0]) and ds.latents["radius"][1] == 2.0
    for i, frame in enumerate(ds):
        assert frame.dtype == np.float32 and frame.shape == SHAPE
        np.testing.assert_allclose(frame, np.round(frames[i] * maxval) / maxval, rtol=0, atol=1e-7)
    # The PNGs are ordinary grayscale images of the stated depth.
    png = cv2.imread(str(ds.frame_path(0)), cv2.IMREAD_UNCHANGED)
    assert png.dtype == (np.uint8 if bit_depth == 8 else np.uint16) and png.shape == SHAPE
    np.testing.assert_array_equal(png, np.round(frames[0] * maxval))


def test_integer_frames_are_stored_exactly(tmp_path):
    rng = np.random.default_rng(3)
    image8 = rng.integers(0, 256, size=SHAPE, dtype=np.uint8)
    image16 = rng.integers(0, 65536, size=SHAPE, dtype=np.uint16)
    with DatasetWriter(tmp_path / "ds", device=DEVICE, bit_depth=16) as writer:
        writer.add(image8, np.zeros(6))
        writer.add(image16, np.zeros(6))
    ds = open_dataset(tmp_path / "ds")
    np.testing.assert_array_equal(ds.frame(0), image8 / np.float32(255))
    np.testing.assert_array_equal(ds.frame(-1), image16 / np.float32(65535))
    # Export writes only the columns the dataset has.
    export_recording(tmp_path / "ds", tmp_path / "out", tmp_path / "out.csv")
    assert (tmp_path / "out.csv").read_text().splitlines()[0] == "frame,fx,fy,fz,tx,ty,tz"
    assert cv2.imread(str(tmp_path / "out" / "000001.png"), cv2.IMREAD_UNCHANGED).dtype == np.uint16


def test_frames_are_read_lazily(tmp_path, monkeypatch):
    _write(tmp_path / "ds", n=7)
    reads = []
    load_gray = _dataset._load_gray
    monkeypatch.setattr(_dataset, "_load_gray", lambda path: reads.append(path.name) or load_gray(path))

    ds = open_dataset(tmp_path / "ds")
    assert reads == []
    ds.frame(3)
    assert reads == ["000003.png"]
    frames = iter(ds)
    next(frames)
    assert reads == ["000003.png", "000000.png"]
    batches = ds.iter_batches(3)
    batch = next(batches)
    assert len(reads) == 5
    np.testing.assert_array_equal(batch.indices, [0, 1, 2])
    assert batch.frames.shape == (3, *SHAPE) and batch.frames.dtype == np.float32
    np.testing.assert_array_equal(batch.wrenches, ds.wrenches[:3])
    assert [len(b.indices) for b in batches] == [3, 1]


def test_a_frame_sequence_reads_its_frames_in_its_order_when_indexed(tmp_path, monkeypatch):
    written, _ = _write(tmp_path / "ds", n=7)
    reads = []
    load_gray = _dataset._load_gray
    monkeypatch.setattr(_dataset, "_load_gray", lambda path: reads.append(path.name) or load_gray(path))
    ds = open_dataset(tmp_path / "ds")
    frames = ds.frames([5, 2, 6])
    assert reads == [] and len(frames) == 3 and frames.shape == (3, *SHAPE)
    # 8-bit files: each frame is its written values to the quantisation step.
    np.testing.assert_allclose(frames[0], written[5], atol=0.5 / 255 + 1e-6)
    assert reads == ["000005.png"]
    np.testing.assert_array_equal(frames[1:], np.stack([ds.frame(2), ds.frame(6)]))
    np.testing.assert_array_equal(np.asarray(frames), np.stack([frame for frame in frames]))
    assert frames[3:].shape == (0, *SHAPE) and frames[-1].shape == SHAPE
    with pytest.raises(IndexError, match="frame index 9 out of range for 7 frames"):
        ds.frames([1, 9])
    with pytest.raises(IndexError):
        frames[3]


@pytest.mark.parametrize(
    "row, column, text, message",
    [
        (4, "fz", "abc", "wrench.csv row 4: field 'fz': 'abc' is not a number"),
        (2, "tx", "nan", "wrench.csv row 2: field 'tx': 'nan' is not finite"),
        (3, "fy", "", "wrench.csv row 3: field 'fy': is empty"),
        (5, "contact", "2", "wrench.csv row 5: field 'contact': '2' is not 0 or 1"),
        (6, "frame", "../x.png", "wrench.csv row 6: field 'frame': '../x.png' is not a file name"),
        (7, "frame", "000000.png", "wrench.csv row 7: field 'frame': '000000.png' already appears in row 2"),
    ],
)
def test_csv_errors_name_file_row_and_field(tmp_path, row, column, text, message):
    _write(tmp_path / "ds")
    _rewrite_csv_cell(tmp_path / "ds" / "wrench.csv", row, column, text)
    with pytest.raises(DataError, match=message.replace("(", r"\(").replace(".", r"\.")):
        open_dataset(tmp_path / "ds")


def test_csv_missing_column_and_missing_frame_file(tmp_path):
    _write(tmp_path / "ds")
    csv_path = tmp_path / "ds" / "wrench.csv"
    original = csv_path.read_text()
    csv_path.write_text(
        "\n".join(",".join(line.split(",")[:6] + line.split(",")[7:]) for line in original.splitlines())
    )
    with pytest.raises(DataError, match=r"wrench\.csv: missing column\(s\) 'tz'"):
        open_dataset(tmp_path / "ds")
    csv_path.write_text(original)
    (tmp_path / "ds" / "frames" / "000002.png").unlink()
    with pytest.raises(DataError, match=r"wrench\.csv row 4: field 'frame': .*000002\.png does not exist"):
        open_dataset(tmp_path / "ds")


def test_unreadable_and_wrong_size_frames_are_named(tmp_path):
    _write(tmp_path / "ds", n=4)
    frames_dir = tmp_path / "ds" / "frames"
    (frames_dir / "000001.png").write_bytes(b"\x89PNG\r\n\x1a\n this is not an image")
    cv2.imwrite(str(frames_dir / "000002.png"), np.zeros((SHAPE[0] + 1, SHAPE[1]), np.uint8))
    ds = open_dataset(tmp_path / "ds")
    with pytest.raises(DataError, match=r"000001\.png: not a readable image"):
        ds.frame(1)
    with pytest.raises(DataError, match=r"000002\.png: image size 13x17 .* differs from the dataset's 12x17"):
        ds.frame(2)
    with pytest.raises(DataError, match=r"000001\.png"):
        list(ds.iter_frames())
    status = list(ds.iter_frames(on_error="status"))
    assert [i for i, _, _ in status] == [0, 1, 2, 3]
    assert [frame is None for _, frame, _ in status] == [False, True, True, False]
    assert "000001.png" in status[1][2] and "000002.png" in status[2][2]
    assert status[0][2] is None and status[3][1].shape == SHAPE


def test_writer_rejects_bad_input(tmp_path):
    with DatasetWriter(tmp_path / "ds", device=DEVICE) as writer:
        writer.add(np.zeros(SHAPE), np.zeros(6))
        with pytest.raises(ValueError, match=r"000001\.png.*not finite"):
            writer.add(np.zeros(SHAPE), [0, 0, np.nan, 0, 0, 0])
        with pytest.raises(ValueError, match=r"shape \(12, 16\) differs from the dataset's \(12, 17\)"):
            writer.add(np.zeros((12, 16)), np.zeros(6))
        with pytest.raises(ValueError, match=r"\[0, 1\]"):
            writer.add(np.full(SHAPE, 1.5), np.zeros(6))
        with pytest.raises(ValueError, match="every frame or for none"):
            writer.add(np.zeros(SHAPE), np.zeros(6), t=1.0)
        with pytest.raises(ValueError, match="already used"):
            writer.add(np.zeros(SHAPE), np.zeros(6), name="000000.png")
    assert len(open_dataset(tmp_path / "ds")) == 1
    with pytest.raises(DataError, match="not empty; pass overwrite=True"):
        DatasetWriter(tmp_path / "ds", device=DEVICE)
    with pytest.raises(DataError, match="field 'fps'"):
        DatasetWriter(tmp_path / "other", device=DEVICE, fps=-1.0)


@pytest.mark.parametrize("interrupt", [RuntimeError, KeyboardInterrupt])
def test_interrupted_writer_leaves_no_manifest(tmp_path, interrupt):
    with pytest.raises(interrupt):
        with DatasetWriter(tmp_path / "ds", device=DEVICE) as writer:
            writer.add(np.zeros(SHAPE), np.zeros(6))
            raise interrupt()
    assert (tmp_path / "ds" / "frames" / "000000.png").exists()
    assert not (tmp_path / "ds" / "manifest.json").exists()
    assert not (tmp_path / "ds" / "wrench.csv").exists()
    with pytest.raises(DataError, match="incomplete"):
        open_dataset(tmp_path / "ds")
    # An overwrite replaces the remains.
    _write(tmp_path / "ds", n=2, overwrite=True)
    assert len(open_dataset(tmp_path / "ds")) == 2


def test_schema_rejects_manifest_without_n_frames(tmp_path):
    _write(tmp_path / "ds")
    manifest_path = tmp_path / "ds" / "manifest.json"
    manifest = json.loads(manifest_path.read_text())
    validate_json(manifest, "dataset")
    del manifest["n_frames"]
    with pytest.raises(DataError, match="'n_frames' is a required property"):
        validate_json(manifest, "dataset")
    manifest_path.write_text(json.dumps(manifest))
    with pytest.raises(DataError, match=r"manifest\.json: .*'n_frames'"):
        open_dataset(tmp_path / "ds")
    assert load_schema("dataset")["properties"]["wrench_convention"]["const"] == WRENCH_CONVENTION


def test_device_may_be_a_relative_path(tmp_path):
    with DatasetWriter(tmp_path / "ds", device="device.json") as writer:
        writer.add(np.zeros(SHAPE), np.zeros(6))
    (tmp_path / "ds" / "device.json").write_text(json.dumps(DEVICE))
    assert open_dataset(tmp_path / "ds").device == DEVICE


def _make_recording(root, n=6):
    """A lab recording: colour PNG/BMP images plus a CSV with an extra column."""
    rng = np.random.default_rng(5)
    (root / "images").mkdir(parents=True)
    colour = rng.integers(0, 256, size=(n, *SHAPE, 3), dtype=np.uint8)
    names = [f"img{i:03d}.{'bmp' if i % 3 == 0 else 'png'}" for i in range(n)]
    for name, image in zip(names, colour):
        cv2.imwrite(str(root / "images" / name), image)
    wrenches = _wrenches(n)
    lines = ["frame,fx,fy,fz,tx,ty,tz,t,contact,temperature"]
    lines += [
        ",".join([name, *map(repr, w.tolist()), repr(0.01 * i), str(i % 2), "21.5"])
        for i, (name, w) in enumerate(zip(names, wrenches))
    ]
    (root / "forces.csv").write_text("\n".join(lines) + "\n")
    gray = np.stack([cv2.cvtColor(image, cv2.COLOR_BGR2GRAY) for image in colour])
    return names, gray, wrenches


def test_import_export_import_round_trip(tmp_path):
    names, gray, wrenches = _make_recording(tmp_path / "rec")
    report = import_recording(
        tmp_path / "rec" / "images", tmp_path / "rec" / "forces.csv", DEVICE, tmp_path / "ds", progress=False
    )
    assert report.n_frames == report.n_rows == len(names) and report.skipped == ()
    assert report.ignored_columns == ("temperature",) and report.bit_depth == 8
    ds = open_dataset(tmp_path / "ds")
    assert ds.frame_names == tuple(name.rsplit(".", 1)[0] + ".png" for name in names)
    np.testing.assert_array_equal(ds.wrenches, wrenches)
    for i in range(len(ds)):
        np.testing.assert_array_equal(ds.frame(i), gray[i] / np.float32(255))

    export_recording(ds, tmp_path / "out" / "images", tmp_path / "out" / "forces.csv")
    device_path = tmp_path / "device.json"
    device_path.write_text(json.dumps(DEVICE))
    import_recording(
        tmp_path / "out" / "images", tmp_path / "out" / "forces.csv", device_path, tmp_path / "ds2", progress=False
    )
    ds2 = open_dataset(tmp_path / "ds2")
    assert ds2.frame_names == ds.frame_names and ds2.device == DEVICE
    np.testing.assert_array_equal(ds2.wrenches, ds.wrenches)
    np.testing.assert_array_equal(ds2.t, ds.t)
    np.testing.assert_array_equal(ds2.contact, ds.contact)
    for a, b in zip(ds, ds2):
        np.testing.assert_array_equal(a, b)


def test_import_reports_every_bad_frame(tmp_path):
    names, _, _ = _make_recording(tmp_path / "rec", n=8)
    images = tmp_path / "rec" / "images"
    (images / names[1]).unlink()
    (images / names[4]).unlink()
    (images / names[5]).write_bytes(b"corrupt bytes")
    cv2.imwrite(str(images / names[6]), np.zeros((5, 5), np.uint8))
    args = (images, tmp_path / "rec" / "forces.csv", DEVICE)

    with pytest.raises(DataError) as info:
        import_recording(*args, tmp_path / "ds", progress=False)
    message = str(info.value)
    assert message.startswith("4 of 8 frames")
    for i, what in [(1, "no such file"), (4, "no such file"), (5, "not a readable image"), (6, "image size 5x5")]:
        assert f"row {i + 2}: {images / names[i]}: {what}" in message
    assert not (tmp_path / "ds" / "manifest.json").exists()

    report = import_recording(*args, tmp_path / "ds", skip_bad=True, progress=False, overwrite=True)
    assert report.n_frames == 4 and [name for name, _ in report.skipped] == [names[i] for i in (1, 4, 5, 6)]
    assert open_dataset(tmp_path / "ds").frame_names == tuple(names[i].rsplit(".", 1)[0] + ".png" for i in (0, 2, 3, 7))


def test_import_rejects_missing_column(tmp_path):
    _make_recording(tmp_path / "rec")
    csv_path = tmp_path / "rec" / "forces.csv"
    csv_path.write_text(csv_path.read_text().replace(",fz,", ",force_z,", 1))
    with pytest.raises(DataError, match=r"forces\.csv: missing column\(s\) 'fz'"):
        import_recording(tmp_path / "rec" / "images", csv_path, DEVICE, tmp_path / "ds", progress=False)


def test_import_keeps_16_bit_depth_and_reports_nan_wrench(tmp_path):
    rng = np.random.default_rng(9)
    (tmp_path / "images").mkdir()
    images = rng.integers(0, 65536, size=(3, *SHAPE), dtype=np.uint16)
    for i, image in enumerate(images):
        cv2.imwrite(str(tmp_path / "images" / f"{i}.tif"), image)
    rows = ["0.tif,1,2,3,4,5,6", "1.tif,1,2,nan,4,5,6", "2.tif,1,2,3,4,5,6"]
    (tmp_path / "w.csv").write_text("frame,fx,fy,fz,tx,ty,tz\n" + "\n".join(rows) + "\n")
    args = (tmp_path / "images", tmp_path / "w.csv", DEVICE, tmp_path / "ds")
    with pytest.raises(DataError, match=r"row 3: .*w\.csv row 3: wrench \[1\.0, 2\.0, nan"):
        import_recording(*args, progress=False)
    report = import_recording(*args, progress=False, skip_bad=True, overwrite=True)
    assert report.bit_depth == 16 and report.n_frames == 2
    ds = open_dataset(tmp_path / "ds")
    assert ds.frame_names == ("0.png", "2.png")
    np.testing.assert_array_equal(ds.frame(1), images[2] / np.float32(65535))
