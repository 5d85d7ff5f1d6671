"""The pictures of the vision-mode guide: a raw see-through frame, its restoration, and objects located.

    python benchmarks/vision_figures.py            # writes docs/images/vision_*.png

A 256 x 256 Mid unit (a 16 mm field at 16 px/mm) with every non-ideality `mj.render_scene`
models. `vision_raw.png` is the frame the camera delivers of a picture 5 mm above the pad
(scikit-image's `chelsea`), `vision_restored.png` the same frame restored by
`mj.live.SeeThrough` from eight frames of the empty view, and `vision_located.png` three
restored frames side by side, a green cap 12 mm up, an orange disc on the pad and a blue bar
20 mm up, each with what `mj.live.locate` reports drawn over it: the outline at the located
centre and size (and the long axis where it has one) in white, and the true centre as a black
cross. The see-through image is dim (the crossed gratings pass about a tenth of the light), so
every picture is shown with the same gain, which maps the brightest grating-free value of the
empty view to 90% of full scale.
"""

import argparse
import math
from pathlib import Path

import cv2
import jax
import numpy as np

import moirejax as mj


OUT = Path(__file__).resolve().parents[1] / "docs" / "images"
SCENES = (
    (mj.scene_ring(2.0, -1.5, 12.0, 7.0, height=12.0, rgb=(0.1, 0.7, 0.2)), 12.0),
    (mj.scene_disc(-2.5, 2.0, 7.0, height=0.0, rgb=(0.9, 0.45, 0.05)), 0.0),
    (mj.scene_rectangle(1.0, 1.5, 20.0, 6.0, yaw_deg=30.0, height=20.0, rgb=(0.2, 0.3, 0.9)), 20.0),
)


def _display(image: np.ndarray, gain: float) -> np.ndarray:
    return np.clip(np.round(np.asarray(image, np.float64) * gain * 255), 0, 255).astype(np.uint8)


def _to_pixel(device: mj.Device, x_mm: float, y_mm: float, mm_per_px: float) -> tuple[int, int]:
    col = (device.width - 1) / 2 + x_mm / mm_per_px
    row = (device.height - 1) / 2 - y_mm / mm_per_px
    return round(col), round(row)


def _draw(device: mj.Device, image: np.ndarray, sighting, scene: mj.SceneObject, height: float) -> np.ndarray:
    """The located objects (white) and the true centre (black cross) over a display image."""
    mm_per_px = float(mj.scene_magnification(device, height)) / float(device.px_per_mm)
    canvas = image.copy()
    for seen in sighting.objects:
        centre = _to_pixel(device, seen.x_mm, seen.y_mm, mm_per_px)
        radius = round(seen.size_mm / 2 / mm_per_px)
        if seen.yaw_deg is None:
            cv2.circle(canvas, centre, radius, (255, 255, 255), 1, cv2.LINE_AA)
        else:
            # Image rows run down: the wrench frame's yaw is the image angle negated.
            dx, dy = radius * math.cos(math.radians(seen.yaw_deg)), -radius * math.sin(math.radians(seen.yaw_deg))
            ends = [(round(centre[0] + s * dx), round(centre[1] + s * dy)) for s in (-1, 1)]
            cv2.line(canvas, ends[0], ends[1], (255, 255, 255), 1, cv2.LINE_AA)
        cv2.drawMarker(canvas, centre, (255, 255, 255), cv2.MARKER_TILTED_CROSS, 7, 1)
    truth = _to_pixel(device, float(scene.x), float(scene.y), mm_per_px)
    cv2.drawMarker(canvas, truth, (0, 0, 0), cv2.MARKER_CROSS, 9, 1)
    return canvas


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=OUT, help="folder for the PNGs")
    args = parser.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    device = mj.preset("mid", height=256, width=256)
    key = jax.random.PRNGKey(0)
    reference = np.asarray(mj.empty_scene_reference(jax.random.fold_in(key, 0), device, frames=8))
    see_through = mj.live.SeeThrough(reference, black_level=float(device.optics.offset))
    empty = np.asarray(mj.render_scene(jax.random.fold_in(key, 1), device, None).grating_free)
    gain = 0.9 / float(empty.max())

    picture = mj.render_scene(jax.random.fold_in(key, 2), device, mj.scene_texture("chelsea", 40.0, height=5.0))
    frame = np.asarray(picture.frame, np.float32)
    written = {
        "vision_raw.png": _display(frame, gain),
        "vision_restored.png": _display(see_through(frame), gain),
    }
    panels = []
    for i, (scene, height) in enumerate(SCENES):
        frame = np.asarray(mj.render_scene(jax.random.fold_in(key, 10 + i), device, scene).frame, np.float32)
        sighting = mj.live.locate(frame, device, see_through=see_through, height=height)
        panels.append(_draw(device, _display(see_through(frame), gain), sighting, scene, height))
        for seen in sighting.objects:
            print(
                f"{scene.shape} {height:.0f} mm up: located ({seen.x_mm:+.2f}, {seen.y_mm:+.2f}) mm, "
                f"true ({float(scene.x):+.2f}, {float(scene.y):+.2f}) mm, size {seen.size_mm:.2f} mm, {seen.colour}"
            )
    gap = np.full((device.height, 4, 3), 255, np.uint8)
    written["vision_located.png"] = np.concatenate([panels[0], gap, panels[1], gap, panels[2]], axis=1)
    for name, image in written.items():
        ok, png = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
        assert ok
        mj.atomic_write_bytes(args.out / name, png.tobytes())
        print(f"wrote {args.out / name} ({len(png) // 1024} kB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
