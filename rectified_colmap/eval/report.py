"""Tables and plots from relative-pose records (rectified_colmap.eval.relpose).

- Success per ground-truth rotation bin (the paper's Figure 5): fraction of pairs whose
  rotation error is under the success threshold, bins of ``bin_deg`` over [0, 180].
- Pose AUC at 5/10/20 degrees of max(rotation, translation-angle) error (SuperGlue's
  protocol: area under the cumulative error curve up to each threshold, normalised).
- Degeneracy-aware columns: median number of GT-correct matches and the fraction of pairs
  with at least ``min_correct`` of them.
- Paired comparison with a baseline method (the first one): methods run on the same pairs,
  so the noise of a success difference is judged on the discordant pairs (exact McNemar
  test) and the GT-correct counts by a sign test over pairs, overall and per bin.

Markdown and CSV are plain text; the PNG needs matplotlib (the ``[eval]`` extra), imported
lazily with a clear error when absent.
"""

from __future__ import annotations

import csv
import io
import json
import logging
from pathlib import Path

import numpy as np

logger = logging.getLogger(__name__)

RECORD_FIELDS = [
    "name0",
    "name1",
    "method",
    "gt_rot",
    "viewpoint",
    "category",
    "num_kp0",
    "num_kp1",
    "num_matches",
    "num_inliers",
    "num_correct",
    "num_inliers_correct",
    "R_err",
    "t_err",
    "pose_err",
    "success",
    "success_rate",
    "epipolar_success",
]


BIN_LABELS = {"gt_rot": "GT rotation (deg)", "viewpoint": "viewpoint change (deg)"}
"""What the per-bin tables can bin by: the record field and its column title. ``viewpoint``
(optional, None where unknown): the median angle between the two viewing rays of the
pair's co-visible 3D points (rectified_colmap.eval.wide_pairs)."""


def with_field(records: list[dict], by: str) -> list[dict]:
    """The records whose ``by`` field is known (not None, not missing)."""
    return [r for r in records if r.get(by) is not None]


def methods_of(records: list[dict]) -> list[str]:
    return list(dict.fromkeys(r["method"] for r in records))


def bin_edges(bin_deg: float = 10.0, max_deg: float = 180.0) -> np.ndarray:
    if bin_deg <= 0:
        raise ValueError(f"bin width must be positive, got {bin_deg}")
    edges = np.arange(0.0, max_deg, bin_deg)
    return np.append(edges, max_deg)


def bin_index(angles: np.ndarray, edges: np.ndarray) -> np.ndarray:
    """Bin of each angle: [e_k, e_k+1), the last bin closed at 180."""
    return np.clip(np.searchsorted(edges, angles, side="right") - 1, 0, len(edges) - 2)


def pose_auc(errors: np.ndarray, thresholds=(5.0, 10.0, 20.0)) -> list[float]:
    """Area under the recall-vs-error curve up to each threshold, divided by it (in [0, 1])."""
    errors = np.sort(np.asarray(errors, float))
    n = len(errors)
    if n == 0:
        return [float("nan")] * len(thresholds)
    recall = np.arange(1, n + 1) / n
    errors = np.concatenate([[0.0], errors])
    recall = np.concatenate([[0.0], recall])
    out = []
    for t in thresholds:
        last = np.searchsorted(errors, t)
        r = np.concatenate([recall[:last], [recall[last - 1]]])
        e = np.concatenate([errors[:last], [t]])
        out.append(float(np.trapezoid(r, x=e) / t))
    return out


def success_by_bin(
    records: list[dict], bin_deg: float = 10.0, key: str = "success", by: str = "gt_rot"
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """method -> (success rate per bin of ``by`` (NaN for empty bins), pair count per bin)."""
    edges = bin_edges(bin_deg)
    out = {}
    for m in methods_of(records):
        rs = [r for r in records if r["method"] == m]
        b = bin_index(np.array([r[by] for r in rs]), edges)
        s = np.array([r[key] for r in rs], float)
        count = np.bincount(b, minlength=len(edges) - 1)
        hits = np.bincount(b, weights=s, minlength=len(edges) - 1)
        with np.errstate(invalid="ignore", divide="ignore"):
            out[m] = (np.where(count > 0, hits / np.maximum(count, 1), np.nan), count)
    return out


def median_by_bin(
    records: list[dict], bin_deg: float, key: str, by: str = "gt_rot"
) -> dict[str, np.ndarray]:
    """method -> median of ``key`` per bin of ``by`` (NaN for empty bins)."""
    edges = bin_edges(bin_deg)
    out = {}
    for m in methods_of(records):
        rs = [r for r in records if r["method"] == m]
        b = bin_index(np.array([r[by] for r in rs]), edges)
        v = np.array([r[key] for r in rs], float)
        out[m] = np.array(
            [np.median(v[b == k]) if np.any(b == k) else np.nan for k in range(len(edges) - 1)]
        )
    return out


def summary(records: list[dict], auc_thresholds=(5.0, 10.0, 20.0)) -> list[dict]:
    """One row per method: counts, success rates, AUCs, GT-correct matches."""
    rows = []
    for m in methods_of(records):
        rs = [r for r in records if r["method"] == m]
        aucs = pose_auc([r["pose_err"] for r in rs], auc_thresholds)
        row = {
            "method": m,
            "pairs": len(rs),
            "success": float(np.mean([r["success"] for r in rs])),
            "success_rate": float(np.mean([r.get("success_rate", r["success"]) for r in rs])),
            "epipolar_success": float(np.mean([r["epipolar_success"] for r in rs])),
            "median_matches": float(np.median([r["num_matches"] for r in rs])),
            "median_correct": float(np.median([r["num_correct"] for r in rs])),
            "median_R_err": float(np.median([r["R_err"] for r in rs])),
        }
        for t, a in zip(auc_thresholds, aucs):
            row[f"auc@{t:g}"] = a
        rows.append(row)
    return rows


def binomial_two_sided_p(k: int, n: int) -> float:
    """Exact two-sided p-value of k successes in n fair coin flips (McNemar / sign test)."""
    if n == 0:
        return 1.0
    from math import comb

    tail = sum(comb(n, i) for i in range(0, min(k, n - k) + 1)) / 2.0**n
    return float(min(1.0, 2.0 * tail))


def paired_comparison(
    records: list[dict], baseline: str, bin_deg: float = 10.0, by: str = "gt_rot"
) -> list[dict]:
    """Each other method against ``baseline`` on the pairs both have, per bin of ``by`` (GT
    rotation or viewpoint change, BIN_LABELS) and overall (``bin`` = None):
    ``wins``/``losses`` = pairs only the method / only the baseline solves, ``p_success``
    (exact McNemar), ``more``/``fewer`` = pairs with more / fewer GT-correct matches than
    the baseline, ``p_correct`` (sign test, ties dropped) and ``median_ratio`` of GT-correct
    counts (method / baseline, pairs where the baseline has any).
    """
    key = lambda r: (r["name0"], r["name1"])  # noqa: E731
    base = {key(r): r for r in records if r["method"] == baseline}
    if not base:
        raise ValueError(f"no records of the baseline method {baseline!r}")
    edges = bin_edges(bin_deg)
    rows = []
    for m in methods_of(records):
        if m == baseline:
            continue
        pairs = [(base[key(r)], r) for r in records if r["method"] == m and key(r) in base]
        if not pairs:
            continue
        b = bin_index(np.array([p[0][by] for p in pairs]), edges)
        s0 = np.array([p[0]["success"] for p in pairs], bool)
        s1 = np.array([p[1]["success"] for p in pairs], bool)
        c0 = np.array([p[0]["num_correct"] for p in pairs], float)
        c1 = np.array([p[1]["num_correct"] for p in pairs], float)
        for k in [None] + sorted(set(b.tolist())):
            sel = np.ones(len(pairs), bool) if k is None else b == k
            wins, losses = int((s1 & ~s0)[sel].sum()), int((s0 & ~s1)[sel].sum())
            more, fewer = int((c1 > c0)[sel].sum()), int((c1 < c0)[sel].sum())
            has = sel & (c0 > 0)
            rows.append(
                {
                    "method": m,
                    "bin": None if k is None else (edges[k], edges[k + 1]),
                    "pairs": int(sel.sum()),
                    "wins": wins,
                    "losses": losses,
                    "p_success": binomial_two_sided_p(wins, wins + losses),
                    "more": more,
                    "fewer": fewer,
                    "p_correct": binomial_two_sided_p(more, more + fewer),
                    "median_ratio": float(np.median(c1[has] / c0[has]))
                    if has.any()
                    else float("nan"),
                }
            )
    return rows


def paired_markdown(
    records: list[dict], baseline: str, bin_deg: float = 10.0, by: str = "gt_rot"
) -> str:
    """:func:`paired_comparison` as a Markdown table (p < 0.05 in bold)."""
    head = [
        "method vs " + baseline,
        BIN_LABELS[by],
        "pairs",
        "solved only by method",
        "solved only by baseline",
        "McNemar p",
        "more GT-correct",
        "fewer GT-correct",
        "sign-test p",
        "median GT-correct ratio",
    ]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    fmt = lambda p: f"**{p:.3f}**" if p < 0.05 else f"{p:.3f}"  # noqa: E731
    for r in paired_comparison(records, baseline, bin_deg, by):
        rng = "all" if r["bin"] is None else f"{r['bin'][0]:g}-{r['bin'][1]:g}"
        lines.append(
            "| "
            + " | ".join(
                [
                    r["method"],
                    rng,
                    str(r["pairs"]),
                    str(r["wins"]),
                    str(r["losses"]),
                    fmt(r["p_success"]),
                    str(r["more"]),
                    str(r["fewer"]),
                    fmt(r["p_correct"]),
                    "-" if np.isnan(r["median_ratio"]) else f"{r['median_ratio']:.2f}",
                ]
            )
            + " |"
        )
    return "\n".join(lines) + "\n"


def _pct(v: float) -> str:
    return "-" if np.isnan(v) else f"{100 * v:.1f}"


def markdown_table(
    records: list[dict],
    bin_deg: float = 10.0,
    auc_thresholds=(5.0, 10.0, 20.0),
    success_deg: float = 5.0,
    min_correct: int | None = None,
    by: str = "gt_rot",
    ransac_runs: int = 1,
) -> str:
    """Two Markdown tables: per-method summary, then success (%) per bin of ``by`` (GT
    rotation or viewpoint change, BIN_LABELS). With ``ransac_runs`` > 1 the summary also has
    the mean success over the RANSAC runs (records' ``success_rate``)."""
    rows = summary(records, auc_thresholds)
    mc = f" (>= {min_correct} GT-correct)" if min_correct is not None else ""
    runs = [f"success, mean of {ransac_runs} RANSAC runs %"] if ransac_runs > 1 else []
    head = (
        ["method", "pairs", f"success (R err < {success_deg:g} deg) %"]
        + runs
        + [f"epipolar success{mc} %"]
        + [f"AUC@{t:g} %" for t in auc_thresholds]
        + ["median matches", "median GT-correct", "median R err (deg)"]
    )
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in rows:
        vals = (
            [r["method"], str(r["pairs"]), _pct(r["success"])]
            + ([_pct(r["success_rate"])] if runs else [])
            + [_pct(r["epipolar_success"])]
            + [_pct(r[f"auc@{t:g}"]) for t in auc_thresholds]
            + [
                f"{r['median_matches']:.0f}",
                f"{r['median_correct']:.0f}",
                f"{r['median_R_err']:.2f}",
            ]
        )
        lines.append("| " + " | ".join(vals) + " |")
    edges = bin_edges(bin_deg)
    per_bin = success_by_bin(records, bin_deg, by=by)
    counts = next(iter(per_bin.values()))[1] if per_bin else np.zeros(len(edges) - 1, int)
    used = [k for k in range(len(edges) - 1) if counts[k] > 0]
    correct = median_by_bin(records, bin_deg, "num_correct", by)
    head = (
        [BIN_LABELS[by], "pairs"]
        + [f"{m} success %" for m in per_bin]
        + [f"{m} median GT-correct" for m in per_bin]
    )
    lines += ["", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for k in used:
        vals = [f"{edges[k]:g}-{edges[k + 1]:g}", str(int(counts[k]))]
        vals += [_pct(per_bin[m][0][k]) for m in per_bin]
        vals += [f"{correct[m][k]:.0f}" for m in per_bin]
        lines.append("| " + " | ".join(vals) + " |")
    return "\n".join(lines) + "\n"


def write_csv(path: Path | str, records: list[dict]) -> None:
    """All records, one row per pair and method."""
    buf = io.StringIO()
    w = csv.DictWriter(buf, fieldnames=RECORD_FIELDS, extrasaction="ignore")
    w.writeheader()
    for r in records:
        w.writerow({k: (f"{v:.4f}" if isinstance(v, float) else v) for k, v in r.items()})
    Path(path).write_text(buf.getvalue())


def read_csv(path: Path | str) -> list[dict]:
    """Records written by :func:`write_csv` (types restored)."""
    out = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            r = dict(row)
            for k in ("gt_rot", "R_err", "t_err", "pose_err"):
                r[k] = float(r[k])
            r["viewpoint"] = float(r["viewpoint"]) if r.get("viewpoint") else None
            for k in (
                "num_kp0",
                "num_kp1",
                "num_matches",
                "num_inliers",
                "num_correct",
                "num_inliers_correct",
            ):
                r[k] = int(r[k])
            for k in ("success", "epipolar_success"):
                r[k] = r[k] == "True"
            # files from before RANSAC runs were counted: one run, its outcome
            r["success_rate"] = float(r.get("success_rate") or r["success"])
            r["category"] = r["category"] or None
            out.append(r)
    return out


def plot_success(
    path: Path | str,
    records: list[dict],
    bin_deg: float = 10.0,
    title: str = "",
    success_deg: float = 5.0,
) -> None:
    """PNG like the paper's Figure 5: success rate per GT rotation bin, one curve per method
    (dashed: degeneracy-aware epipolar success)."""
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise ImportError(
            "the plot needs matplotlib: pip install 'rectified-colmap[eval]' "
            "(or pip install matplotlib)"
        ) from None
    edges = bin_edges(bin_deg)
    centres = 0.5 * (edges[:-1] + edges[1:])
    fig, ax = plt.subplots(figsize=(7, 4), dpi=120)
    epi = success_by_bin(records, bin_deg, key="epipolar_success")
    for m, (rate, count) in success_by_bin(records, bin_deg).items():
        ok = count > 0
        (line,) = ax.plot(centres[ok], 100 * rate[ok], "o-", label=f"{m}")
        ax.plot(
            centres[ok],
            100 * epi[m][0][ok],
            "--",
            color=line.get_color(),
            alpha=0.6,
            label=f"{m} (GT-correct matches)",
        )
    ax.set_xlabel("ground-truth relative rotation (deg)")
    ax.set_ylabel(f"success (%): rotation error < {success_deg:g} deg")
    ax.set_xlim(0, 180)
    ax.set_ylim(-2, 102)
    ax.set_xticks(edges[:: max(1, int(round(30 / bin_deg)))])
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8)
    if title:
        ax.set_title(title)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


def write_outputs(records: list[dict], out: Path, conf, plot: bool, title: str = "") -> str:
    """records.csv, summary.md (with the paired comparison against the first method when
    there are several), summary.json and, with ``plot``, success.png into ``out``, for an
    EvalConf ``conf``. Returns the markdown table."""
    out.mkdir(parents=True, exist_ok=True)
    write_csv(out / "records.csv", records)
    runs = conf.ransac_runs
    table = markdown_table(
        records,
        conf.bin_deg,
        conf.auc_thresholds,
        conf.success_deg,
        conf.min_correct,
        ransac_runs=runs,
    )
    methods = methods_of(records)
    if len(methods) > 1:  # the first method of --features is the baseline
        table += (
            "\nPaired with "
            + methods[0]
            + " (same pairs; p: exact two-sided)\n\n"
            + paired_markdown(records, methods[0], conf.bin_deg)
        )
    known = with_field(records, "viewpoint")
    if known:  # wide-baseline scenes (scripts/build_wide_pairs.py): by viewpoint change too
        table += f"\nBy viewpoint change ({len(known) // len(methods)} pairs with 3D points)\n\n"
        table += markdown_table(
            known,
            conf.bin_deg,
            conf.auc_thresholds,
            conf.success_deg,
            by="viewpoint",
            ransac_runs=runs,
        )
        if len(methods) > 1:
            table += "\n" + paired_markdown(known, methods[0], conf.bin_deg, "viewpoint")
    (out / "summary.md").write_text(table)
    (out / "summary.json").write_text(json.dumps(summary(records, conf.auc_thresholds), indent=1))
    if plot:
        plot_success(out / "success.png", records, conf.bin_deg, title, conf.success_deg)
    return table
