"""A classifier of your own through vision mode: a small CNN tells the shipped textures apart in see-through frames.

    python benchmarks/vision_classifier.py            # summary
    python benchmarks/vision_classifier.py --json     # one JSON object

The worked example of `moirejax.live.classify`, with the public API only. Each of the
textures that ship in scikit-image (`mj.SCENE_TEXTURES`) is a 40 mm wide picture placed at
random poses above a 256 x 256 Mid unit (16 mm square at 16 px/mm): centre within 3 mm of
the axis, any yaw, 0 to 20 mm above the pad. `mj.render_scene` renders each with every
non-ideality it models, and gives its grating-free view. Frames are shrunk to 64 x 64
(area average) before the network: three 3 x 3 convolutions with max pooling, a global
average and a linear layer (`equinox`), trained with Adam (`optax`) on the grating-free
views of `--frames` poses per texture.

Its accuracy on `--test-frames` other poses per texture is reported for the same frames
seen four ways: grating-free (what it was trained on), restored (`live.classify` with a
`live.SeeThrough` built from eight frames of the empty view), raw (the fringes left in),
and notch-filtered (`live.MoireNotch` on the moiré and carrier wavevectors, its width in
rad/mm that of `live.make_colour_probe` on the 512 x 512 frame; `make_colour_probe` on this
256 x 256 frame, whose notch is as many frequency bins wide and so twice as wide in rad/mm,
is `notch_default`). `classifier_drop_pp` is accuracy(grating-free) - accuracy(restored)
in percentage points. A second network, trained on restored frames, is scored the same way
(`trained_on_restored`). A frame that `classify` does not pass to the model (dark, saturated,
empty) counts as wrong. One test pose is 1 / (textures x test-frames) of accuracy: raise
`--test-frames` for finer numbers. Where the accuracy saturates, the frames are compared in
pairs with the grating-free view of the same pose: `agreement` (the same answer) and
`probability_shift` (the mean total-variation distance between the softmax of the two
logits, 0 to 1). Timings are wall clock and never asserted.
"""

import argparse
import json
import os
import platform
import sys
import time

import cv2
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax

import moirejax as mj
import moirejax.live as live


TEXTURE_MM = 40.0
REACH_MM = 3.0
MAX_HEIGHT_MM = 20.0
# The notch width of `make_colour_probe`, in frequency bins of a 512-pixel frame.
NOTCH_BINS_AT_512 = 2.5


class SmallCNN(eqx.Module):
    """Three 3 x 3 convolutions, each followed by ReLU and 2 x 2 max pooling; a global average; a linear read-out."""

    convs: list[eqx.nn.Conv2d]
    pool: eqx.nn.MaxPool2d
    head: eqx.nn.Linear

    def __init__(self, classes: int, key):
        keys = jax.random.split(key, 4)
        widths = (3, 16, 32, 32)
        self.convs = [eqx.nn.Conv2d(a, b, 3, padding=1, key=k) for a, b, k in zip(widths[:-1], widths[1:], keys)]
        self.pool = eqx.nn.MaxPool2d(2, 2)
        self.head = eqx.nn.Linear(widths[-1], classes, key=keys[-1])

    def __call__(self, x):
        for conv in self.convs:
            x = self.pool(jax.nn.relu(conv(x)))
        return self.head(x.mean(axis=(1, 2)))


def _shrink(image: np.ndarray, size: int) -> np.ndarray:
    """A BGR image as float32 `(size, size, 3)`, area-averaged."""
    arr = np.asarray(image, np.float32)
    return cv2.resize(arr, (size, size), interpolation=cv2.INTER_AREA)


def _render(device, textures, n: int, rng: np.random.Generator, key) -> dict[str, np.ndarray]:
    """`n` random poses of each texture: frames, grating-free views and labels."""
    frames, truths, labels = [], [], []
    for label, picture in enumerate(textures):
        for _ in range(n):
            x, y = rng.uniform(-REACH_MM, REACH_MM, 2)
            scene = mj.scene_texture(
                picture,
                TEXTURE_MM,
                x=float(x),
                y=float(y),
                yaw_deg=float(rng.uniform(-180.0, 180.0)),
                height=float(rng.uniform(0.0, MAX_HEIGHT_MM)),
            )
            rendered = mj.render_scene(jax.random.fold_in(key, len(labels)), device, scene)
            frames.append(np.asarray(rendered.frame, np.float32))
            truths.append(np.asarray(rendered.grating_free, np.float32))
            labels.append(label)
    return {"frame": np.stack(frames), "grating_free": np.stack(truths), "label": np.asarray(labels)}


def _train(images: np.ndarray, labels: np.ndarray, classes: int, epochs: int, seed: int):
    """A `SmallCNN` trained on `(n, s, s, 3)` images; returns `predict(image) -> logits` for one BGR image."""
    mean = images.mean(axis=(0, 1, 2))
    std = images.std(axis=(0, 1, 2)) + 1e-6

    def standardise(batch):
        return jnp.moveaxis((batch - mean) / std, -1, -3)

    net = SmallCNN(classes, jax.random.PRNGKey(seed))
    optimiser = optax.adam(3e-3)
    state = optimiser.init(eqx.filter(net, eqx.is_array))

    @eqx.filter_jit
    def step(net, state, x, y):
        def loss(net):
            logits = jax.vmap(net)(standardise(x))
            return optax.softmax_cross_entropy_with_integer_labels(logits, y).mean()

        value, grads = eqx.filter_value_and_grad(loss)(net)
        updates, state = optimiser.update(grads, state, eqx.filter(net, eqx.is_array))
        return eqx.apply_updates(net, updates), state, value

    rng = np.random.default_rng(seed)
    batch = 32
    for _ in range(epochs):
        order = rng.permutation(len(images))
        for start in range(0, len(order), batch):
            chosen = order[start : start + batch]
            net, state, _ = step(net, state, jnp.asarray(images[chosen]), jnp.asarray(labels[chosen]))

    logits = eqx.filter_jit(lambda net, x: net(standardise(x)))
    return lambda image: np.asarray(logits(net, jnp.asarray(image)))


def _classified(images, model, *, see_through=None) -> list:
    """`live.classify` of every image, with the texture names as labels."""
    return [live.classify(image, model, see_through=see_through, labels=mj.SCENE_TEXTURES) for image in images]


def _probabilities(result) -> np.ndarray:
    """The softmax of a classification's logits (zeros when the model was not called)."""
    if result.scores is None:
        return np.zeros(len(mj.SCENE_TEXTURES))
    e = np.exp(result.scores - result.scores.max())
    return e / e.sum()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.add_argument("--frames", type=int, default=40, help="training poses per texture")
    parser.add_argument("--test-frames", type=int, default=30, help="test poses per texture")
    parser.add_argument("--epochs", type=int, default=30, help="training epochs")
    parser.add_argument("--size", type=int, default=64, help="side of the network's input (pixels)")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    start = time.perf_counter()

    device = mj.preset("mid", height=256, width=256)
    key = jax.random.PRNGKey(args.seed)
    reference = np.asarray(mj.empty_scene_reference(jax.random.fold_in(key, 0), device, frames=8))
    see_through = live.SeeThrough(reference, black_level=float(device.optics.offset))
    wavevectors = np.concatenate(
        [
            np.asarray(device.moire_wavevectors()),
            np.asarray(device.apparent_upper_wavevectors()),
            np.asarray(device.reference_wavevectors()),
        ]
    )
    notch = live.MoireNotch(
        (device.height, device.width),
        wavevectors,
        px_per_mm=float(device.px_per_mm),
        width=NOTCH_BINS_AT_512 * max(device.height, device.width) / 512,
    )
    notch_default = live.make_colour_probe(device).notch
    assert notch_default is not None

    # One texture's picture, loaded once: a scene is then posed from the array.
    textures = [np.asarray(mj.scene_texture(name, TEXTURE_MM).image) for name in mj.SCENE_TEXTURES]
    rng = np.random.default_rng(args.seed)
    train = _render(device, textures, args.frames, rng, jax.random.fold_in(key, 1))
    test = _render(device, textures, args.test_frames, rng, jax.random.fold_in(key, 2))
    rendered = time.perf_counter()

    classes = len(mj.SCENE_TEXTURES)
    train_restored = np.stack([_shrink(see_through(frame), args.size) for frame in train["frame"]])
    on_grating_free = _train(
        np.stack([_shrink(t, args.size) for t in train["grating_free"]]),
        train["label"],
        classes,
        args.epochs,
        args.seed,
    )
    on_restored = _train(train_restored, train["label"], classes, args.epochs, args.seed)
    trained = time.perf_counter()

    def scores(predict) -> dict:
        model = lambda image: predict(_shrink(image, args.size))  # noqa: E731
        views = {
            "grating_free": _classified(test["grating_free"], model),
            "restored": _classified(test["frame"], model, see_through=see_through),
            "raw": _classified(test["frame"], model),
            "notch": _classified([notch(f) for f in test["frame"]], model),
            "notch_default": _classified([notch_default(f) for f in test["frame"]], model),
        }
        truth = [mj.SCENE_TEXTURES[label] for label in test["label"]]
        out: dict = {
            view: float(np.mean([r.label == t for r, t in zip(results, truth)])) for view, results in views.items()
        }
        out["restored_not_classified"] = sum(r.status != "ok" for r in views["restored"])
        reference = views["grating_free"]
        # Paired with the grating-free view of the same pose: how often the answer is the
        # same, and how far the class probabilities move (total variation, 0 to 1), which
        # shows a change even where the accuracy saturates.
        out["agreement"] = {
            view: float(np.mean([r.label == g.label for r, g in zip(results, reference)]))
            for view, results in views.items()
            if view != "grating_free"
        }
        out["probability_shift"] = {
            view: float(
                np.mean([0.5 * np.abs(_probabilities(r) - _probabilities(g)).sum() for r, g in zip(results, reference)])
            )
            for view, results in views.items()
            if view != "grating_free"
        }
        return out

    grating_free_model = scores(on_grating_free)
    restored_model = scores(on_restored)
    end = time.perf_counter()

    result = {
        "backend": jax.default_backend(),
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "frame": [device.height, device.width],
        "network_input": [args.size, args.size],
        "textures": list(mj.SCENE_TEXTURES),
        "train_frames_per_texture": args.frames,
        "test_frames_per_texture": args.test_frames,
        "epochs": args.epochs,
        "accuracy_grating_free": grating_free_model["grating_free"],
        "accuracy_restored": grating_free_model["restored"],
        "accuracy_raw": grating_free_model["raw"],
        "accuracy_notch": grating_free_model["notch"],
        "accuracy_notch_default": grating_free_model["notch_default"],
        "classifier_drop_pp": 100 * (grating_free_model["grating_free"] - grating_free_model["restored"]),
        "agreement_restored": grating_free_model["agreement"]["restored"],
        "probability_shift_restored": grating_free_model["probability_shift"]["restored"],
        "trained_on_grating_free": grating_free_model,
        "trained_on_restored": restored_model,
        "restored_trained_drop_pp": 100 * (grating_free_model["grating_free"] - restored_model["restored"]),
        "render_s": rendered - start,
        "train_s": trained - rendered,
        "evaluate_s": end - trained,
        "total_s": end - start,
    }
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    test_frames = len(test["label"])
    print(f"{classes} textures, {len(train['label'])} training and {test_frames} test frames, {args.epochs} epochs")
    for name, accuracy in (("trained on grating-free", grating_free_model), ("trained on restored", restored_model)):
        print(
            f"  {name:24s} accuracy on grating-free {accuracy['grating_free']:.3f}, restored {accuracy['restored']:.3f}, "
            f"raw {accuracy['raw']:.3f}, notch {accuracy['notch']:.3f} (default {accuracy['notch_default']:.3f})"
        )
    print(
        f"restored against grating-free views of the same poses: agreement {result['agreement_restored']:.3f}, "
        f"probability shift {result['probability_shift_restored']:.4f}"
    )
    print(
        f"classifier drop on restored frames: {result['classifier_drop_pp']:.1f} pp "
        f"({result['restored_trained_drop_pp']:.1f} pp trained on restored frames)"
    )
    print(f"render {result['render_s']:.0f} s, train {result['train_s']:.0f} s, total {result['total_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
