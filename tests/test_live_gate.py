"""GateER on synthetic moire sequences: touches switch within 2 frames; drift, noise and shadows do not."""

import numpy as np
import pytest

from moirejax.live import GateER


H = W = 128
ROWS, COLS = np.mgrid[0:H, 0:W].astype(np.float64)
P1, P2, TILT = 3.0, 3.5, 0.05  # grating periods (px) and tilt: a ~20 px moire
K1 = 2 * np.pi / P1 * np.array([np.cos(TILT), np.sin(TILT)])  # (col, row) rad/px
K2 = 2 * np.pi / P2 * np.array([1.0, 0.0])


def moire_frame(t, rng, *, touch=None, drift=0.2, noise=0.015, shadow=None, scene=None):
    """Product of two cosine gratings under drifting illumination, with an optional touch.

    `touch = (phase_amplitude, col, row, sigma)`: a Gaussian phase distortion of the upper
    grating plus the brighter LED rim. `shadow = (col, row, sigma)`: a scene object seen
    through the sensor (vision mode), a soft multiplicative shadow; `scene(t)`: any other
    field of what the scene lets through, multiplying the frame.
    Illumination drifts +-`drift` over 200 frames with a changing left-right gradient; the
    moire phase creeps by 0.1 rad (thermal drift); 0.1 of background does not scale.
    """
    phase = 0.1 * np.sin(2 * np.pi * t / 400)
    brightness = np.ones((H, W))
    if touch is not None:
        amplitude, c, r, s = touch
        bump = np.exp(-((COLS - c) ** 2 + (ROWS - r) ** 2) / (2 * s * s))
        phase = phase + amplitude * bump
        brightness = brightness + 0.2 * amplitude * bump
    a = K1[0] * COLS + K1[1] * ROWS + phase
    b = K2[0] * COLS + K2[1] * ROWS
    transmission = (1 + np.cos(a)) * (1 + np.cos(b)) / 4
    illumination = (1 + drift * np.sin(2 * np.pi * t / 200)) * (
        1 + 0.3 * (COLS / W - 0.5) * np.cos(2 * np.pi * t / 300)
    )
    image = 0.1 + 0.6 * transmission * illumination * brightness
    if shadow is not None:
        c, r, s = shadow
        image = image * (1 - 0.6 * np.exp(-((COLS - c) ** 2 + (ROWS - r) ** 2) / (2 * s * s)))
    if scene is not None:
        image = image * scene(t)
    image = image + rng.normal(0.0, noise, image.shape)
    return np.clip(image, 0, 1).astype(np.float32)


def run(gate, n, touch_at=(), seed=0, **kwargs):
    """Feed `n` frames; `touch_at` is a list of (start, stop, touch). Returns the decisions."""
    rng = np.random.default_rng(seed)
    decisions = []
    for t in range(n):
        touch = next((tc for start, stop, tc in touch_at if start <= t < stop), None)
        decisions.append(gate.update(moire_frame(t, rng, touch=touch, **kwargs)))
    return decisions


def switch_frames(decisions):
    return [t for t, d in enumerate(decisions) if d.switched]


def test_drift_and_noise_never_switch():
    decisions = run(GateER(), 400)
    assert all(d.mode == "vision" for d in decisions)
    quiet = max(d.energy_ratio for d in decisions)
    # Not a near miss: the threshold is 4x the floor, and the largest quiet statistic of
    # 400 frames of noise and drift stays under 3x it.
    assert quiet < 0.75 * decisions[-1].threshold


def test_scene_shadow_in_vision_mode_does_not_switch():
    gate = GateER()
    rng = np.random.default_rng(1)
    for t in range(200):
        shadow = (t - 40.0, 64.0, 25.0)  # a soft object a bit larger than a fringe moves across
        decision = gate.update(moire_frame(t, rng, shadow=shadow, noise=0.01))
        assert decision.mode == "vision", (t, decision)


MOIRE = K1 - K2  # (col, row) rad/px


def striped_object(t):
    """An object above the pad striped at the moiré period, sliding and coming into view.

    This is what fooled a gate on the moiré fringes: its stripes change the light at the
    fringes' own frequency. Seen through the sensor it only scales the light, by up to 40 %.
    """
    reach = min(t / 60, 1.0)
    envelope = np.exp(-((COLS - 20 - 0.4 * t) ** 2 + (ROWS - 64) ** 2) / (2 * 30.0**2))
    stripes = 0.5 + 0.5 * np.cos(MOIRE[0] * COLS + MOIRE[1] * ROWS + 0.3 * t)
    return 1 - 0.4 * reach * envelope * stripes


def test_scene_at_the_moire_period_does_not_switch_but_a_light_touch_does():
    """A striped object at the fringe period sliding over the view, with a 20 % drop of
    the light, is no contact; a light touch under it is seen at once and let go within
    2 frames, while the object keeps moving."""
    touches = [(150, 170, (0.6, 80, 60, 8))]
    decisions = run(GateER(), 200, touches, scene=striped_object)
    modes = [d.mode for d in decisions]
    assert modes[:150] == ["vision"] * 150, [t for t, m in enumerate(modes) if m == "tactile"]
    assert all(m == "tactile" for m in modes[151:170]), modes[150:172]
    assert modes[150] == "tactile" or modes[151] == "tactile"
    assert all(m == "vision" for m in modes[172:])


def test_sudden_lighting_change_does_not_switch():
    """The exposure halves and a hard shadow edge sweeps in from one frame to the next:
    a gain of the light, however sharp in time, is no contact."""
    gate = GateER()
    rng = np.random.default_rng(4)
    for t in range(40):
        light = 1.0 if t < 20 else 0.5 * (1 + 0.5 * np.tanh((COLS - 64) / 6.0)).astype(np.float32)
        frame = np.clip(moire_frame(t, rng, drift=0.0, noise=0.01) * light, 0, 1)
        decision = gate.update(frame)
        assert decision.mode == "vision", (t, decision)


@pytest.mark.parametrize("amplitude", [0.6, 2.0], ids=["light", "firm"])
def test_touch_switches_within_two_frames(amplitude):
    touches = [(100, 140, (amplitude, 60, 70, 8)), (250, 262, (amplitude, 35, 90, 8))]
    decisions = run(GateER(), 320, touches)
    switches = switch_frames(decisions)
    assert len(switches) == 4, switches
    for switch, edge in zip(switches, [100, 140, 250, 262]):
        assert edge <= switch <= edge + 1, (switches, edge)
    assert [decisions[t].mode for t in (99, 120, 200, 255, 300)] == ["vision", "tactile", "vision", "tactile", "vision"]


def test_long_contact_does_not_leak_into_baseline():
    # 150 frames of contact while the illumination drifts: release must still be seen.
    decisions = run(GateER(), 320, [(60, 210, (1.0, 64, 64, 10))])
    assert switch_frames(decisions) in ([60, 210], [60, 211])


def test_explicit_wavevectors_match_automatic():
    px_per_mm = 20.0

    def physical(k):  # (col, row) rad/px -> (kx, ky) rad/mm with y up
        return np.array([[k[0] * px_per_mm, -k[1] * px_per_mm]])

    explicit = GateER(carrier_wavevectors=physical(K1), moire_wavevectors=physical(K1 - K2), px_per_mm=px_per_mm)
    touches = [(50, 70, (1.0, 60, 70, 8))]
    assert switch_frames(run(explicit, 100, touches)) == switch_frames(run(GateER(), 100, touches)) == [50, 70]
    automatic = GateER()
    run(automatic, 5)
    # Both gratings' carriers are found; only the upper one moves under a touch.
    found = automatic.carriers_px * np.sign(automatic.carriers_px[:, :1])
    for k in (K1, K2):
        assert np.min(np.linalg.norm(found - k, axis=-1)) < 2 * np.pi / W, (found, k)


def test_hysteresis_and_dwell_state_machine():
    gate = GateER(on_threshold=0.02, hysteresis=0.2, noise_factor=1.0, noise_rate=1e-9)
    modes = [gate.step(e).mode for e in [0.01, 0.021, 0.018, 0.0165, 0.0155, 0.019, 0.0205]]
    assert modes == ["vision", "tactile", "tactile", "tactile", "vision", "vision", "tactile"]
    dwell = GateER(on_threshold=0.02, min_dwell_frames=2, noise_rate=1e-9)
    # Two frames in vision before it may switch, then two in tactile before it may return.
    modes = [dwell.step(e).mode for e in [0.05, 0.05, 0.05, 0.0, 0.0, 0.0]]
    assert modes == ["vision", "vision", "tactile", "tactile", "vision", "vision"]


def test_threshold_adapts_to_noise_floor():
    quiet, noisy = GateER(), GateER()
    run(quiet, 150, noise=0.005)
    run(noisy, 150, noise=0.06, seed=3)
    assert noisy.noise_level > 3 * quiet.noise_level
    assert noisy.threshold >= quiet.threshold >= quiet.on_threshold


def test_rejects_bad_frames():
    gate = GateER()
    gate.update(np.full((64, 64), 0.5, np.float32) + 0.2 * np.cos(0.5 * COLS[:64, :64]).astype(np.float32))
    with pytest.raises(ValueError, match="differs"):
        gate.update(np.zeros((32, 32), np.float32))
    with pytest.raises(ValueError, match="2D"):
        gate.update(np.zeros((64, 64, 3), np.float32))


def test_device_gate_follows_contact_on_a_sequence_dataset(tmp_path):
    """On a high-fidelity `sequence` recording (noise, 8 bits, fabrication deviations) the
    device's gate switches within 2 frames of the recorded contact onset and release, and a
    slow illumination drift over the same unit's contact-free frames never switches it."""
    import moirejax as mj
    from moirejax.data._dataset import Dataset
    from moirejax.live import make_gate
    from moirejax.simulate._simulate import simulate_dataset

    device = mj.preset("mid")
    data = Dataset(simulate_dataset(tmp_path / "seq", device, "sequence", 120, seed=5, progress=False))
    frames = [np.round(data.frame(i) * 255) / 255 for i in range(len(data))]
    gate = make_gate(device)
    tactile = np.array([gate.update(frame).mode == "tactile" for frame in frames])
    truth = data.contact.astype(bool)
    onset, release = np.flatnonzero(np.diff(truth.astype(int))) + 1
    gate_on, gate_off = np.flatnonzero(np.diff(tactile.astype(int))) + 1
    assert abs(gate_on - onset) <= 2 and abs(gate_off - release) <= 2, (onset, release, gate_on, gate_off)

    rows, cols = np.mgrid[0 : device.height, 0 : device.width] / device.height
    rest = [f for f, c in zip(frames, truth) if not c]
    gate = make_gate(device)
    for i in range(160):
        s = i / 160
        light = (1 - 0.3 * s) * (1 + 0.2 * s * (cols - 0.5) + 0.1 * np.sin(2 * np.pi * (rows + s)))
        decision = gate.update(np.clip(np.round(rest[i % len(rest)] * light * 255) / 255, 0, 1))
        assert decision.mode == "vision", (i, decision)
