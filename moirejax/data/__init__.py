"""The on-disk dataset format: its reader and writer, and import and export of lab recordings.

It imports only the foundation modules (`_plotting`, `_fileio`, `_conventions`).
"""

from ._dataset import (
    Batch as Batch,
    Dataset as Dataset,
    DatasetWriter as DatasetWriter,
    export_recording as export_recording,
    import_recording as import_recording,
    ImportReport as ImportReport,
    open_dataset as open_dataset,
    unit_frame as unit_frame,
)
