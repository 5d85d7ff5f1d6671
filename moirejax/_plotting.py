"""Matplotlib without a display, and atomic PNG output."""

import io


def pyplot():
    """`matplotlib.pyplot`, on the Agg backend (no display needed) unless the caller, a
    notebook say, already chose one."""
    import sys

    import matplotlib

    if "matplotlib.pyplot" not in sys.modules:
        matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path, *, dpi: int = 110) -> None:
    """Render `fig` to PNG and write it atomically; closes the figure."""
    from ._fileio import atomic_write_bytes

    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi)
    pyplot().close(fig)
    atomic_write_bytes(path, buf.getvalue())
