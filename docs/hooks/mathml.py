"""mkdocs hook: the LaTeX of the pages and docstrings becomes MathML when the site is built.

`pymdownx.arithmatex` (generic mode) wraps each formula in an `arithmatex` span or div;
this hook replaces the wrapper by MathML, which browsers render natively. The site thus
needs no script and loads nothing from outside. A formula that cannot be converted is a
build warning (so `mkdocs build --strict` fails on it), naming the page and the formula.
"""

import html
import logging
import re

from latex2mathml.converter import convert


log = logging.getLogger("mkdocs.hooks.mathml")

_INLINE = re.compile(r'<span class="arithmatex">\\\((.*?)\\\)</span>', re.DOTALL)
_BLOCK = re.compile(r'<div class="arithmatex">\\\[(.*?)\\\]</div>', re.DOTALL)


def _replacer(page, display: str):
    def replace(match: re.Match) -> str:
        tex = html.unescape(match.group(1)).strip()
        try:
            return convert(tex, display=display)
        except Exception as error:  # latex2mathml raises several exception types
            log.warning(f"{page.file.src_uri}: cannot convert the formula {tex!r} to MathML ({error})")
            return match.group(0)

    return replace


def on_page_content(html_text: str, page, config, files) -> str:
    html_text = _BLOCK.sub(_replacer(page, "block"), html_text)
    return _INLINE.sub(_replacer(page, "inline"), html_text)
