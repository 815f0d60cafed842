"""``dtm-eval`` output: ``report.md`` (Markdown), PNG figures (matplotlib, Agg) and ``results.json``."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .experiments import PAPER_TABLE3, TABLE3_ROWS
from .model_tests import KIND_NAMES, MIXTURE_KINDS, PAPER_TABLE1, PAPER_TABLE2
from ..jsonable import json_default

COLORS = {"JMGW": "tab:red", "JMG": "tab:green", "JG": "tab:blue"}


def _plt():
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    return plt


def pct(x, digits: int = 1) -> str:
    return "n/a" if x is None else f"{100.0 * x:.{digits}f} %"


def num(x, spec: str = ".1f") -> str:
    return "n/a" if x is None else format(x, spec)


def md_table(header: list[str], rows: list[list[str]]) -> str:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(str(c) for c in r) + " |" for r in rows]
    return "\n".join(out)


def _paper(table: dict, row: str, key: str) -> str:
    v = table.get(row, {}).get(key)
    return "—" if v is None else f"{v:g} %"


def _save(fig, path: Path, figures: list) -> str:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _plt().close(fig)
    figures.append(path.name)
    return path.name


# -- sections --------------------------------------------------------------------------------------------
def _intro(meta: dict, results: dict) -> list[str]:
    p = meta["plan"]
    seqs = results.get("sequences", {})
    lines = [
        "# dtm_labeler evaluation — Hu & Wong, section V, on the shared recordings",
        "",
        f"Generated {meta['date']} by `{meta['command']}` in {meta['wall_s'] / 60:.1f} min "
        f"({meta['jobs']} worker processes, {meta['machine']['cpus']} CPUs). "
        f"{'**Quick run: tiny budgets, numbers are a smoke test only.**' if p['quick'] else ''}",
        "",
        "This report reruns the experiments of Hu & Wong (decomposable triangulated model, per-triangle "
        "Gaussian mixtures with MDL, CBGA label search) on the real recordings in the data folder, with the "
        "paper's numbers beside ours where the paper has them. The paper used four CMU sequences (two walks "
        "W1/W2, one run R1, one dance D1); we have one walk, one run and three dances, so the paper's W2 "
        "column has no counterpart here, and our D2/D3 columns have none in the paper.",
        "",
        "## Data and protocol",
        "",
        md_table(["key", "recording", "subject", "frames", "train (first 9/10)", "held out (last 1/10)", "rate"],
                 [[k, f"{v['title']} (`{v['path']}`)", v["subject"], v["frames"], v["train_frames"], v["test_frames"],
                   f"{v['rate']:g} Hz"] for k, v in seqs.items()]),
        "",
        "* **Points**: the paper's 14 body points (head, neck, shoulders, elbows, wrists, hips, knees, "
        "ankles) from the skeleton's joints (BVH: cgspeed joints; AMC: ASF bone ends).",
        "* **Within-sequence protocol** (paper: \"each sequence is divided into ten segments, frames from nine "
        "of the segments are used as the training set\"): the first nine contiguous tenths train, the last "
        "tenth is held out. One fold only (the last segment), not a 10-fold average.",
        "* **Models**: `single` = one Gaussian per triangle (JG), `fixed` = K = 3 (JMG), `mdl` = K chosen by "
        "MDL in [1, 8] (JMGW); `structure='given'` is the hand-made 14-point structure (Fig. 2 style) unless "
        "\"+Struct\" (structure found by CBGA on the training frames). Training as `dtm-train` (heading-"
        "canonical eq. 12 features, small yaw jitter, covariance floors 2 cm / 0.2 m/s).",
        f"* **Accuracy** (Table 3 and figures) is `dtm-label`'s: the fraction of visible true points that were "
        f"published with their true label (unlabelled = wrong), after the labels are stripped and the points "
        f"shuffled. **Single mode** (the paper's setting): {p['frames_per_test']} frames spread evenly over the "
        f"held-out segment, each labelled by a fresh labeler that has only seen the previous frame (for "
        f"velocities). **Stream mode**: one labeler over a contiguous block of the held-out segment (first "
        f"{p['stream_frames']} frames, or the whole segment if shorter; greedy: first "
        f"{p['greedy_stream_frames']} frames because greedy has no warm start and costs ~1-2 s per frame): "
        f"tracks, warm start, votes over a 10-frame window.",
        "* **Search errors**: frames where the true labeling has a higher fitness under the model than the "
        "chosen one (the search, not the model, failed). **Latency**: per-frame processing time, one core.",
        "",
        f"How to reproduce: `{meta['command']}` (data: `{meta['data_dir']}`; results.json holds every number "
        f"below and the budgets).",
        "",
    ]
    return lines


def _tables12(res: dict, out: Path, figures: list) -> list[str]:
    seqs = list(res)
    lines = ["## Tables 1-2: tests of the probability models (section V.A, Figs. 8-9)", "",
             "Held-out frames of each sequence; eq. 12 features of every triple in the heading-normalised frame "
             "(heading from the true labels); each triangle scored with its full 15-D mixture density.", "",
             f"* **Method 1 / Table 1** (\"the correct combination of markers should produce the highest "
             f"probability for the given model\"): for each triangle's model, is the true ordered triple the "
             f"single most likely of **all {res[seqs[0]]['candidates_method1']} ordered triples of distinct body "
             f"points** (every triple obtained by replacing one, two or three of its vertices, permutations "
             f"included)? Fraction of held-out frames, averaged over the 12 triangles.",
             "* **Method 2 / Table 2** (\"the corresponding model should also attain the highest probability\"): "
             "for each true triple, does its own triangle's mixture give it a higher density than each of the "
             "other 11 triangles' mixtures? The paper's wording (\"select the model corresponding to the maximum "
             "probability from 12 different models of a given triangle\") is read as maximum-likelihood "
             "classification of the triple's data among the 12 models; this is sound because every mixture is a "
             "normalised density on the same 15-D feature space.",
             "* The paper's literal alternative for method 1 (\"the triangle with the maximum probability from 12 "
             "different triangles for the given model\", candidates = only the 12 true triples) is reported as "
             "Table 1b; it is much easier than Table 1.", ""]
    for title, key, paper in (("Table 1 — method 1 (all ordered triples as candidates)", "mean_method1", PAPER_TABLE1),
                              ("Table 1b — method 1, candidates = the 12 true triples", "mean_method1_12", None),
                              ("Table 2 — method 2 (which of the 12 models fits the triple best)", "mean_method2",
                               PAPER_TABLE2)):
        header = ["Methods"] + [f"{s} ours" for s in seqs]
        if paper:
            header += ["paper W1", "paper W2", "paper R1", "paper D1"]
        rows = []
        for kind in MIXTURE_KINDS:
            nm = KIND_NAMES[kind]
            row = [nm] + [pct(res[s][kind][key], 2) for s in seqs]
            if paper:
                row += [_paper(paper, nm, c) for c in ("W1", "W2", "R1", "D1")]
            rows.append(row)
        lines += [f"**{title}**", "", md_table(header, rows), ""]
    lines.append("Held-out frames per sequence: " + ", ".join(f"{s} {res[s]['frames']}" for s in seqs) +
                 ". Components chosen by MDL (JMGW) per triangle: " +
                 "; ".join(f"{s} {res[s]['mdl']['components']}" for s in seqs) + ".")
    lines.append("")
    # worst triangles
    worst = []
    for s in seqs:
        m1 = np.asarray(res[s]["mdl"]["method1"])
        i = int(np.argmin(m1))
        worst.append(f"{s}: triangle {i + 1} ({', '.join(res[s]['triangles'][i])}) {pct(m1[i])}, "
                     f"mean rank of the true triple {res[s]['mdl']['method1_mean_rank'][i]:.1f}")
    lines += ["Weakest triangle under JMGW, method 1: " + "; ".join(worst) + ".", ""]
    plt = _plt()
    for fig_no, key, ttl in ((8, "method1", "method 1 (true triple vs all ordered triples)"),
                             (9, "method2", "method 2 (own model vs the other 11 models)")):
        fig, axes = plt.subplots(len(seqs), 1, figsize=(9, 2.2 * len(seqs) + 0.6), sharex=True, squeeze=False)
        for ax, s in zip(axes[:, 0], seqs):
            T = len(res[s]["mdl"][key])
            x = np.arange(1, T + 1)
            for j, kind in enumerate(MIXTURE_KINDS[::-1]):
                nm = KIND_NAMES[kind]
                ax.bar(x + (j - 1) * 0.27, 100 * np.asarray(res[s][kind][key]), width=0.27, color=COLORS[nm],
                       label=nm)
            ax.set_ylim(0, 105)
            ax.set_ylabel(f"{s}\naccuracy (%)")
            ax.set_xticks(x)
            ax.grid(axis="y", alpha=0.3)
        axes[0, 0].set_title(f"Fig. {fig_no} style: per-triangle accuracy, {ttl}")
        axes[0, 0].legend(ncol=3, fontsize=8, loc="lower left")
        axes[-1, 0].set_xlabel("triangle (order of the given structure)")
        name = _save(fig, out / f"fig{fig_no}_{key}_per_triangle.png", figures)
        lines += [f"![Fig. {fig_no}]({name})", ""]
    return lines


def _structure(res: dict, out: Path, figures: list) -> list[str]:
    seqs = list(res)
    p0 = res[seqs[0]]
    lines = ["## Structure search (section IV.A, Fig. 12)", "",
             f"Structures learned on the training frames with a Gaussian per triple (the entropy fitness of "
             f"eq. 18-20): CBGA and the simple GA with the same budget (population {p0['population']}, "
             f"{p0['generations']} generations, no early stop), Song et al.'s greedy construction, and the "
             f"hand-given structure. For each structure MDL mixtures were then fitted on the training part; "
             f"the table gives the mean log-likelihood per frame (nats, higher is better) of the training "
             f"frames and of the held-out frames under those models. The structure score is the GA's fitness "
             f"per training frame.", ""]
    rows = []
    for s in seqs:
        for name in ("cbga", "sga", "greedy", "given"):
            r = res[s]["structures"][name]
            rows.append([s, name, num(r["gaussian_score_per_frame"], ".2f"), num(r["train_loglik_per_frame"], ".2f"),
                         num(r["test_loglik_per_frame"], ".2f"), str(r["components"])])
    lines += [md_table(["seq", "structure", "GA score / frame", "train LL / frame", "held-out LL / frame",
                        "K per triangle"], rows), ""]
    best_test = {s: max(res[s]["structures"], key=lambda k: res[s]["structures"][k]["test_loglik_per_frame"])
                 for s in seqs}
    lines += ["Best held-out log-likelihood: " + ", ".join(f"{s} {b}" for s, b in best_test.items()) + ".", ""]
    plt = _plt()
    fig, axes = plt.subplots(1, len(seqs), figsize=(3.3 * len(seqs), 3.2), squeeze=False)
    for ax, s in zip(axes[0], seqs):
        for name, col in (("cbga", "tab:red"), ("sga", "tab:blue")):
            h = res[s]["structures"][name]["history_per_frame"]
            ax.plot(np.arange(len(h)), h, color=col, label=name.upper())
        ax.axhline(res[s]["structures"]["greedy"]["gaussian_score_per_frame"], color="k", ls="--", lw=1,
                   label="greedy")
        ax.axhline(res[s]["structures"]["given"]["gaussian_score_per_frame"], color="gray", ls=":", lw=1,
                   label="given")
        ax.set_title(s)
        ax.set_xlabel("generation")
        ax.grid(alpha=0.3)
    axes[0, 0].set_ylabel("best structure fitness / frame (nats)")
    axes[0, 0].legend(fontsize=8)
    fig.suptitle("Structure search: best fitness per generation, CBGA vs simple GA")
    name = _save(fig, out / "fig12_structure_search.png", figures)
    lines += [f"![structure search]({name})", "", "<details><summary>Structures (triangles, new vertex first)"
                                                  "</summary>", ""]
    for s in seqs:
        for nm in ("cbga", "sga", "greedy", "given"):
            tri = res[s]["structures"][nm]["triangles"]
            lines.append(f"* {s} {nm}: " + " ".join("(" + ",".join(t) + ")" for t in tri))
    lines += ["", "</details>", ""]
    return lines


def _cell_acc(c) -> str:
    return "n/a" if not c else pct(c["accuracy"], 2)


def _table3(res: dict, seqs_info: dict, out: Path, figures: list) -> list[str]:
    fr = res["frames"]
    seqs = list(fr["single"])
    lines = ["## Table 3: labeling accuracy (section V.B-C, Fig. 11)", "",
             "Within-sequence protocol (train first 9/10, test last 1/10). Single mode: "
             + ", ".join(f"{s} {fr['single'][s]} frames" for s in seqs) + "; stream mode: "
             + ", ".join(f"{s} {fr['stream'][s]} frames (greedy {fr['stream_greedy'][s]})" for s in seqs) +
             ". Paper columns are the paper's Table 3 (its W2 has no counterpart here).", ""]
    header = ["Methods"] + [f"{s} single" for s in seqs] + [f"{s} stream" for s in seqs] + \
             ["paper W1", "paper W2", "paper R1", "paper D1"]
    rows = []
    for name, *_ in TABLE3_ROWS:
        rows.append([name] + [_cell_acc(res["single"][name].get(s)) for s in seqs] +
                    [_cell_acc(res["stream"][name].get(s)) for s in seqs] +
                    [_paper(PAPER_TABLE3, name, c) for c in ("W1", "W2", "R1", "D1")])
    lines += [md_table(header, rows), ""]
    # search errors and latency
    rows = []
    for name, *_ in TABLE3_ROWS:
        row = [name]
        for mode in ("single", "stream"):
            for s in seqs:
                c = res[mode][name].get(s)
                row.append("n/a" if not c else f"{c['search_errors']}/{c['search_checked']} · "
                           f"{num(c['latency_ms']['p50'], '.0f')} ms")
        rows.append(row)
    lines += ["Search errors (frames where the true labeling scores higher than the chosen one / frames "
              "checked) and median latency per frame:", "",
              md_table(["Methods"] + [f"{s} single" for s in seqs] + [f"{s} stream" for s in seqs], rows), ""]
    # per-label figure (Fig. 11 style), single mode
    plt = _plt()
    fig, axes = plt.subplots(len(seqs), 1, figsize=(10, 2.4 * len(seqs) + 0.6), squeeze=False, sharex=True)
    cols = ["tab:blue", "tab:green", "tab:orange", "tab:purple", "tab:red", "darkred"]
    labels = None
    for ax, s in zip(axes[:, 0], seqs):
        for j, (name, *_r) in enumerate(TABLE3_ROWS):
            c = res["single"][name].get(s)
            if not c:
                continue
            labels = list(c["per_label"])
            v = [100 * (c["per_label"][k] if c["per_label"][k] is not None else np.nan) for k in labels]
            ax.bar(np.arange(len(labels)) + (j - 2.5) * 0.13, v, width=0.13, color=cols[j], label=name)
        ax.set_ylim(0, 105)
        ax.set_ylabel(f"{s}\naccuracy (%)")
        ax.grid(axis="y", alpha=0.3)
    if labels:
        axes[-1, 0].set_xticks(np.arange(len(labels)))
        axes[-1, 0].set_xticklabels(labels, rotation=45, ha="right")
    axes[0, 0].legend(ncol=3, fontsize=7, loc="lower left")
    axes[0, 0].set_title("Fig. 11 style: per-point accuracy, single mode")
    name = _save(fig, out / "fig11_per_point_accuracy.png", figures)
    lines += [f"![Fig. 11]({name})", ""]
    return lines


def _curve_fig(out, figures, fname, title, xlabel, series: dict, xs_key=None) -> str:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6, 4))
    for label, (xs, ys) in series.items():
        ax.plot(xs, 100 * np.asarray(ys, dtype=float), marker="o", label=label)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("accuracy (%)")
    ax.set_title(title)
    ax.set_ylim(0, 102)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    return _save(fig, out / fname, figures)


def _acc(c):
    return np.nan if not c or c.get("accuracy") is None else c["accuracy"]


def _occlusion(res: dict, meta: dict, out: Path, figures: list) -> list[str]:
    series, rows = {}, []
    levels = [int(x) for x in meta["plan"]["occlusion_levels"]]
    for method, per_seq in res.items():
        for s, cells in per_seq.items():
            ys = [_acc(cells.get(str(k))) for k in levels]
            series[f"{method} {s}"] = (levels, ys)
            rows.append([f"{method} {s}"] + [pct(y) for y in ys])
    name = _curve_fig(out, figures, "fig13_occlusion.png", "Fig. 13 style: accuracy vs occluded points (single mode)",
                      "points hidden per frame (of 14)", series)
    return ["## Fig. 13: occlusion", "",
            "Single mode, K true points hidden at random in every frame (a new set each frame, also in the "
            "priming frame); accuracy over the remaining visible points. Paper: \"more than 80 % when less than "
            "three points are occluded\".", "",
            md_table(["method / seq"] + [f"{k} hidden" for k in levels], rows), "", f"![Fig. 13]({name})", ""]


def _noise(res: dict, meta: dict, out: Path, figures: list) -> list[str]:
    levels = list(meta["plan"]["noise_levels_mm"])
    series, rows = {}, []
    for method, cells in res.items():
        ys = [_acc(cells.get(str(k), cells.get(str(float(k))))) for k in levels]
        series[method] = (levels, ys)
        rows.append([method] + [pct(y) for y in ys])
    seq = meta["plan"]["noise_seq"]
    name = _curve_fig(out, figures, "fig14_noise.png", f"Fig. 14 style: accuracy vs position noise ({seq}, single)",
                      "Gaussian noise std per coordinate (mm)", series)
    return ["## Fig. 14: measurement noise", "",
            f"Single mode on {seq}; i.i.d. Gaussian noise added to every coordinate of every point (test only; "
            f"the models were trained on clean data). At 120 Hz, noise also enters the velocities "
            f"(σ_v = √2·σ·120 per axis, e.g. 1.7 m/s at 10 mm). The labeler is told the noise level "
            f"(`noise_mm`, as a user sets it for a known system), which widens the model by it.", "",
            md_table(["method"] + [f"{k:g} mm" for k in levels], rows), "", f"![Fig. 14]({name})", ""]


def _voting(res: dict, meta: dict, out: Path, figures: list) -> list[str]:
    windows = [int(w) for w in meta["plan"]["windows"]]
    series, rows = {}, []
    for s, cells in res.items():
        ys = [_acc(cells.get(str(w))) for w in windows]
        series[f"MixGM+CBGA {s}"] = (windows, ys)
        rows.append([s] + [pct(y) for y in ys])
    occ = meta["plan"]["voting_occlude"]
    name = _curve_fig(out, figures, "fig15_voting.png",
                      f"Fig. 15 style: accuracy vs voting frames (stream, {occ} occluded/frame)",
                      "vote window (frames)", series)
    return ["## Fig. 15: voting over frames", "",
            f"Stream mode (MixGM+CBGA, given structure) with {occ} points hidden at random in every frame, so "
            f"single-frame labels are imperfect; the window is the number of frames whose per-track votes are "
            f"combined (eq. 32). The labeler also warm-starts from the tracks' labels, so window 1 is already "
            f"better than single mode.", "",
            md_table(["seq"] + [f"W={w}" for w in windows], rows), "", f"![Fig. 15]({name})", ""]


def _generations(res: dict, out: Path, figures: list) -> list[str]:
    plt = _plt()
    fig, ax = plt.subplots(figsize=(6.5, 4))
    cols = {"W1": "tab:blue", "R1": "tab:green", "D1": "tab:red"}
    rows = []
    for s, r in res.items():
        g = np.arange(len(r["mean_cbga"]))
        c = cols.get(s, None)
        ax.plot(g, r["mean_cbga"], color=c, lw=2, label=f"CBGA {s}")
        ax.plot(g, r["mean_sga"], color=c, lw=1, ls="--", label=f"SGA {s}")
        ax.axhline(r["mean_truth"], color=c, lw=0.8, ls=":")
        pf = [x for x in r["cbga_reaches_sga_final_per_frame"] if x is not None]
        rows.append([s, len(r["frames"]), num(r["mean_truth"]), num(r["mean_sga"][-1]), num(r["mean_cbga"][-1]),
                     str(r["cbga_reaches_sga_final_at"]),
                     f"{int(np.median(pf)) if pf else 'n/a'} ({len(pf)}/{len(r['frames'])})",
                     pct(r["sga_reaches_truth_frac"], 0), pct(r["cbga_reaches_truth_frac"], 0)])
    ax.set_xlabel("generation")
    ax.set_ylabel("best fitness (mean over frames)")
    ax.set_title("Fig. 10 style: label search, CBGA (solid) vs SGA (dashed); dotted = true labeling")
    ax.title.set_fontsize(9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    lo = min(min(r["mean_sga"][1:] + r["mean_cbga"][1:]) for r in res.values())
    hi = max(max(r["mean_cbga"] + [r["mean_truth"]]) for r in res.values())
    ax.set_ylim(lo - 0.05 * (hi - lo), hi + 0.05 * (hi - lo))
    name = _save(fig, out / "fig10_generations.png", figures)
    any_r = next(iter(res.values()))
    return ["## Fig. 10: label-search fitness vs generation", "",
            f"The same held-out frames (clean, shuffled, velocities from the previous frame) searched by CBGA "
            f"and by the simple GA, population {any_r['population']}, {any_r['generations']} generations, no early "
            f"stop and no final polish (the GAs alone). Fitness = relative log-likelihood of the labeling "
            f"(frame_problem); the dotted line is the true labeling's fitness. Paper: CBGA needs 50-100 "
            f"generations, SGA converges after ~500.", "",
            md_table(["seq", "frames", "true labeling", "SGA final", "CBGA final",
                      "gen. where mean CBGA ≥ SGA final", "median per-frame gen. (frames reaching)",
                      "SGA reaches truth", "CBGA reaches truth"], rows), "", f"![Fig. 10]({name})", ""]


def _aug_text(aug: dict | None) -> str:
    if not aug:
        return ""
    d = aug["default"]
    n = d["augment_copies"]
    return (f"Training augmentation (`dtm-train` defaults for the 14 body points): {n} augmented cop{'y' if n == 1 else 'ies'} of every "
            f"frame, each copied frame with a random body (isotropic scale sd {d['scale_jitter']:g}, independent "
            f"length factor per segment of the most rigid point-to-point tree sd {d['proportion_jitter']:g}; "
            f"positions and velocities transformed together) and a random tempo (velocities times a factor of "
            f"sd {d['tempo_jitter']:g}), plus the ±{d['yaw_jitter_deg']:g}° yaw jitter. The \"no body aug.\" "
            f"columns train the same model with scale, proportion and tempo jitter 0 (yaw jitter kept), i.e. the "
            f"training before the augmentation existed.")


def _cross(res: dict, out: Path) -> list[str]:
    folds = res["folds"]
    rows = []
    for subj, f in folds.items():
        for tk in f["test"]:
            cells = res.get(subj, {}).get(tk, {})
            rows.append([subj, tk, ", ".join(f["train"]),
                         _cell_acc(cells.get("MixGM+CBGA single")), _cell_acc(cells.get("MixGM+Greedy single")),
                         _cell_acc(cells.get("MixGM+CBGA stream")),
                         "n/a" if not cells.get("MixGM+CBGA single") else
                         f"{cells['MixGM+CBGA single']['search_errors']}/{cells['MixGM+CBGA single']['search_checked']}",
                         _cell_acc(cells.get("no body aug. single")), _cell_acc(cells.get("no body aug. stream"))])
    lines = ["## Cross-subject protocol", "",
             "Leave one CMU subject out: an MDL model (given structure) is trained on every sequence of the other "
             "subjects and tested on the held-out subject's whole clip(s) (single mode: frames spread over the "
             "clip; stream mode: the clip's first frames). Caveat: the BVH sequences (W1, R1, D1) come from the "
             "cgspeed skeleton that lacks the ASF thorax segment, so their neck/head/shoulders sit ~11.6 cm lower "
             "relative to the pelvis than in the AMC sequences (D2, D3); mixed training/test sets therefore also "
             "measure a skeleton-definition shift, not only a subject change. With one clip per motion class, a "
             "held-out walk or run is labelled by a model that never saw that kind of motion.", ""]
    if res.get("augmentation"):
        lines += [_aug_text(res["augmentation"]), ""]
    lines += [md_table(["held-out subject", "test clip", "trained on", "MixGM+CBGA single", "MixGM+Greedy single",
                        "MixGM+CBGA stream", "search errors (CBGA single)", "CBGA single, no body aug.",
                        "CBGA stream, no body aug."], rows), ""]
    new = res.get("new_subjects") or {}
    if new:
        cells = res.get("new", {})
        nrows = [[f"{v['title']} (`{v['path']}`)", f"{v['rate']:g} Hz",
                  _cell_acc(cells.get(k, {}).get("single")), _cell_acc(cells.get(k, {}).get("stream")),
                  _cell_acc(cells.get(k, {}).get("no body aug. single")),
                  _cell_acc(cells.get(k, {}).get("no body aug. stream"))] for k, v in new.items()]
        first = next(iter(new.values()))
        train = ", ".join(first["train"]) + (f": subjects {', '.join(first['train_subjects'])}"
                                             if first.get("train_subjects") else "")
        lines += ["New subjects, same kinds of motion: one MDL model (given structure) trained on the CMU "
                  f"skeletal sequences ({train}) labels people outside the CMU set. Their 14 "
                  "body points are derived from surface markers (hip = pelvis landmarks above the joint, elbow/"
                  "wrist/knee/ankle = marker means), a point definition that differs from the skeleton joints "
                  "the model was trained on, in addition to the new body and movement style.", "",
                  md_table(["recording", "rate", "CBGA single", "CBGA stream", "CBGA single, no body aug.",
                            "CBGA stream, no body aug."], nrows), ""]
    return lines


def _markers(res: dict, out: Path) -> list[str]:
    files = res["files"]
    rows = []
    for k, f in files.items():
        c = res.get(k, {})
        cl, gp, gh, sg = c.get("clean"), c.get("gaps"), c.get("clutter"), c.get("single")
        rows.append([f"{k} ({f['points']} pts, {f['rate']:g} Hz)", f"{100 * f['test_missing_fraction']:.2f} %",
                     _cell_acc(cl), _cell_acc(gp), _cell_acc(gh),
                     "n/a" if not gh else pct(gh["ghost_rejection"]),
                     _cell_acc(sg),
                     "n/a" if not cl else f"{num(cl['latency_ms']['p50'], '.0f')} / {num(cl['latency_ms']['p99'], '.0f')}",
                     "n/a" if not sg else f"{num(sg['latency_ms']['p50'], '.0f')}",
                     "n/a" if not cl else f"{num(cl['swaps_per_min'], '.0f')}"])
    return ["## Marker recordings at all markers", "",
            "Models over every labelled marker (`--points all`, structure by CBGA, MDL mixtures with K ≤ "
            "4 to bound training time, no body augmentation: `dtm-train`'s default for point sets other than the "
            "14 body points) trained on the frames before the held-out last tenth (at most the last "
            "1500 of them), tested in stream mode (MixGM+CBGA) on the first frames of the held-out tenth: clean "
            "(the MoCap Toolbox walk has real gaps), with simulated gaps (3 markers hidden at a time, mean gap "
            "12 frames), and with 3 ghost points near the body (clutter). Single mode on a few frames shows the "
            "cost of a full search from scratch.", "",
            md_table(["recording", "real missing (test)", "stream clean", "stream gaps", "stream clutter",
                      "ghost rejection", "single mode", "stream latency p50/p99 (ms)", "single latency p50 (ms)",
                      "swaps/min (clean)"], rows), "",
            "Stream frames per recording: " + ", ".join(
                f"{k} {res[k]['clean']['frames']}" for k in files if res.get(k, {}).get("clean")) + ".", ""]


GEN_COLORS = {"today": "tab:gray", "body": "tab:blue", "body + calibration": "tab:green",
              "dtm-label default": "tab:orange"}


def _gen_acc(cell: dict | None, mode: str) -> str:
    if not cell or mode not in cell:
        return "n/a" if not cell or "subject_calibration_error" not in cell else "calibration failed"
    return pct(cell[mode]["accuracy"], 2)


def _generalisation(res: dict, out: Path, figures: list) -> list[str]:
    from .generalisation import GROUPS, VARIANTS
    cases, results, plan = res["cases"], res["results"], res["plan"]
    lines = ["## Generalisation: other takes, other motions, other people", "",
             "Models trained on some recordings label another one (labels stripped, points shuffled). **today** = "
             "the motion mixtures alone (as before the body model: a format-1 model); **body** = the same "
             "training with the motion-independent body terms on the DTM's edges (`dtm-train`'s default): a generic "
             "body, of which only the reach limits apply (segment lengths and the broad motion component wait for "
             "a calibration); **body + calibration** = that model "
             f"calibrated on the first ≤ {plan['calibration_s']:g} s of the test recording (at most a third of "
             "it; its points shuffled as the labeler gets them), labelled by the model itself and kept where the "
             "votes confirm it (no true label used; a "
             "segment whose confirmed length disagrees with its mirror's is dropped and takes the mirror's "
             "length; the segments of a label whose point lies on the wrong side of the trunk keep the generic "
             "range), then its segment lengths, reach limits and the broad motion component apply; **dtm-label "
             "default** = what `dtm-train` then `dtm-label` give with their defaults: `dtm-train` calibrates the "
             "body to its training takes' person when they are one person (one capture, or CMU takes of one "
             "subject), and `dtm-label --calibrate auto` labels a capture of that person with that calibration "
             "(no window of the test used but to check, on another take, for markers placed elsewhere that "
             "session -- those segments measured again -- and to fit the broad weights to the take's motion), "
             "anyone else's with the generic body self-calibrated on the same "
             "window (its points shuffled as the labeler gets them), kept only when the calibrated model keeps "
             ">= 90 % of the labels the model confirmed there, else with the training person's calibration (the "
             "generic model when the training takes are several people). All "
             "variants are scored on the same frames after the calibration window: stream mode on the first "
             f"{plan['stream_frames']} of them ({plan['marker_stream_frames']} at 41 markers), single mode on "
             f"{plan['single_frames']} ({plan['marker_single_frames']}) frames spread over them. Model errors = "
             "frames whose search result is wrong although the true labeling scores lower (the model prefers the "
             "wrong one); the rest of the wrong frames are search errors. The *generic model* group labels each "
             "person with a model of every other person in the shared data (the other CMU subjects' skeletal clips "
             "and the 14 points derived from the marker takes' people), leaving out every recording of the person "
             "labelled.", ""]
    if res.get("note"):
        lines += [res["note"], ""]
    header = ["case", "trained on → tested on"] + [f"{v} {m}" for v in VARIANTS for m in ("stream", "single")] + \
        ["model / search errors (today → body → calibrated → dtm-label default)"]
    for group in GROUPS:
        rows = []
        for key, info in cases.items():
            if info["group"] != group:
                continue
            r = results.get(key, {})
            diag = [r.get(v, {}).get("diagnosis") for v in VARIANTS]
            err = " → ".join("n/a" if not d else f"{d['model_errors']} / {d['search_errors']}" for d in diag)
            train = ", ".join(t["spec"] for t in info["train"])
            rows.append([info["title"] + (f" ({info['note']})" if info["note"] else ""),
                         f"{train} → {info['test']['spec']}"]
                        + [_gen_acc(r.get(v), m) for v in VARIANTS for m in ("stream", "single")] + [err])
        if rows:
            lines += [f"**{group}**", "", md_table(header, rows), ""]
    for variant, who in (("today", "today's"), ("body + calibration", "the calibrated model's")):
        worst = []
        for key, info in cases.items():
            d = results.get(key, {}).get(variant, {}).get("diagnosis")
            if d and d["worst_triangles"]:
                w = d["worst_triangles"][0]
                worst.append(f"{info['title']}: ({', '.join(w['triangle'])}) {w['truth_minus_chosen']:.1f} nats "
                             f"(body terms {w['body_part']:.1f})")
        if worst:
            lines += [f"Where {who} truth loses (mean fitness of the true minus the chosen labeling over the "
                      "model's error frames, worst triangle; of it, the body terms' part): " + "; ".join(worst) + ".",
                      ""]
    lat = [results[k]["body"]["stream"]["latency_ms"] for k in cases if results.get(k, {}).get("body", {}).get("stream")]
    lat0 = [results[k]["today"]["stream"]["latency_ms"] for k in cases
            if results.get(k, {}).get("today", {}).get("stream")]
    if lat and lat0:
        lines += [f"Stream latency (median over cases of the per-run p50 / p99): today "
                  f"{np.median([x['p50'] for x in lat0]):.1f} / {np.median([x['p99'] for x in lat0]):.1f} ms, body "
                  f"{np.median([x['p50'] for x in lat]):.1f} / {np.median([x['p99'] for x in lat]):.1f} ms.", ""]
    keys = [k for k in cases if k in results]
    if keys:
        plt = _plt()
        fig, axes = plt.subplots(2, 1, figsize=(max(8.0, 0.9 * len(keys) + 2), 7), sharex=True)
        x = np.arange(len(keys))
        for ax, mode in zip(axes, ("stream", "single")):
            for i, v in enumerate(VARIANTS):
                acc = [100 * (results[k].get(v, {}).get(mode) or {}).get("accuracy", np.nan) for k in keys]
                w = 0.8 / len(VARIANTS)
                ax.bar(x + (i - (len(VARIANTS) - 1) / 2) * w, acc, w, color=GEN_COLORS[v], label=v)
            ax.set_ylabel(f"{mode} accuracy (%)")
            ax.set_ylim(0, 101)
            ax.axhline(97, color="k", lw=0.6, ls=":")
            ax.grid(axis="y", alpha=0.3)
        axes[0].legend(loc="upper left", bbox_to_anchor=(1.005, 1.0), fontsize=8)
        axes[1].set_xticks(x, keys, rotation=35, ha="right", fontsize=8)
        axes[0].set_title("Generalisation: today, body terms, + calibration, dtm-label's default")
        name = _save(fig, out / "fig_generalisation.png", figures)
        lines += [f"![generalisation]({name})", ""]
    return lines
def _stream_cells(results: dict, path: tuple = ()):
    """(path, cell) of every stream-mode cell with reliability bins, anywhere in ``results``."""
    if isinstance(results, dict):
        if results.get("reliability") and "accuracy" in results:
            yield path, results
            return
        for k, v in results.items():
            yield from _stream_cells(v, path + (str(k),))


def pooled_reliability(cells) -> tuple[list, float | None]:
    """Reliability bins of several cells pooled (bins by their lower edge) and their ECE."""
    acc: dict[float, list] = {}
    for c in cells:
        for lo, hi, n, conf, right in c["reliability"]:
            a = acc.setdefault(lo, [lo, hi, 0, 0.0, 0.0])
            a[2] += n
            a[3] += n * conf
            a[4] += n * right
    rows = [[lo, hi, n, cs / n, r / n] for lo, hi, n, cs, r in (acc[k] for k in sorted(acc)) if n]
    total = sum(r[2] for r in rows)
    ece = sum(r[2] * abs(r[3] - r[4]) for r in rows) / total if total else None
    return rows, ece


def _confidence(results: dict, out: Path, figures: list) -> list[str]:
    """Reliability of the published confidences over every stream cell of this run."""
    cells = list(_stream_cells(results))
    if not cells:
        return []
    rows, ece = pooled_reliability(c for _, c in cells)
    plt = _plt()
    fig, ax = plt.subplots(figsize=(4.6, 4.2))
    mid = [(r[0] + r[1]) / 2 for r in rows]
    ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--", label="calibrated")
    ax.bar(mid, [r[4] for r in rows], width=0.09, alpha=0.6, label="fraction right")
    ax.plot([r[3] for r in rows], [r[4] for r in rows], "o-", color="C3", label="mean confidence")
    ax.set_xlabel("published confidence")
    ax.set_ylabel("fraction of labels right")
    ax.set_xlim(0, 1), ax.set_ylim(0, 1.02)
    ax.legend(loc="upper left", fontsize=8)
    ax.set_title(f"reliability, ECE {100 * ece:.1f} %")
    name = _save(fig, out / "fig_reliability.png", figures)
    per = sorted(((c["calibration_error"], "/".join(p)) for p, c in cells if c.get("calibration_error") is not None),
                 reverse=True)[:5]
    groups = reliability_groups(cells)
    return ["## Confidence: can a consumer threshold it?", "",
            "Every label the labeler publishes carries a confidence (`labeling/confidence.py`: the local "
            "posterior of the label among the labelings one move away, the share of the vote window behind "
            "it, and how far the frame fits below the model's training fit). Of the labels published with "
            "confidence c, about a fraction c should be right. Pooled over the "
            f"{len(cells)} stream-mode cells of this report ({sum(r[2] for r in rows)} labels), in ten bins "
            f"of confidence: expected calibration error **{pct(ece)}**.", "",
            md_table(["confidence", "labels", "mean confidence", "fraction right"],
                     [[f"{r[0]:.1f}-{r[1]:.1f}", str(r[2]), f"{r[3]:.3f}", f"{r[4]:.3f}"] for r in rows]), "",
            f"![reliability]({name})", "",
            "By part of the report (the generalisation section by model variant: *today* is the motion "
            "mixtures alone, the model format before the body terms, kept as the baseline column):", "",
            md_table(["part", "cells", "labels", "fraction right", "mean confidence", "ECE"],
                     [[g, str(k), str(n), f"{right:.3f}", f"{conf:.3f}", pct(e)] for g, k, n, right, conf, e in groups]),
            "",
            "Least calibrated cells: " + "; ".join(f"{p} {pct(e)}" for e, p in per) + ".", ""]


def reliability_groups(cells: list) -> list[tuple]:
    """(group, cells, labels, fraction right, mean confidence, ECE) of the stream cells ``cells``
    ((path, cell) pairs) pooled by the report's section -- the generalisation section by model
    variant (the path's second-to-last part) -- and of all of them but the generalisation
    section's *today* baseline."""
    def group(path):
        return f"{path[0]}: {path[-2]}" if path[0] == "generalisation" and len(path) >= 2 else path[0]
    keys = list(dict.fromkeys(group(p) for p, _ in cells))
    sets = [(k, [c for p, c in cells if group(p) == k]) for k in keys]
    sets.append(("all but generalisation: today", [c for p, c in cells if group(p) != "generalisation: today"]))
    out = []
    for k, cs in sets:
        rows, ece = pooled_reliability(cs)
        n = sum(r[2] for r in rows)
        if n:
            out.append((k, len(cs), n, sum(r[2] * r[4] for r in rows) / n, sum(r[2] * r[3] for r in rows) / n, ece))
    return out


def write_report(out_dir: Path, results: dict, meta: dict) -> dict:
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    figures: list[str] = []
    lines = _intro(meta, results)
    if "tables12" in results:
        lines += _tables12(results["tables12"], out_dir, figures)
    if "structure" in results:
        lines += _structure(results["structure"], out_dir, figures)
    if "table3" in results and "single" in results["table3"]:
        lines += _table3(results["table3"], results.get("sequences", {}), out_dir, figures)
    if "generations" in results:
        lines += _generations(results["generations"], out_dir, figures)
    if "occlusion" in results:
        lines += _occlusion(results["occlusion"], meta, out_dir, figures)
    if "noise" in results:
        lines += _noise(results["noise"], meta, out_dir, figures)
    if "voting" in results:
        lines += _voting(results["voting"], meta, out_dir, figures)
    if "cross" in results and "folds" in results["cross"]:
        lines += _cross(results["cross"], out_dir)
    if "markers" in results and "files" in results["markers"]:
        lines += _markers(results["markers"], out_dir)
    if "generalisation" in results and "cases" in results["generalisation"]:
        lines += _generalisation(results["generalisation"], out_dir, figures)
    lines += _confidence(results, out_dir, figures)
    if meta.get("notes"):
        lines += ["## Notes", ""] + [f"* {n}" for n in meta["notes"]] + [""]
    report = out_dir / "report.md"
    report.write_text("\n".join(lines) + "\n", encoding="utf-8")
    (out_dir / "results.json").write_text(json.dumps({"meta": meta, "results": results}, indent=1,
                                                     default=json_default) + "\n", encoding="utf-8")
    return {"report": report, "figures": figures}
