"""Text a requester chose: the one rule for notes, reasons, host and user names.

Whatever a person or program types into a request (a Zenoh query, the dashboard, a command to
an edge) ends up in events.log, the recording, e-mails and the live view. One line of text that
any of them can hold is accepted; anything else is refused with a reason, never replaced:
replacing would record something the requester did not say. Refused:

- not a string, or longer than the field's limit (characters);
- a lone UTF-16 surrogate (U+D800-U+DFFF): valid JSON (``"\\ud800"``) but no UTF-8 encoder
  writes it, so it used to stop a reply, a log line or a record half way;
- control characters (Unicode category Cc: C0 including tab and newline, DEL, C1): a note is
  one line in events.log and on a terminal, and escape sequences must not reach either;
- bidirectional overrides and isolates (U+202A-U+202E, U+2066-U+2069), which make a log line
  read differently from what it holds.

Everything else (accents, CJK, emoji, private-use characters) is kept as typed.
"""

from __future__ import annotations

import unicodedata

_BIDI = frozenset(range(0x202A, 0x202F)) | frozenset(range(0x2066, 0x206A))


class TextRefused(ValueError):
    """A requester's text broke the rule; the message names the field and says why."""


def text_problem(value: object, limit: int) -> str | None:
    """Why `value` is not acceptable requester text of at most `limit` characters, or None."""
    if not isinstance(value, str):
        return f"must be text (got {type(value).__name__})"
    if len(value) > limit:
        return f"must be at most {limit} characters (got {len(value)})"
    for i, c in enumerate(value):
        o = ord(c)
        if 0xD800 <= o <= 0xDFFF:
            return f"holds a lone UTF-16 surrogate (U+{o:04X}) at character {i}"
        if o in _BIDI:
            return f"holds a bidirectional control (U+{o:04X}) at character {i}"
        if (o < 0x20 or 0x7F <= o <= 0x9F) and unicodedata.category(c) == "Cc":
            return f"holds a control character (U+{o:04X}) at character {i}"
    return None


def checked_text(value: object, field: str, limit: int) -> str:
    """`value` if it is acceptable requester text of at most `limit` characters.

    Raises:
        TextRefused: ``"<field> <why>"``, e.g. ``note holds a control character (U+001B) at
            character 3``.
    """
    why = text_problem(value, limit)
    if why is not None:
        raise TextRefused(f"{field} {why}")
    assert isinstance(value, str)
    return value
