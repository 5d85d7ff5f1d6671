"""Simulated units, load schedules and simulated datasets.

It imports `physics`, `data` and the foundation modules, never `observe`.
"""

from ._simulate import (
    Deviations as Deviations,
    load_schedule as load_schedule,
    LoadSchedule as LoadSchedule,
    perturb_device as perturb_device,
    simulate_dataset as simulate_dataset,
    Simulator as Simulator,
)
