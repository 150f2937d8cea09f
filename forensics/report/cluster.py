"""Figures and report of clustering a collection by camera (:func:`forensics.prnu.cluster.cluster_images`).

Drawing and page layout only: each function takes a :class:`~forensics.prnu.cluster.ClusterResult` and
draws what it holds (the similarity matrix is only put in cluster order, never recomputed).
"""
from __future__ import annotations

import math
from typing import Any

import numpy as np

from forensics.prnu.cluster import ClusterResult, SizeGroup
from forensics.report.html import Report, new_figure

__all__ = ["add_clusters", "cluster_order", "cluster_report", "plot_cluster_sizes", "plot_image_scores",
           "plot_similarity"]


def cluster_order(result: ClusterResult, group: SizeGroup) -> tuple[list[int], list[int]]:
    """Positions of a group's images (into its similarity matrix) ordered by cluster, largest first, then the
    unattributed ones; and the sizes of the consecutive blocks (clusters, then one block of unattributed)."""
    position = {i: k for k, i in enumerate(group.members)}
    order: list[int] = []
    sizes: list[int] = []
    for c in result.clusters:
        if c.group == group.index:
            order += [position[i] for i in c.members]
            sizes.append(c.size)
    rest = [position[i] for i in group.members if result.images[i].cluster is None]
    if rest:
        order += rest
        sizes.append(len(rest))
    return order, sizes


def plot_similarity(ax: Any, result: ClusterResult, group: SizeGroup) -> Any:
    """The group's pairwise z matrix in cluster order, the clusters outlined; returns the image (for a colour bar)."""
    z = result.similarity[group.index]
    order, sizes = cluster_order(result, group)
    shown = z[np.ix_(order, order)] if len(order) else z
    top = max(2 * group.threshold_merge if math.isfinite(group.threshold_merge) else 10.0, 10.0)
    image = ax.imshow(np.clip(np.nan_to_num(shown, nan=0.0), -top, top), cmap="RdBu_r", vmin=-top, vmax=top,
                      interpolation="nearest")
    n_clustered = sum(c.size for c in result.clusters if c.group == group.index)
    start = 0
    for size in sizes:
        if start < n_clustered:  # a cluster: outline its block
            ax.add_patch(_rectangle(start - 0.5, size, "k"))
        start += size
    ax.set_xlabel("image (ordered by cluster, unattributed last)")
    ax.set_ylabel("image")
    return image


def _rectangle(corner: float, size: int, colour: str) -> Any:
    from matplotlib.patches import Rectangle

    return Rectangle((corner, corner), size, size, fill=False, edgecolor=colour, linewidth=1.0)


def plot_cluster_sizes(ax: Any, result: ClusterResult) -> None:
    """Images per cluster (largest first) and the unattributed count."""
    labels = [c.label for c in result.clusters] + ["unattributed"]
    counts = [c.size for c in result.clusters] + [result.n_unattributed]
    colours = ["C0"] * len(result.clusters) + ["0.6"]
    ax.bar(range(len(counts)), counts, color=colours)
    ax.set_xticks(range(len(counts)), labels, rotation=90 if len(counts) > 8 else 0, fontsize=8)
    ax.set_ylabel("images")


def plot_image_scores(ax: Any, result: ClusterResult, group: SizeGroup) -> None:
    """Each image's z against its cluster (or the best cluster, if unattributed), with the two thresholds."""
    order, _ = cluster_order(result, group)
    members = [group.members[k] for k in order]
    values = np.array([result.images[i].cluster_z for i in members], float)
    attributed = np.array([result.images[i].cluster is not None for i in members])
    x = np.arange(len(members))
    finite = np.isfinite(values)
    ax.scatter(x[finite & attributed], values[finite & attributed], s=12, color="C0", label="in a cluster")
    ax.scatter(x[finite & ~attributed], values[finite & ~attributed], s=12, color="C3", marker="x",
               label="unattributed (best cluster)")
    for tau, style, name in ((group.threshold_merge, "--", "merge"), (group.threshold_attach, ":", "attach")):
        if math.isfinite(tau):
            ax.axhline(tau, ls=style, color="0.3", lw=1, label=f"{name} threshold {tau:.2f}")
    if finite.any() and values[finite].max() > 50:  # matching flat fields reach hundreds: compress above 10
        ax.set_yscale("symlog", linthresh=10)
        ticks = [t for t in (-5, 0, 5, 10, 20, 50, 100, 200, 500, 1000) if t <= 2 * values[finite].max()]
        ax.set_yticks(ticks, [str(t) for t in ticks])
    ax.grid(True, axis="y", alpha=0.3)
    ax.set_xlabel("image (ordered by cluster)")
    ax.set_ylabel("z against the rest of the cluster")
    ax.legend(frameon=False, fontsize=8)


def add_clusters(result: ClusterResult, rep: Report, *, prefix: str = "") -> None:
    """Add the summary, the similarity matrices, cluster sizes, per-image scores and tables to a Report."""
    rep.text(f"{len(result.images)} images → {len(result.clusters)} devices, {result.n_unattributed} unattributed. "
             f"The probability that any image is put with another camera's images is at most {result.p_fa:g} "
             "(half for merges, Šidák over every comparison the agglomeration can make; half for attaching "
             "left-over images; Gaussian null of the residual correlation with its scale at the upper 95 % bound).")
    for message in result.warnings:
        rep.text(message, note=True)
    rows = []
    for g in result.groups:
        null = g.null
        if null is None:
            rows.append([f"{g.frame[1]}×{g.frame[0]}", len(g.members), "—", "—", "—", "—", "—", "—"])
            continue
        c = g.crop
        rows.append([f"{g.frame[1]}×{g.frame[0]}", len(g.members), f"{c}²", f"{null.sigma * c:.3f}",
                     f"[{null.sigma_ci[0] * c:.3f}, {null.sigma_ci[1] * c:.3f}]" + (" pooled" if null.pooled else ""),
                     null.n_samples, f"{g.threshold_merge:.2f} ({g.n_comparisons} comparisons)",
                     f"{g.threshold_attach:.2f} ({g.n_attach_tests} tests)" if math.isfinite(g.threshold_attach)
                     else "—"])
    rep.table(["frame size", "images", "crop", "null σ·crop", "95 % interval", "null samples", "merge z ≥",
               "attach z ≥"], rows, caption="Size groups: the null distribution of the residual correlation "
              "(residuals against shifted residuals) and the thresholds in units of its σ")
    for g in result.groups:
        if g.null is None or not len(g.members):
            continue
        name = f"{g.frame[1]}×{g.frame[0]}"
        side = min(9.0, 3.0 + 0.04 * len(g.members))
        fig, ax = new_figure(side + 1.2, side)
        image = plot_similarity(ax, result, g)
        fig.colorbar(image, ax=ax, label="z (NCC above the null centre, in σ)", shrink=0.8)
        rep.figure(fig, f"{prefix}similarity_{g.index}", f"{name}: pairwise z of the residuals, ordered by cluster "
                   "(outlined), unattributed images last.  Single pairs of weak images may be low inside a cluster: "
                   "clusters are merged on their summed residuals.")
        fig, ax = new_figure(8, 3.5)
        plot_image_scores(ax, result, g)
        rep.figure(fig, f"{prefix}scores_{g.index}", f"{name}: each image's z against the summed residuals of the "
                   "rest of its cluster (unattributed: of the best cluster), with the thresholds.")
    fig, ax = new_figure(max(4.0, 0.35 * (len(result.clusters) + 1) + 2), 3.2)
    plot_cluster_sizes(ax, result)
    rep.figure(fig, f"{prefix}sizes", "Images per device found.")
    rep.table(["device", "images", "mean pair z", "weakest z against the rest", "attached"],
              [[c.label, c.size, c.mean_z, c.weakest_z, c.n_attached] for c in result.clusters])
    rep.table(["file", "device", "stage", "rotation", "best match", "best pair z", "z against cluster"],
              [[a.file, a.cluster or "—", a.stage, 90 * a.rotation, a.best_match or "—", _z(a.best_z),
                _z(a.cluster_z)] for a in result.images])


def _z(value: float) -> str:
    return f"{value:.2f}" if math.isfinite(value) else "—"


def cluster_report(result: ClusterResult, command: str = "") -> Report:
    """A page for one clustering; ``command`` (the command line that ran it) is shown first."""
    rep = Report("Which camera? Clusters of a collection")
    if command:
        rep.preformatted(command)
    add_clusters(result, rep)
    return rep
