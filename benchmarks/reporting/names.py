"""Short labels for long configuration names, with a key to the full names.

Runs with imported priors and ``--set`` overrides have configuration names of 100 to 200 characters
(``quick priors.depth_import.fit_scale_shift=true priors.depth_import.kind=disparity ... masks=balloon1``).
Written out in a table column or a plot legend they push the scores off screen and squeeze the axes. When
any name is longer than :data:`MAX_CHARS`, each name gets a code (``A``, ``B``, ..., ``Z``, ``AA``, ...) in
the order the names are given, and a short text of at most :data:`MAX_CHARS` characters: the words that not
every name shares, dotted keys and paths cut to their last part, the most shared words left out first when
that is still too long (:func:`shorten`). Pages show the code and the short text, the
full name in the hover text, and a key table (code -> full name). Short names are shown as they are.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

#: Names up to this many characters are shown whole; longer ones are shortened (and so are short texts).
MAX_CHARS = 48
ELLIPSIS = "…"


def letter_code(i: int) -> str:
    """The ``i``-th code (from 0): ``A`` ... ``Z``, ``AA`` ... ``AZ``, ``BA`` ... (as spreadsheet columns)."""
    if i < 0:
        raise ValueError(f"code index {i}: give 0 or more")
    out = ""
    i += 1
    while i:
        i, r = divmod(i - 1, 26)
        out = chr(ord("A") + r) + out
    return out


def abbreviate(word: str) -> str:
    """One word of a name, cut to what tells it apart: the last part of a dotted key
    (``priors.depth_import.kind=disparity`` -> ``kind=disparity``) and of a path value
    (``masks=/data/priors/balloon1_masks`` -> ``masks=balloon1_masks``); other words as they are."""
    key, eq, value = word.partition("=")
    if not eq:
        return word
    if "." in key.strip("."):
        key = key.strip(".").rsplit(".", 1)[1]
    if "/" in value.strip("/"):
        value = value.rstrip("/").rsplit("/", 1)[1]
    return f"{key}={value}"


def cut(text: str, max_chars: int = MAX_CHARS) -> str:
    """``text`` when it has at most ``max_chars`` characters, else its words that fit (the first word cut when
    even it does not) followed by :data:`ELLIPSIS`, at most ``max_chars`` characters in all."""
    if len(text) <= max_chars:
        return text
    room = max(max_chars - 1, 1)
    kept = ""
    for word in text.split():
        trial = f"{kept} {word}" if kept else word
        if len(trial) > room:
            break
        kept = trial
    return (kept or text[:room]) + ELLIPSIS


def shorten(names: Sequence[str], max_chars: int = MAX_CHARS) -> list[str]:
    """A short text per name (same order): a name of at most ``max_chars`` characters as it is; a longer one
    as its words that not every name shares, each :func:`abbreviate`\\ d (repeats dropped). When they are
    still too long, the words that most names share are left out first (of equally shared ones, the later),
    the rest kept in their order with :data:`ELLIPSIS` after them, so what sets a name apart stays; when
    nothing is left of its own, its abbreviated words :func:`cut`. Not one-to-one: the codes of
    :func:`name_key` tell names apart."""
    words = [str(n).split() for n in names]
    common = set(words[0]).intersection(*words[1:]) if len(words) > 1 else set()
    own_words = []
    for ws in words:
        kept: list[str] = []
        for w in map(abbreviate, [w for w in ws if w not in common]):
            if w not in kept:
                kept.append(w)
        own_words.append(kept)
    shared = Counter(w for ws in own_words for w in set(ws))
    out = []
    for name, ws, own in zip(names, words, own_words, strict=True):
        if len(name) <= max_chars:
            out.append(name)
        elif not own:
            out.append(cut(" ".join(dict.fromkeys(map(abbreviate, ws))), max_chars))
        elif len(" ".join(own)) <= max_chars:
            out.append(" ".join(own))
        else:
            keep = list(own)
            # Most shared first; of equally shared words the later first.
            for w in sorted(own, key=lambda w: (-shared[w], -own.index(w))):
                if len(" ".join(keep)) + 2 <= max_chars or len(keep) == 1:
                    break
                keep.remove(w)
            out.append(cut(" ".join(keep) + " " + ELLIPSIS, max_chars))
    return out


@dataclass(frozen=True)
class NameKey:
    """Codes and short texts of a list of names (:func:`name_key`)."""

    names: tuple[str, ...]
    """The full names, each once, in the order given."""
    codes: tuple[str, ...]
    shorts: tuple[str, ...]
    max_chars: int = MAX_CHARS

    @property
    def shortened(self) -> bool:
        """Whether any name is longer than ``max_chars``: then pages show codes and a key."""
        return any(len(n) > self.max_chars for n in self.names)

    def code(self, name: str) -> str:
        return self.codes[self.names.index(name)]

    def short(self, name: str) -> str:
        return self.shorts[self.names.index(name)]

    def label(self, name: str) -> str:
        """What a page shows for ``name``: the name itself when no name is long, else ``code short``."""
        if not self.shortened:
            return name
        return f"{self.code(name)} {self.short(name)}"

    def entries(self, only: Iterable[str] | None = None) -> list[dict[str, str]]:
        """The key: ``code``, ``short`` and ``full`` name of every name (or of those in ``only``), in order."""
        keep = None if only is None else set(only)
        return [
            {"code": c, "short": s, "full": n}
            for n, c, s in zip(self.names, self.codes, self.shorts, strict=True)
            if keep is None or n in keep
        ]


def name_key(names: Iterable[str], max_chars: int = MAX_CHARS) -> NameKey:
    """Codes ``A``, ``B``, ... for ``names`` in the order of first appearance (repeats get the first one's
    code) and their short texts (:func:`shorten`)."""
    unique = tuple(dict.fromkeys(str(n) for n in names))
    codes = tuple(letter_code(i) for i in range(len(unique)))
    shorts = tuple(shorten(unique, max_chars)) if unique else ()
    return NameKey(unique, codes, shorts, max_chars)
