"""The command line: `moirejax` and its subcommands, the demo, and the README's generated CLI reference.

The top layer: it may import every layer below it, and nothing in the package imports it.
"""

from ._main import main as main
