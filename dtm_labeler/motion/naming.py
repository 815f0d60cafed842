"""Point names across files: prefixes, unnamed channels, copies, and the names several takes share.

Rules (the same for every loader and every tool):

* **Subject prefixes** are dropped: everything up to the last ``':'`` (``Male:LFHD -> LFHD``),
  unless two channels would then share a name (those keep their full label).
* **Unnamed channels** are points without a name: an empty label, or one starting with ``'*'``
  after the prefix (``*0``, ``Bastian:*12``; Vicon/Nexus writes unlabelled trajectories this
  way, and so does ``dtm-label --out``), or a system's word for one with its number
  (``Unidentified 12``, ``Discarded 3``: QTM's; ``Unlabeled 1001``: Motive's;
  :data:`SYSTEM_UNNAMED`). A stray part of a named trajectory kept under the name with a
  ``-N`` suffix (``T10-1`` beside ``T10``, never seen with it) is unnamed too: the loaders
  join it to its marker where it continues it (:mod:`.fragments`). They are kept apart as
  *unlabelled points* (``meta['unlabelled']``), never as model points.
* **Copies**: an unnamed channel that is bit-identical in every frame to a named one (the
  HDM05 takes' ``*0 *1 *2`` = ``LFWT CLAV LFHD``) or to an earlier unnamed one is the same
  physical point twice; it is recorded in ``meta['unlabelled_duplicates']`` and never fed to
  a labeler as a second point.
* **Several subjects** in one capture (two actors, each under a prefix with the same marker
  names, :func:`subjects`): one is chosen (``--subject NAME``); the others' markers are
  unlabelled points of its takes, as any other person near the body would be. Without the
  choice such a capture is refused with the subjects' names.
* **Several takes** (:func:`common_names`): the same names in another channel order are the
  same point set (every take is put in the first one's order); different sets keep the
  names all takes share, in the first take's order, with a one-line note; no name in common
  is an error that names the differences.
"""
from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np


def strip_prefix(label: str) -> str:
    """``'Male:LFHD' -> 'LFHD'`` (everything up to the last ':' removed)."""
    return label.rsplit(":", 1)[-1].strip()


#: a system's name for a trajectory it did not label: the word, then its number (module doc)
SYSTEM_UNNAMED = re.compile(r"^(unlabell?ed|unidentified|discarded|unnamed)[\s_#-]*\d*$", re.IGNORECASE)
#: a stray part of a named trajectory: the name, a dash and a small number (``T10-1``)
STRAY_PART = re.compile(r"^(.+)-(\d{1,2})$")


def is_unnamed(label: str) -> bool:
    """True for an unlabelled channel: ``''``, ``'*3'``, ``'Subject:*0'``, ``'Unidentified 12'``."""
    short = strip_prefix(str(label))
    return not short or short.startswith("*") or SYSTEM_UNNAMED.match(short) is not None


def stray_parts(labels: Sequence[str], xyz: np.ndarray | None = None) -> set[int]:
    """Indices of ``labels`` that are a stray part of another label's trajectory: ``T10-1`` when
    ``T10`` is a label too (prefixes stripped) and, given the channels ``xyz`` (F, N, 3), never
    seen in a frame where ``T10`` is (a marker of its own named so is seen beside it)."""
    short = [strip_prefix(str(s)) for s in labels]
    where = {s: i for i, s in enumerate(short)}
    out = set()
    for i, s in enumerate(short):
        m = STRAY_PART.match(s)
        base = where.get(m.group(1)) if m is not None else None
        if base is None:
            continue
        if xyz is not None and (np.isfinite(xyz[:, i]).all(-1) & np.isfinite(xyz[:, base]).all(-1)).any():
            continue
        out.add(i)
    return out


@dataclass
class ChannelSplit:
    """How a file's channels divide into named points and unlabelled points."""

    named: list[int]                       # channel indices of named points
    names: list[str]                       # their names (prefix stripped where unique)
    raw: list[str]                         # their labels as written
    unnamed: list[int]                     # channel indices of unlabelled points
    unnamed_names: list[str]               # their labels ('*<channel>' when empty)
    duplicates: dict[str, str] = field(default_factory=dict)   # unlabelled copy -> the channel it copies

    @property
    def independent(self) -> list[int]:
        """Indices into ``unnamed`` of the unlabelled points that copy nothing."""
        return [k for k, nm in enumerate(self.unnamed_names) if nm not in self.duplicates]


def subject_of(label: str) -> str:
    """The subject prefix of a channel label (``'Male:LFHD' -> 'Male'``; '' without one)."""
    head, sep, _ = str(label).strip().rpartition(":")
    return head.strip() if sep else ""


def subjects(labels: Sequence[str], min_markers: int = 5) -> list[str]:
    """The subjects of a capture: the prefixes under which at least ``min_markers`` named
    channels share their names with another prefix's (one actor's marker set twice), in
    order of appearance; [] for a capture of one subject (a prop's few channels do not count)."""
    by: dict[str, set[str]] = {}
    for s in labels:
        if not is_unnamed(s):
            by.setdefault(subject_of(s), set()).add(strip_prefix(s))
    return [p for p, names in by.items()
            if any(q != p and len(names & other) >= min_markers for q, other in by.items())]


def split_channels(labels: Sequence[str], xyz: np.ndarray, where: str = "", subject: str | None = None
                   ) -> ChannelSplit:
    """Divide channels (``labels``, ``xyz`` (F, N, 3) with NaN = missing) by the module rules.
    A capture of several subjects (:func:`subjects`) needs ``subject``: that subject's channels
    are its points, every other subject's are unlabelled points (another person near the body)."""
    raw = [str(s).strip() for s in labels]
    several = subjects(raw)
    at = f"{where}: " if where else ""
    if subject is not None:
        have = sorted({subject_of(s) for s in raw if not is_unnamed(s)} - {""})
        if subject not in have:
            raise ValueError(f"{at}no channel of subject {subject!r} (subjects: {', '.join(have) or 'none'})")
    elif len(several) > 1:
        raise ValueError(f"{at}the capture holds {len(several)} subjects ({', '.join(several)}) with the same "
                         "marker names; choose one with --subject NAME (the others' markers are then unlabelled points)")
    others = set() if subject is None else {i for i, s in enumerate(raw) if not is_unnamed(s) and subject_of(s) != subject}
    stray = stray_parts(["" if i in others else s for i, s in enumerate(raw)], xyz)
    unnamed = [i for i, s in enumerate(raw) if is_unnamed(s) or i in stray or i in others]
    skip = set(unnamed)
    named = [i for i in range(len(raw)) if i not in skip]
    short = [strip_prefix(raw[i]) for i in named]
    names = [s if short.count(s) == 1 else raw[i] for s, i in zip(short, named)]
    if len(set(names)) != len(names):
        raise ValueError(f"{where + ': ' if where else ''}duplicate point labels "
                         f"{sorted({s for s in names if names.count(s) > 1})}")
    unnamed_names = [raw[i] or f"*{i}" for i in unnamed]
    dup: dict[str, str] = {}
    for k, u in enumerate(unnamed):
        earlier = list(zip(named, names)) + [(unnamed[j], unnamed_names[j]) for j in range(k)
                                             if unnamed_names[j] not in dup]
        for i, nm in earlier:
            if np.array_equal(xyz[:, u], xyz[:, i], equal_nan=True):
                dup[unnamed_names[k]] = nm
                break
    return ChannelSplit(named, names, [raw[i] for i in named], unnamed, unnamed_names, dup)


def common_names(name_lists: Sequence[Sequence[str]], sources: Sequence[str] | None = None
                 ) -> tuple[list[str], str]:
    """``(names, note)``: the point names every list shares, in the first list's order, and a
    one-line note when some were left out ('' when all lists hold the same names). ValueError
    naming the differences when nothing is shared."""
    if not name_lists:
        raise ValueError("no point names")
    sources = list(sources) if sources is not None else [f"take {i + 1}" for i in range(len(name_lists))]
    first = list(name_lists[0])
    shared = set(first)
    for names in name_lists[1:]:
        shared &= set(names)
    keep = [n for n in first if n in shared]
    if not keep:
        diff = [f"{s}: {', '.join(list(n)[:6])}{' ...' if len(n) > 6 else ''}" for s, n in zip(sources, name_lists)]
        raise ValueError("the takes share no point name (" + "; ".join(diff) + "); give takes of one marker set "
                         "or name the points with --points")
    dropped = sorted(set().union(*map(set, name_lists)) - shared)
    if not dropped:
        return keep, ""
    lacking = [s for s, n in zip(sources, name_lists) if set(dropped) - set(n)]
    note = (f"the takes share {len(keep)} point names; training on those, leaving out {len(dropped)} "
            f"({', '.join(dropped[:8])}{' ...' if len(dropped) > 8 else ''}) that "
            f"{', '.join(lacking[:3])}{' ...' if len(lacking) > 3 else ''} lack{'s' if len(lacking) == 1 else ''}")
    return keep, note


def cmu_subject(stem: str) -> str | None:
    """CMU take naming: ``'93_04' -> '93'`` (subject number before the underscore), also after a
    ``cmu_`` prefix (``'cmu_85_02_jumptwist_s85' -> '85'``), else None."""
    if stem[:4].lower() in ("cmu_", "cmu-"):
        stem = stem[4:]
    head, sep, tail = stem.partition("_")
    return head if sep and head.isdigit() and tail[:1].isdigit() else None


def one_subject(sources: Sequence[str]) -> str | None:
    """Why the captures at paths ``sources`` are of one person -- ``'one capture'`` (every
    path the same file) or ``'CMU subject N'`` (CMU take naming, one subject number) -- or None
    when the names do not tell (several captures of unknown people)."""
    paths = [os.path.realpath(str(s)) for s in sources]
    if not paths:
        return None
    if len(set(paths)) == 1:
        return "one capture"
    subjects = {cmu_subject(Path(p).stem) for p in paths}
    if len(subjects) == 1 and None not in subjects:
        return f"CMU subject {subjects.pop()}"
    return None
