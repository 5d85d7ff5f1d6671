"""Inverting recordings on many processes and machines: segments of frames handed to the
workers of a Dask cluster.

A recording is cut into segments of `segment` consecutive frames; each segment is a
stream that starts cold ([`invert_recording`][] with `restart_every=segment`), so it
needs nothing from any other and any worker can run it. The inverter is built once, here,
sent once to every worker, and each worker process compiles it once for all the segments it
runs. Finished segments are kept beside the output (`OUT.parts/`) as they arrive, so a run
that is interrupted, or loses a worker, redoes only the segments it had not finished;
the output is written, atomically, when every segment is in, and it is the file
`invert_recording` writes with the same `restart_every`, number for number.

Why Dask: its `distributed` scheduler is pure Python, installs with pip wherever moirejax
does, runs the same code on a local cluster of processes (the default here) and on a
cluster of machines (give the scheduler's address; `dask-ssh`, `dask-jobqueue` and the
Kubernetes operator start one), and its futures let the driver store each segment as soon
as it finishes. The frames are read by the workers from the path they are given, so on
several machines the recordings must be on storage they all mount.
"""

import json
import os
import shutil
import uuid
from pathlib import Path
from typing import Any

from .._fileio import atomic_write_text, check_output_file, fingerprint, open_parts
from ._inversion import Inverter
from ._invert_io import (
    _check_count,
    _csv_text,
    check_source,
    count_source_frames,
    CSV_HEADER,
    invert_segment,
    segments,
)


# The inverters of this worker process, by run: built from the run's first segment here.
_WORKER_INVERTERS: dict[str, Any] = {}


def _run_segment(run: str, shipped, source: str, start: int, stop: int, batch: int) -> dict:
    """On a worker: invert frames `start..stop-1` of `source`; the rows as CSV text and the
    count of each status."""
    if run not in _WORKER_INVERTERS:
        _WORKER_INVERTERS.clear()  # one run at a time per worker: free the last run's programs
        _WORKER_INVERTERS[run] = shipped
    inverter, head = _WORKER_INVERTERS[run]
    rows = invert_segment(inverter, source, start, stop, batch=batch, head=head)
    counts: dict[str, int] = {}
    for row in rows:
        counts[row[-2]] = counts.get(row[-2], 0) + 1
    return {"csv": _csv_text(rows), "counts": counts, "frames": len(rows)}


def _segment_name(start: int) -> str:
    return f"segment-{start:09d}.json"


def invert_distributed(
    inverter: Inverter,
    source: str | Path,
    out_csv: str | Path,
    *,
    segment: int = 256,
    batch: int = 1,
    workers: int = 2,
    scheduler: str | None = None,
    head=None,
    progress: bool = True,
) -> dict[str, int]:
    """Invert every frame of a dataset or folder of frames on a Dask cluster and write
    `out_csv`, the file [`invert_recording`][]`(..., restart_every=segment)` writes.

    **Arguments:**

    - `inverter`, `head`: as for [`invert_recording`][]; sent once to every worker.
    - `source`: a dataset or a folder of images, on storage every worker reads.
    - `out_csv`: the wrench CSV. Finished segments are kept in `OUT.parts/` until it is
        written; a rerun with the same inverter, source, `segment` and `batch` picks them up.
    - `segment`: frames per segment, each a stream that starts cold.
    - `batch`: frames vectorised together inside a segment, as for `invert_recording`.
    - `workers`: worker processes of the local cluster started when no `scheduler` is given
        (one thread each).
    - `scheduler`: the address of a running Dask scheduler (`tcp://host:8786`).

    Returns the count of each status.

    **Raises:** `ValueError` for a count below 1; [`DataError`][] for a source that cannot be
    read, a video (import it first: a segment needs a frame count), or parts left by a
    different run; [`OutputError`][moirejax.OutputError] when the output cannot be
    written; `ImportError` naming the `cluster` extra when Dask is not installed.
    """
    try:
        from dask.distributed import as_completed, Client, LocalCluster
    except ImportError as e:
        raise ImportError(
            "the dask engine needs dask.distributed: pip install 'moirejax[cluster]' (or pip install distributed)"
        ) from e
    from tqdm.auto import tqdm

    for value, name in ((segment, "segment"), (batch, "batch"), (workers, "workers")):
        _check_count(value, name)
    check_source(source)
    check_output_file(out_csv, argument="out_csv")
    source = os.path.abspath(source)
    n_frames = count_source_frames(source)
    parts = Path(f"{out_csv}.parts")
    plan = {
        "source": source,
        "frames": n_frames,
        "segment": segment,
        "batch": batch,
        "inverter": fingerprint(inverter, head),
    }
    done = _resume(parts, plan)
    todo = [(start, stop) for start, stop in segments(n_frames, segment) if start not in done]

    initial = sum(d["frames"] for d in done.values())
    bar = tqdm(total=n_frames, initial=initial, desc="invert", unit="frame", disable=not progress)
    if todo:
        cluster = None
        if scheduler is None:
            cluster = LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None, silence_logs=40
            )
        try:
            with Client(scheduler if cluster is None else cluster) as client:
                run = uuid.uuid4().hex
                shipped = client.scatter((inverter, head), broadcast=True)
                futures = {
                    client.submit(_run_segment, run, shipped, source, start, stop, batch, pure=False, retries=2): start
                    for start, stop in todo
                }
                for future in as_completed(futures):
                    result = future.result()
                    start = futures[future]
                    atomic_write_text(parts / _segment_name(start), json.dumps(result))
                    done[start] = result
                    bar.update(result["frames"])
        finally:
            bar.close()
            if cluster is not None:
                cluster.close()
    else:
        bar.close()
    text = ",".join(CSV_HEADER) + "\n" + "".join(done[start]["csv"] for start, _ in segments(n_frames, segment))
    atomic_write_text(out_csv, text)
    shutil.rmtree(parts, ignore_errors=True)
    counts: dict[str, int] = {}
    for result in done.values():
        for status, n in result["counts"].items():
            counts[status] = counts.get(status, 0) + n
    return counts


def _resume(parts: Path, plan: dict) -> dict[int, dict]:
    """The segments a previous run of the same plan finished, from `parts`."""
    open_parts(parts, plan, argument="out_csv")
    done: dict[int, dict] = {}
    for path in parts.glob("segment-*.json"):
        try:
            done[int(path.stem.split("-")[1])] = json.loads(path.read_text())
        except (OSError, ValueError, IndexError):
            continue  # a part that cannot be read is redone
    return done
