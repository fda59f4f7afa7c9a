"""The one way user text reaches the page: :func:`md_text` turns any string into markdown that
renders as exactly that text.

viser renders markdown as raw HTML without sanitising it (``rehypeRawDom`` in its client), so a
file named ``<img src=x onerror=alert(1)>.xyz`` shown in a markdown widget would run its script
in every browser that opens the app. Every piece of text that does not come from this code
(uploaded file names, error messages, anything read from a file, strings from the core) goes
through :func:`md_text` before it is put into a markdown widget; see ``docs/security.md``.
Notification titles and bodies and dropdown options are rendered by React as text, so they are
passed as they are.
"""

from __future__ import annotations

import string
import unicodedata

MAX_TEXT_CHARS = 300
"""Longest user text shown in a markdown widget (characters); longer text is cut with "..."."""

_ENTITIES = {"&": "&amp;", "<": "&lt;", ">": "&gt;", '"': "&quot;", "'": "&#39;"}
"""HTML-special characters, written as entities (the markdown parser decodes them to text)."""

_PUNCTUATION = frozenset(string.punctuation) - frozenset(_ENTITIES)
"""The other ASCII punctuation, backslash-escaped (CommonMark: an escaped punctuation character
is literal text), so that no link, image, emphasis, table cell or autolink can be formed."""


def md_text(text: object, max_chars: int = MAX_TEXT_CHARS) -> str:
    """``text`` as markdown that shows exactly its characters as plain text.

    HTML-special characters become entities, other ASCII punctuation is backslash-escaped,
    line breaks and tabs become spaces (a line break could start a new block or table row), and
    control and format characters (e.g. the right-to-left override U+202E, which can disguise a
    file name) become U+FFFD. Text longer than ``max_chars`` is cut and ends in "...".
    """
    s = str(text)
    if len(s) > max_chars:
        s = s[: max(max_chars - 3, 0)] + "..."
    out = []
    for ch in s:
        if ch in _ENTITIES:
            out.append(_ENTITIES[ch])
        elif ch in _PUNCTUATION:
            out.append("\\" + ch)
        elif ch in "\r\n\t\f\v":
            out.append(" ")
        elif unicodedata.category(ch) in ("Cc", "Cf", "Cs", "Co", "Cn"):
            out.append("\ufffd")
        else:
            out.append(ch)
    return "".join(out)


__all__ = ["MAX_TEXT_CHARS", "md_text"]
