"""The two entry points of the inversion: [`invert`][] for a set or a recording of frames,
[`frame_tracker`][] for a camera stream, and the chunked tracking they share.

[`Inverter.solve`][] and [`Inverter.track`][] are the pure per-frame functions beneath
them, for use inside a user's own `jit`, `vmap` or `grad`.
"""

import collections
import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, Real

from ..data import unit_frame
from ._inversion import Inverter
from ._second_contact import _SECOND_CONTACT_TRIGGER
from ._state import Estimate, LoadState, N_UNKNOWNS, Status, Track


def invert(
    inverter: Inverter,
    frames: Real[ArrayLike, "*frames h w"] | Iterable[Real[ArrayLike, "h w"]],
    *,
    init: LoadState | None = None,
    sequence: bool = False,
    batch: int = 16,
    threads: int | None = None,
    progress: bool = False,
    desc: str = "invert",
) -> Estimate:
    """Invert one frame, or many into an [`Estimate`][] with a leading frame axis.

    **Arguments:**

    - `frames`: one `(height, width)` frame, or a sequence or iterable of them (a stacked
      array, a list, a generator reading a dataset). Floats in [0, 1], or 8- and 16-bit
      integers as a camera delivers them.
    - `init`: where each frame's solve starts, a [`LoadState`][] (with a leading frame axis
      for many frames), e.g. a previous [`Estimate.state`][moirejax.Estimate] or
      [`LoadState.from_load`][] of a known load; `None`, or a non-finite row, for a cold
      start. A start that explains its frame worse than the cold guess is not used.
    - `sequence`: the frames are consecutive frames of one recording. Each then continues
      from the last ([`Inverter.track`][]), `batch` frames at a time vectorised from the
      previous chunk's solution and split over the devices JAX sees: much faster than
      solving each cold, and the same estimates to about one standard error. Without it,
      every frame is solved on its own ([`Inverter.solve`][]): the choice for frames of
      unrelated loads, such as a calibration set.
    - `threads`: frames solved on their own are solved this many at a time, on threads
      sharing one compiled program (default: the machine's cores, at most 8). A solve is a
      long chain of small operations that keeps about one core busy, so a second one in
      flight uses the second core; the estimates are the same whatever the number.
    - `progress`, `desc`: a progress bar with that label.

    A frame that cannot be inverted gets its status (bad frame, non-finite, no contact) and
    a NaN or zero wrench, never an exception. Every frame of one shape and dtype runs one
    compiled program. Results are numpy arrays for many frames (so a long recording does not
    hold device memory), device arrays for one.

    **Raises:** `ValueError` for no frames, a frame that is not 2-D or of the device's
    size, `init` together with `sequence`, or `batch < 1` or `threads < 1`.
    """
    if isinstance(batch, bool) or not isinstance(batch, int | np.integer) or batch < 1:
        raise ValueError(f"batch must be a whole number >= 1, got {batch!r}")
    if threads is None:
        threads = max(1, min(os.cpu_count() or 1, _SOLVE_THREADS))
    if isinstance(threads, bool) or not isinstance(threads, int | np.integer) or threads < 1:
        raise ValueError(f"threads must be a whole number >= 1, got {threads!r}")
    if sequence and init is not None:
        raise ValueError("init starts frames solved on their own; a sequence continues from its own frames")
    if isinstance(frames, np.ndarray | jax.Array) and frames.ndim == 2:
        start = _cold_start(inverter) if init is None else init
        frame = jnp.asarray(unit_frame(np.asarray(frames)))
        return with_second_contact(inverter, frame, _solve(inverter, frame, start))

    from tqdm.auto import tqdm

    total = len(frames) if hasattr(frames, "__len__") else None  # pyright: ignore[reportArgumentType]
    if sequence:
        bar = tqdm(frames, total=total, desc=desc, unit="frame", disable=not progress)
        estimates = [jax.device_get(e) for e in _tracked(inverter, bar, batch)]
    else:
        cold = _cold_start(inverter)

        def solve(i, frame):
            start = cold if init is None else jax.tree_util.tree_map(lambda x: x[i], init)
            frame = jnp.asarray(unit_frame(frame))
            return jax.device_get(with_second_contact(inverter, frame, _solve(inverter, frame, start)))

        estimates = []
        with tqdm(total=total, desc=desc, unit="frame", disable=not progress) as bar:
            for estimate in _in_order(solve, enumerate(frames), threads):
                estimates.append(estimate)
                bar.update()
    if not estimates:
        raise ValueError("no frames to invert")
    return jax.tree_util.tree_map(lambda *x: np.stack(x), *estimates)


# The most frames `invert` solves at once on their own, whatever the number of cores: each
# solve in flight holds its own intermediates.
_SOLVE_THREADS = 8


def _in_order(solve: Callable, items: Iterable[tuple], threads: int) -> Iterator:
    """`solve(*item)` for every item, in order, with up to `threads` of them running at once
    on threads; the first alone, so that it compiles what the others run. Items are
    taken a few at a time (a generator reading frames is not read ahead of the solves)."""
    items = iter(items)
    first = next(items, None)
    if first is None:
        return
    yield solve(*first)
    if threads == 1:
        yield from (solve(*item) for item in items)
        return
    solve = _under_callers_settings(solve)
    pool = ThreadPoolExecutor(threads)
    pending: collections.deque = collections.deque()
    try:
        for item in items:
            pending.append(pool.submit(solve, *item))
            if len(pending) >= 2 * threads:
                yield pending.popleft().result()
        while pending:
            yield pending.popleft().result()
    finally:
        pool.shutdown(wait=True, cancel_futures=True)


def _under_callers_settings(fn: Callable) -> Callable:
    """`fn` run under the calling thread's JAX settings that a context sets for its own
    thread only (`jax.enable_x64`, `jax.default_device`, `jax.numpy_dtype_promotion`): a
    worker thread would otherwise solve in the process-wide precision, on the default
    device, and compile a program of its own."""
    x64 = jax.config.jax_enable_x64
    device = jax.config.jax_default_device
    promotion = jax.config.jax_numpy_dtype_promotion

    def run(*args):
        with jax.enable_x64(x64), jax.default_device(device), jax.numpy_dtype_promotion(promotion):
            return fn(*args)

    return run


def frame_tracker(inverter: Inverter) -> "FrameTracker":
    """The streaming entry point: `step = frame_tracker(inverter)`, then per camera frame
    `estimate, track = step(frame, track)`, starting from `inverter.cold_track()`.

    Each frame continues from the last good one ([`Inverter.track`][]): a few iterations
    with the last frame's Jacobian while the load moves smoothly, a cold solve after a jump.
    The step compiles on its first frame and never again for frames of the device's size
    and dtype. An `Inverter` is some 130 arrays, which `eqx.filter_jit` would flatten at
    every call; here they are flattened once, and each frame goes through `jax.jit`'s own
    dispatch. A new reference of the same unit ([`FrameTracker.with_inverter`][]) reuses
    the compiled step.
    """
    arrays, static = eqx.partition(inverter, eqx.is_array)

    def track_frame(arrays, frame, track):
        return eqx.combine(arrays, static).track(frame, track)

    return FrameTracker(jax.jit(track_frame), arrays, static)


class FrameTracker:
    """One compiled streaming step of an [`Inverter`][]; made by [`frame_tracker`][].

    `step(frame, track) -> (estimate, track)` inverts one frame of the device's size.
    """

    def __init__(self, compiled: Callable, arrays: Inverter, static: Inverter):
        self._compiled = compiled
        self._arrays = arrays
        self._static = static

    def __call__(self, frame: Real[ArrayLike, "h w"], track: Track) -> tuple[Estimate, Track]:
        return self._compiled(self._arrays, frame, track)

    def with_inverter(self, inverter: Inverter) -> "FrameTracker":
        """The same step for another [`Inverter`][] of the unit, e.g. one built on a new
        no-contact reference (a tare): the compiled program is reused when everything but
        the inverter's array values is the same (build it from `self`'s `inverter.device`
        with `match_reference=False, register_gratings=True`, which keeps the geometry the
        demodulator is laid out on); otherwise the new step compiles on its first frame.
        """
        arrays, static = eqx.partition(inverter, eqx.is_array)
        same_layout = jax.tree_util.tree_structure(arrays) == jax.tree_util.tree_structure(self._arrays) and all(
            jnp.shape(a) == jnp.shape(b) and jnp.result_type(a) == jnp.result_type(b)
            for a, b in zip(jax.tree_util.tree_leaves(arrays), jax.tree_util.tree_leaves(self._arrays))
        )
        if same_layout and eqx.tree_equal(static, self._static) is True:
            return FrameTracker(self._compiled, arrays, self._static)
        return frame_tracker(inverter)


@eqx.filter_jit
def _solve(inverter: Inverter, frame, init: LoadState) -> Estimate:
    return inverter.solve(frame, init)


@eqx.filter_jit
def _second_contact(inverter: Inverter, frame, estimate: Estimate) -> Estimate:
    return inverter.second_contact(frame, estimate)


def with_second_contact(inverter: Inverter, frame, estimate: Estimate) -> Estimate:
    """[`Inverter.second_contact`][] of one frame's estimate, compiled only once a frame
    needs it: most sets never do, and the two-patch solve is a program of its own."""
    status = int(estimate.status)
    believed = status in (Status.CONVERGED, Status.MAX_STEPS, Status.UNEXPLAINED)
    if believed and int(estimate.contacts) == 1 and float(estimate.misfit) > _SECOND_CONTACT_TRIGGER:
        return _second_contact(inverter, frame, estimate)
    return estimate


def _cold_start(inverter: Inverter) -> LoadState:
    # A non-finite start is a cold one; passing one always keeps a single compiled program
    # for cold and warm starts.
    return LoadState.from_vector(jnp.full(N_UNKNOWNS, jnp.nan, inverter.device.p1.dtype))


def _tracked(inverter: Inverter, frames: Iterable, batch: int) -> Iterator[Estimate]:
    """The estimates of consecutive `frames`, `batch` at a time through `_invert_chunk`
    (one at a time through [`frame_tracker`][] for `batch == 1`)."""
    track = inverter.cold_track()
    if batch == 1:
        step = frame_tracker(inverter)
        for frame in frames:
            estimate, track = step(jnp.asarray(unit_frame(frame)), track)
            yield estimate
        return
    pending: list = []
    for frame in frames:
        pending.append(unit_frame(frame))
        if len(pending) == batch:
            estimates, track = _invert_chunk(inverter, pending, track, batch)
            yield from estimates
            pending = []
    if pending:
        estimates, track = _invert_chunk(inverter, pending, track, batch)
        yield from estimates


def _over_devices(frames: Float[Array, "b h w"]) -> Float[Array, "b h w"]:
    """Inside a jit: split a batch of frames over every device JAX sees, so a recording
    scales to more devices with no code change; unchanged on one device, or when the batch
    does not divide evenly (callers pad it, see `_invert_chunk`)."""
    devices = jax.devices()
    if len(devices) == 1 or frames.shape[0] % len(devices):
        return frames
    mesh = jax.sharding.Mesh(np.asarray(devices), ("frames",))
    return jax.lax.with_sharding_constraint(
        frames, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec("frames"))
    )


@eqx.filter_jit
def _track_frame(inverter: Inverter, frame, track: Track) -> tuple[Estimate, Track]:
    return inverter.track(frame, track)


@eqx.filter_jit
def _chord_batch(inverter: Inverter, frames, track: Track):
    return inverter.chord_batch(_over_devices(frames), track)


@eqx.filter_jit
def _relinearise(inverter: Inverter, track: Track) -> Track:
    # The data Jacobian depends on the frame only through the reference wavevectors, which
    # every frame shares with the reference.
    jacobian = inverter._fit._data_jacobian(track.state.vector(), inverter.reference)
    return eqx.tree_at(lambda t: t.jacobian, track, jnp.where(track.valid, jacobian, track.jacobian))


def _invert_chunk(inverter: Inverter, frames, track: Track, batch: int) -> tuple[list[Estimate], Track]:
    """Invert up to `batch` consecutive frames of a stream that continues from `track`.

    The frames go through frozen-Jacobian iterations from `track`, vectorised
    ([`Inverter.chord_batch`][]; a short chunk is padded so one program serves all) and
    split over the devices JAX sees; frames those do not settle are solved one by one
    with [`Inverter.track`][] from the previous frame's track, which also starts a stream
    when `track` is not valid yet. Returns the estimates, in order, and the track to
    continue from.
    """
    dtype = np.dtype(inverter.device.p1.dtype)
    frames = [np.asarray(f, dtype) for f in frames]
    n = len(frames)
    if n > batch:
        raise ValueError(f"{n} frames do not fit a chunk of {batch}")
    out: list = [None] * n
    start = 0
    # Nothing to linearise around yet: solve frames one by one until one converges.
    while start < n and not bool(track.valid):
        out[start], track = _track_frame(inverter, frames[start], track)
        start += 1
    if start < n:
        # Padded to the chunk size (one program serves all), and up to a whole number of
        # frames per device.
        size = -(-batch // jax.device_count()) * jax.device_count()
        stack = np.stack(frames[start:] + [frames[-1]] * (size - (n - start)))
        estimates, accepted, tracks = _chord_batch(inverter, stack, track)
        # One transfer, then numpy slicing: a device slice per field and frame costs more
        # than a frame's solve.
        estimates, accepted, status = jax.device_get((estimates, accepted, estimates.status))
        latest = None  # the last frame whose track the stream continues from
        for i in range(start, n):
            j = i - start
            if accepted[j]:
                out[i] = jax.tree_util.tree_map(lambda x, j=j: x[j], estimates)
                # A converged frame's track carries its Broyden-updated Jacobian on, as a
                # stream would; other settled frames (no contact, bad) leave it as it was.
                if status[j] == Status.CONVERGED:
                    latest = j
            else:
                if latest is not None:
                    track, latest = jax.tree_util.tree_map(lambda x, j=latest: x[j], tracks), None
                out[i], track = _track_frame(inverter, frames[i], track)
        if latest is not None:
            track = jax.tree_util.tree_map(lambda x, j=latest: x[j], tracks)
    # A Jacobian carried over many frames by secant updates drifts, and a whole chunk's
    # frames stop where it says the gradient vanishes: a fresh one per chunk keeps them
    # within a fraction of a standard error of the least-squares solution.
    return out, _relinearise(inverter, track)
