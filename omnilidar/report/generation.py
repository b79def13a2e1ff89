"""Tables and figures of the generation-quality results.

Markdown tables in the paper's layout (rows: domains or configurations,
columns: metrics per method; the better value of each pair in bold; lower is
better for every metric), a provenance line naming the extractor weights
(self-trained numbers flagged as not comparable with the paper's), sample
figures (range images and BEVs, generated beside real), the accuracy/time
figure with the Pareto front, and the generator-evidence figure.
"""

from __future__ import annotations

import numpy as np

from omnilidar.data.range_image import RangeImageSpec

LOWER_IS_BETTER = ("JSD", "MMD", "FRD", "FRID", "FSVD", "FPVD", "FPD")


def metric_value(scores: dict, metric: str):
    """The reported number of ``metric`` (MMD in units of 1e-4), or None."""
    return scores.get("MMD_1e4") if metric == "MMD" else scores.get(metric)


def _fmt(v) -> str:
    if v is None:
        return "n/a"
    return f"{v:.3f}" if abs(v) < 100 else f"{v:.1f}"


def metric_table(rows: dict[str, dict[str, dict]], metrics: list[str], methods: list[str]) -> str:
    """Markdown table: one row per key of ``rows`` ({row: {method: scores}}), one
    column per metric and method; the best method per metric in bold."""
    head = ["", *[f"{m} {meth}" if len(methods) > 1 else m for m in metrics for meth in methods]]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for row, by_method in rows.items():
        cells = [row]
        for m in metrics:
            vals = [metric_value(by_method.get(meth, {}), m) for meth in methods]
            known = [v for v in vals if v is not None]
            best = min(known) if known and len(methods) > 1 else None
            cells += [f"**{_fmt(v)}**" if v is not None and v == best else _fmt(v) for v in vals]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def provenance_note(weights: dict[str, str], comparable: dict[str, bool]) -> str:
    """One markdown line naming the weights behind every feature metric."""
    if not weights:
        return "Feature-free metrics only (JSD, MMD in units of 1e-4)."
    parts = [f"{m}: `{w}`" for m, w in sorted(weights.items())]
    note = "Extractor weights: " + ", ".join(parts) + ". MMD in units of 1e-4."
    if not all(comparable.values()):
        bad = ", ".join(m for m, ok in sorted(comparable.items()) if not ok)
        note += (f" **{bad} come from self-trained extractors: comparable between the rows of this table, "
                 "not with published numbers.**")
    return note


def collect_weights(results: dict) -> tuple[dict, dict]:
    """Union of the ``weights`` / ``comparable_with_paper`` maps of nested score dicts."""
    weights, comparable = {}, {}

    def walk(node):
        if isinstance(node, dict):
            if "weights" in node and isinstance(node["weights"], dict):
                weights.update(node["weights"])
                comparable.update(node.get("comparable_with_paper", {}))
            for v in node.values():
                walk(v)

    walk(results)
    return weights, comparable


# --------------------------------------------------------------------------- figures


def _bev_image(points: np.ndarray, half: float = 50.0, bins: int = 200) -> np.ndarray:
    h, _, _ = np.histogram2d(points[:, 0], points[:, 1], bins=bins, range=[[-half, half], [-half, half]])
    return np.log1p(h).T


def samples_figure(path, spec: RangeImageSpec, columns: dict[str, dict[str, np.ndarray]]) -> None:
    """Per domain (rows) and set (columns, e.g. Real, OmniLiDAR, baseline) one range image
    (log-range channel) above its BEV. ``columns``: {set: {domain: (2, H, W) image}}."""
    from omnilidar.io.figure import plt, save_figure

    from omnilidar.metrics.extractors.views import range_views

    sets = list(columns)
    domains = list(dict.fromkeys(d for c in columns.values() for d in c))
    fig, axes = plt.subplots(2 * len(domains), len(sets), figsize=(3.2 * len(sets), 1.9 * len(domains) + 0.5),
                             squeeze=False, gridspec_kw={"height_ratios": [1, 2.2] * len(domains)})
    for r, dom in enumerate(domains):
        for c, name in enumerate(sets):
            ax_img, ax_bev = axes[2 * r, c], axes[2 * r + 1, c]
            img = columns[name].get(dom)
            for ax in (ax_img, ax_bev):
                ax.set_xticks([])
                ax.set_yticks([])
            if img is None:
                continue
            ax_img.imshow(img[0], cmap="turbo", vmin=-1, vmax=1, aspect="auto", interpolation="nearest")
            pts = range_views(img[None], spec)["points"][0]
            ax_bev.imshow(_bev_image(pts), cmap="magma", origin="lower", aspect="equal")
            if r == 0:
                ax_img.set_title(name, fontsize=9)
            if c == 0:
                ax_img.set_ylabel(dom, fontsize=8)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def pareto_front(seconds: list[float], errors: list[float]) -> list[bool]:
    """Which points are Pareto-optimal (no other point is at least as fast and as accurate,
    and strictly better in one); lower is better on both axes."""
    s = np.asarray(seconds, float)
    e = np.asarray(errors, float)
    out = []
    for i in range(len(s)):
        dominated = (s <= s[i]) & (e <= e[i]) & ((s < s[i]) | (e < e[i]))
        out.append(not dominated.any())
    return out


def tradeoff_figure(path, tradeoff: dict) -> None:
    """Each metric against network evaluations per solver (mean and spread over the seed groups;
    the distilled student as a star), the domain effects' error/time curves, and downstream mIoU
    against the total compute of the generated scans (points labelled with their number) when a
    GDA curve was read."""
    from omnilidar.io.figure import plt, save_figure

    from omnilidar.report.gda_curve import draw_miou_vs_compute
    from omnilidar.report.log_axis import readable_log_x

    points = tradeoff["points"]
    metrics = tradeoff.get("metrics") or ["JSD", "MMD"]
    extra = [k for k in ("effects", "downstream") if tradeoff.get(k)]
    fig, axes = plt.subplots(1, len(metrics) + len(extra), figsize=(4.2 * (len(metrics) + len(extra)), 3.6),
                             squeeze=False)
    for ax, metric in zip(axes[0], metrics):
        key = f"mean_{metric}"
        for sampler in dict.fromkeys(p["sampler"] for p in points):
            pts = [p for p in points if p["sampler"] == sampler and p.get(key) is not None]
            ax.errorbar([p["steps"] for p in pts], [p[key] for p in pts],
                        yerr=[p.get(f"std_{metric}") or 0.0 for p in pts], fmt="*" if sampler == "student" else "o-",
                        ms=10 if sampler == "student" else 4, capsize=2, label=sampler)
        ax.set_xlabel("network evaluations per scan")
        ax.set_ylabel(f"{metric}{' (x1e-4)' if metric == 'MMD' else ''}, mean over domains")
        readable_log_x(ax)
        ax.legend(fontsize=6)
    col = len(metrics)
    if tradeoff.get("effects"):
        ax = axes[0, col]
        col += 1
        for curve in tradeoff["effects"]:
            ax.plot(curve["seconds"], curve["error"], "o-", ms=3, label=curve["name"])
        readable_log_x(ax)
        ax.set_xlabel("seconds per scan")
        ax.set_ylabel("effect error")
        ax.set_title("domain effects", fontsize=9)
        ax.legend(fontsize=6)
    if tradeoff.get("downstream"):
        setup = tradeoff.get("downstream_setup") or {}
        title = "downstream GDA" + (f" ({setup['backbone']}, {setup['percent']:g} % labels)"
                                    if setup.get("backbone") and isinstance(setup.get("percent"), (int, float)) else "")
        draw_miou_vs_compute(axes[0, col], tradeoff["downstream"], title)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def evidence_figure(path, evidence: dict) -> None:
    """Trained vs untrained BEV JSD per domain, and generated vs real domain statistics."""
    from omnilidar.io.figure import plt, save_figure

    doms = list(evidence["domains"])
    stats = ["empty_row_fraction", "near_range_fraction", "points_per_scan", "mean_elevation_deg"]
    fig, axes = plt.subplots(1, 1 + len(stats), figsize=(3.6 * (1 + len(stats)), 3.4), squeeze=False)
    x = np.arange(len(doms))
    ax = axes[0, 0]
    for k, (name, off) in enumerate((("trained", -0.2), ("untrained", 0.2))):
        vals = [evidence["domains"][d][name]["JSD"] or 0.0 for d in doms]
        ax.bar(x + off, vals, 0.4, label=name)
    ax.set_xticks(x, doms, rotation=60, fontsize=7)
    ax.set_ylabel("BEV JSD to real (lower is better)")
    ax.legend(fontsize=7)
    for ax, stat in zip(axes[0, 1:], stats):
        for name, off in (("real", -0.2), ("generated", 0.2)):
            ax.bar(x + off, [evidence["domains"][d]["statistics"][name][stat] for d in doms], 0.4, label=name)
        ax.set_xticks(x, doms, rotation=60, fontsize=7)
        ax.set_title(stat.replace("_", " "), fontsize=9)
        ax.legend(fontsize=7)
    fig.tight_layout()
    save_figure(fig, path, dpi=90)


def write_outputs(result: dict, out, markdown_path=None, markdown: str | None = None) -> None:
    """Write the results JSON (and its markdown table) atomically."""
    import json

    from omnilidar.io.atomic import write_text_atomic

    write_text_atomic(out, json.dumps(result, indent=1, sort_keys=False, allow_nan=False))
    if markdown_path is not None and markdown is not None:
        write_text_atomic(markdown_path, markdown + "\n")
