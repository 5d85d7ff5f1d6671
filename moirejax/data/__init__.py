"""The on-disk dataset format: its reader and writer, import and export of lab recordings,
and the alignment of a force/torque log to a recording's frames.

It imports only the foundation modules (`_plotting`, `_fileio`, `_conventions`).
"""

from ._dataset import (
    Batch as Batch,
    Dataset as Dataset,
    DatasetWriter as DatasetWriter,
    export_recording as export_recording,
    FrameSequence as FrameSequence,
    IMAGE_SUFFIXES as IMAGE_SUFFIXES,
    import_recording as import_recording,
    ImportReport as ImportReport,
    open_dataset as open_dataset,
    read_ft_log as read_ft_log,
    unit_frame as unit_frame,
)
from ._ft import (
    align_ft as align_ft,
    fringe_change as fringe_change,
    FtAlignment as FtAlignment,
)
