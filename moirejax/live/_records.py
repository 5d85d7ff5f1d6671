"""What turns the loop's raw records into a sensor driver's: identity, sequence, tare bias,
range flags, centre of pressure, and an optional filter that weighs each frame by its own
covariance.

A force/torque driver's consumers expect each record to say which sensor and frame it is
in, whether the sensor is touched, whether an axis has left the calibrated range, and
where the load sits. [`RecordStream`][] adds these to every record [`run_pipeline`][]
emits. [`WrenchFilter`][] is a constant-wrench Kalman filter: a frame with a large
covariance (a fringe phase the model barely explains) moves the estimate little, a sharp
one moves it much.
"""

import dataclasses
import threading

import numpy as np

from .._conventions import centre_of_pressure_mm, WRENCH_SCALE
from ._sinks import WrenchRecord
from ._types import Real


# Statuses whose wrench is an estimate of the load (others carry no wrench, or one that the
# inversion itself flags as unexplained); an MCAP file also publishes the zero of no contact.
LOAD_STATUSES = ("converged", "max_steps")
# Statuses of a frame the inversion found touched, whether or not its wrench is believed.
_TOUCHED_STATUSES = (*LOAD_STATUSES, "unexplained")


class WrenchFilter:
    """A Kalman filter of the wrench under a random-walk load, measured with each frame's covariance.

    Between frames the load may change by `process_noise` of each axis's calibrated range
    (one standard deviation per frame); a frame measures it with the covariance the
    inversion reports. While the load holds still the filter averages frames in proportion
    to their precision; a change of many process standard deviations passes in a few
    frames. The filter restarts at the first frame of every contact.

    **Arguments:**

    - `process_noise`: load change per frame, as a fraction of each axis's range.
    - `ranges`: the six ranges (N, N*m); default the paper's.
    """

    def __init__(self, process_noise: Real = 0.05, ranges: np.ndarray | None = None):
        if not process_noise > 0:
            raise ValueError(f"process_noise must be positive, got {process_noise}")
        scale = np.asarray(WRENCH_SCALE if ranges is None else ranges, np.float64).reshape(6)
        self.process = np.diag((float(process_noise) * scale) ** 2)
        self.reset()

    def reset(self) -> None:
        """Forget the load: the next frame starts the filter."""
        self.mean: np.ndarray | None = None
        self.covariance: np.ndarray | None = None

    def update(self, wrench: np.ndarray, covariance: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fold in one frame's wrench and 6x6 covariance; returns the filtered pair."""
        z = np.asarray(wrench, np.float64)
        r = np.asarray(covariance, np.float64)
        if self.mean is None or self.covariance is None:
            self.mean, self.covariance = z.copy(), r.copy()
            return self.mean.copy(), self.covariance.copy()
        predicted = self.covariance + self.process
        gain = np.linalg.solve((predicted + r).T, predicted.T).T
        self.mean = self.mean + gain @ (z - self.mean)
        self.covariance = (np.eye(6) - gain) @ predicted
        self.covariance = 0.5 * (self.covariance + self.covariance.T)
        return self.mean.copy(), self.covariance.copy()


class RecordStream:
    """Completes the records of one sensor's stream (see the module docstring).

    **Arguments:**

    - `sensor_id`: which sensor the records are from.
    - `frame_id`: the ROS frame name of its wrench frame.
    - `ranges`: calibrated range of each axis `[fx, fy, fz, tx, ty, tz]` (N, N*m) for the
        `out_of_range` flags; default the paper's.
    - `filter`: a [`WrenchFilter`][] applied to in-contact wrenches, or `None`.
    - `cop_sigmas`: the centre of pressure is given while `fz` exceeds this many of its
        standard deviations (and 1% of the range when there is no covariance).

    [`set_bias`][RecordStream.set_bias] sets the wrench a tare measured, which is
    subtracted from every in-contact wrench. Thread-safe: the bias may be set from another
    thread while records stream.
    """

    def __init__(
        self,
        *,
        sensor_id: str = "moirejax",
        frame_id: str = "moirejax_sensor",
        ranges: np.ndarray | None = None,
        filter: WrenchFilter | None = None,
        cop_sigmas: Real = 3.0,
    ):
        self.sensor_id = str(sensor_id)
        self.frame_id = str(frame_id)
        self.ranges = np.asarray(WRENCH_SCALE if ranges is None else ranges, np.float64).reshape(6)
        self.filter = filter
        self.cop_sigmas = float(cop_sigmas)
        self._bias = np.zeros(6)
        self._seq = 0
        self._lock = threading.Lock()

    @property
    def bias(self) -> np.ndarray:
        """The wrench subtracted from in-contact wrenches (N, N*m)."""
        with self._lock:
            return self._bias.copy()

    def set_bias(self, bias: np.ndarray) -> None:
        """Subtract `bias` (`[fx, fy, fz, tx, ty, tz]`, N and N*m) from in-contact wrenches from now on."""
        bias = np.asarray(bias, np.float64).reshape(6)
        if not np.all(np.isfinite(bias)):
            raise ValueError(f"a bias must be finite, got {bias}")
        with self._lock:
            self._bias = bias

    def finish(self, record: WrenchRecord, monotonic: float | None = None) -> WrenchRecord:
        """`record` with the stream's identity, its sequence number, and the fields a driver's record carries."""
        with self._lock:
            seq, bias = self._seq, self._bias
            self._seq += 1
        wrench, covariance = record.wrench, record.covariance
        fields: dict = dict(sensor_id=self.sensor_id, frame_id=self.frame_id, seq=seq, monotonic=monotonic)
        in_contact = record.mode == "tactile" and record.status in _TOUCHED_STATUSES
        if not in_contact and self.filter is not None:
            self.filter.reset()
        if not in_contact or wrench is None or record.status not in LOAD_STATUSES:
            # Touched but not believed (unexplained): the record says so, and its wrench
            # is neither corrected nor filtered.
            return dataclasses.replace(record, **fields, in_contact=in_contact)
        wrench = wrench - bias
        cov = None if covariance is None else np.asarray(covariance, np.float64)
        filtered = False
        if self.filter is not None and cov is not None and np.all(np.isfinite(cov)):
            wrench, cov = self.filter.update(wrench, cov)
            filtered = True
        force, torque = tuple(float(v) for v in wrench[:3]), tuple(float(v) for v in wrench[3:])
        return dataclasses.replace(
            record,
            **fields,
            force=force,
            torque=torque,
            covariance=None if cov is None else tuple(tuple(float(v) for v in row) for row in cov),
            in_contact=True,
            out_of_range=tuple(bool(v) for v in np.abs(wrench) > self.ranges),
            centre_of_pressure_mm=self._centre_of_pressure(wrench, cov),
            filtered=filtered,
        )

    def _centre_of_pressure(self, wrench: np.ndarray, cov: np.ndarray | None) -> tuple[float, float] | None:
        fz = wrench[2]
        sigma = np.sqrt(cov[2, 2]) if cov is not None and np.isfinite(cov[2, 2]) else 0.0
        if not fz > max(self.cop_sigmas * sigma, 0.01 * self.ranges[2]):
            return None
        x, y = centre_of_pressure_mm(wrench)
        return (float(x), float(y))
