"""Any classifier through vision mode: `classify` restores the frame, calls the user's model
only on frames that show something, and reports what the model returned."""

import jax.random as jr
import numpy as np
import pytest

import moirejax as mj
from moirejax.live import Classification, classify, Frame, VisionClassifier


LABELS = ("astronaut", "chelsea", "coffee")


@pytest.fixture(scope="module")
def cat(vision_device):
    """A see-through frame of scikit-image's cat 8 mm above the pad, and its grating-free view."""
    rendered = mj.render_scene(
        jr.PRNGKey(2), vision_device, mj.scene_texture("chelsea", 40.0, yaw_deg=20.0, height=8.0)
    )
    return np.asarray(rendered.frame, np.float32), np.asarray(rendered.grating_free, np.float32)


def never_called(image):
    raise AssertionError("the model was called")


def test_a_label_comes_back_as_the_model_returned_it_from_the_image_as_given(cat):
    frame, _ = cat
    seen = []
    result = classify(frame, lambda image: seen.append(image) or "cat")
    assert result == Classification("cat", None, "ok")
    # Without a SeeThrough the model gets the frame itself.
    assert len(seen) == 1 and seen[0] is frame
    # NumPy scalars become Python ones.
    assert classify(frame, lambda image: np.int64(2)).label == 2


def test_scores_are_kept_as_returned_and_name_the_highest(cat):
    frame, _ = cat
    logits = np.array([-3.0, 2.5, 0.5])
    result = classify(frame, lambda image: logits, labels=LABELS)
    assert result.label == "chelsea" and result.status == "ok"
    np.testing.assert_array_equal(result.scores, logits)  # not softmax-normalised
    # A batch of one, as ONNX Runtime and PyTorch return it, and a plain list.
    assert classify(frame, lambda image: logits[None, :].astype(np.float32), labels=LABELS).label == "chelsea"
    assert classify(frame, lambda image: [0.1, 0.2, 0.7]).label == 2


def block_means(image):
    """A "classifier" whose 192 scores are the mean colours of 8 x 8 blocks of 32 pixels:
    about half a moiré period, so the fringes change them."""
    return image.reshape(8, 32, 8, 32, 3).mean(axis=(1, 3)).reshape(-1)


def test_the_model_gets_the_restored_image_which_matches_the_grating_free_view(cat, see_through):
    frame, truth = cat
    seen = []
    result = classify(frame, lambda image: seen.append(image) or block_means(image), see_through=see_through)
    assert result.status == "ok"
    np.testing.assert_array_equal(seen[0], see_through(frame))
    # The model sees the grating-free view's colours block by block, which the raw frame's
    # moiré changes by up to a fifth.
    assert result.scores is not None
    np.testing.assert_allclose(result.scores, block_means(truth), rtol=0.06)
    assert np.max(np.abs(block_means(frame) / block_means(truth) - 1)) > 0.15
    # uint8 frames reach the model as uint8.
    as_uint8 = (frame * 255 + 0.5).astype(np.uint8)
    assert classify(as_uint8, lambda image: str(image.dtype), see_through=see_through).label == "uint8"


def test_dark_saturated_and_empty_frames_never_reach_the_model(vision_device, see_through):
    shape = (vision_device.height, vision_device.width, 3)
    black = float(vision_device.optics.offset)
    assert classify(np.zeros(shape, np.uint8), never_called) == Classification(None, None, "dark")
    assert classify(np.full(shape, 255, np.uint8), never_called).status == "saturated"
    # A frame at the camera's black level is dark only when the black level is known.
    at_black = np.full(shape, black, np.float32)
    assert classify(at_black, never_called, see_through=see_through).status == "dark"
    assert classify(at_black, never_called, black_level=black).status == "dark"
    assert classify(at_black, lambda image: "lit").status == "ok"
    # The empty view, with nothing above the pad: empty with a SeeThrough, unless asked otherwise.
    empty = np.asarray(mj.render_scene(jr.PRNGKey(3), vision_device, None).frame, np.float32)
    assert classify(empty, never_called, see_through=see_through).status == "empty"
    assert classify(empty, lambda image: "backdrop", see_through=see_through, min_contrast=None).label == "backdrop"


def test_a_model_that_raises_is_an_error_naming_its_exception(cat):
    frame, _ = cat

    def broken(image):
        raise KeyError("input")

    with pytest.raises(RuntimeError, match="classifier raised KeyError") as info:
        classify(frame, broken)
    assert isinstance(info.value.__cause__, KeyError)


def test_misshapen_scores_and_frames_are_value_errors(cat):
    frame, _ = cat
    with pytest.raises(ValueError, match=r"shape \(2, 3\)"):
        classify(frame, lambda image: np.zeros((2, 3)))
    with pytest.raises(ValueError, match="neither a label nor scores"):
        classify(frame, lambda image: ["cat", "dog"])
    with pytest.raises(ValueError, match="4 scores for 3 labels"):
        classify(frame, lambda image: np.zeros(4), labels=LABELS)
    with pytest.raises(ValueError, match="BGR"):
        classify(frame[..., 0], lambda image: 0)


def test_the_vision_hook_classifies_colour_frames_and_keeps_the_result(cat, see_through):
    frame, _ = cat
    hook = VisionClassifier(lambda image: np.array([0.0, 1.0, 0.0]), see_through=see_through, labels=LABELS)
    color = (frame * 255 + 0.5).astype(np.uint8)
    assert hook(Frame(0, 0.0, color.mean(axis=-1) / 255, color)) == "label=chelsea status=ok"
    assert hook.last is not None and hook.last.scores is not None
    dark = np.zeros_like(color)
    assert hook(Frame(1, 0.0, dark[..., 0].astype(np.float32), dark)) == "label=none status=dark"
    assert hook(Frame(2, 0.0, dark[..., 0].astype(np.float32))) is None
