"""Names people give (structures, fault modes, channels, operating conditions, organisations):
one form each, and shown as what they are.

A name is kept in Unicode's composed form (NFC) without surrounding whitespace, so that "Pump 3",
" Pump 3 " and the same letters typed with combining accents are stored alike, not as three names
that look the same. A name that would not display as what it is, is refused: one empty once
trimmed, or holding a character that is invisible or reorders its neighbours: a bidirectional
control ("pump", U+202E, "gnp.exe" shows as "pumpexe.png"), a byte-order mark, any other format
character (Unicode category Cf, such as zero-width spaces and joiners), a control character (Cc),
or a lone surrogate half (Cs, which no UTF-8 database column stores).
"""

from __future__ import annotations

import unicodedata

from models.errors import InputError

REFUSED_CATEGORIES = {
    "Cc": "a control character",
    "Cf": "an invisible format character",
    "Cs": "a lone surrogate, not a character",
}
BIDI_CONTROLS = frozenset("\u061c\u200e\u200f\u202a\u202b\u202c\u202d\u202e\u2066\u2067\u2068\u2069")
BYTE_ORDER_MARK = "\ufeff"


def normalised_name(text: str, what: str = "name") -> str:
    """``text`` in NFC without surrounding whitespace; ``InputError`` (a ``ValueError``, so also a
    validation error in a schema) saying which character, by its code point and place in the text
    as given, is not allowed, or that the ``what`` is empty."""
    trimmed = text.strip()  # a trailing tab or newline, though control characters, just goes
    leading = len(text) - len(text.lstrip())
    for place, character in enumerate(trimmed, start=leading + 1):
        category = unicodedata.category(character)
        if category in REFUSED_CATEGORIES:
            raise InputError(
                f"a {what} cannot hold {_kind(character, category)}: U+{ord(character):04X}"
                f"{_called(character)} is character {place} of the {what} given"
            )
    name = unicodedata.normalize("NFC", trimmed).strip()
    if not name:
        raise InputError(f"a {what} cannot be empty or only whitespace")
    return name


def _kind(character: str, category: str) -> str:
    if character in BIDI_CONTROLS:
        return "a bidirectional control character, which reorders what is shown"
    if character == BYTE_ORDER_MARK:
        return "a byte-order mark (zero-width no-break space)"
    return REFUSED_CATEGORIES[category]


def _called(character: str) -> str:
    name = unicodedata.name(character, "")
    return f" ({name})" if name else ""
