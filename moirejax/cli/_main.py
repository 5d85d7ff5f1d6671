"""The `moirejax` command line: one subcommand per thing a user does.

It is one module because most of its length is the argument table of every subcommand,
whose flags and help a user reads together; each command's body is a few lines calling the
public API."""

import argparse
import dataclasses
import importlib.metadata
import json
import math
import os
import sys
import warnings
from collections.abc import Sequence
from pathlib import Path

from .._fileio import check_output_file, check_output_folder, DataError, DataWarning, OutputError
from ._errors import COMMAND_LINE, run_command


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be at least 1, got {value}")
    return value


def _real_number(*, zero_allowed: bool):
    """An argparse type: a finite number above zero (or from zero on, `zero_allowed`)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
        if not (math.isfinite(value) and (value >= 0 if zero_allowed else value > 0)):
            raise argparse.ArgumentTypeError(f"must be a number {'>= 0' if zero_allowed else '> 0'}, got {text}")
        return value

    return parse


_positive_float = _real_number(zero_allowed=False)
_non_negative_float = _real_number(zero_allowed=True)


def _check_new_folder(path: str, overwrite: bool) -> None:
    """A dataset folder to write: writable, and empty unless --overwrite (checked before any work)."""
    folder = check_output_folder(path, argument="out")
    if folder.is_dir() and any(folder.iterdir()) and not overwrite:
        raise OutputError(f"{folder}: folder is not empty; pass {{argument}} to replace it", argument="overwrite")


def _add_device_arguments(parser: argparse.ArgumentParser, *, design_flags: bool = False) -> None:
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--preset", choices=["dense", "mid", "sparse"], help="one of the paper's designs")
    group.add_argument("--device", metavar="FILE", help="a device JSON file")
    if design_flags:
        g = parser.add_argument_group("design parameters (override the preset)")
        g.add_argument("--p1", type=float, help="upper (far) grating pitch, mm")
        g.add_argument("--p2", type=float, help="reference (near) grating pitch, mm")
        g.add_argument("--alpha1-deg", type=float, help="upper grating angle, degrees")
        g.add_argument("--alpha2-deg", type=float, help="reference grating angle, degrees")
        g.add_argument("--a", type=float, help="grating separation, mm")
        g.add_argument("--Z", type=float, help="camera distance to the reference grating, mm")
        g.add_argument("--px-per-mm", type=float, help="rectified resolution, px/mm")
        g.add_argument("--size", type=int, help="rectified image size, pixels (square)")
        g.add_argument("--height", type=int, help="rectified image height, pixels (with --width: not square)")
        g.add_argument("--width", type=int, help="rectified image width, pixels")
        g.add_argument("--E", type=float, help="elastomer Young's modulus, MPa")
        g.add_argument("--nu", type=float, help="elastomer Poisson ratio")
        g.add_argument("--thickness", type=float, help="elastomer thickness, mm")
        g.add_argument("--layout", choices=["lines", "crossed"], help="line gratings or crossed grids")
        g.add_argument("--duty1", type=float, help="open fraction of the upper grating's lines, 0 to 1")
        g.add_argument("--duty2", type=float, help="open fraction of the reference grating's lines, 0 to 1")
        g.add_argument("--cross-angle-deg", type=float, help="angle between a crossed grid's two line sets, degrees")
        o = parser.add_argument_group("optics and photometry (override the preset)")
        for name, text in _OPTICS_FLAGS.items():
            o.add_argument(f"--{name.replace('_', '-')}", type=float, help=text)


# The optical values of a unit that a command may set, with what each is (docs/physics.md).
_OPTICS_FLAGS = {
    "defocus": "blur of the far grating's image, mm (Gaussian sd)",
    "psf_sigma": "lens point spread, pixels (Gaussian sd)",
    "background": "scene radiance behind the sensor, 0 to 1",
    "vignetting": "fall-off of the illumination towards the corners, 0 to 1",
    "glow_gain": "light the elastomer scatters under a contact, per unit of pressure (0: none)",
    "glow_width": "width of that glow, mm",
    "rim_gain": "brightness of the rim around a contact (0: none)",
    "rim_width": "width of the rim, mm",
    "gain": "camera gain",
    "offset": "camera black level",
    "gamma": "camera response exponent",
}


def _device_from_args(args: argparse.Namespace):
    from ..physics import device_from_json, device_to_json, load_device, preset

    if getattr(args, "device", None):
        device = load_device(args.device)
    else:
        device = preset(args.preset or "mid", **({"layout": args.layout} if getattr(args, "layout", None) else {}))
    changes: dict = {}
    for flag, field in (
        ("p1", "p1"),
        ("p2", "p2"),
        ("a", "a"),
        ("Z", "Z"),
        ("px_per_mm", "px_per_mm"),
        ("duty1", "duty1"),
        ("duty2", "duty2"),
    ):
        value = getattr(args, flag, None)
        if value is not None:
            changes[field] = value
    for flag, field in (("alpha1_deg", "alpha1"), ("alpha2_deg", "alpha2"), ("cross_angle_deg", "cross_angle")):
        value = getattr(args, flag, None)
        if value is not None:
            changes[field] = math.radians(value)
    if getattr(args, "size", None) is not None:
        changes["height"] = changes["width"] = args.size
    for side in ("height", "width"):
        if getattr(args, side, None) is not None:
            changes[side] = getattr(args, side)
    elastomer = {k: getattr(args, k) for k in ("E", "nu", "thickness") if getattr(args, k, None) is not None}
    optics = {k: getattr(args, k) for k in _OPTICS_FLAGS if getattr(args, k, None) is not None}
    if not changes and not elastomer and not optics and not getattr(args, "layout", None):
        return device
    obj = device_to_json(device)
    obj.update(changes)
    obj["elastomer"].update(elastomer)
    obj["optics"].update(optics)
    if getattr(args, "layout", None) and args.layout != obj["layout"]:
        obj["layout"] = args.layout
        n = 1 if args.layout == "lines" else 2
        obj["optics"]["phase1"] = [0.0] * n
        obj["optics"]["phase2"] = [0.0] * n
    return device_from_json(obj, source=COMMAND_LINE)


# ---------------------------------------------------------------------------------------


def _cmd_design(args: argparse.Namespace) -> int:
    from ..design import design_table, format_design_table, plot_design_maps
    from ..physics import save_device

    for flag in ("write", "plot", "observability_plot"):
        if getattr(args, flag):
            check_output_file(getattr(args, flag), argument=flag)
    device = _device_from_args(args)
    table = design_table(device)
    if args.sensitivity or args.observability or args.optimise:
        from ..design import force_sensitivity

        table["force_sensitivity"] = force_sensitivity(device)
    if args.observability or args.optimise:
        from ..design import observability_table

        table["observability"] = observability_table(device)
    if args.optimise:
        from ..design import optimise_design

        optimum, report = optimise_design(
            device,
            min_pitch=args.min_pitch,
            min_fringes=args.min_fringes,
            max_phase_range=args.max_phase_range if args.max_phase_range > 0 else None,
            steps=args.steps,
            estimator=args.estimator,
            progress=not args.json,
        )
        table["optimisation"] = report
        device = optimum
    if args.json:
        print(json.dumps(table, indent=2))
    else:
        print(format_design_table(table))
    if args.write:
        save_device(args.write, device)
        print(f"wrote device {args.write}", file=sys.stderr)
    if args.plot:
        plot_design_maps(args.plot, device)
        print(f"wrote design maps {args.plot}", file=sys.stderr)
    if args.observability_plot:
        from ..design import plot_observability

        plot_observability(args.observability_plot, device, estimator=args.estimator)
        print(f"wrote observability maps {args.observability_plot}", file=sys.stderr)
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    from ..simulate import simulate_dataset

    if args.max_force is not None and args.protocol != "shapes":
        raise ValueError("--max-force applies to --protocol shapes only")
    _check_new_folder(args.out, args.overwrite)
    device = _device_from_args(args)
    out = simulate_dataset(
        args.out,
        device,
        args.protocol,
        args.n,
        seed=args.seed,
        fidelity=args.fidelity,
        overwrite=args.overwrite,
        max_force=args.max_force,
    )
    print(f"wrote {args.n} {args.fidelity}-fidelity frames of protocol {args.protocol!r} to {out}")
    print(f"contact sheet: {out.with_name(out.name + '_contact_sheet.png')}")
    return 0


def _cmd_import(args: argparse.Namespace) -> int:
    from ..data import import_recording
    from ..physics import load_device

    if args.wrench is None and args.ft is None:
        raise ValueError("--wrench is required, unless the wrenches come from a force/torque log (--ft)")
    if args.ft is None and (args.align or args.max_offset is not None):
        raise ValueError("--align and --max-offset apply to a force/torque log: give it with --ft")
    # Validate the device and the outputs before converting thousands of frames.
    if not Path(args.frames).is_dir():
        raise DataError(f"{args.frames}: no such folder")
    for path in (args.wrench, args.ft):
        if path is not None and not Path(path).is_file():
            raise DataError(f"{path}: no such file")
    load_device(args.device)
    _check_new_folder(args.out, args.overwrite)
    report = import_recording(
        args.frames,
        args.wrench,
        args.device,
        args.out,
        skip_bad=args.skip_bad,
        overwrite=args.overwrite,
        fps=args.fps,
        ft_csv=args.ft,
        align=args.align,
        max_offset=args.max_offset,
    )
    print(report)
    return 0


def _reference_for(device, source, reference_path):
    """The no-contact reference frame (or None) and a line saying where it came from."""
    from ..inverse import find_reference, load_reference_image

    shape = (device.height, device.width)
    if reference_path:
        if not Path(reference_path).is_file():
            raise DataError(f"{reference_path}: no such file")
        reference, note = load_reference_image(reference_path), f"reference: {reference_path}"
        if reference.shape != shape:
            raise DataError(
                f"{reference_path}: reference frame is {reference.shape[0]}x{reference.shape[1]}, "
                f"the device expects {shape[0]}x{shape[1]}"
            )
        return reference, note
    reference, note = find_reference(source, shape)
    if reference is None:
        warnings.warn(
            f"{note}. Inverting against the model's own no-load prediction, which is right only for the unit the "
            "device file describes: frames of another unit (or the same unit after a change) give wrong wrenches "
            "without any error. Give --reference IMAGE, a no-contact frame of this unit.",
            DataWarning,
            stacklevel=2,
        )
    return reference, note


def _open_mcap(path: str, **options):
    """The `McapSink` of `--mcap PATH` (its folder made), checked before any long work."""
    from ..live import McapSink

    check_output_file(path, argument="mcap")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    try:
        return McapSink(path, **options)
    except ImportError as e:  # without the `ros` extra: a usage error, not a crash
        raise ValueError(f"--mcap: {e}") from e
    except FileExistsError:
        raise OutputError(
            f"{path}.part: the unfinished file of an interrupted run; salvage it with `mcap recover` or delete it, "
            "or change {argument}",
            argument="mcap",
        ) from None


# Frames per segment of `invert --engine dask` when --segment is not given.
DASK_SEGMENT = 256


def _cmd_invert(args: argparse.Namespace) -> int:
    import numpy as np

    from ..calibration import load_calibrated
    from ..inverse import check_source, invert_distributed, invert_recording, Inverter
    from ..live import record_inversion, RecordStream, WRENCH_STATUSES

    # Everything that can be checked is checked before the inversion is compiled.
    if args.engine == "local" and (args.scheduler or args.workers != 2):
        raise ValueError("--workers and --scheduler apply to --engine dask")
    if args.engine == "dask":
        if check_source(args.data) == "video":
            raise ValueError(f"--engine dask: {args.data} is a video; import it into a dataset first (moirejax import)")
        try:
            import distributed  # noqa: F401
        except ImportError:
            raise ValueError("--engine dask needs Dask: pip install 'moirejax[cluster]'") from None
    if args.fps is not None and not args.mcap:
        raise ValueError("--fps sets the stamps of --mcap: give the MCAP file with --mcap")
    if args.plot_frames is not None and not args.plot:
        raise ValueError("--plot-frames sets how many frames --plot draws: give the folder with --plot")
    device, head = load_calibrated(args.device)
    check_source(args.data)
    check_output_file(args.out, argument="out")
    outputs = {"--out": args.out, "--mcap": args.mcap, "--maps": args.maps, "--plot": args.plot}
    named = [(flag, os.path.abspath(path)) for flag, path in outputs.items() if path]
    for k, (flag, path) in enumerate(named):
        for other, other_path in named[k + 1 :]:
            if path == other_path:
                raise ValueError(f"{flag} and {other} name the same path")
    if args.maps:
        check_output_file(args.maps, argument="maps")
    if args.plot:
        check_output_folder(args.plot, argument="plot")
    mcap = _open_mcap(args.mcap, wrench_statuses=WRENCH_STATUSES) if args.mcap else None
    try:
        reference, note = _reference_for(device, args.data, args.reference)
        if reference is not None:
            print(note, file=sys.stderr)
        inverter = Inverter(device, reference=None if reference is None else np.asarray(reference))
        if args.engine == "dask":
            counts = invert_distributed(
                inverter,
                args.data,
                args.out,
                segment=args.segment or DASK_SEGMENT,
                batch=args.batch,
                workers=args.workers,
                scheduler=args.scheduler,
                head=head,
                progress=not args.quiet,
            )
        else:
            counts = invert_recording(
                inverter,
                args.data,
                args.out,
                batch=args.batch,
                restart_every=args.segment,
                progress=not args.quiet,
                head=head,
            )
        if args.maps or args.plot:
            _write_invert_views(args, inverter)
        stamps = None
        if mcap is not None:
            records = RecordStream(sensor_id=args.sensor_id, frame_id=args.frame_id)
            stamps = record_inversion(mcap, args.data, args.out, device, records=records, fps=args.fps)
            if mcap.stats["errors"]:
                raise OutputError(f"{args.mcap}: {mcap.stats['errors']} messages could not be written (see the log)")
            mcap.close()
    except BaseException:
        if mcap is not None:
            mcap.abort()  # no half MCAP file, at its name or beside it
        raise
    print(f"wrote {args.out}: " + ", ".join(f"{n} {status}" for status, n in sorted(counts.items())))
    if args.maps:
        print(f"wrote {args.maps}: the traction maps of every frame")
    if args.plot:
        print(f"wrote {args.plot}: the wrench's timeline and the frames worth a look")
    if mcap is not None:
        print(
            f"wrote {args.mcap}: {mcap.stats['sent']} records, {mcap.stats['images']} frames, "
            f"{mcap.stats['pressure_maps']} pressure maps; stamps: {stamps}"
        )
    return 0


def _write_invert_views(args: argparse.Namespace, inverter) -> None:
    """The traction maps (`--maps`) and plots (`--plot`) of an inverted recording, drawn
    from its CSV and moved into place as a set: both or neither."""
    from .._fileio import commit_staged, staging_folder
    from ..inverse import plot_inversion, write_traction_maps

    beside = args.maps or args.plot
    with staging_folder(beside) as staging:
        moves = []
        if args.maps:
            staged = staging / Path(args.maps).name  # an error names the file the user gave
            write_traction_maps(staged, inverter.device, args.out)
            moves.append((staged, Path(args.maps)))
        if args.plot:
            staged = staging / "plots"
            plot_inversion(staged, inverter, args.data, args.out, frames=args.plot_frames or 6)
            moves.append((staged, Path(args.plot)))
        commit_staged(staging, moves)


def _cmd_calibrate(args: argparse.Namespace) -> int:
    from ..calibration import calibrate, format_metrics, load_recipe

    recipe = load_recipe(args.recipe)
    if args.rounds is not None:
        recipe = recipe.replace(rounds=args.rounds)
    summary = calibrate(
        args.device,
        args.data,
        args.out,
        max_frames=args.max_frames,
        recipe=recipe,
        progress=not args.quiet,
        force=args.force,
    )
    print(format_metrics(summary["physics_only"], title="physics only (calibration frames)"))
    print(format_metrics(summary["metrics"], title="with residual head (calibration frames)"))
    print("fitted parameters:")
    for p in summary["parameters"]:
        true = f"  true {p['true']:.5g}" if "true" in p else ""
        print(f"  {p['parameter']:20s} {p['nominal']:.5g} -> {p['fitted']:.5g} +- {p['sd']:.2g}{true}")
    print("ridge baseline, cross-validated R2 by training frames:")
    for n_train, r2 in summary["baselines"].items():
        print(f"  {n_train:>4s}: " + "  ".join(f"{axis} {value:.3f}" for axis, value in r2.items()))
    print(f"wrote {args.out} and {summary['report']}/")
    verdict = summary["verdict"]
    if not verdict["inside_model"]:
        axes = ", ".join(
            f"{axis} {v['calibrated']:.3f} < {v['ridge_baseline']:.3f}"
            for axis, v in verdict["axes_behind_baseline"].items()
        )
        strained = ", ".join(p["parameter"] for p in verdict["strained_parameters"]) or "none"
        print(
            f"WARNING: {args.data}: this unit is outside the model: a pixel regression reads {axes} (R2, calibrated "
            f"< ridge). Parameters pulled far from their start: {strained}. See {summary['report']}/residuals.png and "
            "metrics.json 'verdict'; more frames (--max-frames) or a recipe that frees more (--recipe) may help.",
            file=sys.stderr,
        )
    return 0


def _cmd_evaluate(args: argparse.Namespace) -> int:
    from ..calibration import evaluate, format_metrics

    metrics = evaluate(args.device, args.data, args.out, progress=not args.quiet)
    print(format_metrics(metrics, title=f"{args.device} on {args.data}"))
    print(f"wrote {args.out}/metrics.json, parity.png, residuals.png")
    return 0


def _cmd_transfer(args: argparse.Namespace) -> int:
    from ..calibration import transfer

    summary = transfer(
        args.from_, args.data, args.out, max_frames=args.max_frames, recipe=args.recipe, progress=not args.quiet
    )
    print(f"refitted {len(summary['uncertainty'])} parameters on {summary['frames']} frames; wrote {args.out}")
    check = summary["residual_head_check"]
    if check is not None:
        verdict = "kept" if check["kept"] else "dropped (it made the new unit's frames worse)"
        print(
            f"residual head {verdict}: scaled MSE {check['scaled_mse_with_head']:.3g} with, "
            f"{check['scaled_mse_without_head']:.3g} without"
        )
    return 0


# Suffixes that make a `--source` that does not exist a missing file rather than a camera name.
_FILE_SUFFIXES = (".mp4", ".avi", ".mkv", ".mov", ".webm", ".m4v", ".mpg", ".mpeg", ".wmv", ".json", ".csv")


def _live_source(spec: str) -> str:
    """The `--source` of `live` as `run_live` takes it: a camera named by its name, serial
    number or path becomes its index; the rest is checked and passed on."""
    from ..data import IMAGE_SUFFIXES
    from ..live import find_camera

    if spec == "sim" or spec.isdigit() or "://" in spec or "!" in spec:
        return spec
    if Path(spec).exists():
        if Path(spec).is_file():
            from ..inverse import check_source

            check_source(spec)
        return spec
    not_a_source = f"{spec}: not 'sim', a camera index, a URL, a folder or a video file"
    if "/" in spec or os.sep in spec or Path(spec).suffix.lower() in _FILE_SUFFIXES + tuple(IMAGE_SUFFIXES):
        raise DataError(not_a_source)
    try:
        index = find_camera(spec)
    except ImportError as e:
        raise DataError(f"{not_a_source}; to open a camera by its name, {e}") from None
    print(f"camera {spec!r}: index {index}", file=sys.stderr)
    return str(index)


def _cmd_cameras(args: argparse.Namespace) -> int:
    from ..live import list_cameras

    try:
        cameras = list_cameras()
    except ImportError as e:  # without the `cameras` extra: a usage error, not a crash
        raise ValueError(str(e)) from e
    if args.json:
        print(json.dumps([dataclasses.asdict(c) for c in cameras], indent=2))
        return 0
    if not cameras:
        print("no cameras found", file=sys.stderr)
        return 0
    header = ("index", "name", "backend", "usb id", "path")
    rows = [(str(c.index), c.name, c.backend, c.usb_id or "-", c.path or "-") for c in cameras]
    widths = [max(len(r[k]) for r in (header, *rows)) for k in range(len(header) - 1)]
    for row in (header, *rows):
        print("  ".join(cell.ljust(w) for cell, w in zip(row, widths)) + "  " + row[-1])
    for camera in cameras:
        for alias in camera.aliases:
            print(f"{camera.index}: also {alias}")
    print(
        "index is what `live --source` takes (a backend's camera number plus OpenCV's id of the backend: 200 is "
        "V4L2's camera 0); --source also takes a camera's name or part of its name, serial number or path. "
        "Resolutions and frame rates: cv2-enumerate-cameras does not report them; `live` uses the camera's default.",
        file=sys.stderr,
    )
    return 0


# `live` flags that belong to one sensor, refused with --sensor (each sensor is named by its spec).
_ONE_SENSOR_FLAGS = (
    "record",
    "record_frames",
    "ft",
    "rerun",
    "rerun_save",
    "plot",
    "rectification",
    "reference",
    "replay_fps",
    "sensor_id",
    "frame_id",
)


def _live_sensors(args: argparse.Namespace) -> dict[str, tuple[str, str]]:
    """`--sensor NAME=DEVICE.json@SOURCE` (repeatable) as `{name: (device file, source)}`."""
    for flag in ("device", "source"):
        if getattr(args, flag) is not None:
            raise ValueError(f"--sensor and --{flag} do not mix: give each sensor's device and source in its --sensor")
    for dest in _ONE_SENSOR_FLAGS:
        if getattr(args, dest) not in (None, False):
            flag = "--" + dest.replace("_", "-")
            raise ValueError(f"{flag} is for one sensor: drop it with --sensor (each sensor is named by its spec)")
    sensors: dict[str, tuple[str, str]] = {}
    for spec in args.sensor:
        name, _, rest = spec.partition("=")
        device, _, source = rest.partition("@")
        if not (name.strip() and device and source):
            raise ValueError(f"--sensor: {spec!r} is not NAME=DEVICE.json@SOURCE (e.g. left=unit_a.json@0)")
        if name in sensors:
            raise ValueError(f"--sensor: the name {name!r} is given twice")
        sensors[name] = (device, source)
    return sensors


def _live_mounts(args: argparse.Namespace, names) -> dict:
    """`--mount NAME=x,y,z,roll,pitch,yaw` (metres, degrees; repeatable) as `{name: Mount}`."""
    from ..live import Mount

    mounts: dict = {}
    for spec in args.mount or []:
        name, _, pose = spec.partition("=")
        try:
            values = [float(v) for v in pose.split(",")]
        except ValueError:
            values = []
        if len(values) != 6 or not all(math.isfinite(v) for v in values):
            raise ValueError(f"--mount: {spec!r} is not NAME=x,y,z,roll,pitch,yaw (metres, degrees)")
        if name not in names:
            raise ValueError(f"--mount: {name!r} is not a sensor (sensors: {', '.join(names)})")
        if name in mounts:
            raise ValueError(f"--mount: the sensor {name!r} is mounted twice")
        mounts[name] = Mount.from_rpy(values[:3], *(math.radians(v) for v in values[3:]))
    if "grip" in names and mounts:
        raise ValueError("--sensor: the name 'grip' is the grip records' name: call the sensor something else")
    if args.grip_frame is not None and not mounts:
        raise ValueError("--grip-frame needs --mount: the grip wrench sums the mounted sensors")
    return mounts


def _live_sinks(args: argparse.Namespace) -> list:
    """The sinks of `--sink` and `--mcap`, checked before any long work."""
    from ..live import parse_sink

    for spec in args.sink or []:
        if spec not in ("-", "stdout") and not spec.lower().startswith("udp://"):
            check_output_file(spec, argument="sink")
    mcap = [_open_mcap(args.mcap)] if args.mcap else []
    return [parse_sink(spec) for spec in (args.sink or ["-"])] + mcap


def _live_group(args: argparse.Namespace) -> int:
    """`live --sensor ...`: every sensor on its own thread, every record to the same sinks."""
    from ..calibration import load_calibrated
    from ..live import format_summary, open_sensors, WrenchFilter

    sensors = _live_sensors(args)
    mounts = _live_mounts(args, list(sensors))
    specs = {}
    for name, (device_file, source) in sensors.items():
        try:
            device, head = load_calibrated(device_file)
        except DataError as e:
            raise DataError(f"{e} (given by --sensor {name})") from None
        specs[name] = {"device": device, "source": _live_source(source), "head": head}
        if args.filter == "kalman":
            specs[name]["filter"] = WrenchFilter(args.process_noise)
    sinks = _live_sinks(args)
    group = None
    try:
        group = open_sensors(
            specs, mounts, grip_frame=args.grip_frame or "gripper", sinks=sinks, max_frames=args.max_frames
        )
        group.join()
    finally:
        if group is not None:
            group.close()
        for sink in sinks:
            sink.close()
    for name, handle in group.handles.items():
        if handle.summary is not None:
            print(f"{name}: " + format_summary(handle.summary).replace("\n", f"\n{name}: "), file=sys.stderr)
    for error in group.errors.values():
        raise error
    return 0


def _cmd_live(args: argparse.Namespace) -> int:
    from ..calibration import load_calibrated
    from ..live import format_summary, RecordStream, run_live, WrenchFilter

    if args.sensor:
        return _live_group(args)
    if args.mount or args.grip_frame is not None:
        raise ValueError(f"{'--mount' if args.mount else '--grip-frame'} needs --sensor: a grip is several sensors")
    if args.device is None:
        raise ValueError("live needs --device FIT.json (one sensor) or --sensor NAME=DEVICE.json@SOURCE (several)")
    if args.ft and not args.record_frames:
        raise ValueError("--ft logs a force/torque sensor beside recorded frames: give the folder with --record-frames")
    device, head = load_calibrated(args.device)
    source = _live_source(args.source or "sim")
    if args.record:
        check_output_file(args.record, argument="record")
    if args.record_frames:
        check_output_folder(args.record_frames, argument="record_frames")
    ft = None
    if args.ft:
        from ..live import open_ft_source

        try:
            ft = open_ft_source(args.ft)
        except (ValueError, OSError) as e:
            raise ValueError(f"--ft: {e}") from None
    sinks = _live_sinks(args)
    if args.record_frames:
        from ..live import RecordingSink

        sinks.append(RecordingSink(args.record_frames, ft=ft))
    if args.rerun or args.rerun_save:
        from ..live import RerunSink

        if args.rerun_save:
            check_output_file(args.rerun_save, argument="rerun_save")
        sinks.append(RerunSink(save=args.rerun_save) if args.rerun_save else RerunSink(spawn=True))
    records = RecordStream(
        sensor_id=args.sensor_id or "moirejax",
        frame_id=args.frame_id or "moirejax_sensor",
        filter=WrenchFilter(args.process_noise) if args.filter == "kalman" else None,
    )
    try:
        summary = run_live(
            device,
            source,
            sinks=sinks,
            max_frames=args.max_frames,
            record=args.record,
            plot=args.plot,
            rectification=args.rectification,
            reference=args.reference,
            replay_fps=args.replay_fps,
            records=records,
            head=head,
        )
    finally:
        for sink in sinks:
            sink.close()
    # The default sink writes the records to stdout; the summary goes to stderr.
    print(format_summary(summary), file=sys.stderr)
    return 0


# Frames of the empty view that `vision` averages for its reference when none is given.
VISION_REFERENCE_FRAMES = 5


def _vision_frames(spec: str):
    """The frame source of `vision --frames`: a folder of images (a dataset's `frames/`) or a video."""
    from ..inverse import check_source
    from ..live import FolderSource, VideoSource

    path = Path(spec)
    kind = check_source(path)  # no such path, a folder without images, not a video: named
    if kind == "dataset":
        return FolderSource(path / "frames")
    return FolderSource(path) if kind == "folder" else VideoSource(path)


def _bgr(frame):
    """A frame's uint8 BGR image; a gray frame repeated in the three channels."""
    import cv2
    import numpy as np

    if frame.color is not None:
        return frame.color
    return cv2.cvtColor((frame.gray * 255 + 0.5).astype(np.uint8), cv2.COLOR_GRAY2BGR)


def _frame_name(source, index: int) -> str:
    files = getattr(source, "files", None)
    return files[index].name if files and index < len(files) else f"{index:06d}"


def _vision_reference(args: argparse.Namespace, shape: tuple[int, int]):
    """The empty view for `vision` (a stack of uint8 BGR frames) and a line saying where it came from."""
    import cv2
    import numpy as np

    from ..live import FolderSource, SourceEvent, VideoSource

    if args.reference:
        path, flag = Path(args.reference), "--reference"
        if not path.exists():
            raise DataError(f"{path}: no such image, folder of images or video")
        if path.is_file():
            data = np.fromfile(path, dtype=np.uint8)
            # An image file as 8-bit BGR (gray repeated); anything else is read as a video.
            image = cv2.imdecode(data, cv2.IMREAD_COLOR) if data.size else None
            if image is not None:
                if image.shape[:2] != shape:
                    raise DataError(
                        f"{path}: reference frame is {image.shape[0]}x{image.shape[1]}, the device expects "
                        f"{shape[0]}x{shape[1]} (given by {flag})"
                    )
                return image[None], f"reference: {path}"
        source, limit = (FolderSource(path), None) if path.is_dir() else (VideoSource(path), VISION_REFERENCE_FRAMES)
        what = "{n} images of" if path.is_dir() else "the first {n} frames of"
    else:
        path, flag = Path(args.frames), "--frames"
        source, limit = _vision_frames(args.frames), VISION_REFERENCE_FRAMES
        what = "the first {n} frames of"
    frames = []
    with source:
        for item in source:
            if isinstance(item, SourceEvent):
                if item.final and not frames and item.status != "end_of_stream":
                    unreadable = item.status == "open_failed" and path.is_file()
                    raise DataError(
                        f"{path}: " + ("cannot be read as an image or a video" if unreadable else item.message)
                    )
                continue
            frames.append(_bgr(item))
            if limit is not None and len(frames) == limit:
                break
    if not frames:
        raise DataError(f"{path}: no readable frame for the reference of the empty view")
    sizes = sorted({f.shape[:2] for f in frames})
    if sizes != [shape]:
        found = ", ".join(f"{h}x{w}" for h, w in sizes)
        raise DataError(
            f"{path}: reference frames are {found}, the device expects {shape[0]}x{shape[1]} (given by {flag})"
        )
    return np.stack(frames), f"reference: mean of {what} {path}".replace("{n}", str(len(frames)))


def _vision_record(index: int, name: str, status: str, objects=(), message: str | None = None) -> dict:
    def number(value, digits: int):
        return None if value is None or not math.isfinite(value) else round(float(value), digits)

    record: dict = {"frame": index, "file": name, "mode": "vision", "status": status}
    record["objects"] = [
        {
            "x_mm": number(o.x_mm, 4),
            "y_mm": number(o.y_mm, 4),
            "yaw_deg": number(o.yaw_deg, 2),
            "size_mm": number(o.size_mm, 4),
            "hue": number(o.hue, 1),
            "colour": o.colour,
            "confidence": number(o.confidence, 3),
        }
        for o in objects
    ]
    if message:
        record["message"] = message
    return record


def _vision_line(record: dict) -> str:
    """One human-readable line per frame (without --json)."""
    head = f"frame {record['frame']} ({record['file']}): {record['status']}"
    if record.get("message"):
        return f"{head}: {record['message']}"
    parts = []
    for o in record["objects"]:
        yaw = "round" if o["yaw_deg"] is None else f"yaw {o['yaw_deg']:.1f} deg"
        parts.append(
            f"{o['colour']} object at ({o['x_mm']:.2f}, {o['y_mm']:.2f}) mm, {o['size_mm']:.2f} mm, {yaw}, "
            f"confidence {o['confidence']:.2f}"
        )
    return head + (": " + "; ".join(parts) if parts else "")


def _cmd_vision(args: argparse.Namespace) -> int:
    import cv2

    from .._fileio import atomic_write_bytes
    from ..calibration import load_calibrated
    from ..live import locate, SeeThrough, SourceEvent

    # Everything that can be checked is checked before the first frame.
    device, _ = load_calibrated(args.device)
    source = _vision_frames(args.frames)
    out = None
    if args.restore:
        out = check_output_folder(args.restore, argument="restore")
        frames_folder = Path(args.frames).resolve()
        if out.resolve() in (frames_folder, frames_folder / "frames"):
            raise ValueError("--restore must not be the --frames folder: the restored images would replace the frames")
        if out.is_dir() and any(out.iterdir()) and not args.overwrite:
            raise OutputError(f"{out}: folder is not empty; pass {{argument}} to replace it", argument="overwrite")
    shape = (device.height, device.width)
    reference, note = _vision_reference(args, shape)
    print(note, file=sys.stderr)
    see_through = SeeThrough(reference, black_level=float(device.optics.offset))
    counts: dict[str, int] = {}
    with source:
        for item in source:
            if isinstance(item, SourceEvent):
                if item.status == "corrupt_frame":
                    record = _vision_record(
                        item.index, _frame_name(source, item.index), "corrupt_frame", (), item.message
                    )
                elif item.final and item.status != "end_of_stream":
                    # A source that fails before its first frame is bad input; one that stops
                    # part way (a video shorter than it declares) is reported as far as it went.
                    if not counts:
                        raise DataError(f"{args.frames}: {item.message}")
                    warnings.warn(f"{args.frames}: {item.message}", DataWarning, stacklevel=1)
                    continue
                else:
                    continue
            else:
                name = _frame_name(source, item.index)
                image = _bgr(item)
                if image.shape[:2] != shape:
                    message = f"frame is {image.shape[0]}x{image.shape[1]}, the device expects {shape[0]}x{shape[1]}"
                    record = _vision_record(item.index, name, "wrong_size", (), message)
                else:
                    sighting = locate(image, device, see_through=see_through, height=args.height)
                    record = _vision_record(item.index, name, sighting.status, sighting.objects)
                    if out is not None:
                        ok, png = cv2.imencode(".png", see_through(image))
                        if not ok:
                            raise RuntimeError("OpenCV failed to encode a PNG image")
                        atomic_write_bytes(out / (Path(name).stem + ".png"), png.tobytes())
            counts[record["status"]] = counts.get(record["status"], 0) + 1
            print(json.dumps(record) if args.json else _vision_line(record), flush=True)
    summary = ", ".join(f"{n} {status}" for status, n in sorted(counts.items())) or "no frames"
    print(f"{sum(counts.values())} frames: {summary}" + (f"; restored images in {out}" if out else ""), file=sys.stderr)
    return 0


def _cmd_cap_removal(args: argparse.Namespace) -> int:
    from ..calibration import load_calibrated
    from ..live import plot_timeline, run_cap_removal

    check_output_file(args.out, argument="out")
    device, _ = load_calibrated(args.device) if args.device else (None, None)
    if device is None:
        from ..physics import preset

        device = preset("mid")
    rig = None
    if args.cap_offset is not None:
        from ..live import CapRig

        # The paper's green cap, seen through the sensor and aligned on before pressing.
        rig = CapRig(cap_x=args.cap_offset[0], cap_y=args.cap_offset[1], cap_rgb=(0.1, 0.7, 0.2))
    timeline = run_cap_removal(device, cycles=args.cycles, rig=rig)
    plot_timeline(args.out, timeline)
    touches = [i for i, mode in enumerate(timeline.mode) if mode == "tactile"]
    if args.cap_offset is not None and touches:
        offset = math.hypot(*timeline.cap_offset[touches[0]])
        print(f"the cap's axis was {offset:.2f} mm off the sensor's at the first touch")
    print(f"wrote {args.out}")
    return 0


def _cmd_demo(args: argparse.Namespace) -> int:
    from ._demo import run_demo

    check_output_folder(args.out, argument="out")
    return run_demo(out=args.out, smoke=args.smoke)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of the `moirejax` command (also used to document the CLI)."""
    from ..live import WRENCH_STATUSES

    parser = argparse.ArgumentParser(
        prog="moirejax",
        description="Design, simulate, calibrate and invert moire visuotactile sensors.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {importlib.metadata.version('moirejax')}")
    parser.add_argument("--debug", action="store_true", help=_DEBUG_HELP)
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    p = sub.add_parser("design", help="geometry and sensitivity table of a design")
    _add_device_arguments(p, design_flags=True)
    p.add_argument("--json", action="store_true", help="print JSON instead of a table")
    p.add_argument("--write", metavar="FILE", help="write the device JSON")
    p.add_argument("--plot", metavar="FILE.png", help="draw design maps")
    p.add_argument("--sensitivity", action="store_true", help="force sensitivities through the forward model")
    p.add_argument("--observability", action="store_true", help="per-axis Cramer-Rao bounds at a nominal load")
    p.add_argument("--observability-plot", metavar="FILE.png", help="per-axis bounds over p1 x p2 and angle")
    p.add_argument(
        "--optimise", action="store_true", help="minimise the worst-axis relative bound (--write saves the optimum)"
    )
    p.add_argument("--steps", type=_positive_int, default=300, help="optimiser steps")
    p.add_argument("--min-pitch", type=float, default=0.15, help="smallest pitch the laser can cut, mm")
    p.add_argument("--min-fringes", type=float, default=4.0, help="fewest moire fringes across the frame")
    p.add_argument(
        "--max-phase-range",
        type=float,
        default=0.0,
        help="largest fringe phase change of any axis over its range, rad (0: no limit)",
    )
    p.add_argument(
        "--estimator",
        choices=("bands", "pixels"),
        default="bands",
        help="whose bound --optimise and --observability-plot use: the band inversion of `invert`, "
        "or an efficient whole-frame fit",
    )
    p.set_defaults(run=_cmd_design)

    p = sub.add_parser("simulate", help="render a dataset of a simulated unit under a load protocol")
    _add_device_arguments(p)
    p.add_argument(
        "--protocol",
        choices=["paper", "mixed", "sequence", "none", "shapes", "vision"],
        default="paper",
        help="paper: isolated axes; mixed: combined loads; sequence: a press-twist-slide-release video; "
        "none: no contact; shapes: spheres, flat and square punches, rings, lines and two fingertips; "
        "vision: no contact, colour frames of discs, rings, rectangles and pictures 0-30 mm above the pad, "
        "with their grating-free views (grating_free/) and poses (contact.csv)",
    )
    p.add_argument(
        "--max-force",
        type=_positive_float,
        metavar="N",
        help="largest normal force of --protocol shapes (default the paper's 1.2 N; grasps reach 10 N), "
        "with shear and twist scaled to it",
    )
    p.add_argument("--n", type=_positive_int, default=500, help="number of frames")
    p.add_argument("--out", required=True, metavar="DIR", help="dataset folder to write")
    p.add_argument("--seed", type=int, default=0, help="draws the unit's deviations, the loads and the noise")
    p.add_argument("--fidelity", choices=["model", "high"], default="high")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset in DIR")
    p.set_defaults(run=_cmd_simulate)

    p = sub.add_parser("import", help="turn image files plus a force/torque CSV into a dataset")
    p.add_argument("--frames", required=True, metavar="DIR", help="folder of images")
    p.add_argument(
        "--wrench",
        metavar="CSV",
        help="columns frame,fx,fy,fz,tx,ty,tz[,t][,contact]; with --ft only frame, t and contact are read, "
        "and without it the frames are the images in DIR in name order",
    )
    p.add_argument(
        "--ft",
        metavar="CSV",
        help="a force/torque sensor's log on its own clock, any rate: a time column (t, time or timestamp; s) "
        "and fx,fy,fz,tx,ty,tz; its wrench is interpolated to each frame's time, frames outside it are dropped",
    )
    p.add_argument(
        "--align",
        action="store_true",
        help="estimate the clock offset of --ft by cross-correlating its |F| with the frames' fringe change "
        "(without it the log runs on the frames' clock)",
    )
    p.add_argument(
        "--max-offset",
        type=_non_negative_float,
        metavar="S",
        help="with --align, the largest clock offset considered, s (default: any at which the two overlap)",
    )
    p.add_argument(
        "--fps",
        type=_positive_float,
        help="frame rate, recorded in the dataset; with --ft, frames without a t are at index / FPS",
    )
    p.add_argument("--device", required=True, metavar="FILE", help="device JSON of the unit")
    p.add_argument("--out", required=True, metavar="DATASET")
    p.add_argument("--skip-bad", action="store_true", help="skip missing or unreadable frames (listed)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing dataset in DATASET")
    p.set_defaults(run=_cmd_import)

    p = sub.add_parser("invert", help="turn every frame of a recording into a wrench with uncertainty")
    p.add_argument("--device", required=True, metavar="FILE", help="device JSON (nominal or calibrated)")
    p.add_argument("--data", required=True, metavar="SOURCE", help="dataset folder, video file or folder of frames")
    p.add_argument("--out", required=True, metavar="CSV", help="output wrench CSV")
    p.add_argument("--reference", metavar="IMAGE", help="no-contact frame of this unit (default: from the dataset)")
    p.add_argument(
        "--batch", type=_positive_int, default=1, help="invert N frames at once, N >= 1 (throughput; no warm start)"
    )
    p.add_argument(
        "--segment",
        type=_positive_int,
        metavar="N",
        help="start the stream cold every N frames (independent segments; default: one stream, or 256 with "
        "--engine dask)",
    )
    p.add_argument(
        "--engine",
        choices=("local", "dask"),
        default="local",
        help="local: this process; dask: segments on the workers of a Dask cluster (needs moirejax[cluster]; "
        "the same numbers as local with the same --segment)",
    )
    p.add_argument("--workers", type=_positive_int, default=2, help="worker processes of the local Dask cluster")
    p.add_argument("--scheduler", metavar="ADDRESS", help="a running Dask scheduler (tcp://host:8786) instead")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.add_argument(
        "--mcap",
        metavar="OUT.mcap",
        help="also write ROS 2 messages of every frame to MCAP: its record with its status, its wrench "
        f"(statuses {', '.join(WRENCH_STATUSES)}), the frame and the pressure map",
    )
    p.add_argument(
        "--fps",
        type=_positive_float,
        help="frame rate of the --mcap stamps (default: the dataset's t column, else the recording's frame rate, "
        "else one frame a second)",
    )
    p.add_argument("--sensor-id", default="moirejax", help="the --mcap records' sensor name")
    p.add_argument("--frame-id", default="moirejax_sensor", help="ROS frame name of the --mcap wrenches")
    p.add_argument(
        "--maps",
        metavar="OUT.h5",
        help="also write the traction maps (shear x, y and pressure, Pa) of every frame to one HDF5 file, a frame "
        "to a chunk, with the centre of pressure and contact area",
    )
    p.add_argument(
        "--plot",
        metavar="DIR",
        help="also draw the wrench's timeline and, for the frames worth a look, pressure, shear and where the "
        "reading leaves the fringes unexplained",
    )
    p.add_argument("--plot-frames", type=_positive_int, metavar="N", help="frames --plot draws (default 6)")
    p.set_defaults(run=_cmd_invert)

    p = sub.add_parser("calibrate", help="fit a unit's physical parameters and residual head to a dataset")
    p.add_argument("--device", metavar="NOMINAL", help="nominal device JSON (default: the dataset's)")
    p.add_argument("--data", required=True, metavar="DATASET")
    p.add_argument(
        "--out",
        required=True,
        metavar="FIT.json",
        help="fitted device; head and report go beside it, and the work done so far in FIT.json.parts/ "
        "(a rerun after an interruption resumes from it)",
    )
    p.add_argument("--max-frames", type=_positive_int, default=500)
    p.add_argument(
        "--recipe",
        default="unit",
        metavar="NAME|FILE",
        help="what to fit: a named recipe of moirejax/fits/recipes/ or a JSON file",
    )
    p.add_argument(
        "--rounds", type=_positive_int, help="alternations of parameter and latent solves (default: the recipe's)"
    )
    p.add_argument(
        "--force",
        action="store_true",
        help="write a calibration its frames cannot identify (identical frames, no load), flagged, instead of refusing",
    )
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(run=_cmd_calibrate)

    p = sub.add_parser("evaluate", help="accuracy of a device on a dataset: metrics.json and plots")
    p.add_argument("--device", required=True, metavar="FIT.json")
    p.add_argument("--data", required=True, metavar="DATASET")
    p.add_argument("--out", required=True, metavar="DIR")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(run=_cmd_evaluate)

    p = sub.add_parser("transfer", help="move a calibration to a new unit with a handful of frames")
    p.add_argument("--from", dest="from_", required=True, metavar="FIT.json")
    p.add_argument("--data", required=True, metavar="DATASET", help="frames of the new unit")
    p.add_argument("--out", required=True, metavar="FIT_B.json")
    p.add_argument("--max-frames", type=_positive_int, default=20)
    p.add_argument("--recipe", default="transfer", metavar="NAME|FILE", help="what to refit (default: transfer)")
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(run=_cmd_transfer)

    p = sub.add_parser("live", help="stream wrenches from a camera, video or the simulated sensor")
    p.add_argument("--device", metavar="FIT.json", help="the unit (one sensor; required unless --sensor)")
    p.add_argument(
        "--source",
        help="sim (default), a camera index, a camera's name or part of its name, serial number or path (see "
        "`moirejax cameras`), a video file or URL, or a folder of frames",
    )
    p.add_argument(
        "--sensor",
        action="append",
        metavar="NAME=DEVICE.json@SOURCE",
        help="one of several sensors, each on its own thread, its records named NAME (SOURCE as --source takes); "
        "repeatable, instead of --device and --source. Every record goes to the sinks; --mcap gets no frames",
    )
    p.add_argument(
        "--mount",
        action="append",
        metavar="NAME=x,y,z,roll,pitch,yaw",
        help="where sensor NAME's pad sits on the gripper: its origin (m) and its axes turned by roll, pitch, yaw "
        "(degrees, about the fixed gripper axes); repeatable. Adds grip records, sensor_id grip, the wrench of the "
        "mounted pads together in the gripper frame",
    )
    p.add_argument("--grip-frame", metavar="NAME", help="frame name of the grip records (default: gripper)")
    p.add_argument(
        "--sink",
        action="append",
        metavar="SPEC",
        help="- (stdout, default), a file path, or udp://host:port; repeatable",
    )
    p.add_argument("--max-frames", type=_positive_int, help="stop after N frames")
    p.add_argument("--record", metavar="OUT.mp4", help="write an annotated video")
    p.add_argument(
        "--record-frames",
        metavar="DIR",
        help="also write the raw frames with their capture times and contact flags, a recording "
        "`moirejax import --ft FT.csv --align` turns into a calibration dataset",
    )
    p.add_argument(
        "--ft",
        metavar="SPEC",
        help="with --record-frames, also log a reference force/torque sensor to DIR/ft.csv: udp://HOST:PORT "
        "(text lines t,fx,fy,fz,tx,ty,tz or fx..tz) or netft://HOST[?cpf=N&cpt=N] (an ATI Net F/T box)",
    )
    p.add_argument("--rerun", action="store_true", help="show the stream in a Rerun viewer (needs moirejax[viewer])")
    p.add_argument("--rerun-save", metavar="OUT.rrd", help="write the stream to a Rerun file (needs moirejax[viewer])")
    p.add_argument("--plot", action="store_true", help="live strip chart when a display exists")
    p.add_argument("--rectification", metavar="RECT.json", help="pixel-to-mm rectification of the camera")
    p.add_argument("--reference", metavar="IMAGE", help="no-contact frame (default: the first frames of the source)")
    p.add_argument(
        "--replay-fps", type=float, metavar="FPS", help="play a video file at this rate, as a camera would deliver it"
    )
    p.add_argument("--mcap", metavar="OUT.mcap", help="also write ROS 2 messages (wrench, frames, pressure) to MCAP")
    p.add_argument("--sensor-id", help="the records' sensor name (default: moirejax)")
    p.add_argument("--frame-id", help="ROS frame name of the wrench (default: moirejax_sensor)")
    p.add_argument(
        "--filter",
        choices=("none", "kalman"),
        default="none",
        help="kalman: filter in-contact wrenches with each frame's covariance",
    )
    p.add_argument(
        "--process-noise",
        type=float,
        default=0.05,
        metavar="FRACTION",
        help="the Kalman filter's load change per frame, as a fraction of each axis's range",
    )
    p.set_defaults(run=_cmd_live)

    p = sub.add_parser("cameras", help="list the cameras attached, with the index and name `live --source` takes")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    p.set_defaults(run=_cmd_cameras)

    p = sub.add_parser("vision", help="see through the sensor: restored images and objects located before contact")
    p.add_argument("--device", required=True, metavar="FILE", help="device JSON of the unit (nominal or calibrated)")
    p.add_argument(
        "--frames", required=True, metavar="DIR|VIDEO", help="colour frames, rectified: a folder of images or a video"
    )
    p.add_argument(
        "--reference",
        metavar="DIR|FILE",
        help="the empty view (nothing above the sensor, no contact): an image, a folder of images (averaged) or "
        f"a video (its first {VISION_REFERENCE_FRAMES} frames); default: the first {VISION_REFERENCE_FRAMES} "
        "frames of --frames, which must then show the empty view",
    )
    p.add_argument(
        "--height",
        type=_non_negative_float,
        metavar="MM",
        help="the objects' height above the contact surface, for their scale (default: 0, on the surface)",
    )
    p.add_argument("--restore", metavar="OUTDIR", help="write each restored image there, as PNG named like its frame")
    p.add_argument("--overwrite", action="store_true", help="write into a non-empty --restore folder")
    p.add_argument(
        "--json",
        action="store_true",
        help="print one JSON object per frame instead of a line of text: frame, file, mode (vision), status (ok, "
        "empty, dark, saturated, corrupt_frame, wrong_size) and objects, each with x_mm, y_mm (wrench frame), "
        "yaw_deg (null when round), size_mm, hue, colour and confidence",
    )
    p.set_defaults(run=_cmd_vision)

    p = sub.add_parser(
        "cap-removal", help="the paper's cap-removal cycle against the simulated sensor, with a timeline plot"
    )
    p.add_argument("--device", metavar="FIT.json", help="device (default: the Mid preset)")
    p.add_argument("--cycles", type=_positive_int, default=3)
    p.add_argument(
        "--cap-offset",
        nargs=2,
        type=float,
        metavar=("X_MM", "Y_MM"),
        help="a green cap this far off the sensor's axis, seen through it and aligned on before pressing",
    )
    p.add_argument("--out", default="cap_removal.png", metavar="FILE.png")
    p.set_defaults(run=_cmd_cap_removal)

    p = sub.add_parser("demo", help="the whole product on an embedded default, no hardware needed")
    p.add_argument("--out", default="moirejax-demo", help="output folder (default: moirejax-demo)")
    p.add_argument("--smoke", action="store_true", help="tiny sizes, for tests")
    p.set_defaults(run=_cmd_demo)
    for command in sub.choices.values():
        # SUPPRESS: given before the command or after it, `--debug` is seen either way.
        command.add_argument("--debug", action="store_true", default=argparse.SUPPRESS, help=_DEBUG_HELP)
    return parser


_DEBUG_HELP = "on an error, print the Python traceback too (see docs/errors.md for the exit codes)"


def use_compilation_cache() -> str | None:
    """Keep compiled programs on disk between runs of the command; returns the folder used.

    Compiling the inversion takes 10-20 s on a laptop CPU, paid again by every `invert`,
    `live` or `calibrate` that meets the same design and frame size, and a command also
    compiles a few hundred small programs (the arithmetic of setting up an inverter or a
    calibration), each below JAX's default threshold of a second for caching but together
    several seconds. JAX's persistent cache, kept here for every program whatever its
    compile time unless `JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS` says otherwise, saves
    both. The folder is the user's own `JAX_COMPILATION_CACHE_DIR` if
    set, else `$XDG_CACHE_HOME/moirejax/jax` (`~/.cache/moirejax/jax`);
    `MOIREJAX_COMPILATION_CACHE=0` turns it off. Call it before anything is compiled.
    """
    import jax

    if os.environ.get("MOIREJAX_COMPILATION_CACHE", "1") == "0":
        return None
    if "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS" not in os.environ:
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    if jax.config.jax_compilation_cache_dir:
        return jax.config.jax_compilation_cache_dir
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    folder = os.path.join(base, "moirejax", "jax")
    jax.config.update("jax_compilation_cache_dir", folder)
    return folder


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `moirejax` command. Returns the process exit status.

    The exit codes and the error policy are in `moirejax/cli/_errors.py` and
    docs/errors.md: 0 success, 1 internal error, 2 usage, 3 bad input, 4 unwritable
    output, 130 interrupted; one line per failure, a traceback only with `--debug`.
    """
    parser = build_parser()
    # A usage error exits here with argparse's status 2 and its usage line.
    args = parser.parse_args(argv)
    use_compilation_cache()
    return run_command(args.command, args.run, args)


if __name__ == "__main__":
    sys.exit(main())
