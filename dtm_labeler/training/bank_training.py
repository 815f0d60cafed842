"""Training a model bank (Ukita L1-L3): one model per action, each trained on its own
recordings plus the synthesized transition paths to the other actions
(:mod:`dtm_labeler.training.transitions`). Storage and validation of banks are in
:mod:`dtm_labeler.model.bank`."""
from __future__ import annotations

from pathlib import Path

from ..model.bank import ModelBank, check_action_name, now_iso
from .train import train_model
from .transitions import TransitionSource, transitions_between


def source_record(clip) -> dict:
    """How to find a training recording again: path and frame range."""
    fr = clip.meta.get("frame_range")
    return {"path": str(clip.source), "frames": [int(fr[0]), int(fr[1])] if fr else None,
            "n_frames": int(clip.n_frames), "class": clip.motion_class}


def load_sources(record: dict, skeletal: bool = True) -> list:
    """:class:`TransitionSource` objects of an action's recorded training recordings (those
    that no longer exist are skipped)."""
    out = []
    for src in record.get("sources", []):
        p = Path(src["path"])
        if not p.is_file():
            continue
        fr = tuple(src["frames"]) if src.get("frames") else None
        out.append(TransitionSource.load(p, fr, skeletal=skeletal))
    return out


def train_action(action: str, sources: list, others: dict | None = None, config=None, transitions=None,
                 progress=None):
    """Train one action model (Ukita L2): its own recordings plus the synthesized paths
    between them and every recording of each action in ``others`` (both directions, P3).

    ``sources``: :class:`TransitionSource` list of this action; ``others``: ``{action:
    [TransitionSource, ...]}``; ``transitions``: :class:`TransitionSettings` or None (no paths).
    Returns ``(model, record, summary)``; ``record`` goes into ``bank.json``.
    """
    check_action_name(action)
    clips = [s.clip for s in sources]
    t_records, paths = [], []
    if transitions is not None:
        for other, osrc in (others or {}).items():
            if other == action or not osrc:
                continue
            rep = transitions_between(sources, osrc, transitions)
            paths += rep.paths
            t_records.append({"with": other, "paths": len(rep.paths), "frames": rep.frames,
                              "rejected": rep.rejected,
                              "paths_detail": [{k: p.meta[k] for k in ("from_source", "from_frame", "to_source",
                                                                       "to_frame", "n_inbetween", "widened",
                                                                       "method", "distance")}
                                               for p in rep.paths]})
    train_clips = clips + [p._replace(meta={}) for p in paths]
    model, summary = train_model(train_clips, config, progress)
    record = {"sources": [source_record(c) for c in clips], "points": "body14",
              "transitions": t_records, "synthesized_frames": int(sum(t["frames"] for t in t_records)),
              "trained": now_iso(), "frames": int(sum(c.n_frames for c in clips))}
    return model, record, summary


def build_bank(sources: dict, config=None, transitions=None, mode: str = "all") -> ModelBank:
    """Train a whole bank from ``{action: [TransitionSource, ...]}``.

    ``mode='all'``: every model gets the paths to every other action (the synthesized frames
    join the training data of *both* models they connect); ``mode='incremental'``: the paper's
    L1-L3 literally -- action ``i`` gets the paths to actions ``j < i`` only (dict order).
    ``transitions=None`` trains without synthesized paths.
    """
    if mode not in ("all", "incremental"):
        raise ValueError("mode must be 'all' or 'incremental'")
    bank = ModelBank()
    names = list(sources)
    for i, a in enumerate(names):
        others = {b: sources[b] for j, b in enumerate(names) if j != i and (mode == "all" or j < i)}
        model, record, _ = train_action(a, sources[a], others, config, transitions)
        record["transition_mode"] = mode if transitions is not None else "none"
        bank.add(a, model, record)
    return bank
