"""Vision mode on simulated see-through frames: restoration quality, localisation before contact, speed.

    python benchmarks/vision.py            # summary
    python benchmarks/vision.py --json     # one JSON object

Every frame is rendered by `mj.render_scene` with every non-ideality it models on
(parallax, defocus of the far grating and of the object by its height, binary gratings'
harmonics aliased by 2x2 supersampling, PSF, vignetting, shot and read noise, 8 bits, colour)
on a 512 x 512 Mid unit. Restoration (`mj.live.SeeThrough`, from a reference of eight empty
frames) and the notch filter vision mode used before it (`mj.live.make_colour_probe(...).notch`)
are scored against the grating-free render with scikit-image's PSNR and SSIM: `psnr_db` and
`ssim` at the 8-bit full scale (data range 1), `*_scene_range_*` with the data range of the
grating-free image itself (the see-through image is dim: the crossed gratings pass about a
tenth of the light, so the full-scale numbers flatter both methods). Medians over the shipped
textures. Localisation: discs, rings (caps) and rectangles at 0-30 mm above the surface at
random poses, located with their height known; centre errors in the object plane (mm), yaw
errors of rectangles (degrees, modulo 180). Timings are wall clock of `locate` with the
`SeeThrough` (restore and locate) per 512 x 512 frame, against the notch filter alone measured
in the same run (the floor); timings are never asserted.

Residual energy at the pattern's frequencies: of the error image (method minus grating-free
render), the spectral power summed over B, G, R within `RESIDUAL_BINS` frequency bins of each
moiré wavevector and its second harmonic (`residual_moire_db`), and of each grating's
wavevectors, the upper one's seen through parallax, with their harmonics up to the third,
aliased as the camera samples them (`residual_grating_db`); in dB against the same power of
the raw frame's error, so 0 dB leaves the pattern as it was and -20 dB removes 99% of its power
there. Medians over the textures, for the restoration and the notch filter alike.

The issue's other vision numbers come from the two benchmarks that train or render for
minutes: `classifier_drop_pp` from `benchmarks/vision_classifier.py`, and `onset_frames`,
`release_frames` and `false_switches_per_1000` from `benchmarks/gate_switching.py`; the JSON
names them under `measured_by`.
"""

import argparse
import json
import os
import platform
import sys
import time

import jax
import numpy as np
from skimage.metrics import peak_signal_noise_ratio, structural_similarity

import moirejax as mj


HEIGHTS = (0.0, 10.0, 20.0, 30.0)
COLOURS = ((0.1, 0.7, 0.2), (0.9, 0.5, 0.1), (0.2, 0.3, 0.9), (0.8, 0.1, 0.1))
# Radius (frequency bins of the larger side) around each pattern frequency whose power counts.
RESIDUAL_BINS = 2.0
# The vision numbers of the issue that other benchmarks measure.
MEASURED_BY = {
    "classifier_drop_pp": "benchmarks/vision_classifier.py",
    "onset_frames": "benchmarks/gate_switching.py",
    "release_frames": "benchmarks/gate_switching.py",
    "false_switches_per_1000": "benchmarks/gate_switching.py",
}


def _pattern_mask(device: mj.Device, wavevectors: np.ndarray, harmonics: int) -> np.ndarray:
    """`(h, w)` boolean mask of the FFT bins within `RESIDUAL_BINS` of every harmonic of `wavevectors`
    (rad/mm, y up) and of its mirror, aliased into the sampled spectrum."""
    h, w = device.height, device.width
    px_per_mm = float(device.px_per_mm)
    rows = np.fft.fftfreq(h)[:, None] * h
    cols = np.fft.fftfreq(w)[None, :] * w
    mask = np.zeros((h, w), bool)
    for kx, ky in np.asarray(wavevectors, np.float64).reshape(-1, 2):
        for m in range(1, harmonics + 1):
            for sign in (1, -1):
                # Cycles per pixel, as bins; image rows run down, so +ky is a negative row frequency.
                col = sign * m * kx / (2 * np.pi * px_per_mm) * w
                row = -sign * m * ky / (2 * np.pi * px_per_mm) * h
                d_col = (cols - col + w / 2) % w - w / 2
                d_row = (rows - row + h / 2) % h - h / 2
                mask |= np.hypot(d_col * max(h, w) / w, d_row * max(h, w) / h) <= RESIDUAL_BINS
    return mask


def _pattern_power(error: np.ndarray, mask: np.ndarray) -> float:
    """Spectral power of a `(h, w, 3)` error image inside `mask`, summed over the channels."""
    spectrum = np.fft.fft2(error.astype(np.float64), axes=(0, 1))
    return float(np.sum(np.abs(spectrum[mask]) ** 2))


def _residual_db(masks: dict[str, np.ndarray], truth: np.ndarray, frame: np.ndarray, image: np.ndarray) -> dict:
    """Power of `image - truth` at each pattern's frequencies, in dB against that of `frame - truth`."""
    return {
        f"residual_{name}_db": 10 * np.log10(_pattern_power(image - truth, mask) / _pattern_power(frame - truth, mask))
        for name, mask in masks.items()
    }


def _scores(truth: np.ndarray, image: np.ndarray) -> dict[str, float]:
    scene_range = float(truth.max() - truth.min())
    return {
        "psnr_db": float(peak_signal_noise_ratio(truth, image, data_range=1.0)),
        "ssim": float(structural_similarity(truth, image, data_range=1.0, channel_axis=-1)),
        "psnr_scene_range_db": float(peak_signal_noise_ratio(truth, image, data_range=scene_range)),
        "ssim_scene_range": float(structural_similarity(truth, image, data_range=scene_range, channel_axis=-1)),
    }


def _objects(rng: np.random.Generator, per_height: int) -> list:
    scenes = []
    for height in HEIGHTS:
        # The view at this height spans (Z + a + h) / Z times the rectified field: keep the object inside.
        reach = 6.0 * (15.0 + height) / 12.0
        for i in range(per_height):
            x, y = rng.uniform(-reach, reach, 2)
            rgb = COLOURS[i % len(COLOURS)]
            diameter = rng.uniform(8.0, 14.0) * (12.0 + height) / 12.0
            scenes.append(mj.scene_disc(x, y, diameter, height=height, rgb=rgb))
            scenes.append(mj.scene_ring(x, y, diameter, 0.55 * diameter, height=height, rgb=rgb))
            yaw = rng.uniform(-90.0, 90.0)
            scenes.append(mj.scene_rectangle(x, y, diameter * 1.4, diameter * 0.5, yaw_deg=yaw, height=height, rgb=rgb))
    return scenes


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.add_argument("--per-height", type=int, default=3, help="poses of each shape per height")
    parser.add_argument("--empty", type=int, default=10, help="empty frames checked for false objects")
    parser.add_argument("--repeats", type=int, default=50, help="timed restore+locate calls")
    args = parser.parse_args(argv)

    device = mj.preset("mid")
    black = float(device.optics.offset)
    key = jax.random.PRNGKey(0)
    reference = np.asarray(mj.empty_scene_reference(jax.random.fold_in(key, 0), device, frames=8))
    see_through = mj.live.SeeThrough(reference, black_level=black)
    notch = mj.live.make_colour_probe(device).notch
    assert notch is not None

    masks = {
        "moire": _pattern_mask(device, np.asarray(device.moire_wavevectors()), 2),
        "grating": _pattern_mask(
            device,
            np.concatenate(
                [np.asarray(device.apparent_upper_wavevectors()), np.asarray(device.reference_wavevectors())]
            ),
            3,
        ),
    }
    restoration = []
    for i, name in enumerate(mj.SCENE_TEXTURES):
        scene = mj.scene_texture(name, 80.0, height=5.0)
        rendered = mj.render_scene(jax.random.fold_in(key, 100 + i), device, scene)
        frame, truth = np.asarray(rendered.frame, np.float32), np.asarray(rendered.grating_free)
        restored, notched = see_through(frame), notch(frame)
        restoration.append(
            {
                "scene": name,
                "restored": {**_scores(truth, restored), **_residual_db(masks, truth, frame, restored)},
                "notch": {**_scores(truth, notched), **_residual_db(masks, truth, frame, notched)},
            }
        )

    centre, size, yaw = [], [], []
    missed = 0
    for i, scene in enumerate(_objects(np.random.default_rng(1), args.per_height)):
        frame = np.asarray(mj.render_scene(jax.random.fold_in(key, 200 + i), device, scene).frame, np.float32)
        sighting = mj.live.locate(frame, device, see_through=see_through, height=float(scene.height))
        if not sighting.objects:
            missed += 1
            continue
        seen = sighting.objects[0]
        centre.append(float(np.hypot(seen.x_mm - float(scene.x), seen.y_mm - float(scene.y))))
        size.append(abs(seen.size_mm - float(scene.length)))
        if scene.shape == "rectangle":
            yaw.append(
                abs((seen.yaw_deg - float(scene.yaw_deg) + 90.0) % 180.0 - 90.0) if seen.yaw_deg is not None else 90.0
            )

    false_objects = 0
    for i in range(args.empty):
        frame = np.asarray(mj.render_scene(jax.random.fold_in(key, 300 + i), device, None).frame, np.float32)
        false_objects += len(mj.live.locate(frame, device, see_through=see_through).objects)
    statuses = {
        name: mj.live.locate(
            np.full((device.height, device.width, 3), value, np.float32), device, see_through=see_through
        ).status
        for name, value in (("dark", 0.0), ("saturated", 1.0))
    }

    timing_frame = np.asarray(
        mj.render_scene(jax.random.fold_in(key, 400), device, mj.scene_disc(3.0, -2.0, 12.0, height=10.0)).frame,
        np.float32,
    )

    def timed(fn) -> dict[str, float]:
        fn()
        times = []
        for _ in range(args.repeats):
            start = time.perf_counter()
            fn()
            times.append(1e3 * (time.perf_counter() - start))
        return {"median": float(np.median(times)), "p90": float(np.percentile(times, 90))}

    ms_per_frame = timed(lambda: mj.live.locate(timing_frame, device, see_through=see_through, height=10.0))
    restore_ms = timed(lambda: see_through(timing_frame))
    notch_ms = timed(lambda: notch(timing_frame))

    def median(method: str, score: str) -> float:
        return float(np.median([r[method][score] for r in restoration]))

    result = {
        "backend": jax.default_backend(),
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "frame": [device.height, device.width],
        "psnr_db": median("restored", "psnr_db"),
        "ssim": median("restored", "ssim"),
        "notch_psnr_db": median("notch", "psnr_db"),
        "notch_ssim": median("notch", "ssim"),
        "psnr_scene_range_db": median("restored", "psnr_scene_range_db"),
        "ssim_scene_range": median("restored", "ssim_scene_range"),
        "notch_psnr_scene_range_db": median("notch", "psnr_scene_range_db"),
        "notch_ssim_scene_range": median("notch", "ssim_scene_range"),
        "residual_moire_db": median("restored", "residual_moire_db"),
        "residual_grating_db": median("restored", "residual_grating_db"),
        "notch_residual_moire_db": median("notch", "residual_moire_db"),
        "notch_residual_grating_db": median("notch", "residual_grating_db"),
        "restoration": restoration,
        "heights_mm": list(HEIGHTS),
        "objects": len(centre) + missed,
        "objects_missed": missed,
        "centre_error_mm": float(np.median(centre)),
        "centre_error_p90_mm": float(np.percentile(centre, 90)),
        "size_error_mm": float(np.median(size)),
        "yaw_error_deg": float(np.median(yaw)),
        "yaw_error_p90_deg": float(np.percentile(yaw, 90)),
        "empty_frames": args.empty,
        "empty_frame_false_objects": false_objects,
        "dark_frame_status": statuses["dark"],
        "saturated_frame_status": statuses["saturated"],
        "ms_per_frame": ms_per_frame,
        "restore_ms": restore_ms,
        "floor_notch_ms": notch_ms,
        "measured_by": MEASURED_BY,
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"restoration (median of {len(restoration)} textures), full scale / scene range:")
    print(
        f"  restored  PSNR {result['psnr_db']:.1f} / {result['psnr_scene_range_db']:.1f} dB  SSIM {result['ssim']:.3f}"
    )
    print(
        f"  notch     PSNR {result['notch_psnr_db']:.1f} / {result['notch_psnr_scene_range_db']:.1f} dB  "
        f"SSIM {result['notch_ssim']:.3f}"
    )
    print(
        f"residual power at the moire / grating frequencies, against the raw frame's: restored "
        f"{result['residual_moire_db']:.1f} / {result['residual_grating_db']:.1f} dB, notch "
        f"{result['notch_residual_moire_db']:.1f} / {result['notch_residual_grating_db']:.1f} dB"
    )
    print(
        f"localisation of {result['objects']} objects ({missed} missed): centre {result['centre_error_mm']:.3f} mm "
        f"(p90 {result['centre_error_p90_mm']:.3f}), yaw {result['yaw_error_deg']:.2f} deg, size {result['size_error_mm']:.3f} mm"
    )
    print(
        f"false objects on {args.empty} empty frames: {false_objects}; dark -> {statuses['dark']}, saturated -> {statuses['saturated']}"
    )
    print(
        f"restore+locate {ms_per_frame['median']:.1f} ms (p90 {ms_per_frame['p90']:.1f}); "
        f"restore {restore_ms['median']:.1f} ms; notch floor {notch_ms['median']:.1f} ms"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
